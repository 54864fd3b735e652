"""`pitta_jax.segment` and `pitta-jax segment`: Mask2Former panoptic maps as frames and files.

Reference: `pitta_jax.models.mask2former.segment` called directly on the same image with the
same `InferenceConfig` (its parity with Hugging Face's Mask2Former is `test_mask2former.py`);
here we check that the frames, the files and the readers carry exactly its id maps and
segments. The weights directory is a tiny random Mask2Former (Swin depths 1, 32 channels, 16
queries, 3 decoder layers, COCO's 133 classes) written by `save_mask2former`, the format the
converter writes; its class head is scaled so that some queries pass detectron2's 0.8
thresholds (the fixture asserts segments exist). Images are 60x90: the network input is 64x96
(padded to a multiple of 32, or resized with --height 64 --width 96), one compile.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax.traverse_util import flatten_dict, unflatten_dict

from pitta_jax import cli
from pitta_jax.data import panoptic_io
from pitta_jax.data.errors import DataError
from pitta_jax.data.folder import open_folder
from pitta_jax.data.frame import Frame
from pitta_jax.data.image_io import read_image, write_image
from pitta_jax.data.readers import open_dataset
from pitta_jax.models.mask2former import (InferenceConfig, Mask2Former, Mask2FormerConfig,
                                          segment)
from pitta_jax.models.mask2former.swin import SwinConfig
from pitta_jax.segment import MappedFrames, Segmenter, segment_images, segmented_frames
from pitta_jax.sources import open_frames
from weights_convert.mask2former import save_mask2former

H, W = 60, 90  # not multiples of 32: the network pads to 64x96
TINY = Mask2FormerConfig(
    swin=SwinConfig(embed_dim=16, depths=(1, 1, 1, 1), num_heads=(1, 1, 2, 2)),
    num_queries=16, hidden_dim=32, num_heads=2, dim_feedforward=32, dec_layers=3, mask_dim=32,
    conv_dim=32, enc_layers=1, enc_dim_feedforward=32, enc_n_points=2, num_groups=8)


def _random_variables(cfg: Mask2FormerConfig, seed: int = 0) -> dict:
  """Seeded random variables of the right shapes (from `eval_shape`: no init compile).

  Kernels ~ N(0, 1 / fan_in), norm scales ~ 1 + N(0, 0.1), biases ~ N(0, 0.05), embeddings and
  relative position tables ~ N(0, 1). Plain random weights segment nothing (no query reaches
  class probability 0.8; all queries predict about the same mask, so none owns 80% of it), so:
  no level embedding and larger query features (else the memory's shared level embedding
  dominates every query), mask MLP kernels centred over their inputs (else the ReLU means give
  every query the same mask embedding), the class head x10, and every mask logit shifted by -1
  through a constant mask-feature channel (smaller, less overlapping masks).
  """
  shapes = jax.eval_shape(Mask2Former(cfg).init, jax.random.PRNGKey(0),
                          jnp.zeros((1, 64, 96, 3), jnp.float32))
  rs = np.random.RandomState(seed)
  flat = {}
  for path, leaf in sorted(flatten_dict(shapes).items()):
    noise = rs.randn(*leaf.shape).astype(np.float32)
    if path[-1] == "kernel":
      flat[path] = noise / np.sqrt(np.prod(leaf.shape[:-1]))
    elif path[-1] == "scale":
      flat[path] = 1 + 0.1 * noise
    elif path[-1] == "bias":
      flat[path] = 0.05 * noise
    else:
      flat[path] = noise
  pred = ("params", "predictor")
  flat[pred + ("level_embed",)] *= 0.0
  flat[pred + ("query_feat",)] *= 3.0
  flat[pred + ("class_embed", "kernel")] *= 10.0
  for name in ("mask_embed_1", "mask_embed_2"):
    kernel = flat[pred + (name, "kernel")]
    flat[pred + (name, "kernel")] = kernel - kernel.mean(0)
  features = ("params", "pixel_decoder", "mask_features")  # channel 0 := 1 everywhere
  flat[features + ("kernel",)][..., 0] = 0.0
  flat[features + ("bias",)][0] = 1.0
  flat[pred + ("mask_embed_2", "kernel")][:, 0] = 0.0  # mask logits += bias[0] * 1
  flat[pred + ("mask_embed_2", "bias")][0] = -1.0
  return unflatten_dict(flat)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
  """(weights dir, module, variables) of the tiny random Mask2Former."""
  variables = _random_variables(TINY)
  out = save_mask2former(tmp_path_factory.mktemp("m2f"), TINY, variables, {"format": "random"})
  segmenter = Segmenter(out)
  assert segmenter.module.config == TINY
  return out, segmenter.module, segmenter.variables


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory):
  root = tmp_path_factory.mktemp("images")
  rs = np.random.RandomState(1)
  for stem in ("a", "b"):
    image = np.clip(rs.rand(H, W, 3) + np.linspace(0, 0.5, W)[None, :, None], 0, 1)
    write_image(root / f"{stem}.png", (image * 255).astype(np.uint8))
  return root


def _direct(weights, path, input_size):
  _, module, variables = weights
  return segment(module, variables, read_image(path), InferenceConfig(input_size=input_size))


@pytest.fixture(scope="module")
def cli_out(weights, image_dir, tmp_path_factory):
  """`pitta-jax segment` on the folder, default input size."""
  out = tmp_path_factory.mktemp("panoptic")
  assert cli.main(["segment", "--weights", str(weights[0]), "--images", str(image_dir),
                   "--out", str(out), "--quiet"]) == 0
  return out


def test_fixture_is_not_trivial(weights, image_dir):
  """The random model paints segments (else every comparison below would compare zeros)."""
  ids, segments = _direct(weights, image_dir / "a.png", (H, W))
  print(f"{len(segments)} segments, {np.mean(ids > 0):.0%} of pixels: {segments}")
  assert len(segments) >= 2 and (ids > 0).any()
  assert {s.isthing for s in segments} == {True, False}


def test_cli_writes_coco_panoptic_equal_to_segment(weights, image_dir, cli_out, capsys):
  assert sorted(p.name for p in cli_out.iterdir()) == ["a.json", "a.png", "b.json", "b.png"]
  for stem in ("a", "b"):
    ref_ids, ref_segments = _direct(weights, image_dir / f"{stem}.png", (H, W))
    ids = panoptic_io.read_panoptic_png(cli_out / f"{stem}.png")
    segments = panoptic_io.read_segments_json(cli_out / f"{stem}.json")
    assert ids.shape == (H, W)
    np.testing.assert_array_equal(ids, ref_ids)
    assert segments == tuple(ref_segments)


def test_cli_input_size_resizes(weights, image_dir, tmp_path, capsys):
  """--height/--width: the image is resized to 64x96 for the network, the map stays 60x90."""
  out = tmp_path / "resized"
  assert cli.main(["segment", "--weights", str(weights[0]), "--images", str(image_dir / "b.png"),
                   "--out", str(out), "--height", "64", "--width", "96", "--quiet"]) == 0
  assert "wrote 1 panoptic maps" in capsys.readouterr().out
  ref_ids, ref_segments = _direct(weights, image_dir / "b.png", (64, 96))
  ids = panoptic_io.read_panoptic_png(out / "b.png")
  np.testing.assert_array_equal(ids, ref_ids)
  assert panoptic_io.read_segments_json(out / "b.json") == tuple(ref_segments)


def test_cli_detectron2_resize(weights, image_dir, tmp_path, capsys):
  """--detectron2-resize: upstream's test-time ResizeShortestEdge(800, max 1333); the 60x90
  image enters at 800 x 1200 (scale 800 / 60, the long side 1200 <= 1333), the map stays 60x90;
  with --height/--width as well it is refused."""
  from pitta_jax.models.mask2former.model import resized_shape
  assert resized_shape(H, W, InferenceConfig()) == (800, 1200)
  out = tmp_path / "d2"
  assert cli.main(["segment", "--weights", str(weights[0]), "--images", str(image_dir / "a.png"),
                   "--out", str(out), "--detectron2-resize", "--quiet"]) == 0
  ref_ids, ref_segments = _direct(weights, image_dir / "a.png", None)
  ids = panoptic_io.read_panoptic_png(out / "a.png")
  assert ids.shape == (H, W)
  np.testing.assert_array_equal(ids, ref_ids)
  assert panoptic_io.read_segments_json(out / "a.json") == tuple(ref_segments)
  capsys.readouterr()
  assert cli.main(["segment", "--weights", str(weights[0]), "--images", str(image_dir / "a.png"),
                   "--out", str(tmp_path / "d3"), "--detectron2-resize", "--height", "64",
                   "--width", "96"]) == 2
  assert capsys.readouterr().err == ("error: --detectron2-resize and --height/--width both "
                                     "choose the input size: give one\n")
  assert not (tmp_path / "d3").exists()


def test_an_image_too_thin_for_the_detectron2_resize_is_named_before_any_is_segmented(
    weights, image_dir, tmp_path, capsys):
  """A 1x4000 image under --detectron2-resize: its short edge rounds to 0 pixels (1333 / 4000
  of 1), which stopped the command with a traceback halfway through its images; now one line
  naming the file, before any image is segmented (the 60x90 one beside it is not written)."""
  from pitta_jax.data.image_io import write_image
  thin = tmp_path / "in" / "thin.png"
  write_image(thin, np.full((1, 4000, 3), 0.5, np.float32))
  write_image(tmp_path / "in" / "a.png", np.full((60, 90, 3), 0.5, np.float32))
  out = tmp_path / "o"
  capsys.readouterr()
  assert cli.main(["segment", "--weights", str(weights[0]), "--images", str(tmp_path / "in"),
                   "--out", str(out), "--detectron2-resize", "--quiet"]) == 2
  err = capsys.readouterr().err
  assert err.startswith(f"error: {thin}: a 1x4000 image resized to at most 1333 pixels a side "
                        f"is 0x1333") and err.count("\n") == 1
  assert not out.exists()


def test_a_segment_whose_out_is_made_again_stops_with_one_line(weights, image_dir, tmp_path,
                                                                 capsys, monkeypatch):
  """--out removed and made again after the first map: the command stops before the next map
  with one line naming --out (the rest went into the new directory, without its lock)."""
  import shutil
  from pitta_jax import segment as segment_lib
  out, real, written = tmp_path / "o", segment_lib.write_panoptic, []

  def replacing(png, ids, segments):
    real(png, ids, segments)
    written.append(png.name)
    shutil.rmtree(out)
    out.mkdir()
  monkeypatch.setattr(segment_lib, "write_panoptic", replacing)
  capsys.readouterr()
  assert cli.main(["segment", "--weights", str(weights[0]), "--images", str(image_dir),
                   "--out", str(out), "--quiet"]) == 2
  assert capsys.readouterr().err == (f"error: --out {out}: removed while the command ran; its "
                                     f"results are not written (run it again)\n")
  assert written == ["a.png"] and list(out.iterdir()) == []


def test_segmented_frames_over_a_frame_sequence(weights, image_dir):
  frames = segmented_frames(open_folder(image_dir), weights[0])
  assert len(frames) == 2 and frames.names == ("a", "b")  # still a lazy FrameSequence
  for stem, frame in zip(("a", "b"), frames):
    ref_ids, ref_segments = _direct(weights, image_dir / f"{stem}.png", (H, W))
    assert frame.panoptic.dtype == np.int32
    np.testing.assert_array_equal(frame.panoptic, ref_ids)
    assert frame.segments == tuple(ref_segments)
  np.testing.assert_array_equal(frames[1:][0].panoptic, frames[1].panoptic)


def test_segmented_frames_over_a_list(weights, image_dir):
  """Any sequence of frames (here a list with a stale map) gets the segmenter's maps."""
  image = read_image(image_dir / "a.png")
  stale = Frame(image=image, panoptic=np.full((H, W), 7, np.int32), name="a")
  frames = segmented_frames([stale, stale], Segmenter(weights[0]))
  assert isinstance(frames, MappedFrames) and len(frames) == 2 and len(frames[:1]) == 1
  ref_ids, ref_segments = _direct(weights, image_dir / "a.png", (H, W))
  for frame in frames:
    np.testing.assert_array_equal(frame.panoptic, ref_ids)
    assert frame.segments == tuple(ref_segments) and frame.name == "a"


