"""experiments/ against the paper's tables: a diverged lambda of Table 4's sweep, a
--quick table labelled as such in every file, the row cache's served rows, and the LaTeX."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from experiments import common, render
from experiments.common import Entry


def test_a_diverged_lambda_is_a_diverged_row_not_a_failed_sweep(monkeypatch):
  """One of the sweep's streams whose depth stops being finite at frame 2 of 4 is reported as
  that lambda's divergence (as `run_row` reports a row's, docs/experiments.md), with its means
  before kept apart; the other lambdas keep their numbers. The sweep stopped with the metrics'
  ValueError "pred contains NaN", losing Table 4 and the sensitivity study whole."""
  from tiny_net import SPEC, tiny_variables
  from experiments import table4
  from pitta_jax import run
  from pitta_jax.checkpoint import Weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  weights = Weights(SPEC, {"height": 64, "width": 96}, tiny_variables(0))
  frames = list(generate_sequence(SyntheticConfig(height=64, width=96, num_frames=4,
                                                  domain="fog")))

  class Poisoned(run.Runners):  # stream 1's depth is NaN from frame 2 on
    def custom(self, key, build):
      model, tx, runner = super().custom(key, build)
      seen = []

      def poisoned(states, chunk, consts):
        states, out = runner(states, chunk, consts)
        depth = np.array(out.depth)                                 # (T, K, H, W)
        for t in range(depth.shape[0]):
          if len(seen) + t >= 2:
            depth[t, 1] = np.nan
        seen.extend(range(depth.shape[0]))
        return states, out._replace(depth=depth)
      return model, tx, poisoned
  result = table4.lambda_sweep(weights, frames, (0.0, 0.5), runners=Poisoned())
  ok, blown = result
  assert ok.get("status", "ok") == "ok" and all(math.isfinite(v) for v in ok["metrics"].values())
  assert blown["status"].startswith("diverged: non-finite depth from frame 2 of 4")
  # every frame's place kept (a curve's x is the frame index): NaN where not scored
  series = blown["abs_rel_per_frame"]
  assert blown["metrics"] == {} and len(series) == 4
  assert np.isfinite(series[:2]).all() and np.isnan(series[2:]).all()
  assert blown["metrics_before_divergence"]["abs_rel"] == np.mean(series[:2])


def test_a_sweep_without_a_scorable_frame_says_so():
  """A test case whose ground truth has no valid pixel in any frame (the zero-valid-frames
  case) gives every lambda "not scored", as a table row; the sweep failed with "mean_metrics
  needs at least one frame"."""
  import dataclasses
  from tiny_net import SPEC, tiny_variables
  from experiments import table4
  from pitta_jax.checkpoint import Weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  weights = Weights(SPEC, {"height": 64, "width": 96}, tiny_variables(0))
  frames = [dataclasses.replace(f, depth=np.zeros_like(f.depth)) for f in generate_sequence(
      SyntheticConfig(height=64, width=96, num_frames=2, domain="fog"))]
  for r in table4.lambda_sweep(weights, frames, (0.0, 0.5)):
    assert r["status"] == "not scored: no frame has valid ground truth" and r["metrics"] == {}
    assert len(r["abs_rel_per_frame"]) == 2 and np.isnan(r["abs_rel_per_frame"]).all()


def test_per_frame_series_keeps_each_frames_place():
  """A run's per-frame curve is over all its frames, NaN where one was not scored (no valid
  ground truth, a non-finite depth): the tables' figures drew the scored values one after
  another, so every frame after an unscored one was drawn one frame early (and Table 3's Sunny
  rows under the wrong frames of All). Hand values."""
  from pitta_jax.run import RunResult
  names = ["a", "b", "c", "d", "e"]
  per_frame = [{"name": "a", "abs_rel": 0.1}, {"name": "c", "abs_rel": 0.3}]
  r = RunResult(name="x", per_frame=per_frame, mean={}, logs={}, frame_names=names,
                seconds=1.0, kept_depths={}, excluded=["b"], nonfinite_indices=[3, 4])
  np.testing.assert_array_equal(r.per_frame_series("abs_rel"), [0.1, np.nan, 0.3, np.nan, np.nan])


