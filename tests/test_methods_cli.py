"""The pose-based baselines from the CLI on a DrivingStereo-layout dataset (images, depth,
panoptic PNGs, calibration as the official download lays them out) with a KITTI raw replay root:
results.json with the method's own logs.

CoMoDa (pose net, K, previous frames, replay) and Ada-Depth (the same minus the replay), each on
the tiny network with its pose network (`tiny_net`, registered as a user registers one): what is
under test is the data path, not the networks, whose steps on MonoDepth2's ResNet-18 compile for
30 s and more each here. The engine-level bitwise reproducibility and the PyTorch one-step references
of every method on MonoDepth2 are in its own test file, and `OWN_LOGS` names every registered
method's own log.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pitta_jax.cli import main
from pitta_jax.methods import METHODS

H, W, N = 64, 96, 2  # the second frame pairs with the first (previous frame, pose)
OWN_LOGS = {"pitta": "loss_e", "comoda": "loss_comoda", "adadepth": "loss_adadepth",
            "actmad": "loss_actmad", "cotta": "loss_cotta"}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
  """A foggy DrivingStereo subset (N consecutive frames, full size only, with calibration), a
  KITTI raw replay root, random weights of the tiny network with its pose network (`tiny_net`,
  registered for this module as a user registers a network: the data path, not the network,
  is under test here; MonoDepth2's ResNet-18 pose and depth networks made this CoMoDa run's
  compile for ~30 s), and a source image folder."""
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.data.image_io import write_image
  from pitta_jax.data.synthetic import SyntheticConfig, export_drivingstereo, generate_sequence
  from tiny_net import SPEC, registered, tiny_pose_variables, tiny_variables
  root = tmp_path_factory.mktemp("ds")
  export_drivingstereo(generate_sequence(SyntheticConfig(height=H, width=W, num_frames=N,
                                                         domain="fog", seed=7)), root, "foggy")
  # source domain: clear frames as images (ActMAD, CoTTA) and as a KITTI raw drive (CoMoDa)
  source = root / "source"
  date = root / "kitti" / "2011_09_26"
  clear = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=3, seed=3))
  for i, f in enumerate(clear):
    write_image(source / f"{i}.png", f.image)
    write_image(date / "2011_09_26_drive_0001_sync" / "image_02" / "data" / f"{i:010d}.png",
                f.image)
  K = clear[0].intrinsics
  p_rect = f"{K[0, 0]} 0 {K[0, 2]} 0 0 {K[1, 1]} {K[1, 2]} 0 0 0 1 0"
  (date / "calib_cam_to_cam.txt").write_text(f"S_rect_02: {W}.0 {H}.0\nP_rect_02: {p_rect}\n")
  weights = root / "weights"
  with registered():
    save_weights(weights, SPEC.name, {"height": H, "width": W}, tiny_variables(0),
                 tiny_pose_variables(1))
    yield root, weights, source


def test_every_method_has_its_own_log_named():
  assert set(OWN_LOGS) | {"none"} == set(METHODS)


@pytest.mark.parametrize("method", ["comoda", "adadepth"])
def test_method_runs_from_the_cli_on_drivingstereo(method, dataset, tmp_path):
  from pitta_jax.methods import method_setting
  root, weights, source = dataset
  setting = [f"--{k.replace('_', '-')}={v}" for k, v in method_setting(method).items()]
  out = tmp_path / "out"
  rc = main(["adapt", "--dataset", "drivingstereo", "--root", str(root), "--option",
             "weather=foggy", "--segmentation", f"png:{root / 'foggy' / 'panoptic'}",
             "--weights", str(weights), "--source-images", str(source), "--replay-root",
             str(root / "kitti"), "--method", method, *setting, "--max-instances", "4",
             "--quiet", "--out", str(out)] if method == "comoda" else
            ["adapt", "--dataset", "drivingstereo", "--root", str(root), "--option",
             "weather=foggy", "--segmentation", f"png:{root / 'foggy' / 'panoptic'}",
             "--weights", str(weights), "--source-images", str(source), "--method", method,
             *setting, "--max-instances", "4", "--quiet", "--out", str(out)])
  assert rc == 0
  data = json.loads((out / "results.json").read_text())
  assert len(data["per_frame"]) == N
  logs = data["logs"]
  assert OWN_LOGS[method] in logs and "loss_d" in logs
  assert all(np.isfinite(v) for v in logs["loss"])


def test_demo_rows_keep_the_flags_given_and_refuse_a_method(capsys, tmp_path):
  """The demo applies each row's own setting (CoTTA: selector all) except where a flag was
  given (it replaced --selector silently), and --method, which it never used (results.json
  recorded it), is refused for --demo.methods."""
  out = str(tmp_path / "unused")  # never made: each command is refused before
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.demo import row_config
  from pitta_jax.methods import build
  cotta = build("cotta")
  assert row_config(AdaptConfig(), cotta, {}).selector == "all"
  kept = row_config(AdaptConfig(selector="encoder_bn"), cotta, {}, given={"selector"})
  assert kept.selector == "encoder_bn" and kept.bn_stats == "running" and kept.method == "cotta"
  assert row_config(AdaptConfig(), build("none"), {"bn_stats": "batch"}).bn_stats == "batch"
  assert main(["demo", "--method", "cotta", "--out", out]) == 2
  assert capsys.readouterr().err == ("error: --method: the demo runs the rows of --demo.methods "
                                     "(e.g. --demo.methods none,bn,pitta,cotta)\n")


def test_demo_frames_beyond_the_rendered_street_and_an_empty_out_are_named(capsys, tmp_path):
  """--demo.num-frames beyond the street the synthetic renderer draws exactly is refused naming
  the flag before any work (it had removed an earlier demo's results, then failed naming
  num_frames); --demo.out '' names --demo.out (not --out)."""
  out = tmp_path / "d"
  out.mkdir()
  (out / "results.json").write_text("{}")
  assert main(["demo", "--demo.num-frames", "100000000", "--demo.out", str(out)]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: --demo.num-frames: frames up to 100000000 drive") and (
      err.count("\n") == 1), err
  assert (out / "results.json").read_text() == "{}"
  assert main(["demo", "--demo.out", ""]) == 2
  assert capsys.readouterr().err == "error: --demo.out: an empty path\n"


def test_the_demo_notes_a_row_that_runs_with_a_flag_instead_of_its_own_setting(tmp_path,
                                                                             monkeypatch, capsys):
  """A flag given wins over a row's own setting (CoTTA adapts every parameter, selector all):
  the demo says so on stderr before it runs, for the rows it changes; a flag equal to the row's
  setting changes nothing and is not noted. (The run itself is stubbed: only the notes.)"""
  from pitta_jax import demo, source_model
  ran = []
  monkeypatch.setattr(demo, "run_demo", lambda *a, **k: ran.append(k["given"]))
  monkeypatch.setattr(source_model, "enable_compilation_cache", lambda: None)
  out = str(tmp_path / "d")
  assert main(["demo", "--demo.methods", "none,pitta,cotta", "--selector", "encoder_bn",
               "--out", out, "--quiet"]) == 0
  assert capsys.readouterr().err == ("note: CoTTA + L_d runs with --selector encoder_bn as "
                                     "given, not its own setting\n")
  assert main(["demo", "--demo.methods", "cotta", "--selector", "all", "--out", out,
               "--quiet"]) == 0
  assert capsys.readouterr().err == ""
  assert [("selector" in given) for given in ran] == [True, True]


def test_help_offers_only_flags_the_command_takes(capsys, tmp_path):
  """adapt's --method help names every registered method; the demo's --help shows neither
  --method (its rows come from --demo.methods) nor --max-depth / --min-depth, which it would
  always refuse (Ada-Depth has both its own and its photometric loss's: ambiguous), while both
  still fail in one line naming what to use."""
  out = str(tmp_path / "unused")  # never made: each command is refused before
  with pytest.raises(SystemExit):
    main(["adapt", "--help"])
  text = " ".join(capsys.readouterr().out.split())
  listed = text.split("the TTA method: ", 1)[1].split(" (registry", 1)[0].split(" | ")
  assert sorted(listed) == sorted(METHODS)
  with pytest.raises(SystemExit):
    main(["demo", "--help"])
  text = capsys.readouterr().out
  import re
  for flag in ("--method", "--adapt.method", "--max-depth", "--min-depth"):  # offered as options
    assert not re.search(rf"(\[|^ +|, ){re.escape(flag)}[ ,\]]", text, re.M), flag
  assert "used with --method" not in text  # the methods' groups say which rows use them
  assert "--adadepth.max-depth" in text and "--adadepth.sfm.max-depth" in text
  assert main(["demo", "--max-depth", "50", "--out", out]) == 2
  assert capsys.readouterr().err == ("error: --max-depth is ambiguous for adadepth: use "
                                     "--adadepth.max-depth or --adadepth.sfm.max-depth\n")
