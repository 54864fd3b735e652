"""`adapt` refuses data a method cannot use, before any work: one line, exit 2, nothing written.

A method declares what it needs besides images (`Method.needs`: "pose", "intrinsics",
"previous_frame"); the CLI checks the reader's metadata (no frame is read, no weights are
loaded), the synthetic options, the replay root and the weights' model.json. Two stand-in
methods are registered for the test (the real ones, CoMoDa and Ada-Depth, live elsewhere);
the weights directory holds only a model.json, so any run that got past the checks would fail
on loading the weights, not on a need.
"""

from __future__ import annotations

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

from pitta_jax import methods
from pitta_jax.cli import main
from pitta_jax.methods.base import Aux, Method
from pitta_jax.sources import check_run_needs
from test_layouts import make_foggy, make_raw
from test_readers import _rgb, _write_rgb


@dataclasses.dataclass(frozen=True)
class StandInConfig:
  pass


def _stand_in(name: str, needs: tuple[str, ...]):
  def build(config: StandInConfig) -> Method:
    def loss(trainable, *, frame, **_):
      return jnp.zeros(()), Aux(frame.image[..., 0], {})
    return Method(name, config, init=lambda *a: {}, loss=loss, prepare=lambda *a: {},
                  needs=needs)
  return StandInConfig, build


@pytest.fixture
def cli(tmp_path, monkeypatch, capsys):
  monkeypatch.setitem(methods.METHODS, "needy",
                      _stand_in("needy", ("intrinsics", "previous_frame")))
  monkeypatch.setitem(methods.METHODS, "posey", _stand_in("posey", ("pose",)))
  weights = tmp_path / "weights"
  weights.mkdir()
  (weights / "model.json").write_text(json.dumps(
      {"architecture": "monodepth2", "height": 64, "width": 96, "num_layers": 18,
       "has_pose": False}))
  for name, n, calib in (("seq", 3, True), ("nocalib", 3, False), ("one", 1, True)):
    for k in range(n):
      _write_rgb(tmp_path / name / f"{k:06d}.png", _rgb(k))
    if calib:
      (tmp_path / name / "calib.json").write_text(json.dumps(
          {"K": [[8.0, 0, 4], [0, 8, 3], [0, 0, 1]], "width": 8, "height": 6}))
  make_foggy(tmp_path / "ds")
  make_raw(tmp_path / "raw")
  (tmp_path / "bogus.npz").write_bytes(b"not a zip")

  def run(*args: str) -> tuple[int, str]:
    out = tmp_path / "out"
    rc = main(["adapt", "--weights", str(weights), "--out", str(out), "--quiet",
               *[a.replace("TMP", str(tmp_path)) for a in args]])
    err = capsys.readouterr().err
    assert not out.exists()  # nothing written, not even the directory
    return rc, err

  run.weights = weights

  return run