def test_mapped_frames_transform_only_the_frames_read():
  """`MappedFrames` runs the transform (the network) when a frame is read, not when the
  sequence is sliced: a slice of a long list stays lazy, a MappedFrames of the sliced frames.
  Integers stand for frames and +100 for the segmenter."""
  calls = []

  def transform(x):
    calls.append(x)
    return x + 100

  frames = MappedFrames(list(range(10)), transform)
  part = frames[2:8:2]
  assert isinstance(part, MappedFrames) and len(part) == 3 and calls == []
  assert part[1] == 104 and calls == [4]
  assert list(part) == [102, 104, 106] and calls == [4, 2, 4, 6]


def test_written_directory_is_png_segmentation_input(weights, image_dir, cli_out):
  """OUT is what `--segmentation png:OUT` gives the folder reader (`panoptic_dir`), and
  `--segmentation mask2former:DIR` gives the same frames without files."""
  segmented = segmented_frames(open_folder(image_dir), weights[0])
  for frames in (open_dataset("folder", image_dir, panoptic_dir=cli_out),
                 open_frames("folder", str(image_dir), [], f"png:{cli_out}", 192, 640),
                 open_frames("folder", str(image_dir), [], f"mask2former:{weights[0]}", 192, 640)):
    assert len(frames) == 2
    for frame, ref in zip(frames, segmented):
      np.testing.assert_array_equal(frame.panoptic, ref.panoptic)
      assert frame.segments == ref.segments