def test_per_frame_series_places_frames_of_one_name_by_their_index():
  """Two frames of one name (a user's list), the first without ground truth: the scored
  second frame's value had been drawn at the first one's place, matched by name. Hand
  values, as `run_sequence` records them (each scored frame with its index)."""
  from pitta_jax.run import RunResult
  names = ["a", "a", "b"]
  per_frame = [{"name": "a", "index": 1, "abs_rel": 0.2}, {"name": "b", "index": 2, "abs_rel": 0.3}]
  r = RunResult(name="x", per_frame=per_frame, mean={}, logs={}, frame_names=names,
                seconds=1.0, kept_depths={})
  np.testing.assert_array_equal(r.per_frame_series("abs_rel"), [np.nan, 0.2, 0.3])


METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


def _fake_rows(monkeypatch, runs):
  """Rows without networks: tiny weights (with a stand-in pose network) and `run_sequence`
  answering `runs(name, frames)` -> (per-frame AbsRel, indices of non-finite frames); every
  call's name is recorded in the returned list."""
  from tiny_net import SPEC, tiny_variables
  from pitta_jax import run as run_lib, sources
  from pitta_jax.checkpoint import Weights
  from pitta_jax.run import RunResult
  weights = Weights(SPEC, {"height": 64, "width": 96}, tiny_variables(0), pose={"params": {}})
  monkeypatch.setattr(common, "weights_for", lambda ctx, model: weights)
  monkeypatch.setattr(sources, "method_resources", lambda *a, **k: None)
  calls = []

  def fake(weights, frames, cfg, method, eval_cfg, name, **kw):
    calls.append(name)
    values, bad = runs(name, len(frames))
    per_frame = [{"name": f"f{i}", **{m: v for m in METRICS}} for i, v in enumerate(values)]
    mean = {m: float(np.mean(values)) for m in METRICS} if values else {}
    return RunResult(name=name, per_frame=per_frame, mean=mean, logs={},
                     frame_names=[f"f{i}" for i in range(len(frames))], seconds=1.0,
                     kept_depths={}, nonfinite_indices=list(bad))
  monkeypatch.setattr(run_lib, "run_sequence", fake)
  return calls


def test_one_frame_per_part_is_refused_before_the_first_row_for_a_method_that_pairs_frames(
    tmp_path, monkeypatch, capsys):
  """--frames 1 gives CoMoDa (and Ada-Depth) no previous frame in Foggy: the table is refused
  before any row runs, as docs/experiments.md says of every need ("refused before any work");
  it ran No adaptation first and then stopped with exit 2 at CoMoDa's row."""
  from experiments import table1
  calls = _fake_rows(monkeypatch, lambda name, n: ([0.2] * n, ()))
  assert table1.main(["--quick", "--quiet", "--frames", "1", "--out", str(tmp_path / "t1"),
                      "--rows", "No adaptation,CoMoDa + L_d"]) == 2
  assert calls == []
  assert "at least 2 frames" in capsys.readouterr().err


def test_a_diverged_sensitivity_run_is_said_not_shown_as_blanks(tmp_path, monkeypatch):
  """The sensitivity study's default PITTA run diverging at frame 2 of 4: its rows (lr x
  steps, and the sequence lengths the run does not cover) say "diverged", as a table's row
  does, instead of an "ok" row of blank cells (or a difference of 2 frames against 4)."""
  from experiments import sensitivity, table4
  _fake_rows(monkeypatch, lambda name, n: (([0.3, 0.3], (2, 3)) if "PITTA lr" in name
                                            else ([0.2] * n, ())))
  sweep = [{"metrics": {m: 0.25 for m in METRICS}, "frames": 4, "abs_rel_per_frame": [0.25] * 4}
           for _ in table4.LAMBDAS]
  monkeypatch.setattr(table4, "lambda_sweep", lambda *a, **k: sweep)
  out = tmp_path / "s"
  assert sensitivity.main(["--quick", "--quiet", "--out", str(out)]) == 0
  rows = {r["label"]: r for r in json.loads((out / "results.json").read_text())["rows"]}
  assert rows["lr 0.0001, 1 step"]["status"].startswith("diverged: non-finite depth from "
                                                        "frame 2 of 4")
  assert rows["first 4 frames"]["status"] != "ok"
  assert "diverged" in (out / "sensitivity.md").read_text()