@pytest.mark.parametrize("args, message", [
    (("--method", "needy", "--dataset", "folder", "--root", "TMP/seq", "--source-images",
      "TMP/seq"),
     "--method needy needs consecutive frames (each frame's previous one), and the order of "
     "dataset folder is not known to be capture order: provide --option temporal=true when the "
     "images are consecutive video frames in file-name order"),
    (("--method", "needy", "--dataset", "folder", "--root", "TMP/nocalib", "--option",
      "temporal=true", "--source-images", "TMP/seq"),
     "--method needy needs camera intrinsics K for every frame, and frame 000000 of dataset "
     "folder has none: provide a calib.json ({\"K\": 3x3, \"width\": W, \"height\": H}) in "
     "--root or --option calib=FILE"),
    (("--method", "needy", "--dataset", "folder", "--root", "TMP/one", "--option",
      "temporal=true", "--source-images", "TMP/seq"),
     "--method needy needs consecutive frames (each frame's previous one), and dataset folder "
     "has 1 frame(s): provide at least 2 frames"),
    (("--method", "needy", "--dataset", "drivingstereo", "--root", "TMP/ds", "--option",
      "weather=foggy", "--source-images", "TMP/seq"),
     "--method needy needs camera intrinsics K for every frame, and frame foggy/"
     "2018-10-25-07-37-26_2018-10-25-07-37-40-000 of dataset drivingstereo has none: provide "
     "DrivingStereo's calibration files <seq>.txt (half-image-calib/ or full-image-calib/ of "
     "the calibration download) in --root or --root/calib/, or --option calib_dir=DIR"),
    (("--method", "needy", "--dataset", "synthetic", "--option", "num_frames=1"),
     "--method needy needs consecutive frames (each frame's previous one), and the synthetic "
     "sequence has 1 frame(s): provide --option num_frames=N with N >= 2"),
    (("--method", "needy", "--dataset", "folder", "--root", "TMP/seq", "--option",
      "temporal=true", "--replay-root", "TMP/nowhere"),
     "TMP/nowhere: KITTI raw root (--replay-root) not found"),
    (("--method", "needy", "--dataset", "folder", "--root", "TMP/seq", "--option",
      "temporal=true", "--replay-root", "TMP/raw"),
     "--method needy needs camera intrinsics K for every frame, and frame 2011_09_28/"
     "2011_09_28_drive_0005_sync/image_02/0000000000 of --replay-root TMP/raw has none: "
     "provide KITTI raw's <date>/calib_cam_to_cam.txt (the date's calibration download) in "
     "--root"),
    (("--method", "needy", "--dataset", "folder", "--root", "TMP/seq", "--option",
      "temporal=true"),
     "--method needy needs source-domain data: --source-images PATH or --replay-root DIR"),
    (("--method", "actmad", "--bn-stats", "running", "--dataset", "folder", "--root", "TMP/seq"),
     "--method actmad needs source-domain data: --source-images PATH, --source-stats FILE or "
     "--replay-root DIR"),
    (("--method", "needy", "--dataset", "synthetic", "--option", "height=32"),
     "--option height: the synthetic frames are rendered at the weights' input size (their "
     "model.json height and width)"),
    (("--method", "posey", "--dataset", "synthetic"),
     "--method posey needs a pose network, and the weights have none (convert with "
     "--pose-encoder/--pose, or train-source)"),
    (("--method", "needy", "--dataset", "synthetic", "--source-stats", "TMP/bogus.npz"),
     "TMP/bogus.npz: holds ActMAD's source statistics; --method needy does not use them (drop "
     "--source-stats)"),
    (("--method", "actmad", "--bn-stats", "running", "--dataset", "synthetic", "--source-stats",
      "TMP/bogus.npz"),
     "TMP/bogus.npz: not an .npz file (write one with `pitta-jax source-stats`)"),
    (("--method", "actmad", "--bn-stats", "running", "--dataset", "synthetic", "--source-stats",
      "TMP/bogus.npz", "--source-images", "TMP/seq"),
     "--source-images and --source-stats: --source-stats holds the statistics the source data "
     "would give; give one of them"),
    # the dataset flags themselves (`check_dataset_args`, `check_run_needs`): each mistake is
    # named before the weights load, not met as the weights' (or a reader's) error later
    (("--dataset", "synthetic", "--segmentation", "png:TMP/seq"),
     "the synthetic benchmark carries exact panoptic maps: use --segmentation gt"),
    (("--dataset", "folder"), "--root is required for dataset folder"),
    (("--dataset", "synthetic", "--root", "TMP/seq"),
     "--root TMP/seq: for real datasets (the synthetic benchmark is generated); drop it or name "
     "the dataset with --dataset"),
    (("--dataset", "folder", "--root", "TMP/seq", "--segmentation", "png"),
     "--segmentation png:DIR needs a directory"),
    # gt with a directory (a mistyped png:DIR) read no directory and went on with gt's maps
    (("--dataset", "folder", "--root", "TMP/seq", "--segmentation", "gt:TMP/seq"),
     "--segmentation 'gt:TMP/seq': gt takes no directory (the dataset's own panoptic maps); "
     "png:DIR reads maps from DIR"),
    (("--dataset", "synthetic", "--option", "num_frames=0"),
     "--option num_frames=0: the synthetic sequence has no frames"),
    # a negative count named as the option it is (was "synthetic options: num_frames must be
    # >= 0, got -3", where 0 is refused too)
    (("--dataset", "synthetic", "--option", "num_frames=-3"),
     "--option num_frames=-3: the synthetic sequence has no frames"),
    (("--dataset", "synthetic", "--option", "=3"), "--option '=3' is not KEY=VALUE"),
])
def test_unmet_needs_fail_before_work(cli, tmp_path, args, message):
  rc, err = cli(*args)
  assert rc == 2
  assert err == f"error: {message.replace('TMP', str(tmp_path))}\n"


