"""The main job and the adapt/evaluate commands, end to end at a tiny size.

`pitta-jax demo` with a 2-step source model at 96x64 and 3-frame sequences: checks the files a
user gets and that every number in them is consistent with the per-frame logs (independent
recomputation of the means from results.json's per-frame values); `adapt`/`evaluate` on the
synthetic dataset reuse the demo's cached source model and its compiled steps.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from pitta_jax import source_model
from pitta_jax.adapt import AdaptConfig
from pitta_jax.cli import main
from pitta_jax.demo import DemoConfig, run_demo
from pitta_jax.metrics import METRIC_NAMES
from pitta_jax.source_model import SourceConfig

TINY = SourceConfig(height=64, width=96, sequences=1, frames_per_sequence=4, steps=2, batch_size=2,
                    pose_fraction=0.0)  # no pose net: the demo's rows do not use one


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
  cache = tmp_path_factory.mktemp("cache")
  mp = pytest.MonkeyPatch()
  mp.setenv(source_model.CACHE_ENV, str(cache))
  out = tmp_path_factory.mktemp("demo")
  # what an earlier demo with more shifts left (removed by this run) and a file of the user's
  (out / "figures").mkdir()
  for name in ("figures/snow_frame039.png", "figures/snow_abs_rel_per_frame.png", "results.json",
               "notes.txt"):
    (out / name).write_text("earlier")
  result = run_demo(DemoConfig(shifts=("fog",), num_frames=3, methods=("none", "bn", "pitta"),
                               out=str(out)), AdaptConfig(),
                    source=TINY, quiet=True)
  yield out, result, cache
  mp.undo()


def test_a_long_demo_shift_is_rendered_as_its_rows_read_it(demo_out, tmp_path, monkeypatch):
  """Beyond demo.RENDER_ONCE_FRAMES frames a shift is rendered as each row reads it (a shift of
  a million frames had been rendered whole into memory first): the same frames, so the same
  results as the demo fixture's shared frames."""
  from pitta_jax import demo as demo_lib
  from pitta_jax.data.synthetic import SyntheticSequence
  seen = []
  real = demo_lib.run_sequence
  monkeypatch.setattr(demo_lib, "RENDER_ONCE_FRAMES", 0)
  monkeypatch.setattr(demo_lib, "run_sequence", lambda weights, frames, *a, **k: seen.append(
      type(frames)) or real(weights, frames, *a, **k))
  result = run_demo(DemoConfig(shifts=("fog",), num_frames=3, methods=("none", "bn", "pitta"),
                               out=str(tmp_path / "d")), AdaptConfig(), source=TINY, quiet=True)
  assert seen and set(seen) == {SyntheticSequence}
  assert [(r.group, r.method, r.metrics) for r in result["rows"]] == [
      (r.group, r.method, r.metrics) for r in demo_out[1]["rows"]]


@pytest.mark.parametrize("replaced", [False, True])
def test_a_demo_whose_out_is_removed_stops_without_making_it_again(demo_out, tmp_path,
                                                                  monkeypatch, replaced):
  """--out removed (rm -rf), or removed and made again (another run's now), while the demo runs
  a row: the demo stops with one OutputError before its next figure, instead of making the
  directory again without the command's lock or writing into the new one, and it leaves the
  new one's files alone (a failed demo removes its own figures)."""
  import shutil
  from pitta_jax import demo as demo_lib
  from pitta_jax.outputs import OutputError
  real = demo_lib.run_sequence
  out = tmp_path / "d"
  out.mkdir()
  theirs = out / "figures" / "fog_frame002.png"  # a name this demo's figures take

  def removing(weights, frames, cfg, method, *a, name="", **k):
    result = real(weights, frames, cfg, method, *a, name=name, **k)
    if name.startswith("fog"):
      shutil.rmtree(out)
      if replaced:
        theirs.parent.mkdir(parents=True)
        theirs.write_text("another run's")
    return result
  monkeypatch.setattr(demo_lib, "run_sequence", removing)
  with pytest.raises(OutputError, match=f"^--out {out}: removed while the command ran"):
    run_demo(DemoConfig(shifts=("fog",), num_frames=3, methods=("none",), out=str(out)),
             AdaptConfig(), source=TINY, quiet=True)
  if replaced:
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        "figures", "figures/fog_frame002.png"]
  else:
    assert not out.exists()