def test_the_lambda_sweeps_row_has_a_cache_key(tmp_path):
  """Table 4's and the sensitivity study's sweep is one cached row holding all 12 lambdas
  (method_config lam = LAMBDAS): its key is computed, and differs from one lambda's. Both
  commands stopped with "error: lam must be a number, got (0.0, 0.1, ...)" before any work."""
  from experiments.common import RowSpec
  from experiments.table4 import LAMBDAS
  ctx = common.Context("synthetic", None, [], "gt", {}, tmp_path, True, 2, True)
  sweep = RowSpec("lambda sweep", "pitta", method_config=(("lam", LAMBDAS),))
  keys = {common.row_key(ctx, row, "Waymo", ({"domain": "rain"},), {})
          for row in (sweep, RowSpec("lambda sweep", "pitta", method_config=(("lam", 0.2),)))}
  assert len(keys) == 2


def test_the_latex_caption_and_cells_print_what_the_markdown_says():
  """In LaTeX's text mode "<" prints as "¡" and "--" as an en dash (OT1, the default font
  encoding): Table 4's caption "δ<1.25" and "--quick", and a row's "needs weights: --weights
  DIR", must reach the PDF as written; "$", "~", "^", "{", "}" in a path or label must not
  break the table."""
  entries = [Entry("Waymo", "x", {"abs_rel": 0.2}),
             Entry("Waymo", "y_{1}", {}, status="needs weights: --weights depth_anything_v2=DIR")]
  tex = render.latex(entries, "rows", "G", "M", ("abs_rel",),
                     "AbsRel, δ<1.25 and δ>0. --quick: weights in ~/w$1^2.", "t")
  caption = next(line for line in tex.splitlines() if line.startswith(r"\caption"))
  assert "$\\delta$<" not in caption and "$\\delta$>" not in caption
  assert "--quick" not in caption and "--weights" not in tex
  assert "~/" not in caption and "w$1" not in caption and "1^2" not in caption
  assert "y_{1}" not in tex and r"y\_\{1\}" in tex


def test_a_quick_table_says_so_in_its_csv_and_figures(tmp_path, monkeypatch):
  """--quick numbers (random networks, 2 frames) sit beside the paper's: the caption of the .md
  and .tex says "not results", and so must the files read without it, the CSV's rows of ours
  (results.json has "quick") and the figures' titles."""
  from experiments import table2
  from pitta_jax import plots
  _fake_rows(monkeypatch, lambda name, n: ([0.2] * n, ()))
  titles, save = [], plots.save_figure
  monkeypatch.setattr(plots, "save_figure", lambda fig, path, *a: titles.append(
      fig.axes[0].get_title()) or save(fig, path, *a))
  out = tmp_path / "t2"
  assert table2.main(["--quick", "--quiet", "--out", str(out), "--rows", "PITTA"]) == 0
  with open(out / "table2.csv", newline="") as f:
    lines = list(csv.DictReader(f))
  ours = [x for x in lines if x["source"] == "ours"]
  assert ours and all(x["quick"] == "true" for x in ours)
  assert titles and all("--quick" in t for t in titles)


def test_a_difference_that_rounds_to_zero_prints_as_zero():
  """The sensitivity study's differences (4 decimals): -0.00001 and 0.00001 are one value as
  shown, ranked as a tie, and printed alike (the markdown had "**-0.0000**" beside
  "**0.0000**")."""
  entries = [Entry("S", k, {"abs_rel": v}) for k, v in (("a", -0.00001), ("b", 0.00001),
                                                         ("c", 0.0031))]
  assert render.ranks(entries, "abs_rel", decimals=4) == {0: 1, 1: 1, 2: 2}
  md = render.markdown(entries, "rows", "G", "M", ("abs_rel",), decimals=4)
  assert "-0.0000" not in md and md.count("**0.0000**") == 2