def test_met_needs_and_notes(cli, tmp_path, capsys):
  # the check passes: a temporal folder with calib.json, its reader returned for the run
  needy = methods.build("needy")
  reader = check_run_needs(needy, "folder", str(tmp_path / "seq"), ["temporal=true"], "gt",
                           str(tmp_path / "raw" / "2011_09_26"), source_given=True)
  assert reader.temporal and len(reader) == 3
  np.testing.assert_array_equal(reader[0].intrinsics, [[8, 0, 4], [0, 8, 3], [0, 0, 1]])
  # a replay drive with missing frames is read in runs; its note reaches the run's notes once
  drive = tmp_path / "raw" / "2011_09_26" / "2011_09_26_drive_0001_sync" / "image_02" / "data"
  first = sorted(drive.iterdir())[0]
  first.rename(drive / f"0000000007{first.suffix}")
  notes = []
  check_run_needs(needy, "folder", str(tmp_path / "seq"), ["temporal=true"], "gt",
                  str(tmp_path / "raw" / "2011_09_26"), source_given=True, notes=notes)
  assert len(notes) == 1 and notes[0].startswith(
      "--replay-root: 2011_09_26/2011_09_26_drive_0001_sync: frame numbers jump after ")
  # DrivingStereo with full size only: the reader says so, the unused replay root is named; the
  # run then stops at the weights (only a model.json here), as any checked run would
  rc, err = cli("--dataset", "drivingstereo", "--root", "TMP/ds", "--option", "weather=foggy",
                "--replay-root", "TMP/nowhere")
  lines = err.splitlines()
  assert rc == 2 and lines[:2] == [
      "note: --method pitta uses no source-domain data: --replay-root ignored",
      "note: DrivingStereo size=full: the only left-image-*-size/ directory (foggy)"]
  assert lines[2] == ("note: dataset drivingstereo has no panoptic maps: no frame has instances, "
                      "so L_d (eq. 8) is 0 (--segmentation png:DIR or mask2former:DIR)")
  assert len(lines) == 4 and lines[3].startswith("error: ") and "weights" in lines[3]


def test_evaluation_without_ground_truth_is_refused_before_work(cli, tmp_path, capsys):
  """`evaluate` on frames none of which has ground truth has nothing to do: one line, exit 2,
  before the weights load (here only a model.json); `adapt` runs with a note instead."""
  out = tmp_path / "ev"
  assert main(["evaluate", "--weights", str(tmp_path / "weights"), "--dataset", "folder",
               "--root", str(tmp_path / "seq"), "--out", str(out), "--quiet"]) == 2
  assert capsys.readouterr().err == ("error: dataset folder has no ground-truth depth to "
                                     "evaluate against (--option depth_dir=DIR)\n")
  assert not out.exists()


def test_a_loss_with_l_d_on_frames_without_panoptic_maps_is_noted(cli):
  """PITTA (and a baseline + L_d) on a dataset without panoptic maps under --segmentation gt
  has no instances, so L_d is 0 on every frame: a note says so before any work (the run went
  on silently); PITTA with L_e only (lambda = inf) and no adaptation need no maps."""
  no_maps = ("note: dataset folder has no panoptic maps: no frame has instances, so L_d (eq. 8) "
             "is 0 (--option panoptic_dir=DIR, --segmentation png:DIR or mask2former:DIR)")
  cotta = ("--method", "cotta", "--bn-stats", "running")
  for flags, noted in [((), True), (cotta, True),
                       ((*cotta, "--cotta.ld-weight", "0"), False),
                       (("--lam", "inf"), False), (("--method", "none"), False)]:
    rc, err = cli("--dataset", "folder", "--root", "TMP/seq", *flags)
    assert rc == 2 and (no_maps in err.splitlines()) == noted, (flags, err)
  # CoMoDa masks the moving objects out of its own loss: without L_d it still needs the maps
  # (weights with a pose network, named by their model.json only: the run stops at loading them)
  posed = cli.weights.parent / "posed"
  posed.mkdir()
  (posed / "model.json").write_text(json.dumps(
      {**json.loads((cli.weights / "model.json").read_text()), "has_pose": True}))
  comoda = ("--method", "comoda", "--bn-stats", "running", "--selector", "no_bn", "--weights",
            str(posed), "--option", "temporal=true", "--replay-root", "TMP/raw/2011_09_26")
  mask = "CoMoDa's loss masks no moving object"
  for flags, said in [(comoda, f"L_d (eq. 8) is 0 and {mask}"),
                      ((*comoda, "--comoda.ld-weight", "0"), mask)]:
    rc, err = cli("--dataset", "folder", "--root", "TMP/seq", *flags)
    note = (f"note: dataset folder has no panoptic maps: no frame has instances, so {said} "
            f"(--option panoptic_dir=DIR, --segmentation png:DIR or mask2former:DIR)")
    assert rc == 2 and note in err.splitlines(), (flags, err)


