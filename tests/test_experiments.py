"""experiments/: the table commands run end to end (--quick: structure and finiteness, not
values), rows are cached and resumed, and the rendering marks best/second as the paper does."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import common, render
from experiments.common import Entry


def test_ranks_bold_best_and_underline_second_per_group_with_the_metric_direction():
  entries = [Entry("A", "x", {"abs_rel": 0.20, "a1": 0.70}), Entry("A", "y", {"abs_rel": 0.10,
             "a1": 0.60}), Entry("A", "z", {"abs_rel": 0.30, "a1": 0.80}),
             Entry("B", "x", {"abs_rel": 0.5, "a1": 0.1})]
  assert render.ranks(entries, "abs_rel") == {1: 1, 0: 2}   # lower is better
  assert render.ranks(entries, "a1") == {2: 1, 0: 2}        # higher is better; B has one row
  tex = render.latex(entries, "rows", "G", "M", ("abs_rel", "a1"), "cap", "tab:x")
  assert r"\textbf{0.100}" in tex and r"\underline{0.200}" in tex and r"\toprule" in tex
  md = render.markdown(entries, "rows", "G", "M", ("abs_rel",))
  assert "**0.100**" in md and "<u>0.200</u>" in md
  # as the paper: only its compared rows are marked when the table has them (here y and z)
  from experiments.common import RowSpec
  for e, paper in zip(entries, (None, "Y", "Z", None)):
    e.spec = RowSpec(e.label, "pitta", paper=paper)
  assert render.ranks(entries, "abs_rel") == {1: 1, 2: 2}
  assert render.ranks(entries, "abs_rel", marked=False) == {}
  # values that all tie at the decimals shown (Table 4's 12 lambdas on a short run): no marks
  tied = [Entry("W", f"{k}", {"abs_rel": 0.2001 + 1e-5 * k}) for k in range(3)]
  assert render.ranks(tied, "abs_rel") == {} and render.ranks(tied, "abs_rel", decimals=5)
  assert r"$\delta$" in render.latex(entries, "columns", "G", "M", ("a1",), "δ<1.25", "t")


def test_ranks_share_a_tie_and_the_next_value_is_second():
  # 0.1, 0.1, 0.2: both 0.1 rows are best, 0.2 is the second value (bold, bold, underline)
  entries = [Entry("A", k, {"abs_rel": v}) for k, v in (("x", 0.1), ("y", 0.1), ("z", 0.2))]
  assert render.ranks(entries, "abs_rel") == {0: 1, 1: 1, 2: 2}


def test_ranks_and_values_follow_the_decimals_shown():
  """The sensitivity table prints 4 decimals: -0.0031 best, -0.0014 second, -0.0012 unmarked,
  in the markdown and in the LaTeX (at 3 decimals the last two would tie)."""
  entries = [Entry("S", k, {"abs_rel": v}) for k, v in (("a", -0.0012), ("b", -0.0014),
                                                         ("c", -0.0031))]
  assert render.ranks(entries, "abs_rel", decimals=4) == {2: 1, 1: 2}
  md = render.markdown(entries, "rows", "G", "M", ("abs_rel",), decimals=4)
  assert "**-0.0031**" in md and "<u>-0.0014</u>" in md and "| -0.0012 |" in md
  tex = render.latex(entries, "rows", "G", "M", ("abs_rel",), "cap", "t", decimals=4)
  assert r"\textbf{-0.0031}" in tex and r"\underline{-0.0014}" in tex
  assert r"\underline{-0.0012}" not in tex and "-0.0012" in tex


def test_the_papers_block_carries_the_papers_own_marks():
  """The paper's numbers are marked as the paper prints them (its bold and underline), whatever
  they are: here the paper bolds x's 0.3 and underlines y's 0.1."""
  from experiments.common import RowSpec
  entries = [Entry("A", "x", {"abs_rel": 0.2}, paper={"abs_rel": 0.3},
                   spec=RowSpec("x", "pitta", paper="X"), paper_marks={"bold": ["abs_rel"]}),
             Entry("A", "y", {"abs_rel": 0.1}, paper={"abs_rel": 0.1},
                   spec=RowSpec("y", "none", paper="Y"), paper_marks={"underline": ["abs_rel"]})]
  assert render.ranks(entries, "abs_rel", "paper") == {0: 1, 1: 2}
  paper_block = render.markdown(entries, "rows", "G", "M", ("abs_rel",)).split("**Paper**")[1]
  assert "**0.300**" in paper_block and "<u>0.100</u>" in paper_block


def test_csv_columns_hold_their_values():
  text = render.csv_text([Entry("A", "x", {"abs_rel": 0.25}, extra={"frames": 50,
                                                                    "seconds": 12.3})], "t1")
  header, row = list(csv.reader(text.splitlines()))
  got = dict(zip(header, row))
  assert (got["frames"], got["seconds"], got["abs_rel"], got["source"]) == (
      "50", "12.3", "0.250000", "ours")


def test_rows_selects_by_label_parts_or_whole_names():
  ctx = common.Context("synthetic", None, [], "gt", {}, Path("."), True, 2, True,
                       rows=("depth",))
  assert not ctx.wants("PITTA", "pitta", "monodepth2")   # 'depth' is part of the network only
  assert ctx.wants("Depth Anything V2", "none", "depth_anything_v2")   # part of the label
  ctx.rows = ("monodepth2",)
  assert ctx.wants("PITTA", "pitta", "monodepth2")       # a whole name


def test_a_rows_cache_key_holds_the_frame_count(tmp_path):
  """A rerun with --frames 50 after --frames 10 is not served the 10-frame row."""
  from experiments.common import RowSpec
  keys = set()
  for frames in (10, 50):
    ctx = common.Context("synthetic", None, [], "gt", {}, tmp_path, True, frames, True)
    keys.add(common.row_key(ctx, RowSpec("PITTA", "pitta"), "fog", ({"domain": "fog"},), {}))
  assert len(keys) == 2


def test_a_rows_cache_key_holds_its_methods_source_data(tmp_path):
  """A rerun with another --source-images (ActMAD's statistics) or --replay-root (CoMoDa's
  replay) is not served the rows computed from the earlier source data; a row whose method
  uses no source data stays cached."""
  from experiments.common import RowSpec
  case, parts = "fog", ({"domain": "fog"},)
  for row, changed in ((RowSpec("ActMAD", "actmad"), True), (RowSpec("CoMoDa", "comoda"), True),
                       (RowSpec("PITTA", "pitta"), False)):
    keys = {common.row_key(common.Context("synthetic", None, [], "gt", {}, tmp_path, True, 2, True,
                                          source_images=images, replay_root=replay),
                           row, case, parts, {})
            for images, replay in ((f"{tmp_path}/a/*.png", None), (f"{tmp_path}/b/*.png", None),
                                   (None, f"{tmp_path}/raw_a"), (None, f"{tmp_path}/raw_b"))}
    assert (len(keys) > 1) == changed, row.label


def test_table1_rows_run_the_papers_settings():
  """Table 1's rows as the paper compares them: BN batch stats is no update with the frames'
  statistics, each baseline with L_d (its own weight) and without it (weight 0), every compared
  row under the paper's label."""
  from experiments.table1 import ROWS
  from pitta_jax.methods import method_config_class
  by = {r.label: r for r in ROWS}
  assert dict(by["BN batch stats"].adapt) == {"bn_stats": "batch"}
  assert by["BN batch stats"].method == by["No adaptation"].method == "none"
  for name, method, paper in (("CoMoDa", "comoda", "CoMoDA"), ("CoTTA", "cotta", "CoTTA"),
                              ("ActMAD", "actmad", "ActMAD"),
                              ("Ada-Depth", "adadepth", "Ada-Depth")):
    with_ld, without = by[f"{name} + L_d"], by[f"{name} (no L_d)"]
    assert (with_ld.method, without.method, with_ld.paper) == (method, method, paper)
    assert with_ld.method_config == () and method_config_class(method)().ld_weight > 0
    assert dict(without.method_config) == {"ld_weight": 0.0} and without.paper is None
  assert (by["PITTA"].method, by["PITTA"].paper) == ("pitta", "PITTA (ours)")


def test_sensitivity_deltas_and_verdicts():
  """A study's row is ours minus its reference (negative AbsRel: the loss helps), and the
  verdict calls a change within +-noise (0.002) noise. Hand values."""
  from experiments.sensitivity import _delta, verdict
  e = _delta("lr", "lr 0.001", Entry("fog", "lr 0.001", {"abs_rel": 0.20, "a1": 0.8}),
             Entry("fog", "reference", {"abs_rel": 0.22, "a1": 0.7}))
  assert e.metrics == pytest.approx({"abs_rel": -0.02, "a1": 0.1})
  rows = [Entry("lr", "a", {"abs_rel": -0.001}), Entry("lr", "b", {"abs_rel": 0.0015}),
          Entry("steps", "c", {"abs_rel": -0.01}), Entry("len", "d", {"abs_rel": 0.004})]
  assert verdict(rows).splitlines() == [
      "lr: the loss is within noise (best -0.0010 at a, worst +0.0015 at b)",
      "steps: the loss helps (best -0.0100 at c, worst -0.0100 at c)",
      "len: the loss hurts (best +0.0040 at d, worst +0.0040 at d)"]