def test_a_demo_rows_unscored_frame_keeps_its_place_in_the_per_frame_values(demo_out, tmp_path,
                                                                           monkeypatch):
  """The per-frame AbsRel (results.json, the per-frame figure) has each value at its frame's
  index and null where a frame was not scored (here frame 1 of the fog row, as a diverged
  method leaves it): the scored frames had been closed up, shifting the curve left."""
  import dataclasses
  from pitta_jax import demo as demo_lib
  real = demo_lib.run_sequence

  def one_unscored(weights, frames, cfg, method, *a, name="", **k):
    res = real(weights, frames, cfg, method, *a, name=name, **k)
    if not name.startswith("fog"):
      return res
    return dataclasses.replace(res, per_frame=[res.per_frame[0], res.per_frame[2]],
                               nonfinite_indices=[1])
  monkeypatch.setattr(demo_lib, "run_sequence", one_unscored)
  out = tmp_path / "d"
  run_demo(DemoConfig(shifts=("fog",), num_frames=3, methods=("none",), out=str(out)),
           AdaptConfig(), source=TINY, quiet=True)
  data = json.loads((out / "results.json").read_text())
  fog = data["per_frame_abs_rel"]["fog"]["No adaptation"]
  clear = data["per_frame_abs_rel"]["clear"]["No adaptation"]
  assert fog[1] is None and fog[0] is not None and fog[2] is not None and None not in clear
  assert len(fog) == len(clear) == 3


def test_an_interrupted_demo_leaves_no_figures_without_results(demo_out, tmp_path, monkeypatch):
  """A demo interrupted after its clear street's figure (during the first shift) removes the
  figures it wrote: they stayed without any results beside them."""
  from pitta_jax import demo as demo_lib
  real = demo_lib.run_sequence

  def interrupted(weights, frames, cfg, method, *a, name="", **k):
    if name.startswith("fog"):
      raise KeyboardInterrupt
    return real(weights, frames, cfg, method, *a, name=name, **k)
  monkeypatch.setattr(demo_lib, "run_sequence", interrupted)
  out = tmp_path / "d"
  (out / "figures").mkdir(parents=True)
  (out / "figures" / "mine.png").write_text("the user's")
  from pitta_jax.data import image_io
  wrote = []
  monkeypatch.setattr(demo_lib, "write_image",
                      lambda path, image: wrote.append(path) or image_io.write_image(path, image))
  with pytest.raises(KeyboardInterrupt):
    run_demo(DemoConfig(shifts=("fog",), num_frames=3, methods=("none",), out=str(out)),
             AdaptConfig(), source=TINY, quiet=True)
  assert [p.name for p in wrote] == ["clear_frame002.png"] and not wrote[0].exists()
  assert sorted(p.name for p in out.rglob("*")) == ["figures", "mine.png"]
  # interrupted while it draws the per-frame plots, after every row ran: no results either
  # (they were written before the plots and stayed, complete-looking, without figures)
  monkeypatch.setattr(demo_lib, "run_sequence", real)
  plots, real_save = [], demo_lib.save_figure

  def save_figure(figure, path, cfg):
    plots.append(path)
    if len(plots) == 2:
      raise KeyboardInterrupt
    return real_save(figure, path, cfg)
  monkeypatch.setattr(demo_lib, "save_figure", save_figure)
  with pytest.raises(KeyboardInterrupt):
    run_demo(DemoConfig(shifts=("fog",), num_frames=3, methods=("none",), out=str(out)),
             AdaptConfig(), source=TINY, quiet=True)
  assert [p.name for p in plots] == ["clear_abs_rel_per_frame.png", "fog_abs_rel_per_frame.png"]
  assert sorted(p.name for p in out.rglob("*")) == ["figures", "mine.png"]
  # into a new directory: the figures/ it made goes too (it stayed, empty)
  fresh = tmp_path / "fresh"
  plots.clear()
  with pytest.raises(KeyboardInterrupt):
    run_demo(DemoConfig(shifts=("fog",), num_frames=3, methods=("none",), out=str(fresh)),
             AdaptConfig(), source=TINY, quiet=True)
  assert len(plots) == 2 and list(fresh.rglob("*")) == []