def test_flags_beyond_any_use_are_refused_before_work(capsys, tmp_path):
  """Tables larger than any frame needs (10^9 segments was killed for memory after a minute,
  10^9 instances asked for 25 TB after 15 s of compiling) and a momentum Adam would ignore
  are one line naming the flags, before any work."""
  out = str(tmp_path / "unused")  # never made: each command is refused before
  for flags, message in [
      (("--max-segments", "4097"), "--adapt.max-segments: max_segments must be in 1..4096, got "
                                   "4097"),
      (("--max-instances", "1025"), "--pitta.ld.max-instances: max_instances must be an int in "
                                    "1..1024, got 1025"),
      # both overflowed int32 when the step was called, after the weights had loaded
      (("--reset-every", "3000000000"), "--adapt.reset-every: reset_every must be in [0, 2^31), "
                                        "got 3000000000"),
      (("--method", "cotta", "--bn-stats", "running", "--cotta.n-augment", "1000000000000"),
       "--cotta.n-augment: n_augment must be in 1..1024, got 1000000000000"),
      # 2^32 overflowed fold_in's uint32 after the weights loaded (a traceback); 3e9 unrolled
      # the step that many times before any frame ran
      (("--adapt.steps-per-frame", "4294967296"), "--adapt.steps-per-frame: steps_per_frame "
                                                  "must be in 1..1024, got 4294967296"),
      (("--momentum", "0.9"), "--adapt.optimizer, --adapt.momentum: momentum applies to "
                              "optimizer sgd only, got momentum 0.9 with adam")]:
    assert main(["adapt", "--dataset", "synthetic", "--quiet", "--out", out, *flags]) == 2
    assert capsys.readouterr().err == f"error: {message}\n"
  assert main(["adapt", "--dataset", "synthetic", "--quiet", "--out", out, "--momentum",
               "0.9", "--optimizer", "sgd", "--lr", "nan"]) == 2  # sgd takes it: the lr fails
  assert "momentum" not in capsys.readouterr().err


def test_python_m_weights_convert_errors_are_one_line(capsys, tmp_path):
  """`python -m weights_convert` reports as `pitta-jax convert` does: a usage error is one line
  (it printed argparse's usage block first), --debug is a flag, and a converter's flags are
  checked before its checkpoint is read (the file here does not exist)."""
  from weights_convert.cli import main as convert_main
  missing, out = str(tmp_path / "missing.pth"), str(tmp_path / "out")
  with pytest.raises(SystemExit) as usage:
    convert_main(["monodepth2", "--encoder", missing])
  assert usage.value.code == 2 and capsys.readouterr().err == ("error: the following arguments are required: --depth, "
                                     "--out (see python -m weights_convert monodepth2 --help)\n")
  for flags, message in [
      (("sgdepth", "--model", missing, "--height", "0", "--width", "0"),
       "--height/--width: input size 0x0 (WxH) is not supported by sgdepth: width and height "
       "must be positive multiples of 32 (default 640x192)"),
      (("depth-anything-v2", "--from", "official", missing, "--num-heads", "0"),
       "num_heads (--num-heads) must be a positive int, got 0"),
      (("depth-anything-v2", "--from", "official", missing, "--layer-idx=-1,3"),
       "layer_idx (--layer-idx) must be increasing 0-based block numbers, got [-1, 3]"),
      (("depth-anything-v2", "--from", "official", missing, "--layer-idx", "a,b"),
       "argument --layer-idx: expected comma-separated block numbers such as 2,5,8,11, got "
       "'a,b' (see python -m weights_convert depth-anything-v2 --help)"),
      (("depth-anything-v2", "--from", "official", missing, "--max-depth", "nan"),
       "max_depth (--max-depth) must be > 0 (metres), got nan")]:
    try:
      rc = convert_main([*flags, "--out", out])
    except SystemExit as e:  # argparse's own (a flag's type)
      rc = e.code
    assert rc == 2 and capsys.readouterr().err == f"error: {message}\n"
  with pytest.raises(Exception, match="no such file"):  # --debug: the traceback
    convert_main(["--debug", "sgdepth", "--model", missing, "--out", out])