def test_written_tables_are_titled_as_the_paper(tmp_path):
  entries = [Entry("A", "x", {"abs_rel": 0.2})]
  for name, title in (("table1", "### Table 1\n"), ("sensitivity", "### Sensitivity\n")):
    md = render.write_table(tmp_path / name, name, entries, layout="rows", caption="c",
                            group_title="G", row_title="M", seconds=1.0, meta={})
    assert md.startswith(title)


def test_cached_rows_are_computed_once(tmp_path, capsys):
  ctx = common.Context("synthetic", None, [], "gt", {}, tmp_path, True, 2, True)
  calls = []

  from pitta_jax.metrics import METRIC_NAMES
  full = dict.fromkeys(METRIC_NAMES, 0.5) | {"a1": None}

  def compute():
    calls.append(1)
    return {"metrics": full, "abs_rel_per_frame": [0.4, None], "frames": 2, "seconds": 1.5}
  assert common.cached(ctx, "k", compute) == common.cached(ctx, "k", compute)
  assert len(calls) == 1 and (tmp_path / "rows" / "k.json").is_file()
  # a row file that is JSON but not a row (hand-edited, another tool's, values of the wrong
  # kind: the table failed at rendering, naming no file) is computed again, with a warning
  texts = ("{}", "[1]", '{"metrics": 3}', "\xff", '{"metrics": {"abs_rel": "garbage"}}',
           '{"metrics": {"abs_rel": true}}', '{"metrics": {}, "abs_rel_per_frame": ["x"]}',
           '{"metrics": {}, "metrics_before_divergence": [1]}', '{"metrics": {}, "status": 1}',
           # metrics not of a row (served with status ok and blank cells), an ok row without
           # metrics, counts and times that are not numbers (written into the CSV)
           '{"metrics": {"bogus": 1.0}}', '{"metrics": {"abs_rel": 0.5}}', '{"metrics": {}}',
           json.dumps({"metrics": full, "frames": "lots"}),
           json.dumps({"metrics": full, "seconds": "abc"}))
  for text in texts:
    (tmp_path / "rows" / "k.json").write_text(text)
    assert common.cached(ctx, "k", compute) == compute()
    assert capsys.readouterr().err == (f"warning: {tmp_path / 'rows' / 'k.json'}: not a stored "
                                       f"row result (edited or damaged); computing the row "
                                       f"again\n")
  assert len(calls) == 1 + 2 * len(texts)
  # a lambda sweep's result (Table 4, the sensitivity study) is {"sweep": [...]}: cached too
  # (it was recomputed on every run: the check asked for "metrics")
  calls.clear()
  one = {"metrics": full, "frames": 2, "abs_rel_per_frame": [0.4, 0.5]}
  sweep = lambda: calls.append(1) or {"sweep": [one, one], "seconds": 3.0}
  assert common.cached(ctx, "s", sweep, field="sweep", length=2) == common.cached(
      ctx, "s", sweep, field="sweep", length=2)
  assert len(calls) == 1
  # a sweep cut short (served as complete: Table 4 showed 3 of its 12 lambdas), an entry
  # without its frame count or per-frame AbsRel (a KeyError traceback at the table)
  bad = ('{"sweep": []}', '{"sweep": [{"metrics": {"abs_rel": "x"}}]}',
         json.dumps({"sweep": [one]}), json.dumps({"sweep": [one, {**one, "frames": None}]}),
         json.dumps({"sweep": [one, {k: v for k, v in one.items() if k != "abs_rel_per_frame"}]}))
  for text in bad:
    (tmp_path / "rows" / "s.json").write_text(text)
    common.cached(ctx, "s", sweep, field="sweep", length=2)
  assert len(calls) == 1 + len(bad) and "not a stored row result" in capsys.readouterr().err


@pytest.mark.parametrize("replaced", [False, True])
def test_a_row_is_not_written_where_out_was_removed_or_replaced(tmp_path, replaced):
  """--out removed, or removed and made again (another run's), while a row computes: the row's
  result is not written (it would re-make the directory without the command's lock, or go into
  the other run's), the command stops with one line."""
  import shutil
  from pitta_jax.outputs import OutputError, open_output_dir
  out = tmp_path / "out"
  held = open_output_dir(out)
  ctx = common.Context("synthetic", None, [], "gt", {}, out, True, 2, True, out_check=held.check)

  def compute():
    shutil.rmtree(out)
    if replaced:
      out.mkdir()
    return {"metrics": {"abs_rel": 0.5}}
  with pytest.raises(OutputError, match=f"^--out {out}: removed while the command ran"):
    common.cached(ctx, "k", compute)
  assert (list(out.iterdir()) == []) if replaced else not out.exists()
  held.close()


def test_a_table_is_not_published_where_out_was_replaced(tmp_path, capsys):
  """--out removed and made again after the rows ran: neither the figures nor the table's files
  go into the new directory (they did, and the command exited 0)."""
  import shutil
  from experiments import figures, tables
  from pitta_jax.outputs import OutputError, open_output_dir
  out = tmp_path / "out"
  held = open_output_dir(out)
  ctx = common.Context("synthetic", None, [], "gt", {}, out, True, 2, True, out_check=held.check)
  entry = common.Entry("fog", "PITTA", {"abs_rel": 0.5}, extra={"abs_rel_per_frame": [0.4, 0.6]})
  shutil.rmtree(out)
  out.mkdir()
  with pytest.raises(OutputError, match=f"^--out {out}: removed while the command ran"):
    figures.per_frame_figures(out, "table1", [entry], check=lambda: common.check_out(ctx))
  with pytest.raises(OutputError, match=f"^--out {out}: removed while the command ran"):
    tables.publish(ctx, "table1", [entry], 1.0, layout="rows", caption="c")
  assert list(out.iterdir()) == []
  held.close()


def test_captions_say_quick_weights_and_row_subsets():
  ctx = common.Context("synthetic", None, [], "gt", {"monodepth2": "w/md2"}, None, True, 2, True,
                       rows=("PITTA",))
  assert common.caption_notes(ctx) == (
      "--quick: the networks without --weights: seeded random 96x64 networks, 2 frames per "
      "part: a test of the pipeline, not results. Weights: monodepth2=w/md2. Only the rows "
      "selected by --rows PITTA.")
  assert common.caption_notes(common.Context("synthetic", None, [], "gt", {}, None, False, 50,
                                             True)) == ""


def test_row_keys_see_the_weights_values():
  """Weights re-converted or retrained into the same directory (same path, same model.json)
  are other weights: the row key's weights identity changes with any depth or pose value
  (each command, a fresh Context, hashes its weights once)."""
  import numpy as np
  from pitta_jax.checkpoint import Weights
  from pitta_jax.models.registry import get_spec
  command = lambda: common.Context("synthetic", None, [], "gt", {}, None, True, 2, True)
  make = lambda d, p: Weights(get_spec("monodepth2"), {"height": 64, "width": 96},
                              {"params": {"w": np.asarray(d, np.float32)}},
                              None if p is None else {"params": {"w": np.asarray(p, np.float32)}})
  identity = lambda weights: common.weights_identity(command(), "monodepth2", weights)
  base = identity(make([1.0, 2.0], [3.0]))
  assert base == identity(make([1.0, 2.0], [3.0]))
  for other in (make([1.0, 2.5], [3.0]), make([1.0, 2.0], [3.5]), make([1.0, 2.0], None)):
    assert identity(other) != base
  ctx = command()  # the rows of one command share one hash
  assert common.weights_identity(ctx, "monodepth2", make([1.0, 2.0], [3.0])) is \
      common.weights_identity(ctx, "monodepth2", make([1.0, 2.0], [3.0]))