def test_demo_writes_results_table_and_figures(demo_out):
  out, result, _ = demo_out
  data = json.loads((out / "results.json").read_text())
  rows = [(r["group"], r["method"]) for r in data["rows"]]
  assert rows == [("clear", "No adaptation"), ("fog", "No adaptation"), ("fog", "BN batch stats"),
                  ("fog", "PITTA")]
  for r in data["rows"]:  # the table's means are the means of the per-frame values
    per_frame = data["per_frame_abs_rel"][r["group"]][r["method"]]
    assert len(per_frame) == 3
    np.testing.assert_allclose(r["metrics"]["abs_rel"], np.mean(per_frame), rtol=1e-6)
    assert set(r["metrics"]) == set(METRIC_NAMES) and r["extra"]["frames"] == 3
  assert data["pitta"]["lam"] == 0.2 and data["adapt"]["lr"] == 1e-4  # the paper's defaults
  with open(out / "results.csv") as f:
    assert len(list(csv.reader(f))) == 5
  assert (out / "table.md").read_text() == result["table"]
  for name in ("fog_frame002.png", "fog_abs_rel_per_frame.png", "clear_frame002.png"):
    assert (out / "figures" / name).stat().st_size > 1000
  # the earlier run's snow figures are gone, the user's file is not
  assert sorted(p.name for p in (out / "figures").iterdir()) == [
      "clear_abs_rel_per_frame.png", "clear_frame002.png", "fog_abs_rel_per_frame.png",
      "fog_frame002.png"]
  assert (out / "notes.txt").read_text() == "earlier"
  head = (out / "figures" / "fog_abs_rel_per_frame.png").read_bytes()[:24]  # PNG + IHDR
  assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[16:24] == (720).to_bytes(4, "big") + (
      360).to_bytes(4, "big")  # matplotlib, 7.2 x 3.6 inches at 100 dpi
  # the source model was cached and is found again (no retraining)
  weights, report = source_model.load_or_train_source(TINY, quiet=True)
  assert report["weights_dir"] == str(source_model.cached_dir(TINY))


def test_adapt_and_evaluate_on_synthetic(demo_out, tmp_path, monkeypatch):
  _, _, cache = demo_out
  monkeypatch.setenv(source_model.CACHE_ENV, str(cache))
  weights = str(source_model.cached_dir(TINY))
  common = ["--dataset", "synthetic", "--weights", weights, "--option", "num_frames=3",
            "--option", "domain=fog", "--quiet"]
  assert main(["adapt", *common, "--out", str(tmp_path / "a"), "--lam", "0.5"]) == 0
  import jax  # the command persists its compiled steps (a rerun or --resume loads them)
  assert jax.config.jax_compilation_cache_dir == str(cache / "xla")
  assert main(["evaluate", *common, "--out", str(tmp_path / "e")]) == 0
  adapt = json.loads((tmp_path / "a" / "results.json").read_text())
  evaluate = json.loads((tmp_path / "e" / "results.json").read_text())
  assert adapt["method"]["lam"] == 0.5 and adapt["adapt"]["method"] == "pitta"
  assert evaluate["adapt"]["method"] == "none" and evaluate["adapt"]["bn_stats"] == "running"
  assert len(adapt["per_frame"]) == 3 and len(adapt["logs"]["loss"]) == 3
  # evaluate on the demo's fog sequence (same seed) gives the demo's No adaptation numbers
  demo = json.loads((demo_out[0] / "results.json").read_text())
  ref = [r for r in demo["rows"] if r["group"] == "fog" and r["method"] == "No adaptation"][0]
  np.testing.assert_allclose(evaluate["rows"][0]["metrics"]["abs_rel"],
                             ref["metrics"]["abs_rel"], rtol=1e-6)