def test_a_sweep_leaves_a_frame_without_ground_truth_unscored():
  """A frame without ground truth (a reader's `--option depth=false`) is not scored, as
  `run.run_sequence` leaves it (a table row is then "not scored"); the sweep stopped with the
  metrics' "gt must be a 2-D (H, W) map, got shape ()". The compiled step is stood in for by
  constant depths (the scoring is what is tested)."""
  import dataclasses
  from tiny_net import SPEC, tiny_variables
  from experiments import table4
  from pitta_jax import run
  from pitta_jax.checkpoint import Weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  weights = Weights(SPEC, {"height": 64, "width": 96}, tiny_variables(0))
  frames = list(generate_sequence(SyntheticConfig(height=64, width=96, num_frames=3,
                                                  domain="fog")))
  frames[1] = dataclasses.replace(frames[1], depth=None)

  class Constant(run.Runners):  # every stream predicts 10 m everywhere
    def custom(self, key, build):
      model, tx, _ = super().custom(key, build)

      def runner(states, chunk, consts):
        t = chunk.image.shape[0]
        return states, type("Out", (), {"depth": np.full((t, 2, 64, 96), 10.0, np.float32)})
      return model, tx, runner
  want = [run.frame_metrics(np.full((64, 96), 10.0), f.depth, run.EvalConfig(), "median")
          for f in (frames[0], frames[2])]
  for r in table4.lambda_sweep(weights, frames, (0.0, 0.5), runners=Constant()):
    assert r["status"] == "ok" and r["frames"] == 3
    series = r["abs_rel_per_frame"]
    assert series[0] == want[0]["abs_rel"] and math.isnan(series[1])
    assert series[2] == want[1]["abs_rel"]
    assert r["metrics"]["abs_rel"] == np.mean([w["abs_rel"] for w in want])


def test_the_caption_gives_the_open_mask_and_the_closed_clamp():
  """The caption said ground truth "in [0.001, 80] m", where the scored pixels are those with
  0.001 < gt < 80 (MonoDepth2's mask; a pixel at exactly 80 m is not scored) and only the
  prediction is clamped to the closed range."""
  from experiments.common import evaluation_note
  from pitta_jax.run import EvalConfig
  note = evaluation_note(EvalConfig())
  assert "ground truth in (0.001, 80) m, predictions clamped to [0.001, 80] m" in note
  assert "predictions clamped to [0.001, 20] m" in evaluation_note(
      EvalConfig(max_depth=20.0, valid_gt="positive"))


def test_a_sweep_refuses_ground_truth_of_another_aspect_before_its_chunk_runs():
  """The prediction is resized onto the ground truth: a frame whose depth map has another
  aspect ratio is refused naming it, before the chunk runs, as `run.run_sequence` refuses it
  (the sweep scored the stretched prediction)."""
  import dataclasses
  from tiny_net import SPEC, tiny_variables
  from experiments import table4
  from pitta_jax import run
  from pitta_jax.checkpoint import Weights
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  weights = Weights(SPEC, {"height": 64, "width": 96}, tiny_variables(0))
  frames = list(generate_sequence(SyntheticConfig(height=64, width=96, num_frames=2,
                                                  domain="fog")))
  frames[1] = dataclasses.replace(frames[1], depth=np.ones((64, 64), np.float32), name="sq")
  ran = []

  class Never(run.Runners):  # records a chunk run
    def custom(self, key, build):
      model, tx, _ = super().custom(key, build)
      return model, tx, lambda *a: ran.append(1)
  with pytest.raises(DataError, match="^sq: "):
    table4.lambda_sweep(weights, frames, (0.0, 0.5), runners=Never())
  assert ran == []