def test_table_arguments_are_checked_before_work(tmp_path, capsys):
  from experiments import table1
  assert table1.main(["--dataset", "drivingstereo", "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert "--root" in err and err.count("\n") == 1 and not (tmp_path / "o").exists()
  assert table1.main(["--weights", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
  assert "model.json" in capsys.readouterr().err
  assert table1.main(["--weights", f"={tmp_path}", "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == (f"error: --weights ={tmp_path}: no network before '=' "
                                     f"(NAME=DIR, or DIR alone for a monodepth2)\n")
  # an empty DIR (it printed 'error: : --weights: no model.json'), an --out name too long (it
  # printed the OS's message without the flag)
  assert table1.main(["--weights", "monodepth2=", "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == ("error: --weights monodepth2=: no directory (NAME=DIR, or "
                                     "DIR alone for a monodepth2)\n")
  long_out = tmp_path / ("x" * 300)
  assert table1.main(["--out", str(long_out)]) == 2
  assert capsys.readouterr().err == (f"error: --out {long_out}: cannot write there (File name "
                                     f"too long)\n")
  # --rows that selects nothing, an --out that is a file: one line, nothing written
  assert table1.main(["--quick", "--rows", "zzz", "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert "--rows zzz: matches none of this table's rows (No adaptation, " in err
  assert err.count("\n") == 1 and not (tmp_path / "o").exists()
  (tmp_path / "file").write_text("")
  assert table1.main(["--quick", "--out", str(tmp_path / "file")]) == 2
  assert (f"error: --out {tmp_path / 'file'}: exists and is not a directory"
          in capsys.readouterr().err)  # as pitta-jax adapt words it
  # table3's rows are known by network, row label and method too (the help's example)
  from experiments import table3
  assert table3.main(["--quick", "--rows", "zzz", "--out", str(tmp_path / "o")]) == 2
  assert ("matches none of this table's rows (SGDepth, No adaptation, No adaptation (Sunny), "
          "Sunny, All, HR-Depth, "
          in capsys.readouterr().err)
  pick = lambda *rows: [(g, r.label) for g, _, r in table3.selected(common.Context(
      "synthetic", None, [], "gt", {}, None, True, 2, True, rows=rows))]
  assert pick("No adaptation") == [(label, row) for label, _ in table3.NETWORKS.values()
                                   for row in ("No adaptation", "No adaptation (Sunny)")]
  assert pick("hrdepth") == [("HR-Depth", "No adaptation"), ("HR-Depth", "No adaptation (Sunny)"),
                             ("HR-Depth", "Sunny"), ("HR-Depth", "All")]
  # --rows with separators only (it would have run every row), --root on a synthetic-only table
  assert table1.main(["--quick", "--rows", " , ", "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == "error: --rows ' , ': no row name in it (comma-separated labels)\n"
  from experiments import sensitivity
  assert sensitivity.main(["--quick", "--root", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == ("error: --root is for real datasets: sensitivity runs on "
                                     "the synthetic benchmark only\n")
  assert table1.main(["--quick", "--root", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
  assert "add --dataset drivingstereo\n" in capsys.readouterr().err

  assert not (tmp_path / "o").exists()
  # flags the synthetic benchmark cannot use are refused, not ignored
  for flags, message in ((["--source-images", "x"], "--source-images: for real datasets only"),
                         (["--option", "foo=1"], "--option foo=1: for real datasets' "),
                         # a valid synthetic option was taken and ignored (rows unchanged)
                         (["--option", "domain=fog"], "the synthetic stand-ins of the test cases "
                                                      "are fixed"),
                         (["--segmentation", "mask2former:x"], "use --segmentation gt")):
    assert table1.main(["--quick", *flags, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and not (tmp_path / "o").exists(), err
  # weights named for one network but holding another
  _model_json(tmp_path / "w", "monodepth2")
  assert table1.main(["--weights", f"depth_anything_v2={tmp_path / 'w'}", "--out",
                      str(tmp_path / "o")]) == 2
  assert "the directory holds a monodepth2, not a depth_anything_v2" in capsys.readouterr().err
  # flags a table cannot use: weights of a network it does not run, source data without rows
  # that take it (the weights' directory is checked first, the table's rows next)
  _model_json(tmp_path / "sg", "sgdepth")
  from experiments import table5
  assert table5.main(["--weights", f"sgdepth={tmp_path / 'sg'}", "--out",
                      str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == (f"error: --weights sgdepth={tmp_path / 'sg'}: this table "
                                     f"has no sgdepth row (its networks: monodepth2)\n")
  assert not (tmp_path / "o").exists()
  ctx = common.Context("drivingstereo", str(tmp_path), [], "gt", {}, None, True, 2, True,
                       source_images="x")
  with pytest.raises(Exception, match=r"--source-images: no row of this table uses "
                                      r"source-domain data"):
    common.check_flags_used(ctx, table5.ROWS)
  common.check_flags_used(ctx, table1.ROWS)  # CoMoDa's and ActMAD's rows take it
  with pytest.raises(Exception, match=r"--source-images: no row selected uses source-domain"):
    common.check_flags_used(ctx, table1.ROWS, [r for r in table1.ROWS if r.method == "none"])
  # a second command on the same --out is refused while the first holds it
  from pitta_jax.outputs import open_output_dir
  with open_output_dir(tmp_path / "busy"):
    assert table1.main(["--quick", "--out", str(tmp_path / "busy")]) == 2
    assert "another pitta-jax run is writing there" in capsys.readouterr().err


def test_rows_entries_each_select_a_row_and_may_name_a_test_case(tmp_path, monkeypatch):
  """--rows Foggy computes the rows of test case Foggy (the help names test cases; it had
  matched nothing); an entry that selects no row is an error also beside one that does (a
  misspelt name had left its rows out, with exit 0)."""
  from experiments import table1, tables
  from pitta_jax.data.errors import DataError
  ran = []
  monkeypatch.setattr(common, "check_rows", lambda ctx, todo: None)
  monkeypatch.setattr(tables, "run_row", lambda ctx, row, case, *a: ran.append((case, row.label)))
  ctx = common.Context("synthetic", None, [], "gt", {}, tmp_path, True, 2, True, rows=("Foggy",))
  tables.run_grid(ctx, table1.ROWS, ["Foggy", "Rainy"])
  assert ran == [("Foggy", row.label) for row in table1.ROWS]
  ran.clear()
  for rows in (("No adaptation", "Nonexistent"), ("Nonexistent",)):
    with pytest.raises(DataError, match="^--rows Nonexistent: matches none of this table's rows"):
      tables.run_grid(dataclasses.replace(ctx, rows=rows), table1.ROWS, ["Foggy", "Rainy"])
  assert ran == []


def test_table_flags_refused_before_an_earlier_tables_files_go(tmp_path, capsys):
  """Each refused with one line and exit 2, and an earlier table in --out stays: the same
  network's --weights twice (the last had silently won); --frames beyond the street the
  synthetic renderer draws (refused after the earlier table was removed, naming num_frames);
  --out '' (had written to experiments_out/NAME); Table 4 on a real dataset without weights
  (had written a table of 'needs weights', exit 0); the sensitivity study with weights of a
  network it does not run, or weights that do not load."""
  from experiments import sensitivity, table1, table2, table4
  for d, arch in (("a", "monodepth2"), ("b", "monodepth2"), ("sg", "sgdepth")):
    _model_json(tmp_path / d, arch)
  out = tmp_path / "o"
  out.mkdir()
  earlier = {f"{name}.md": "earlier" for name in ("table1", "table4", "sensitivity")}
  for name, text in earlier.items():
    (out / name).write_text(text)
  (tmp_path / "empty").mkdir()
  cases = [
      (table1, ["--quick", "--weights", str(tmp_path / "a"), "--weights",
                f"monodepth2={tmp_path / 'b'}"],
       f"error: --weights monodepth2={tmp_path / 'b'}: monodepth2 weights given twice "
       f"({tmp_path / 'a'} and {tmp_path / 'b'}): one directory per network\n"),
      (table1, ["--quick", "--frames", "1000000000000"],
       "error: --frames 1000000000000: frames up to 1000000000000 drive 1e+11 s"),
      (table4, ["--dataset", "waymo", "--root", str(tmp_path / "empty")],
       "error: no weights for the sweep: --weights monodepth2=DIR (on waymo no network is "
       "trained for you)\n"),
      (sensitivity, ["--quick", "--weights", f"sgdepth={tmp_path / 'sg'}"],
       f"error: --weights sgdepth={tmp_path / 'sg'}: this table has no sgdepth row"),
      (sensitivity, ["--quick", "--weights", str(tmp_path / "a")],
       f"error: {tmp_path / 'a' / 'depth'}")]
  for module, args, want in cases:
    assert module.main([*args, "--quiet", "--out", str(out)]) == 2, args
    err = capsys.readouterr().err
    assert err.startswith(want) and err.count("\n") == 1, (args, err)
    assert {p.name: p.read_text() for p in out.glob("*.md")} == earlier, args
  assert table2.main(["--quick", "--quiet", "--out", ""]) == 2
  assert capsys.readouterr().err == "error: --out: an empty path\n"


def _model_json(directory, architecture: str) -> None:
  """A weights directory with only a model.json (enough for the checks before any work)."""
  directory.mkdir()
  (directory / "model.json").write_text(json.dumps(
      {"architecture": architecture, "height": 64, "width": 96, "num_layers": 18,
       "has_pose": False}))


def test_weights_directories_may_hold_an_equals_sign(tmp_path, capsys):
  """--weights [MODEL=]DIR with a DIR such as `runs/lam=0.5/w`: split at the last '=', it was
  refused as an unknown network ('runs/lam', or 'monodepth2=runs/lam'). Both forms now pass the
  weights' checks and reach the next flag's (--frames 0, refused before any work)."""
  from experiments import table4
  _model_json(tmp_path / "lam=0.5", "monodepth2")
  out = tmp_path / "o"
  for given in (str(tmp_path / "lam=0.5"), f"monodepth2={tmp_path / 'lam=0.5'}"):
    assert table4.main(["--weights", given, "--frames", "0", "--out", str(out)]) == 2
    assert capsys.readouterr().err == "error: --frames must be >= 1, got 0\n"
  assert not out.exists()
  # a bare DIR holding '=' that is another network's still gets the NAME=DIR hint
  _model_json(tmp_path / "sg=1", "sgdepth")
  assert table4.main(["--weights", str(tmp_path / "sg=1"), "--out", str(out)]) == 2
  assert capsys.readouterr().err == (f"error: --weights {tmp_path / 'sg=1'}: the directory holds "
                                     f"a sgdepth, not a monodepth2 (write --weights "
                                     f"sgdepth=DIR)\n")


def test_a_real_datasets_cases_are_opened_before_the_first_row(tmp_path, capsys):
  """A DrivingStereo root with the foggy part only: the table fails on the rainy part before it
  computes the foggy rows."""
  from experiments import common, table1
  from pitta_jax.data.errors import DataError
  computed = []
  with pytest.MonkeyPatch.context() as m:
    m.setattr(common, "run_row", lambda *a, **k: computed.append(a) or None)
    m.setattr("pitta_jax.sources.open_reader", lambda dataset, root, options, seg: (
        [0] if "weather=foggy" in options else _raise(DataError(root, "no rainy frames"))))
    assert table1.main(["--dataset", "drivingstereo", "--root", str(tmp_path), "--rows",
                        "No adaptation", "--quiet", "--out", str(tmp_path / "o")]) == 2
  assert "no rainy frames" in capsys.readouterr().err and computed == []


def test_a_real_datasets_case_is_read_as_its_run_goes(tmp_path, monkeypatch):
  """A real dataset's test case (here DrivingStereo, two weathers) is a lazily read sequence:
  no frame is decoded before the run reaches it (every frame of a case had been decoded into
  memory at its full size before the row's run started), the parts in order, each part's first
  frame starting a recording."""
  from test_readers import make_drivingstereo
  from pitta_jax.data.sequence import FrameFiles
  make_drivingstereo(tmp_path, size="half")
  loads = []
  real = FrameFiles.load
  monkeypatch.setattr(FrameFiles, "load", lambda self: loads.append(self.name) or real(self))
  ctx = common.Context("drivingstereo", str(tmp_path), ["size=half"], "gt", {}, tmp_path / "o",
                       False, 0, True)
  frames = common.case_frames(ctx, ({"weather": "rainy"}, {"weather": "foggy"}), 16, 24)
  assert loads == [] and len(frames) == 3
  got = list(frames)
  assert [f.name.split("/")[0] for f in got] == ["rainy", "rainy", "foggy"]
  assert [f.starts_recording for f in got] == [True, False, True]
  assert len(loads) == 3
  two = common.case_frames(dataclasses.replace(ctx, frames=1),
                           ({"weather": "rainy"}, {"weather": "foggy"}), 16, 24)
  assert [f.name.split("/")[0] for f in two] == ["rainy", "foggy"]


def _raise(error):
  raise error


def test_ada_depth_rows_on_weights_up_to_scale_are_captioned():
  """Ada-Depth's metre thresholds on monocular weights: the caption says the depth was taken
  as metres (the rows were printed and ranked with no word of it); not for weights with a
  factor to metres (our source models, stereo-trained ones)."""
  from types import SimpleNamespace
  from pitta_jax.models.registry import get_spec
  ctx = common.Context("synthetic", None, [], "gt", {}, None, True, 2, True)
  rows = [common.Entry("Foggy", label, {}, spec=common.RowSpec(label, method))
          for label, method in (("PITTA", "pitta"), ("Ada-Depth + L_d", "adadepth"))]
  for config, noted in (({"use_stereo": False}, True), ({"use_stereo": True}, False),
                        ({"source": {"trained_by": "train-source"}}, False)):
    ctx.loaded["monodepth2"] = SimpleNamespace(spec=get_spec("monodepth2"), config=config)
    note = common.units_note(ctx, rows)
    assert (note == "Ada-Depth's thresholds are in metres, and the monodepth2 weights are up to "
                    "scale (monocular training): its rows take their depth as metres.") == noted
    assert common.units_note(ctx, rows[:1]) == ""


def test_rows_with_l_d_on_frames_without_panoptic_maps_are_noted(capsys):
  """Real data under --segmentation gt without panoptic maps: PITTA's and the '+ L_d' rows ran
  with L_d = 0 and the table said nothing (`pitta-jax adapt` notes it). A note on stderr and in
  the caption, naming the test cases; none for rows without L_d, maps present, or another
  --segmentation."""
  from types import SimpleNamespace
  from experiments import table1
  reader = lambda pan: SimpleNamespace(files=[SimpleNamespace(panoptic=pan)] * 2)
  readers = {"Foggy": [("foggy", reader(None))], "Rainy": [("rainy", reader("maps"))]}
  rows = {r.label: r for r in table1.ROWS}
  selected = [(case, [{}], rows[label]) for case in ("Foggy", "Rainy")
              for label in ("No adaptation", "CoTTA (no L_d)", "PITTA")]
  ctx = common.Context("drivingstereo", "/d", [], "gt", {}, None, False, 0, True)
  common.no_instances(ctx, selected, readers)
  note = ("drivingstereo has no panoptic maps in test case Foggy: no frame has instances, so "
          "L_d (eq. 8) is 0 in PITTA's and the '+ L_d' rows (--segmentation png:DIR or "
          "mask2former:DIR).")
  assert capsys.readouterr().err == f"note: {note}\n" and ctx.notes == [note]
  assert common.caption_notes(ctx) == note
  for ctx, chosen in ((common.Context("drivingstereo", "/d", [], "gt", {}, None, False, 0, True),
                       [s for s in selected if s[2].label != "PITTA"]),
                      (common.Context("drivingstereo", "/d", [], "png:/p", {}, None, False, 0,
                                      True), selected)):
    common.no_instances(ctx, chosen, readers)
    assert capsys.readouterr().err == "" and ctx.notes == []
  # CoMoDa masks the moving objects out of its own loss: its row without L_d needs them too
  ctx = common.Context("drivingstereo", "/d", [], "gt", {}, None, False, 0, True)
  common.no_instances(ctx, [("Foggy", [{}], rows["CoMoDa (no L_d)"])], readers)
  assert ctx.notes == ["drivingstereo has no panoptic maps in test case Foggy: no frame has "
                       "instances, so CoMoDa's loss masks no moving object (--segmentation "
                       "png:DIR or mask2former:DIR)."]
  ctx = common.Context("drivingstereo", "/d", [], "gt", {}, None, False, 0, True)
  common.no_instances(ctx, [("Foggy", [{}], rows[label]) for label in ("PITTA", "CoMoDa + L_d")],
                      readers)
  assert ctx.notes == ["drivingstereo has no panoptic maps in test case Foggy: no frame has "
                       "instances, so L_d (eq. 8) is 0 in PITTA's and the '+ L_d' rows and "
                       "CoMoDa's loss masks no moving object (--segmentation png:DIR or "
                       "mask2former:DIR)."]
  capsys.readouterr()


def test_a_rows_stale_checkpoints_go_when_the_row_is_stored(tmp_path):
  """A row interrupted, then run again with other settings (--frames: another key), left the
  first run's checkpoints for good (hundreds of MB for a method that adapts the whole network).
  Once the row is stored, the checkpoints of the same table row go; another row's, another
  table's and a folder that does not say whose it is stay."""
  ctx = common.Context("synthetic", None, [], "gt", {}, tmp_path, False, 0, True, name="table2")
  old = common.checkpoints(ctx, "k1", "Foggy: PITTA")
  (old / "state_000032.json").write_text("{}")
  new = common.checkpoints(ctx, "k2", "Foggy: PITTA")
  other_row = common.checkpoints(ctx, "k3", "Foggy: CoTTA")
  other_table = common.checkpoints(dataclasses.replace(ctx, name="table1"), "k4", "Foggy: PITTA")
  unmarked = tmp_path / "rows" / "k5.ckpt"
  unmarked.mkdir()
  common.remove_checkpoints(ctx, "k2")
  assert sorted(p.name for p in (tmp_path / "rows").iterdir()) == ["k3.ckpt", "k4.ckpt", "k5.ckpt"]
  assert not old.exists() and not new.exists() and other_row.is_dir() and other_table.is_dir()
  assert common.checkpoints(dataclasses.replace(ctx, quick=True), "k6", "Foggy: PITTA") is None


def test_row_cache_sees_the_files_it_reads(tmp_path):
  """A row's cache key holds the files under --root and the --segmentation directory (their
  sizes and times), not only their paths: re-segmented maps were served the old rows. The
  table's own --out under the root is left out (its row files would change every key)."""
  import os
  (tmp_path / "ds" / "foggy").mkdir(parents=True)
  (tmp_path / "pan").mkdir()
  (tmp_path / "ds" / "foggy" / "a.png").write_bytes(b"1")
  (tmp_path / "pan" / "a.png").write_bytes(b"2")

  def identity(segmentation="png:" + str(tmp_path / "pan")):
    return common.files_identity(common.Context("drivingstereo", str(tmp_path / "ds"), [],
                                                segmentation, {}, tmp_path / "ds" / "out",
                                                False, 2, True))
  first = identity()
  assert identity() == first and identity("gt") != first
  (tmp_path / "ds" / "out" / "rows").mkdir(parents=True)
  (tmp_path / "ds" / "out" / "rows" / "k.json").write_text("{}")
  assert identity() == first
  (tmp_path / "pan" / "a.png").write_bytes(b"22")  # re-segmented
  second = identity()
  assert second != first
  os.utime(tmp_path / "ds" / "foggy" / "a.png", ns=(1, 1))  # re-exported ground truth, say
  assert identity() != second


class _OneFrame(list):
  """A reader of one frame with its panoptic map, as `check_rows` asks of it (paths only)."""
  def __init__(self):
    from types import SimpleNamespace
    super().__init__([0])
    self.files = [SimpleNamespace(panoptic="maps")]


def test_rows_needs_are_checked_before_the_first_row(tmp_path, monkeypatch):
  """common.check_rows, before any row runs: a method's source data, its pose network, weights
  for at least one row, and an --option the test cases set; it was found at the row, after the
  rows before it had run (an exit 0 with only 'needs weights' rows, for the weights)."""
  from types import SimpleNamespace
  from experiments.table1 import ROWS
  from pitta_jax.data.errors import DataError
  by_label = {row.label: row for row in ROWS}
  foggy = ({"weather": "foggy"},)
  monkeypatch.setattr("pitta_jax.sources.open_reader", lambda *a: _OneFrame())

  def ctx(weights=True, **kw):
    c = common.Context("drivingstereo", str(tmp_path), kw.pop("options", []), "gt",
                       {"monodepth2": "w"} if weights else {}, tmp_path, False, 2, True, **kw)
    if weights:
      c.loaded["monodepth2"] = SimpleNamespace(pose=None)
    return c

  def refused(c, labels, message):
    with pytest.raises(DataError, match=message):
      common.check_rows(c, [("Foggy", foggy, by_label[label]) for label in labels])

  refused(ctx(), ["No adaptation", "ActMAD + L_d"],
          r"row ActMAD \+ L_d: actmad needs source-domain data: --source-images PATH or "
          r"--replay-root DIR")
  refused(ctx(source_images="src"), ["CoMoDa + L_d"],
          r"row CoMoDa \+ L_d: comoda needs a pose network, and the weights have none")
  refused(ctx(weights=False), ["No adaptation", "PITTA"],
          r"no weights for the selected rows: --weights monodepth2=DIR")
  refused(ctx(options=["weather=rainy"]), ["PITTA"],
          r"--option weather=rainy: each test case sets weather itself")
  common.check_rows(ctx(), [("Foggy", foggy, by_label["PITTA"])])


@pytest.fixture(scope="module")
def quick_out(tmp_path_factory):
  """One output directory for the quick tables, and one compile cache: a row that two tables
  share (same network, method and config) compiles once."""
  from pitta_jax.run import Runners
  return tmp_path_factory.mktemp("experiments"), Runners()


def _quick(name, quick_out, *extra):
  import importlib
  out, shared = quick_out
  return importlib.import_module(f"experiments.{name}").main(
      ["--quick", "--quiet", "--out", str(out / name), *extra], runners=shared)


def _check_files(out, name):
  for suffix in (".md", ".csv", ".tex"):
    assert (out / f"{name}{suffix}").is_file()
  payload = json.loads((out / "results.json").read_text())
  with open(out / f"{name}.csv", newline="") as f:
    lines = list(csv.DictReader(f))
  return payload, lines


def _finite(entry):
  return all(math.isfinite(v) for v in entry["metrics"].values())


# The suite's budget allows a few compiles per table: the tables run --quick with --rows where
# a table's rows are many settings of one method (the baselines' engine runs have their own
# tests); `pitta-jax experiment NAME --quick` computes every row.
QUICK_ROWS = {"table1": "No adaptation,PITTA,Depth Anything", "table2": "No adaptation,PITTA,"
              "Depth Anything", "table3": "SGDepth,depth_anything_v2", "table5": "CNN 0% + BN 100%"}


@pytest.mark.parametrize("name", ["table1", "table2"])
def test_method_tables_quick(name, quick_out, monkeypatch):
  from experiments.table1 import CASES, ROWS
  from pitta_jax import checkpoint
  reads = []
  load = checkpoint.load_weights
  monkeypatch.setattr(checkpoint, "load_weights", lambda d: reads.append(d) or load(d))
  assert _quick(name, quick_out, "--rows", QUICK_ROWS[name]) == 0
  assert len(reads) == 1  # the rows share one read of the weights
  import jax
  from pitta_jax.source_model import cache_root
  # the command persists its compiled steps under the (here: the session's private) cache root
  assert jax.config.jax_compilation_cache_dir == str(cache_root() / "xla")
  ROWS = [r for r in ROWS if r.label in ("No adaptation", "PITTA", "Depth Anything V2")]
  payload, lines = _check_files(quick_out[0] / name, name)
  groups = list(CASES) if name == "table1" else ["Waymo"]
  assert [(r["group"], r["label"]) for r in payload["rows"]] == [
      (g, r.label) for g in groups for r in ROWS]
  for r in payload["rows"]:
    if r["label"] == "Depth Anything V2":  # no weights here: said, not invented
      assert r["status"].startswith("needs weights: --weights depth_anything_v2=")
      assert r["metrics"] == {}
    else:
      assert r["status"] == "ok" and len(r["metrics"]) == 7 and _finite(r)
      # the resolved configuration the row ran with, beside its changes in "spec"
      assert r["extra"]["adapt"]["lr"] > 0 and r["extra"]["adapt"]["bn_stats"] in (
          "batch", "running") and isinstance(r["extra"]["method_config"], dict)
      assert len(r["extra"]["row_key"]) == 20
  assert len([x for x in lines if x["source"] == "ours"]) == len(payload["rows"])

  papers = [r for r in payload["rows"] if r["paper"]]
  assert len(papers) == len([r for r in ROWS if r.paper]) * len(groups)  # every paper row found
  figures = list((quick_out[0] / name / "figures").glob("*.png"))
  assert len(figures) == len(groups)


def test_rows_are_cached_and_a_rerun_computes_nothing(quick_out, monkeypatch):
  """table2 again on the same --out: every row is read back, no run starts."""
  from pitta_jax import run as run_lib
  calls = []
  monkeypatch.setattr(run_lib, "run_sequence", lambda *a, **k: calls.append(1))
  before = (quick_out[0] / "table2" / "results.json").read_text()
  assert _quick("table2", quick_out, "--rows", QUICK_ROWS["table2"]) == 0
  assert calls == []
  after = json.loads((quick_out[0] / "table2" / "results.json").read_text())
  assert [r["metrics"] for r in after["rows"]] == [r["metrics"] for r in json.loads(before)["rows"]]


def test_a_command_refuses_an_out_holding_another_commands_results(quick_out, monkeypatch,
                                                                     capsys):
  """`pitta-jax adapt` and another table given table2's directory: both write results.json, so
  either would have left table2.md beside results that are not its own. Refused before any work,
  one line naming the table and its files; nothing there changes."""
  from pitta_jax import run as run_lib
  from pitta_jax.cli import main
  out = quick_out[0] / "table2"
  before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
  calls = []
  monkeypatch.setattr(run_lib, "run_sequence", lambda *a, **k: calls.append(1))
  assert main(["adapt", "--dataset", "synthetic", "--quiet", "--out", str(out)]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and err.startswith(f"error: --out {out}: holds the results of "
                                                  f"`pitta-jax experiment table2` (results.json, "
                                                  f"table2.md, table2.csv, table2.tex)")
  assert _quick("table5", quick_out, "--out", str(out)) == 2
  assert "`pitta-jax experiment table2`" in capsys.readouterr().err
  assert calls == []
  assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_an_interrupted_rerun_leaves_no_earlier_table(quick_out, monkeypatch, capsys):
  """table2 rerun on the same --out with another row selected, interrupted at its first new
  row: the earlier table's files and figures are gone (they stayed, looking current), the
  cached rows stay, and the earlier command run again reads them back."""
  from pitta_jax import run as run_lib
  out = quick_out[0] / "table2"
  earlier = ["results.json", "table2.csv", "table2.md", "table2.tex"]
  assert sorted(p.name for p in out.glob("*") if p.is_file()) == earlier
  assert list(out.glob("figures/table2_*.png")) and list(out.glob("rows/*.json"))

  def interrupted(*a, **k):
    raise KeyboardInterrupt
  monkeypatch.setattr(run_lib, "run_sequence", interrupted)
  assert _quick("table2", quick_out, "--rows", "BN batch stats") == 130
  assert "removed an earlier run's results" in capsys.readouterr().err
  assert not [p for p in out.glob("*") if p.is_file()] and not list(out.glob("figures/*.png"))
  monkeypatch.undo()
  calls = []
  monkeypatch.setattr(run_lib, "run_sequence", lambda *a, **k: calls.append(1))
  assert _quick("table2", quick_out, "--rows", QUICK_ROWS["table2"]) == 0 and calls == []
  assert sorted(p.name for p in out.glob("*") if p.is_file()) == earlier


def test_eval_flags_score_every_row(quick_out, monkeypatch, capsys):
  """--eval.* flags reach every row's scoring, its cache key, results.json's eval and the caption; a bad
  value is one line before any work. Before, the tables always scored with the defaults."""
  from pitta_jax import run as run_lib
  from pitta_jax.run import EvalConfig
  seen, real = [], run_lib.run_sequence
  monkeypatch.setattr(run_lib, "run_sequence",
                      lambda *a, **k: seen.append(a[4]) or real(*a, **k))
  out = quick_out[0] / "table1_eval"
  assert _quick("table1", quick_out, "--out", str(out), "--eval.alignment", "bogus") == 2
  assert "alignment must be model, median, scale_shift, stereo or none, got 'bogus'" in \
      capsys.readouterr().err and not out.exists()
  flags = ("--rows", "No adaptation", "--eval.max-depth", "20", "--eval.valid-gt", "positive")
  assert _quick("table1", quick_out, "--out", str(out), *flags) == 0
  assert seen == [EvalConfig(max_depth=20.0, valid_gt="positive")] * 3  # Foggy, Rainy, All
  payload = json.loads((out / "results.json").read_text())
  assert payload["eval"]["max_depth"] == 20.0
  assert payload["eval"]["valid_gt"] == "positive"
  assert "ground truth > 0 (--eval.valid-gt positive; predictions clamped to [0.001, 20] m)" in \
      (out / "table1.md").read_text()
  default = {(r["group"], r["label"]): r for r in json.loads(
      (quick_out[0] / "table1" / "results.json").read_text())["rows"]}
  for r in payload["rows"]:  # other scores under another row key than the default run's
    assert r["extra"]["row_key"] != default[r["group"], r["label"]]["extra"]["row_key"]
    assert r["metrics"] != default[r["group"], r["label"]]["metrics"]


def test_table3_quick(quick_out):
  from experiments.table3 import NETWORKS, ROWS
  assert _quick("table3", quick_out, "--rows", QUICK_ROWS["table3"]) == 0
  payload, _ = _check_files(quick_out[0] / "table3", "table3")
  assert [(r["group"], r["label"]) for r in payload["rows"]] == [
      (label, row) for label in ("SGDepth", "DepthAnythingV2") for row, _, _, _ in ROWS]
  assert set(NETWORKS) == {"sgdepth", "hrdepth", "monovit", "litemono", "depth_anything_v2"}
  for r in payload["rows"]:
    if r["spec"]["model"] == "depth_anything_v2":
      assert r["status"].startswith("needs weights")
    else:
      assert r["status"] == "ok" and _finite(r)
      assert (r["paper"] is None) == (r["label"] == "No adaptation (Sunny)")


def test_table4_quick_is_one_vmapped_sweep(quick_out):
  from experiments.table4 import LAMBDAS
  assert _quick("table4", quick_out) == 0
  payload, lines = _check_files(quick_out[0] / "table4", "table4")
  assert [r["label"] for r in payload["rows"]] == [
      "0", "0.1", "0.2", "0.3", "0.4", "0.5", "0.6", "0.7", "0.8", "0.9", "1.0", "∞"]
  assert all(_finite(r) and r["paper"] for r in payload["rows"]) and len(LAMBDAS) == 12
  assert payload["rows"][2]["paper"]["abs_rel"] == 1.999  # printed as in the paper (a typo)
  assert {"table4_lambda.png", "table4_lambda_paper.png"} <= {
      p.name for p in (quick_out[0] / "table4" / "figures").iterdir()}
  md = (quick_out[0] / "table4" / "table4.md").read_text()
  assert "**Ours**" in md and "**Paper**" in md and "Waymo" in md
  assert "- Paper: AbsRel at λ = 0.2 is printed as 1.999" in md  # the misprint said under it
  assert payload["rows"][2]["extra"]["method_config"]["lam"] == 0.2  # each stream's config
  seconds = {x["seconds"] for x in lines if x["source"] == "ours"}   # the sweep's, every row
  assert len(seconds) == 1 and float(seconds.pop()) > 0


def test_table5_quick(quick_out):
  from experiments.table5 import ROWS
  assert [r.label for r in ROWS] == ["CNN 0% + BN 50%", "CNN 0% + BN 100%", "CNN 20% + BN 80%",
                                     "CNN 40% + BN 60%", "CNN 60% + BN 40%"]  # the paper's
  assert _quick("table5", quick_out, "--rows", QUICK_ROWS["table5"]) == 0
  payload, _ = _check_files(quick_out[0] / "table5", "table5")
  (row,) = payload["rows"]
  assert row["label"] == "CNN 0% + BN 100%" and _finite(row) and row["paper"]["abs_rel"] == 0.199
  assert row["spec"]["adapt"] == [["selector", "fraction(cnn=0,bn=100)"]]
  assert (quick_out[0] / "table5" / "figures" / "table5_waymo_abs_rel.png").is_file()


def test_sensitivity_quick(quick_out):
  assert _quick("sensitivity", quick_out) == 0
  payload, _ = _check_files(quick_out[0] / "sensitivity", "sensitivity")
  studies = {r["group"] for r in payload["rows"]}
  assert studies == {"lr x steps", "BN mode", "traffic", "lambda", "sequence length"}
  assert all(_finite(r) for r in payload["rows"]) and payload["verdict"]


def test_experiment_subcommand_dispatches_and_names_a_bad_experiment(capsys):
  from pitta_jax.cli import main
  assert main(["experiment", "nope"]) == 2
  assert capsys.readouterr().err.count("\n") == 1
  with pytest.raises(SystemExit) as e:
    main(["experiment", "table4", "--help"])
  assert e.value.code == 0 and "--quick" in capsys.readouterr().out


@pytest.mark.parametrize("signal_name, code", [("SIGTERM", 143), ("SIGINT", 130)])
def test_a_signal_stops_a_table_like_the_pitta_jax_commands(tmp_path, capsys, signal_name, code):
  """`python -m experiments.NAME` too: SIGTERM stops as Ctrl-C does (rows cached, --out
  unlocked) and exits 143 as `pitta-jax adapt`; Ctrl-C 130."""
  import signal
  p = common.parser("table1", "t")
  before = signal.getsignal(signal.SIGTERM)

  def run(args, runners):
    common.context(args, "table1")  # locks --out
    signal.raise_signal(getattr(signal, signal_name))
    return 0
  # a background job (nohup, CI) may start with SIGINT ignored: Python's own handler here
  previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
  try:
    assert common.main_wrapper(run, p, ["--quick", "--out", str(tmp_path / "o")]) == code
  finally:
    signal.signal(signal.SIGINT, previous_int)
  assert "interrupted: finished rows are cached" in capsys.readouterr().err
  assert not (tmp_path / "o" / ".pitta-jax.lock").exists()
  assert signal.getsignal(signal.SIGTERM) is before  # the handler is the command's only


def test_a_case_of_several_parts_marks_where_each_starts():
  """Table 1's "All" is four streets in one run: each part's first frame starts a recording,
  so CoMoDa and Ada-Depth never pair frames of two streets (before: no frame was marked)."""
  ctx = common.Context("synthetic", None, [], "gt", {}, None, True, 3, True)
  parts = [{"domain": "clear", "seed": 1}, {"domain": "fog", "seed": 2},
           {"domain": "rain", "seed": 3}]
  frames = common.case_frames(ctx, parts, 32, 48)
  assert [f.starts_recording for f in frames] == [True, False, False] * 3


def test_a_changed_library_default_changes_the_row_key(monkeypatch):
  """A cached row is keyed by the configurations it resolves to: a method setting (e.g. the
  selector Ada-Depth's setting gained) or a config default that changes is a new key, so the
  row is computed again instead of read back (the key hashed the row's own changes only)."""
  from experiments import common
  from experiments.common import RowSpec
  from pitta_jax.methods.adadepth import AdadepthConfig
  ctx = common.Context("synthetic", None, [], "gt", {}, None, False, 50, True)
  row = RowSpec("Ada-Depth + L_d", "adadepth")
  key = common.row_key(ctx, row, "Foggy", ("fog",), {"w": 1})
  assert common.row_key(ctx, row, "Foggy", ("fog",), {"w": 1}) == key  # deterministic
  monkeypatch.setattr("pitta_jax.methods.method_setting",
                      lambda name: {"bn_stats": "running", "selector": "encoder_bn"})
  assert common.row_key(ctx, row, "Foggy", ("fog",), {"w": 1}) != key
  monkeypatch.undo()
  monkeypatch.setattr("pitta_jax.methods.method_config_class",
                      lambda name: lambda: AdadepthConfig(lr=2e-5))
  assert common.row_key(ctx, row, "Foggy", ("fog",), {"w": 1}) != key


def test_table3_figures_draw_sunny_under_alls_sunny_part():
  """Sunny is its own run on All's last part (cloudy, foggy, rainy, sunny): its curve starts at
  All's frame 6 of 8 here (two frames per part), not at frame 0 beside All's cloudy part."""
  from experiments.table3 import _aligned_for_figures
  entries = [Entry("SGDepth", "No adaptation", {}, extra={"abs_rel_per_frame": [0.5] * 8}),
             Entry("SGDepth", "No adaptation (Sunny)", {}, extra={"abs_rel_per_frame": [0.4] * 2}),
             Entry("SGDepth", "Sunny", {}, extra={"abs_rel_per_frame": [0.1, 0.2]}),
             Entry("SGDepth", "All", {}, extra={"abs_rel_per_frame": [0.3] * 8})]
  drawn = _aligned_for_figures(entries)
  assert drawn[2].label == "Sunny, its own run under All's sunny part"
  np.testing.assert_array_equal(drawn[2].extra["abs_rel_per_frame"], [np.nan] * 6 + [0.1, 0.2])
  assert drawn[1].label == "No adaptation (Sunny), its own run under All's sunny part"
  np.testing.assert_array_equal(drawn[1].extra["abs_rel_per_frame"], [np.nan] * 6 + [0.4, 0.4])
  assert drawn[0] is entries[0] and drawn[3] is entries[3]
  assert entries[2].extra["abs_rel_per_frame"] == [0.1, 0.2]  # the table's own entry unchanged


def test_lambda_sweep_resumes_after_an_interrupt(tmp_path, monkeypatch):
  """Table 4's sweep checkpoints its vmapped states and per-frame results: interrupted while
  scoring frame 4 of 6 (checkpoints every 2 frames), a rerun starts at frame 2 and ends with
  an uninterrupted sweep's numbers (it started again from frame 0, losing the work)."""
  from tiny_net import SPEC, tiny_variables
  from experiments import table4
  from pitta_jax import run
  from pitta_jax.checkpoint import Weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  monkeypatch.setattr(common, "CHECKPOINT_EVERY", 2)
  weights = Weights(SPEC, {"height": 64, "width": 96}, tiny_variables(0))
  frames = list(generate_sequence(SyntheticConfig(height=64, width=96, num_frames=6,
                                                  domain="fog")))
  lams = (0.0, 0.5)
  shared = run.Runners()
  whole = table4.lambda_sweep(weights, frames, lams, runners=shared)
  # a frame without a valid ground-truth pixel is left out of every lambda's mean (not a NaN)
  import dataclasses
  blind = list(frames)
  blind[1] = dataclasses.replace(blind[1], depth=np.zeros_like(blind[1].depth))
  for r in table4.lambda_sweep(weights, blind, lams, runners=shared):
    series = r["abs_rel_per_frame"]  # the blind frame's place kept, as a gap
    assert len(series) == 6 and np.isnan(series[1]) and np.isfinite(np.delete(series, 1)).all()
    assert all(math.isfinite(v) for v in r["metrics"].values())
  scored, real = [], run.frame_metrics

  def interrupting(depth, *a):
    scored.append(1)
    if len(scored) == 7:  # frame 3's first lambda: frames 0-1 saved, 2-3 the cut chunk
      raise KeyboardInterrupt
    return real(depth, *a)
  # in a folder not made yet, as --out/rows/KEY.ckpt on a fresh --out: the sweep makes it (a
  # save had taken the missing folder for one removed while the run went on, and every
  # non-quick Table 4 failed at its first checkpoint)
  ckpt = tmp_path / "rows" / "sweep.ckpt"
  monkeypatch.setattr(run, "frame_metrics", interrupting)
  with pytest.raises(KeyboardInterrupt):
    table4.lambda_sweep(weights, frames, lams, runners=shared, checkpoint_dir=ckpt)
  assert [p.name for p in run.complete_checkpoints(ckpt)] == ["state_000002.json"]
  monkeypatch.setattr(run, "frame_metrics", real)
  from pitta_jax.adapt import inputs
  starts, real_chunks = [], inputs.chunks
  monkeypatch.setattr(inputs, "chunks", lambda frames, *a: starts.append(frames[0].name)
                      or real_chunks(frames, *a))
  resumed = table4.lambda_sweep(weights, frames, lams, runners=shared, checkpoint_dir=ckpt)
  assert starts == [frames[2].name]
  assert resumed == whole
  # a Ctrl-C landing as the first checkpoint's state is written: the save removes what it
  # wrote, and the chunk it saved is saved again (it was lost: n % every == 0 saved nothing)
  real_save, saves = run.save_state, []

  def cut_save(path, state):
    real_save(path, state)
    saves.append(path)
    if len(saves) == 1:
      raise KeyboardInterrupt
  cut = tmp_path / "cut.ckpt"
  monkeypatch.setattr(run, "save_state", cut_save)
  with pytest.raises(KeyboardInterrupt):
    table4.lambda_sweep(weights, frames, lams, runners=shared, checkpoint_dir=cut)
  assert [p.name for p in run.complete_checkpoints(cut)] == ["state_000002.json"]
  monkeypatch.setattr(run, "save_state", real_save)
  starts.clear()
  assert table4.lambda_sweep(weights, frames, lams, runners=shared, checkpoint_dir=cut) == whole
  assert starts == [frames[2].name]
  # a Ctrl-C while the second chunk runs: XLA runs it to its end all the same, and its frames
  # are scored and checkpointed before the sweep stops (they were dropped)
  from interrupts import interrupt_a_wait
  kept = tmp_path / "kept.ckpt"
  with monkeypatch.context() as patch:
    interrupt_a_wait(patch, 2)
    with pytest.raises(KeyboardInterrupt):
      table4.lambda_sweep(weights, frames, lams, runners=shared, checkpoint_dir=kept)
  assert [p.name for p in run.complete_checkpoints(kept)][-1] == "state_000004.json"
  starts.clear()
  assert table4.lambda_sweep(weights, frames, lams, runners=shared, checkpoint_dir=kept) == whole
  assert starts == [frames[4].name]


def test_experiments_without_a_name_is_a_usage_error_on_stderr(capsys):
  """No experiment named: the list goes to stderr with exit 2 (it went to stdout); asked for
  with --help: stdout, 0."""
  import experiments
  assert experiments.main([]) == 2
  out, err = capsys.readouterr()
  assert out == "" and "table1" in err
  assert err.splitlines()[-1] == ("error: name an experiment: " + ", ".join(experiments.NAMES))
  assert experiments.main(["--help"]) == 0
  out, err = capsys.readouterr()
  assert "table1" in out and err == ""


def test_an_unknown_flag_points_at_the_help_of_the_command_as_started(monkeypatch, capsys):
  """Usage and errors name the command as the user typed it: `python -m experiments NAME`,
  `python -m experiments.NAME` or `pitta-jax experiment NAME` (all three said the last)."""
  from experiments import table1
  import experiments
  pkg = Path(experiments.__file__).parent
  for argv0, typed in [(pkg / "__main__.py", "python -m experiments table1"),
                       (pkg / "table1.py", "python -m experiments.table1"),
                       ("/venv/bin/pitta-jax", "pitta-jax experiment table1")]:
    monkeypatch.setattr(sys, "argv", [str(argv0), "table1", "--bogus"])
    with pytest.raises(SystemExit) as e:
      table1.main(["--bogus"])
    assert e.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"error: unrecognized arguments: --bogus (see {typed} --help)")


def test_sensitivity_help_gives_its_own_frames_and_no_real_data_flags(capsys):
  """The sensitivity study runs 100 frames (its longest sequence-length setting; --quick: 4),
  not the tables' 50 (2), and offers no flag it always refuses (it runs on synthetic only)."""
  from experiments import sensitivity
  with pytest.raises(SystemExit):
    sensitivity.main(["--help"])
  text = " ".join(capsys.readouterr().out.split())
  assert "(synthetic default 100)" in text and "testing: 4 frames per part" in text
  for flag in ("--root", "--option", "--segmentation", "--source-images", "--replay-root"):
    assert flag not in text


@pytest.mark.parametrize("name", ["table1", "table2", "table3", "table4", "table5",
                                  "sensitivity"])
# the package imports its tables, so runpy finds the module loaded: as under python -m
@pytest.mark.filterwarnings("ignore:.*found in sys.modules after import:RuntimeWarning")
def test_python_m_a_table_runs_as_the_commands_do(name, tmp_path, monkeypatch, capsys):
  """`python -m experiments.NAME` goes through the commands' wrapper (signals from the first
  line, the libraries' log lines and tensorstore's closed-loop tracebacks silenced), as
  `python -m experiments` and `pitta-jax experiment` do; it called main() bare."""
  import runpy
  from pitta_jax import cli
  wrapped = []

  def interruptible(body, debug=None):
    wrapped.append(body)
    return body()

  monkeypatch.setattr(cli, "interruptible", interruptible)
  monkeypatch.setattr(sys, "argv", [name, "--quick", "--dataset", "nope", "--out",
                                    str(tmp_path / "o")])
  with pytest.raises(SystemExit) as e:
    runpy.run_module(f"experiments.{name}", run_name="__main__")
  assert e.value.code == 2 and len(wrapped) == 1
  assert "invalid choice: 'nope'" in capsys.readouterr().err


def test_out_of_memory_is_one_line_and_other_runtime_errors_raise(tmp_path, capsys):
  """XLA running out of memory under a table is one line and exit 2, as under the pitta-jax
  commands (the tables printed its traceback); any other runtime error keeps its traceback."""
  import jax

  def failing(error):
    def run(args, runners):
      raise error
    return run

  p = common.parser("table1", "t")
  oom = jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 9 bytes.")
  assert common.main_wrapper(failing(oom), p, ["--quick", "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: out of ") and "Out of memory allocating 9 bytes." in err
  assert err.count("\n") == 1
  other = jax.errors.JaxRuntimeError("INTERNAL: something else")
  with pytest.raises(jax.errors.JaxRuntimeError, match="INTERNAL"):
    common.main_wrapper(failing(other), p, ["--quick", "--out", str(tmp_path / "o2")])
  with pytest.raises(jax.errors.JaxRuntimeError, match="RESOURCE_EXHAUSTED"):  # --debug: raised
    common.main_wrapper(failing(oom), p, ["--quick", "--debug", "--out", str(tmp_path / "o3")])


def test_an_os_error_is_one_line_naming_its_file(tmp_path, capsys):
  """A full disk or a read-only directory under a table: "error: FILE: reason", as the
  pitta-jax commands print it (the tables printed "[Errno 28] ...: 'FILE'")."""
  from pitta_jax.cli import error_line
  from pitta_jax.data.errors import DataError

  def run(args, runners):
    raise OSError(28, "No space left on device", str(tmp_path / "o" / "table1.md"))

  p = common.parser("table1", "t")
  assert common.main_wrapper(run, p, ["--quick", "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert err == f"error: {tmp_path / 'o' / 'table1.md'}: No space left on device\n"
  assert error_line(FileNotFoundError("no such split file: x.txt")) == "no such split file: x.txt"
  assert error_line(PermissionError(13, "Permission denied")) == "Permission denied"
  assert error_line(DataError(None, "bad")) == str(DataError(None, "bad"))


def test_a_diverged_row_keeps_its_means_before_divergence_unranked(quick_out, tmp_path,
                                                                    monkeypatch):
  """A row whose depth stopped being finite at frame 2 of 4: results.json and the row file say
  so, its "metrics" are empty (no score on the case), and the means of the frames scored before
  are kept apart as metrics_before_divergence; the table prints the status, not those means."""
  import importlib
  from pitta_jax import run as run_lib
  from pitta_jax.run import RunResult
  names = ["f0", "f1", "f2", "f3"]
  scored = [{"name": "f0", "abs_rel": 0.25, "sq_rel": 1.5, "rmse": 4.0, "rmse_log": 0.5,
             "a1": 0.75, "a2": 0.875, "a3": 0.9375},
            {"name": "f1", "abs_rel": 0.125, "sq_rel": 0.5, "rmse": 2.0, "rmse_log": 0.25,
             "a1": 0.5, "a2": 0.625, "a3": 0.6875}]
  means = {"abs_rel": 0.1875, "sq_rel": 1.0, "rmse": 3.0, "rmse_log": 0.375, "a1": 0.625,
           "a2": 0.75, "a3": 0.8125}  # by hand from the two frames
  monkeypatch.setattr(run_lib, "run_sequence", lambda *a, **k: RunResult(
      name="x", per_frame=scored, mean=dict(means), logs={}, frame_names=names, seconds=2.0,
      kept_depths={}, n_skipped=0, excluded=[], resumed_at=0, nonfinite_indices=[2, 3]))
  out = tmp_path / "t2"
  assert importlib.import_module("experiments.table2").main(
      ["--quick", "--quiet", "--out", str(out), "--rows", "PITTA"], runners=quick_out[1]) == 0
  rows = json.loads((out / "results.json").read_text())["rows"]
  assert [r["label"] for r in rows] == ["PITTA"] and all(r["status"] == "diverged: non-finite depth from frame 2 of 4 (2 frames "
                                     "not scored)" for r in rows)
  for r in rows:
    assert r["metrics"] == {} and r["extra"]["metrics_before_divergence"] == means
    assert r["extra"]["abs_rel_per_frame"] == [0.25, 0.125, None, None]  # gaps: not scored
  stored = [json.loads(p.read_text()) for p in (out / "rows").glob("*.json")]
  assert stored and all(s["metrics"] == {} and s["metrics_before_divergence"] == means
                        for s in stored)
  table = (out / "table2.md").read_text()
  assert "diverged" in table and "0.188" not in table and "0.1875" not in table


def test_sensitivity_rows_take_their_studys_reference(quick_out, tmp_path, monkeypatch):
  """Each study against its own reference, with hand values for the runs (no step runs): the
  BN-mode row is PITTA with running statistics minus No adaptation (not minus BN batch stats),
  the traffic row is against BN batch stats on the dense street, and the sequence-length rows
  are PITTA's mean over its first n frames minus the reference's over the same n frames."""
  import importlib
  from experiments import common
  from experiments import table4
  from experiments.common import Entry
  runs = {  # (row label, dense street) -> (AbsRel, per-frame AbsRel)
      ("BN batch stats", False): (0.30, [0.4, 0.2, 0.3, 0.1]),
      ("PITTA lr 0.0001 x1", False): (0.28, [0.1, 0.2, 0.6, 0.0]),
      ("No adaptation", False): (0.50, [0.5] * 4),
      ("PITTA BN running", False): (0.45, [0.45] * 4),
      ("BN batch stats", True): (0.35, [0.35] * 4),
      ("PITTA", True): (0.33, [0.33] * 4)}

  def fake_row(ctx, row, case, parts, shared, resources):
    abs_rel, per_frame = runs[(row.label, "dense" in case)]
    return Entry(case, row.label, {"abs_rel": abs_rel, "a1": 0.5}, spec=row,
                 extra={"abs_rel_per_frame": per_frame})
  monkeypatch.setattr(common, "run_row", fake_row)
  monkeypatch.setattr(table4, "lambda_sweep", lambda weights, frames, lams, *a: [
      {"metrics": {"abs_rel": 0.29, "a1": 0.5}} for _ in lams])
  out = tmp_path / "sens"
  assert importlib.import_module("experiments.sensitivity").main(
      ["--quick", "--quiet", "--out", str(out)], runners=quick_out[1]) == 0
  rows = {(r["group"], r["label"]): r["metrics"]["abs_rel"]
          for r in json.loads((out / "results.json").read_text())["rows"]}
  assert rows[("BN mode", "running statistics")] == pytest.approx(0.45 - 0.50)
  assert rows[("traffic", "dense: PITTA")] == pytest.approx(0.33 - 0.35)
  assert rows[("lr x steps", "lr 0.0001, 1 step")] == pytest.approx(0.28 - 0.30)
  assert rows[("lambda", "λ = 0.2")] == pytest.approx(0.29 - 0.30)
  assert rows[("sequence length", "first 1 frame")] == pytest.approx(0.1 - 0.4)
  assert rows[("sequence length", "first 2 frames")] == pytest.approx(0.15 - 0.3)
  assert rows[("sequence length", "first 4 frames")] == pytest.approx(0.225 - 0.25)