def test_adapt_refuses_the_demos_directory(demo_out, capsys):
  """The demo's --out given to adapt: its results.json would be replaced and its figures left
  beside it; refused before any work, the demo's files untouched."""
  out = demo_out[0]
  before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
  assert main(["adapt", "--dataset", "synthetic", "--quiet", "--out", str(out)]) == 2
  err = capsys.readouterr().err
  assert err.startswith(f"error: --out {out}: holds the results of `pitta-jax demo` "
                        f"(results.json, results.csv, table.md, figures/)") and err.count("\n") == 1
  assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_user_errors_are_one_line(tmp_path, capsys):
  assert main(["adapt", "--dataset", "kitti", "--weights", str(tmp_path), "--out",
               str(tmp_path / "o")]) == 2
  assert "model.json" in capsys.readouterr().err
  assert main(["adapt", "--dataset", "folder", "--root", str(tmp_path / "missing"), "--out",
               str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: ") and err.count("\n") == 1


def test_cottas_blur_range_is_refused_naming_its_flags(tmp_path, capsys):
  """--cotta.blur-sigma-min above --cotta.blur-sigma-max was refused as 'blur sigma range must
  be 0 < min <= max', naming no flag; an infinite maximum (sigmas drawn up to inf, NaN where
  the uniform draw is 0) was taken."""
  out = tmp_path / "o"
  head = ["adapt", "--dataset", "synthetic", "--method", "cotta", "--bn-stats", "running",
          "--out", str(out)]
  assert main(head + ["--cotta.blur-sigma-min", "1", "--cotta.blur-sigma-max", "0.5"]) == 2
  assert capsys.readouterr().err == ("error: --cotta.blur-sigma-min, --cotta.blur-sigma-max: "
                                     "need 0 < blur_sigma_min <= blur_sigma_max, got 1.0, 0.5\n")
  assert main(head + ["--cotta.blur-sigma-max", "inf"]) == 2
  assert capsys.readouterr().err == ("error: --cotta.blur-sigma-max: blur_sigma_max must be a "
                                     "finite number >= 0, got inf\n")
  assert not out.exists()


def test_a_selector_of_no_parameter_is_refused_naming_the_flag(tmp_path, monkeypatch, capsys):
  """--selector cnn0_bn0 (fraction 0% + 0%) adapts nothing on any network: it was refused only
  once the weights were loaded, as 'selector fraction(cnn=0,bn=0) selects no parameter', naming
  no flag. Now at the flag's check, before any weights are opened."""
  import pitta_jax.sources as sources
  monkeypatch.setattr(sources, "open_weights", lambda *a, **k: pytest.fail("weights opened"))
  out = tmp_path / "o"
  for selector in ("cnn0_bn0", "fraction(cnn=0,bn=0.0)"):
    assert main(["adapt", "--dataset", "synthetic", "--selector", selector, "--out",
                 str(out)]) == 2
    assert capsys.readouterr().err == (f"error: --adapt.selector: selector {selector!r} selects "
                                       f"no parameter (0% of the convolutions and 0% of the "
                                       f"norm layers)\n")
  assert not out.exists()


def test_adapt_runs_a_method_in_its_own_setting_unless_a_flag_says_otherwise():
  """`--method cotta` adapts every parameter as upstream (Method.setting) with a note; a given
  flag wins; what a method requires is still the user's to give."""
  from pitta_jax.cli import adapt_config, build_parser
  base = ["adapt", "--dataset", "synthetic", "--bn-stats", "running"]
  cfg, method, notes = adapt_config(build_parser().parse_args([*base, "--method", "cotta"]))
  assert (method.name, cfg.selector, cfg.bn_stats) == ("cotta", "all", "running")
  assert notes == ["--method cotta runs in its own setting: --selector all (give the flag to "
                   "change it)"]
  cfg, _, notes = adapt_config(build_parser().parse_args(
      [*base, "--method", "adadepth", "--selector", "encoder_bn"]))
  assert cfg.selector == "encoder_bn" and notes == []
  cfg, _, notes = adapt_config(build_parser().parse_args([*base, "--method", "pitta"]))
  assert cfg.selector == "encoder_bn" and notes == []
  with pytest.raises(ValueError, match="--bn-stats running"):
    adapt_config(build_parser().parse_args(["adapt", "--dataset", "synthetic", "--method",
                                            "actmad"]))


def test_kitti_eigen_split_is_scored_inside_the_garg_crop_unless_a_flag_says_otherwise():
  """A dataset's own protocol (`FrameSequence.evaluation`: the Eigen split's Garg crop, as
  MonoDepth2's evaluate_depth.py --eval_split eigen) applies where no --eval flag is given."""
  from pitta_jax.cli import build_parser, dataset_evaluation
  from pitta_jax.config_cli import config_from_args
  from pitta_jax.run import EvalConfig
  base = ["evaluate", "--dataset", "kitti", "--root", "r", "--weights", "w"]
  args = build_parser().parse_args(base)
  cfg, note = dataset_evaluation(config_from_args(EvalConfig, args, "eval"),
                                 {"garg_crop": True}, args)
  assert cfg.garg_crop is True
  assert note == ("dataset kitti is evaluated with its published protocol: --eval.garg-crop "
                  "true (give the flag to change it)")
  args = build_parser().parse_args([*base, "--eval.garg-crop", "false"])
  cfg, note = dataset_evaluation(config_from_args(EvalConfig, args, "eval"),
                                 {"garg_crop": True}, args)
  assert cfg.garg_crop is False and note is None
  args = build_parser().parse_args(base)
  cfg, note = dataset_evaluation(config_from_args(EvalConfig, args, "eval"), {}, args)
  assert cfg.garg_crop is False and note is None
  cfg, note = dataset_evaluation(config_from_args(EvalConfig, args, "eval"),  # eigen_benchmark
                                 {"valid_gt": "positive"}, args)
  assert cfg.valid_gt == "positive" and "--eval.valid-gt positive (give the flag" in note


def test_shared_flags_reach_the_selected_method():
  """A short name several configs share (--lr, --window, --ld-weight) sets the selected method's
  field, else --adapt.*'s (before: the first config registered took it, so `--method cotta
  --ld-weight 0` set CoMoDa's and CoTTA ran with L_d); flags that would be ignored are refused."""
  from pitta_jax.cli import (_method_configs_from_args, _route_method_aliases, adapt_config,
                             build_parser)
  parser = build_parser()

  def adapt(*flags):
    return adapt_config(parser.parse_args(["adapt", "--dataset", "synthetic", *flags]))

  cfg, method, _ = adapt("--method", "cotta", "--bn-stats", "running", "--ld-weight", "0",
                         "--lr", "0.5", "--window", "3")
  assert (method.config.ld_weight, method.config.lr, method.config.ld.window) == (0.0, 0.5, 3)
  assert cfg.lr == 1e-4                                   # AdaptConfig's, unused by CoTTA
  cfg, method, _ = adapt("--lr", "0.5", "--window", "7")  # PITTA: AdaptConfig's lr, its window
  assert (cfg.lr, method.config.ld.window) == (0.5, 7)
  for flags, match in (
      (["--ld-weight", "0"], r"--ld-weight is not a flag of --pitta\.\* or --adapt\.\*"),
      (["--method", "cotta", "--bn-stats", "running", "--adapt.lr", "0.5"],
       "--adapt.lr does not apply to --method cotta: it steps its own optimiser"),
      (["--method", "cotta", "--bn-stats", "running", "--comoda.lr", "1"],
       "--comoda.lr is a flag of --method comoda, not of --method cotta"),
      (["--method", "cotta", "--bn-stats", "running", "--lr", "1", "--cotta.lr", "2"],
       "both --lr and --cotta.lr given"),
      # named as typed: the shared alias (it said --adapt.lr for --lr), or the namespaced flag
      (["--method", "none", "--lr", "1e-3"],
       "^--lr does not apply to --method none: it never updates the network"),
      (["--method", "none", "--adapt.lr", "1e-3"],
       "^--adapt.lr does not apply to --method none: it never updates the network"),
      (["--method", "none", "--steps-per-frame", "5"],
       "^--steps-per-frame does not apply to --method none: it never updates"),
      (["--window", "five"], "--window: expected INT, got 'five'")):
    with pytest.raises(ValueError, match=match):
      adapt(*flags)
  demo = parser.parse_args(["demo", "--ld-weight", "0"])   # the demo runs them all: each one's
  _route_method_aliases(demo, None)
  configs = _method_configs_from_args(demo)
  assert all(c.ld_weight == 0.0 for name, c in configs.items() if hasattr(c, "ld_weight"))


def test_every_flag_of_the_update_is_refused_for_a_method_that_never_updates():
  """`--method none` never updates the network, so each --adapt flag that shapes an update
  (optimiser, momentum, selector, reset, the non-finite guard, as --lr and --steps-per-frame
  above) would be ignored: each is refused by its own name, a flag of the run (--bn-stats)
  is not."""
  from pitta_jax.cli import adapt_config, build_parser
  parser = build_parser()

  def adapt(*flags):
    return adapt_config(parser.parse_args(["adapt", "--dataset", "synthetic", "--method",
                                           "none", *flags]))
  for flags, named in ((["--optimizer", "sgd"], "optimizer"),
                       (["--optimizer", "sgd", "--momentum", "0.5"], "momentum"),
                       (["--selector", "all"], "selector"),
                       (["--reset-every", "5"], "reset-every"),
                       (["--skip-nonfinite", "false"], "skip-nonfinite")):
    with pytest.raises(ValueError) as e:
      adapt(*flags)
    assert str(e.value) == (f"--{named} does not apply to --method none: it never "
                            f"updates the network"), flags  # the flag as typed
  cfg, method, _ = adapt("--bn-stats", "batch")
  assert (method.name, cfg.bn_stats) == ("none", "batch")


def test_a_flag_given_as_zero_or_false_is_a_flag_given():
  """A value that reads as false (0, false) is still a flag the user gave: another method's
  flag is refused, --adapt's optimiser flags for a method with its own optimiser and the update
  flags for one that never updates are refused, as for any other value."""
  from pitta_jax.cli import adapt_config, build_parser
  parser = build_parser()
  cotta = ["--method", "cotta", "--bn-stats", "running"]
  for flags, message in (
      ([*cotta, "--comoda.lr", "0"], "--comoda.lr is a flag of --method comoda, not of --method "
                                     "cotta"),
      ([*cotta, "--adapt.lr", "0"], "--adapt.lr does not apply to --method cotta: it steps its "
                                    "own optimiser (set it with its --cotta.* flags)"),
      (["--method", "none", "--adapt.reset-every", "0"], "--adapt.reset-every does not apply to "
                                                         "--method none: it never updates the "
                                                         "network"),
      (["--method", "none", "--adapt.skip-nonfinite", "false"],
       "--adapt.skip-nonfinite does not apply to --method none: it never updates the network")):
    with pytest.raises(ValueError) as e:
      adapt_config(parser.parse_args(["adapt", "--dataset", "synthetic", *flags]))
    assert str(e.value) == message, flags


def test_a_failed_or_interrupted_command_ends_the_process_at_once(monkeypatch):
  """`exit_with` (the console scripts' exit): a non-zero code ends the process with os._exit
  (no interpreter teardown under a compile still running on JAX's thread, which crashed a
  Ctrl-C'd run with SIGSEGV); 0 exits normally, with Ctrl-C ignored from then on (one landing
  in JAX's exit handler, after a finished run had printed its table, printed a traceback)."""
  import os
  import signal
  from pitta_jax import cli
  ended = []

  def fake_exit(code):
    ended.append(code)
    raise SystemExit(code)
  monkeypatch.setattr(os, "_exit", fake_exit)
  before = signal.getsignal(signal.SIGINT)
  try:
    for code in (2, 130, 143):
      with pytest.raises(SystemExit):
        cli.exit_with(code)
      assert signal.getsignal(signal.SIGINT) is before
    with pytest.raises(SystemExit) as e:
      cli.exit_with(0)
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
  finally:
    signal.signal(signal.SIGINT, before)
  assert ended == [2, 130, 143] and e.value.code == 0


def test_quiet_help_says_it_hides_the_table():
  """The demo's and the tables' --quiet hide the results table on the terminal too (as adapt's
  --quiet says), not only the progress bars their --help named."""
  import argparse
  from experiments import common
  from pitta_jax.cli import build_parser

  def quiet_help(parser):
    return next(a.help for a in parser._actions if "--quiet" in a.option_strings)
  subs = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
  for parser in (subs.choices["demo"], subs.choices["adapt"], common.parser("table4", "")):
    assert "no table on the terminal" in quiet_help(parser), parser.prog


def test_actmad_layers_matching_nothing_is_refused_naming_the_flag(tmp_path, monkeypatch, capsys):
  """`--actmad.layers` that selects no layer: one line naming the flag, before any source data
  is read (it said "layers '...' matches no module", after ActMAD's source pass had started)."""
  monkeypatch.setenv(source_model.CACHE_ENV, str(tmp_path / "cache"))
  from pitta_jax import sources
  monkeypatch.setattr(sources, "synthetic_streets", lambda *a, **k: pytest.fail("source data read"))
  out = tmp_path / "o"
  assert main(["adapt", "--dataset", "synthetic", "--method", "actmad", "--bn-stats", "running",
               "--actmad.layers", "nomatch", "--option", "num_frames=1", "--quiet",
               "--out", str(out)]) == 2
  err = capsys.readouterr().err
  assert err.endswith("error: --actmad.layers 'nomatch' matches no module of monodepth2 "
                      "whose output is one feature map\n")
  assert not out.exists()