def test_audit_messages_name_the_cause(capsys, tmp_path):
  """Messages that named the wrong flag or cause: a figure too large named only --dpi, Depth
  Anything V2 without --weights spoke of train-source, predict's negative --height named an
  internal input_size, an unknown flag pointed at pitta-jax --help instead of the command's,
  and a 16-bit colour depth PNG was asked whether it was 8-bit."""
  import cv2
  from pitta_jax.data.image_io import read_depth_png
  from pitta_jax.data.errors import DataError
  assert main(["demo", "--demo.figures.fig-width", "1e9"]) == 2
  assert capsys.readouterr().err.startswith(
      "error: --demo.figures.fig-width, --demo.figures.fig-height, --demo.figures.dpi: ")
  assert main(["adapt", "--dataset", "synthetic", "--model", "depth_anything_v2", "--quiet",
               "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err.startswith("error: --model depth_anything_v2 needs --weights")
  assert main(["predict", "--weights", str(tmp_path), "--images", str(tmp_path), "--height",
               "-64", "--width", "96", "--out", str(tmp_path / "p")]) == 2
  assert capsys.readouterr().err == "error: --height/--width must be positive, got -64x96\n"
  with pytest.raises(SystemExit) as usage:  # the command's own --help lists its flags
    main(["evaluate", "--dataset", "synthetic", "--lr", "0.1"])
  assert usage.value.code == 2 and capsys.readouterr().err == (
      "error: unrecognized arguments: --lr 0.1 (see pitta-jax evaluate --help)\n")
  for argv, message in [  # a converter's own help; pitta-jax's flag after the command
      (["convert", "sgdepth", "--model", "m.pth", "--out", "o", "--bogus"],
       "unrecognized arguments: --bogus (see pitta-jax convert sgdepth --help)"),
      (["adapt", "--dataset", "synthetic", "--debug"],
       "--debug goes before the command: pitta-jax --debug adapt ... (see pitta-jax --help)")]:
    with pytest.raises(SystemExit):
      main(argv)
    assert capsys.readouterr().err == f"error: {message}\n"
  png = tmp_path / "d.png"
  cv2.imwrite(str(png), np.zeros((4, 5, 3), np.uint16))
  with pytest.raises(DataError) as e:
    read_depth_png(png)
  assert str(e.value).endswith("got uint16 with 3 channel(s)")


def test_dynamic_classes_must_be_coco_ids(cli):
  rc, err = cli("--dataset", "synthetic", "--dynamic-classes", "9999,-5")
  assert rc == 2 and err == ("error: --pitta.ld.dynamic-classes: not COCO panoptic category ids: "
                             "9999, -5 "
                             "(ids 1-200, 133 of them; names such as car work too)\n")


def test_a_window_as_wide_as_the_frames_smaller_side_is_allowed():
  # Hand values at the bound: a 5-pixel window on a 5x8 frame is taken, on a 4x8 frame refused.
  from pitta_jax.methods.depth_refining import DepthRefiningConfig, _check_window
  _check_window(DepthRefiningConfig(window=5), (5, 8))
  with pytest.raises(ValueError, match=r"window 5 exceeds the frame's smaller side \(4 pixels "
                                       r"of 8x4\)"):
    _check_window(DepthRefiningConfig(window=5), (4, 8))


def test_train_source_refuses_a_resnet_depth_for_a_network_without_a_resnet(capsys,
                                                                            monkeypatch):
  """--source.num-layers is the ResNet depth of the networks with a ResNet encoder: for Lite-Mono
  or MonoViT it was accepted and ignored, and the same network trained again (tens of minutes)
  under a cache name saying `_r34_`. Refused before training, naming the flags; ResNet networks
  take it (the check passes on to the next flag's)."""
  import pitta_jax.source_model as source_model
  monkeypatch.setattr(source_model, "load_or_train_source",
                      lambda *a, **k: pytest.fail("training started"))
  for model in ("litemono", "monovit"):
    assert main(["train-source", "--source.model", model, "--source.num-layers", "34"]) == 2
    assert capsys.readouterr().err == (f"error: --source.model, --source.num-layers: num_layers "
                                       f"34 does not apply to model {model}: it has no ResNet "
                                       f"encoder\n")
  for model in ("monodepth2", "sgdepth", "hrdepth"):
    assert main(["train-source", "--source.model", model, "--source.num-layers", "34",
                 "--source.steps", "0"]) == 2
    assert capsys.readouterr().err == "error: --source.steps: steps must be >= 1, got 0\n"
  assert source_model.SourceConfig(model="litemono").network_config() == \
      source_model.SourceConfig(model="litemono", num_layers=18).network_config()


def test_a_config_check_names_the_flag(capsys, tmp_path):
  """A field's check, raised by its config class, is reported with the flag that sets it (it
  named the field: 'steps, batch_size and ... must be >= 1' for --source.steps 0)."""
  out = str(tmp_path / "unused")  # never made: each command is refused before
  from pitta_jax.cli import main
  assert main(["train-source", "--source.steps", "0"]) == 2
  assert capsys.readouterr().err == "error: --source.steps: steps must be >= 1, got 0\n"
  assert main(["train-source", "--source.pose-fraction", "2"]) == 2
  assert capsys.readouterr().err == ("error: --source.pose-fraction: pose_fraction must be in "
                                     "[0, 1], got 2.0\n")
  # a median window wider than the frame (it ran for minutes per frame), an empty --out (the
  # working directory), a reader option given twice (the last one won)
  for flags, message in [
      (("--window", "641", "--out", out), "window 641 exceeds the frame's smaller side (96 "
                                               "pixels of 320x96)"),
      (("--out", ""), "--out: an empty path"),
      (("--option", "domain=fog", "--option", "domain=rain", "--out", out),
       "--option domain given twice (fog, rain): give it once")]:
    assert main(["adapt", "--dataset", "synthetic", "--quiet", *flags]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == f"error: {message}"
  # a seed jax.random.PRNGKey cannot take (it raised OverflowError after the weights loaded)
  for seed in ("-1", str(2**63)):
    assert main(["adapt", "--dataset", "synthetic", "--out", out, "--seed", seed]) == 2
    assert capsys.readouterr().err == (f"error: --adapt.seed: seed must be in [0, 2^63), got "
                                       f"{seed}\n")


def test_depth_refining_config_takes_coco_names_and_refuses_non_integers():
  """The API as the CLI: COCO names become their ids (car = 3, person = 1); a float class id
  (3.7 would have become car in the instance table), a float window or table size are refused
  at construction, not when the step is traced."""
  from pitta_jax.methods.depth_refining import DepthRefiningConfig
  assert DepthRefiningConfig(dynamic_classes=("car", 1, np.int64(2))).dynamic_classes == (3, 1, 2)
  for kwargs, message in [
      ({"dynamic_classes": (3.7,)}, r"dynamic_classes: 3\.7 is neither a COCO id \(int\) nor a "
                                    r"COCO name"),
      ({"dynamic_classes": ("carr",)}, r"no COCO panoptic category named 'carr' \(did you mean "
                                       r"car, carrot\?\)"),
      ({"window": 3.0}, r"window must be an integer, got 3\.0"),
      ({"max_instances": 2.0}, r"max_instances must be an integer, got 2\.0")]:
    with pytest.raises(ValueError, match=message):
      DepthRefiningConfig(**kwargs)


def test_configs_refuse_values_of_another_type():
  """Configs built in Python check their fields' types as the CLI's parser does: a float chunk
  size or seed was taken (and failed when traced), skip_nonfinite="no" is truthy and left the
  guard on, a string table size failed with a bare TypeError."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.methods.adadepth import AdadepthConfig
  from pitta_jax.run import EvalConfig
  for kwargs, message in [
      ({"chunk_size": 2.5}, r"chunk_size must be an integer, got 2\.5"),
      ({"seed": 1.5}, r"seed must be an integer, got 1\.5"),
      ({"steps_per_frame": True}, r"steps_per_frame must be an integer, got True"),
      ({"skip_nonfinite": "no"}, r"skip_nonfinite must be true or false, got 'no'"),
      ({"max_segments": "64"}, r"max_segments must be an integer, got '64'"),
      ({"lr": True}, r"lr must be a number, got True"),
      ({"method": 3}, r"method must be a string, got 3")]:
    with pytest.raises(ValueError, match=message):
      AdaptConfig(**kwargs)
  assert AdaptConfig(seed=np.int64(3), lr=np.float32(1e-3), chunk_size=4).seed == 3
  with pytest.raises(ValueError, match=r"garg_crop must be true or false, got 1"):
    EvalConfig(garg_crop=1)
  from pitta_jax.source_model import SourceConfig  # train-source's: refused before any work
  for kwargs, message in [({"seed": -1}, r"seed must be in \[0, 2\^63\), got -1"),
                          ({"seed": 2**64}, r"seed must be in \[0, 2\^63\)"),
                          ({"num_layers": 19}, r"num_layers must be one of \[18, 34, 50\]"),
                          ({"steps": 2.5}, r"steps must be an integer, got 2\.5")]:
    with pytest.raises(ValueError, match=message):
      SourceConfig(**kwargs)
  assert AdadepthConfig(depth_scale=None).depth_scale is None
  with pytest.raises(ValueError, match=r"depth_scale must be a number or unset, got 'x'"):
    AdadepthConfig(depth_scale="x")


@pytest.mark.parametrize("model_json, flags, noted", [
    ({"use_stereo": False}, (), True),
    ({"use_stereo": False}, ("--adadepth.depth-scale", "30"), False),
    ({"use_stereo": True}, (), False),
])
def test_metre_thresholds_on_weights_up_to_scale_are_noted(tmp_path, capsys, model_json, flags,
                                                           noted):
  """Ada-Depth's thresholds are in metres: monocular weights give no factor to metres, so the
  run notes that their units are taken as metres (the factor is 5.4 for stereo-trained weights;
  a given --adadepth.depth-scale is the user's). The run then stops at the weights (a model.json
  only) after its notes."""
  weights = tmp_path / "weights"
  weights.mkdir()
  (weights / "model.json").write_text(json.dumps(
      {"architecture": "monodepth2", "height": 64, "width": 96, "num_layers": 18,
       "has_pose": True, **model_json}))
  rc = main(["adapt", "--weights", str(weights), "--out", str(tmp_path / "out"), "--quiet",
             "--method", "adadepth", "--bn-stats", "running", "--dataset", "synthetic", *flags])
  lines = capsys.readouterr().err.splitlines()
  note = ("note: --method adadepth's thresholds are in metres and these weights predict depth up "
          "to scale (no stereo pairs in training): their units are taken as metres; "
          "--adadepth.depth-scale F sets the factor")
  assert rc == 2 and lines[-1].startswith("error: ") and "weights" in lines[-1]
  assert (note in lines) == noted


def test_an_unusable_cache_directory_is_named(tmp_path, monkeypatch, capsys):
  """$PITTA_JAX_CACHE pointing at a file: one line naming the variable (it printed OSError's
  bare text, without saying which setting was wrong)."""
  from pitta_jax.cli import main
  from pitta_jax.source_model import CACHE_ENV
  blocker = tmp_path / "file"
  blocker.write_text("x")
  monkeypatch.setenv(CACHE_ENV, str(blocker))
  assert main(["adapt", "--dataset", "synthetic", "--quiet", "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and err.startswith(f"error: {blocker}")
  assert f"set ${CACHE_ENV} to a writable directory" in err


def test_train_source_refuses_an_unwritable_cache_before_training(tmp_path, monkeypatch,
                                                                   capsys):
  """train-source writes its model under the cache root: one that cannot be written is named,
  with the fix, before the training (it failed with OSError's bare text after it)."""
  from pitta_jax import source_model
  from pitta_jax.cli import main
  blocker = tmp_path / "file"
  blocker.write_text("x")
  monkeypatch.setenv(source_model.CACHE_ENV, str(blocker))
  monkeypatch.setattr(source_model, "train_source",
                      lambda *a, **k: pytest.fail("trained before the cache was checked"))
  assert main(["train-source", "--retrain", "--quiet"]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and err.startswith(f"error: {blocker}")
  assert f"set ${source_model.CACHE_ENV} to a writable directory" in err


def test_a_file_where_checkpoints_go_is_refused_before_work(cli, tmp_path, capsys):
  """--checkpoint-every K writes OUT/checkpoints/: a file of that name is one line naming it,
  before the weights load (here only a model.json), and is left as it was; without the flag
  the file is no concern of the run (it goes on, to the weights)."""
  out = tmp_path / "out"
  out.mkdir()
  (out / "checkpoints").write_text("mine")
  argv = ["adapt", "--weights", str(tmp_path / "weights"), "--out", str(out), "--quiet",
          "--dataset", "synthetic"]
  assert main([*argv, "--checkpoint-every", "2"]) == 2
  assert capsys.readouterr().err == (f"error: {out / 'checkpoints'}: is a file; "
                                     "--checkpoint-every writes a directory there\n")
  assert (out / "checkpoints").read_text() == "mine"
  assert main(argv) == 2
  err = capsys.readouterr().err
  assert "is a file" not in err and err.startswith(f"error: {tmp_path / 'weights'}")


def test_input_sizes_are_checked_at_their_bounds(tmp_path, capsys):
  """predict's --height/--width (segment's share the check): 0 is not a size, and MAX_SIDE
  pixels on a side is the largest taken (one more is refused); the checks come before the
  weights (here an empty directory), so a size that passes them fails on the weights instead."""
  from pitta_jax.models.spec import MAX_SIDE
  argv = ["predict", "--weights", str(tmp_path), "--images", str(tmp_path), "--out",
          str(tmp_path / "p")]
  assert main([*argv, "--height", "0", "--width", "96"]) == 2
  assert capsys.readouterr().err == "error: --height/--width must be positive, got 0x96\n"
  assert main([*argv, "--height", "64", "--width", str(MAX_SIDE + 1)]) == 2
  assert capsys.readouterr().err == (f"error: --height/--width: 64x{MAX_SIDE + 1} is more than "
                                     f"{MAX_SIDE} pixels on a side\n")
  assert main([*argv, "--height", str(MAX_SIDE), "--width", str(MAX_SIDE)]) == 2
  err = capsys.readouterr().err
  assert "pixels on a side" not in err and "model.json" in err
  assert not (tmp_path / "p").exists()


def test_ship_into_a_package_it_cannot_write_is_refused_before_training(monkeypatch, capsys):
  """`train-source --ship` writes into the package (pitta_jax/assets/): where that is not
  writable (an installed wheel) it is one line naming --ship, before the training it would
  follow; where it is, the model trains, then ships. (Root may write anywhere: the test makes
  the package's folder read-only to `os.access`, the check the command makes.)"""
  import os
  from pathlib import Path
  from pitta_jax import source_model
  calls = []
  monkeypatch.setattr(source_model, "load_or_train_source",
                      lambda cfg, **k: calls.append("train") or (None, {"weights_dir": "w"}))
  monkeypatch.setattr(source_model, "ship_source", lambda cfg, **k: calls.append("ship") or "s")
  real_access = os.access
  package = {source_model.ASSETS, source_model.ASSETS.parent}
  monkeypatch.setattr(os, "access", lambda path, mode: Path(path) not in package
                      and real_access(path, mode))
  assert main(["train-source", "--ship", "--quiet"]) == 2
  assert capsys.readouterr().err == (f"error: --ship: {source_model.ASSETS} is not writable "
                                     f"(ship from a source checkout)\n")
  assert calls == []
  monkeypatch.setattr(os, "access", real_access)
  assert main(["train-source", "--ship", "--quiet"]) == 0
  assert calls == ["train", "ship"] and capsys.readouterr().out.endswith("shipped: s\n")