def test_missing_weights_is_a_user_error(image_dir, tmp_path, capsys):
  missing = tmp_path / "no_such_dir"
  assert cli.main(["segment", "--weights", str(missing), "--images", str(image_dir),
                   "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and str(missing) in err and "not found" in err
  (tmp_path / "empty").mkdir()
  assert cli.main(["segment", "--weights", str(tmp_path / "empty"), "--images", str(image_dir),
                   "--out", str(tmp_path / "o")]) == 2
  assert "config.json" in capsys.readouterr().err
  assert not (tmp_path / "o").exists()  # nothing written before the weights load
  with pytest.raises(DataError, match="weights directory"):
    segmented_frames(open_folder(image_dir), "")  # --segmentation mask2former: (no DIR)
  # a model of another label set (e.g. Cityscapes' 19 classes) is refused before any image
  config = dataclasses.replace(TINY, num_classes=19)
  other = save_mask2former(tmp_path / "m2f19", config, _random_variables(config),
                           {"format": "random"})
  assert cli.main(["segment", "--weights", str(other), "--images", str(image_dir),
                   "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == (
      f"error: {other / 'config.json'}: a Mask2Former with 19 classes; the segmenter writes COCO "
      f"panoptic categories (the dynamic classes are COCO ids): convert a COCO panoptic model "
      f"(133 classes)\n")
  assert not (tmp_path / "o").exists()


def test_cli_argument_errors(weights, image_dir, tmp_path, capsys):
  assert cli.main(["segment", "--weights", str(weights[0]), "--images", str(image_dir),
                   "--out", str(tmp_path), "--height", "64"]) == 2
  assert "--width" in capsys.readouterr().err
  assert cli.main(["segment", "--weights", str(weights[0]), "--images",
                   str(tmp_path / "*.png"), "--out", str(tmp_path)]) == 2
  assert "no image found" in capsys.readouterr().err
  # the Python API's own check of input_size: an empty network input is refused when the
  # segmenter is made, not by a resize to zero pixels at the first image
  for bad in ((0, W), (H, -1), (H,)):
    with pytest.raises(ValueError, match=r"input_size must be \(height, width\) > 0"):
      Segmenter(weights[0], bad)
  (tmp_path / "x").mkdir()
  write_image(tmp_path / "x" / "a.png", np.zeros((H, W, 3), np.uint8))
  with pytest.raises(DataError, match="same file stem"):  # outputs are named by stem
    segment_images(weights[0], [image_dir / "a.png", tmp_path / "x" / "a.png"], tmp_path / "o")
  # --out in the image directory would write a.png's panoptic map over a.png
  before = (tmp_path / "x" / "a.png").read_bytes()
  with pytest.raises(DataError, match="would overwrite this input"):
    segment_images(weights[0], str(tmp_path / "x"), tmp_path / "x")
  assert (tmp_path / "x" / "a.png").read_bytes() == before
  # a user's file at an output's name (no panoptic JSON beside it) is not replaced either
  write_image(tmp_path / "x" / "b.jpg", np.zeros((H, W, 3), np.uint8))
  write_image(tmp_path / "x" / "b.png", np.full((H, W, 3), 9, np.uint8))
  before = (tmp_path / "x" / "b.png").read_bytes()
  with pytest.raises(DataError, match=r"b\.png: exists and is not an earlier output"):
    segment_images(weights[0], [tmp_path / "x" / "b.jpg"], tmp_path / "x")
  assert (tmp_path / "x" / "b.png").read_bytes() == before
  # nor a labelme annotation `<stem>.json` beside the images (it was replaced, exit 0)
  (tmp_path / "y").mkdir()
  write_image(tmp_path / "y" / "c.jpg", np.zeros((H, W, 3), np.uint8))
  (tmp_path / "y" / "c.json").write_text('{"version": "5.0", "shapes": []}')
  with pytest.raises(DataError, match=r"c\.json: exists and is not an earlier output"):
    segment_images(weights[0], str(tmp_path / "y"), tmp_path / "y")
  assert json.loads((tmp_path / "y" / "c.json").read_text())["version"] == "5.0"
  # a rerun into a folder of JPEG images skips its own c.png + c.json (it took c.png as a
  # second image of stem c and refused)
  (tmp_path / "y" / "c.json").unlink()
  first = segment_images(weights[0], str(tmp_path / "y"), tmp_path / "y")
  assert segment_images(weights[0], str(tmp_path / "y"), tmp_path / "y") == first
