"""`pitta-jax convert` + `pitta-jax predict` end to end, against the PyTorch reference model.

Reference: `tests/torch_monodepth2.py` run on the same resized image.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import torch_monodepth2 as tm
from pitta_jax.cli import main
from pitta_jax.data.image_io import read_image
from pitta_jax.data.resize import resize_image

H, W = 64, 96


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
  root = tmp_path_factory.mktemp("mono_96x64")
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  tm.randomize_(enc, 1), tm.randomize_(dec, 2)
  torch.save({**enc.state_dict(), "height": H, "width": W, "use_stereo": False},
             root / "encoder.pth", _use_new_zipfile_serialization=False)
  torch.save(dec.state_dict(), root / "depth.pth", _use_new_zipfile_serialization=False)
  out = root / "weights"
  assert main(["convert", "monodepth2", "--encoder", str(root / "encoder.pth"),
               "--depth", str(root / "depth.pth"), "--out", str(out)]) == 0
  return out, enc.eval(), dec.eval(), root


def test_predict_writes_outputs_matching_torch(converted, tmp_path):
  weights, enc, dec, _ = converted
  rng = np.random.default_rng(0)
  img_dir = tmp_path / "imgs"
  img_dir.mkdir()
  sizes = [(120, 200), (64, 96)]
  for i, (h, w) in enumerate(sizes):
    cv2.imwrite(str(img_dir / f"im{i}.png"), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
  assert main(["predict", "--weights", str(weights), "--images", str(img_dir), "--out",
               str(tmp_path / "pred"), "--quiet"]) == 0
  for i in range(2):
    disp = np.load(tmp_path / "pred" / f"im{i}_disp.npy")
    depth = np.load(tmp_path / "pred" / f"im{i}_depth.npy")
    assert disp.shape == depth.shape == (H, W)   # test_simple.py's npy: the network's size
    png = cv2.imread(str(tmp_path / "pred" / f"im{i}_disp.png"))
    assert png.shape[:2] == sizes[i]               # its colour map: the image's size
    x = resize_image(read_image(img_dir / f"im{i}.png"), H, W)
    with torch.no_grad():
      sigmoid = dec(enc(torch.from_numpy(x[None]).permute(0, 3, 1, 2)))[("disp", 0)]
    # test_simple.py: scaled_disp, depth = disp_to_depth(disp, 0.1, 100); np.save(scaled_disp)
    min_disp, max_disp = 1 / 100, 1 / 0.1
    ref = (min_disp + (max_disp - min_disp) * sigmoid)[0, 0].numpy()
    diff = float(np.max(np.abs(disp - ref)))
    print(f"predict im{i}: max abs diff vs torch {diff:.2e}")
    assert diff < 1e-4 and 0.01 <= disp.min() and disp.max() <= 10
    np.testing.assert_allclose(depth, 1 / ref, rtol=1e-4)


def test_predict_glob_and_errors(converted, tmp_path, capsys):
  weights = converted[0]
  assert main(["predict", "--weights", str(weights), "--images", str(tmp_path / "*.png"),
               "--out", str(tmp_path / "o")]) == 2
  assert "no image found" in capsys.readouterr().err
  assert main(["predict", "--weights", str(tmp_path / "nowhere"), "--images", "x.png",
               "--out", str(tmp_path / "o")]) == 2
  assert "model.json" in capsys.readouterr().err


def test_predict_checks_every_image_first_and_skips_its_own_outputs(converted, tmp_path, capsys):
  """An unreadable image fails before anything is written; `a.png` beside `a.jpg` is two
  images with one stem (refused); with --out in the image directory a rerun does not predict on
  the `_disp.png` files of the first run."""
  weights = converted[0]
  rng = np.random.default_rng(1)
  d = tmp_path / "imgs"
  d.mkdir()
  for name in ("000", "001", "002"):
    cv2.imwrite(str(d / f"{name}.png"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
  good = (d / "002.png").read_bytes()
  (d / "002.png").write_bytes(good[:len(good) // 2])  # truncated
  args = ["predict", "--weights", str(weights), "--images", str(d), "--quiet", "--out"]
  assert main([*args, str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert str(d / "002.png") in err and err.count("\n") == 1 and not (tmp_path / "o").exists()
  (d / "002.png").write_bytes(good)
  cv2.imwrite(str(d / "001.jpg"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
  assert main([*args, str(tmp_path / "o")]) == 2
  assert "same file stem" in capsys.readouterr().err
  (d / "001.jpg").unlink()
  assert main([*args, str(d)]) == 0 and main([*args, str(d)]) == 0
  assert sorted(p.name for p in d.glob("*.png")) == [
      f"{n}{s}.png" for n in ("000", "001", "002") for s in ("", "_disp")]
  # a user's own image named like an output (no _disp.npy beside it) is neither skipped as an
  # output nor replaced by one: refused before anything is written
  user = tmp_path / "user"
  user.mkdir()
  cv2.imwrite(str(user / "a.png"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
  cv2.imwrite(str(user / "a_disp.png"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
  before = (user / "a_disp.png").read_bytes()
  assert main(["predict", "--weights", str(weights), "--images", str(user), "--quiet", "--out",
               str(user)]) == 2
  err = capsys.readouterr().err
  assert f"{user / 'a_disp.png'}: exists and is not an earlier output of this command" in err
  assert (user / "a_disp.png").read_bytes() == before and not list(user.glob("*.npy"))


def test_an_interrupted_predict_leaves_whole_images_and_reruns(converted, tmp_path, capsys,
                                                               monkeypatch):
  """A Ctrl-C while an image's files are written leaves that image with none of them (no
  temporary file either): the same command then runs again and writes the rest (it refused
  before, the image's .npy files being there without their PNG)."""
  from pitta_jax import predict
  rng = np.random.default_rng(2)
  d = tmp_path / "imgs"
  d.mkdir()
  for name in ("000", "001", "002"):
    cv2.imwrite(str(d / f"{name}.png"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
  encoded = []

  def interrupted(*args, **kwargs):  # the second image's PNG: after its .npy bytes are made
    encoded.append(1)
    if len(encoded) == 2:
      raise KeyboardInterrupt
    return real(*args, **kwargs)
  real = predict.image_bytes
  monkeypatch.setattr(predict, "image_bytes", interrupted)
  out = tmp_path / "o"
  with pytest.raises(KeyboardInterrupt):
    predict.predict_images(converted[0], str(d), out, quiet=True)
  assert sorted(p.name for p in out.iterdir()) == [  # image 000 whole, nothing of 001
      f"000{s}" for s in ("_depth.npy", "_disp.npy", "_disp.png")]
  monkeypatch.setattr(predict, "image_bytes", real)
  args = ["predict", "--weights", str(converted[0]), "--images", str(d), "--quiet", "--out"]
  assert main([*args, str(out)]) == 0
  assert len(list(out.iterdir())) == 9


@pytest.mark.parametrize("replaced", [False, True])
def test_a_predict_whose_out_is_removed_stops_with_one_line(converted, tmp_path, capsys,
                                                            monkeypatch, replaced):
  """--out removed (or removed and made again) after the first image: the command stops before
  the next image's files with one line naming --out (it named the .npy it could not write, or
  wrote the rest into the new directory, without its lock)."""
  import shutil
  from pitta_jax import predict
  rng = np.random.default_rng(3)
  d = tmp_path / "imgs"
  d.mkdir()
  for name in ("000", "001"):
    cv2.imwrite(str(d / f"{name}.png"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
  out, real, written = tmp_path / "o", predict.atomic_write_files, []

  def removing(folder, files):
    real(folder, files)
    written.append(1)
    shutil.rmtree(out)
    if replaced:
      out.mkdir()
  monkeypatch.setattr(predict, "atomic_write_files", removing)
  args = ["predict", "--weights", str(converted[0]), "--images", str(d), "--quiet", "--out"]
  capsys.readouterr()
  assert main([*args, str(out)]) == 2
  assert capsys.readouterr().err == (f"error: --out {out}: removed while the command ran; its "
                                     f"results are not written (run it again)\n")
  assert written == [1] and ((list(out.iterdir()) == []) if replaced else not out.exists())


def test_nothing_to_predict_and_a_non_finite_prediction_are_one_line(converted, tmp_path,
                                                                    monkeypatch, capsys):
  """--images that name only a previous run's outputs (--out there) leave nothing to predict:
  one line naming --out's directory, not "wrote 0 predictions"; a network output that is not
  finite on an image is one line naming the image, with none of its files written (nor the
  --out directory the command made)."""
  from pitta_jax import predict
  d = tmp_path / "imgs"
  d.mkdir()
  for name in ("a.png", "a_disp.png"):  # a_disp.png: with the two arrays, an earlier output
    cv2.imwrite(str(d / name), np.random.default_rng(3).integers(0, 256, (64, 96, 3),
                                                                 dtype=np.uint8))
  for name in ("a_disp.npy", "a_depth.npy"):
    np.save(d / name, np.ones((64, 96), np.float32))
  args = ["predict", "--weights", str(converted[0]), "--quiet", "--images"]
  assert main([*args, str(d / "a_*"), "--out", str(d)]) == 2
  assert capsys.readouterr().err == (f"error: {d}: no image to predict besides this command's "
                                     f"own outputs\n")
  monkeypatch.setattr(predict, "make_predictor", lambda network: lambda v, x: (
      np.full(x.shape[:3], np.nan, np.float32),) * 2)
  out = tmp_path / "o"
  assert main([*args, str(d / "a.png"), "--out", str(out)]) == 2
  assert capsys.readouterr().err == (f"error: {d / 'a.png'}: the network produced non-finite "
                                     f"outputs on this image\n")
  assert not out.exists()


def test_predict_keeps_a_users_files_reads_gray_and_globs_any_depth(converted, tmp_path, capsys):
  """A ground-truth `a_depth.npy` beside `a.png` with --out the image directory is refused, not
  replaced (it was, with exit 0); a grayscale image predicts as its channel repeated three times
  (PIL's convert("RGB"), written by cv2 as a colour image: the reference); `**` in a glob
  matches any depth of folders (KITTI's '<date>/<drive>/image_02/data')."""
  weights = converted[0]
  rng = np.random.default_rng(2)
  d = tmp_path / "gt"
  d.mkdir()
  cv2.imwrite(str(d / "a.png"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
  np.save(d / "a_depth.npy", np.full((64, 96), 7.0, np.float32))
  before = (d / "a_depth.npy").read_bytes()
  args = ["predict", "--weights", str(weights), "--quiet", "--images"]
  assert main([*args, str(d), "--out", str(d)]) == 2
  assert f"{d / 'a_depth.npy'}: exists and is not an earlier output" in capsys.readouterr().err
  assert (d / "a_depth.npy").read_bytes() == before and not (d / "a_disp.png").exists()
  gray = rng.integers(0, 256, (64, 96), dtype=np.uint8)
  tree = tmp_path / "kitti" / "2011_09_26" / "2011_09_26_drive_0001_sync" / "image_02" / "data"
  tree.mkdir(parents=True)
  cv2.imwrite(str(tree / "0000000000.png"), gray)  # one channel
  cv2.imwrite(str(tmp_path / "rgb.png"), cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
  assert main([*args, str(tmp_path / "kitti" / "**" / "image_02" / "data" / "*.png"),
               "--out", str(tmp_path / "o")]) == 0
  assert main([*args, str(tmp_path / "rgb.png"), "--out", str(tmp_path / "ref")]) == 0
  np.testing.assert_array_equal(np.load(tmp_path / "o" / "0000000000_disp.npy"),
                                np.load(tmp_path / "ref" / "rgb_disp.npy"))


def test_convert_errors_exit_2(converted, tmp_path, capsys):
  root = converted[3]
  assert main(["convert", "monodepth2", "--encoder", str(root / "depth.pth"), "--depth",
               str(root / "depth.pth"), "--out", str(tmp_path / "w")]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: ") and "depth.pth" in err and err.count("\n") == 1


def test_an_image_list_a_raw_checkpoint_folder_and_a_bad_size_are_explained(converted, tmp_path,
                                                                              monkeypatch):
  """A Depth Anything V2-style `.txt` list of images (one path per line, from the working
  directory) is read in its order; a line that is not an image is named with its number. A
  --weights folder of unconverted .pth files names the converter; a --height/--width the network
  refuses says the size the weights were trained at."""
  from pitta_jax.checkpoint import WeightsError, read_model_json
  from pitta_jax.data.errors import DataError
  from pitta_jax.predict import expand_images, predict_images
  monkeypatch.chdir(tmp_path)
  for name in ("b.png", "a.jpg"):
    cv2.imwrite(name, np.zeros((8, 8, 3), np.uint8))
  (tmp_path / "list.txt").write_text("b.png\n\na.jpg\n")
  assert expand_images("list.txt") == [Path("b.png"), Path("a.jpg")]
  (tmp_path / "notes.md").write_text("not an image")
  (tmp_path / "list.txt").write_text("b.png\nnotes.md\n")
  with pytest.raises(DataError, match=r"list\.txt: line 2: 'notes\.md' is not an image file"):
    expand_images("list.txt")
  # a path that is not there (e.g. relative to the list's folder) is said to be missing, not
  # "not an image file"
  (tmp_path / "list.txt").write_text("b.png\nframes/c.png\n")
  with pytest.raises(DataError, match=r"list\.txt: line 2: 'frames/c\.png' not found \(a "
                                      r"relative path is taken from the working directory "):
    expand_images("list.txt")
  raw = tmp_path / "mono_640x192"
  raw.mkdir()
  for name in ("encoder.pth", "depth.pth"):
    (raw / name).write_bytes(b"")
  with pytest.raises(WeightsError, match=r"model\.json: not found; .* holds PyTorch files "
                     r"\(depth\.pth, encoder\.pth\): convert them first, e\.g\. `pitta-jax "
                     r"convert monodepth2"):
    read_model_json(raw)
  with pytest.raises(ValueError, match=r"--height/--width: input size 320x100 .*; these "
                     r"weights were trained at \d+x\d+$"):
    predict_images(converted[0], "b.png", tmp_path / "o", size=(100, 320))
  # a size no frame has (OpenCV ran out of memory with a traceback)
  assert main(["predict", "--weights", str(converted[0]), "--images", "b.png", "--out",
               str(tmp_path / "big"), "--height", "3200000", "--width", "3200000"]) == 2
  assert not (tmp_path / "big").exists()


def test_an_undecodable_image_is_one_line_without_opencvs_logs(converted, tmp_path, capfd):
  """A PNG that is only its signature: OpenCV logs a WARN and an ERROR line of its own to the
  process's stderr while decoding it; the command silences them, so the reader's line is all."""
  d = tmp_path / "imgs"
  d.mkdir()
  (d / "a.png").write_bytes(b"\x89PNG\r\n\x1a\n")
  assert main(["predict", "--weights", str(converted[0]), "--images", str(d), "--quiet",
               "--out", str(tmp_path / "o")]) == 2
  err = capfd.readouterr().err
  assert err == f"error: {d / 'a.png'}: cannot decode image (a PNG file cut short: no IEND chunk)\n"
  # a PNG cut short mid-data: libpng printed its own line ('PNG input buffer is incomplete')
  _, png = cv2.imencode(".png", np.full((16, 16, 3), 7, np.uint8))
  (d / "a.png").write_bytes(png.tobytes()[:-20])
  assert main(["predict", "--weights", str(converted[0]), "--images", str(d), "--quiet",
               "--out", str(tmp_path / "o")]) == 2
  err = capfd.readouterr().err
  assert err == f"error: {d / 'a.png'}: cannot decode image (a PNG file cut short: no IEND chunk)\n"
  # a JPEG that is not one: OpenCV's logs are silenced, the reader's line is all
  (d / "a.png").unlink()
  (d / "b.jpg").write_bytes(b"\xff\xd8\xff not a jpeg")
  assert main(["predict", "--weights", str(converted[0]), "--images", str(d), "--quiet",
               "--out", str(tmp_path / "o")]) == 2
  err = capfd.readouterr().err
  assert err == f"error: {d / 'b.jpg'}: cannot decode image (not a PNG/JPEG file, or truncated)\n"


def test_disparity_pictures_are_monodepth2s_colour_map_byte_for_byte():
  """viz.colorize against MonoDepth2's test_simple.py, written as it is there: vmax the 95th
  percentile, matplotlib's Normalize(min, vmax) and 'magma' ScalarMappable, RGB * 255 to uint8.
  OpenCV's magma table (with floor(255 x) indexing) had been a level or two off on 93% of the
  pixels."""
  import matplotlib as mpl
  import matplotlib.cm as cm
  from pitta_jax import viz
  rng = np.random.default_rng(0)
  for disp in (rng.uniform(0.01, 0.3, (48, 160)).astype(np.float32),
               rng.gamma(2.0, 0.05, (37, 91)).astype(np.float32)):
    vmax = np.percentile(disp, 95)
    normalizer = mpl.colors.Normalize(vmin=disp.min(), vmax=vmax)
    mapper = cm.ScalarMappable(norm=normalizer, cmap="magma")
    want = (mapper.to_rgba(disp)[:, :, :3] * 255).astype(np.uint8)
    np.testing.assert_array_equal(viz.colorize(disp), want)
  # a depth map all beyond max_depth (its disparities below vmin = 1 / max_depth): every pixel
  # takes the bottom colour (matplotlib's Normalize refuses vmin > vmax)
  far = viz.colorize_depth(np.full((4, 4), 200.0))
  np.testing.assert_array_equal(far, np.broadcast_to(
      (np.asarray(mpl.colormaps["magma"](0.0))[:3] * 255).astype(np.uint8), (4, 4, 3)))
