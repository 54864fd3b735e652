"""experiments/: the table commands run end to end (--quick: structure and finiteness, not
values), rows are cached and resumed, and the rendering marks best/second as the paper does."""

from __future__ import annotations

import csv
import json
import math

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


def test_cached_rows_are_computed_once(tmp_path):
  ctx = common.Context("synthetic", None, [], "gt", {}, tmp_path, True, 2, True)
  calls = []

  def compute():
    calls.append(1)
    return {"metrics": {"abs_rel": 0.5}}
  assert common.cached(ctx, "k", compute) == common.cached(ctx, "k", compute)
  assert len(calls) == 1 and (tmp_path / "rows" / "k.json").is_file()


def test_table_arguments_are_checked_before_work(tmp_path, capsys):
  from experiments import table1
  assert table1.main(["--dataset", "drivingstereo", "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert "--root" in err and err.count("\n") == 1 and not (tmp_path / "o").exists()
  assert table1.main(["--weights", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
  assert "model.json" in capsys.readouterr().err


@pytest.fixture(scope="module")
def quick_out(tmp_path_factory):
  """One output directory shared by the quick tables (random networks saved once)."""
  return tmp_path_factory.mktemp("experiments")


def _quick(name, out):
  import importlib
  return importlib.import_module(f"experiments.{name}").main(
      ["--quick", "--quiet", "--out", str(out / name)])


def _check_files(out, name):
  for suffix in (".md", ".csv", ".tex"):
    assert (out / f"{name}{suffix}").is_file()
  payload = json.loads((out / "results.json").read_text())
  with open(out / f"{name}.csv", newline="") as f:
    lines = list(csv.DictReader(f))
  return payload, lines


def _finite(entry):
  return all(math.isfinite(v) for v in entry["metrics"].values())


@pytest.mark.parametrize("name", ["table1", "table2"])
def test_method_tables_quick(name, quick_out):
  from experiments.table1 import CASES, ROWS
  assert _quick(name, quick_out) == 0
  payload, lines = _check_files(quick_out / name, name)
  groups = list(CASES) if name == "table1" else ["Waymo"]
  assert [(r["group"], r["label"]) for r in payload["rows"]] == [
      (g, r.label) for g in groups for r in ROWS]
  for r in payload["rows"]:
    if r["label"] == "Depth Anything V2":  # no weights here: said, not invented
      assert r["status"].startswith("needs weights: --weights depth_anything_v2=")
      assert r["metrics"] == {}
    else:
      assert r["status"] == "ok" and len(r["metrics"]) == 7 and _finite(r)
  assert len([x for x in lines if x["source"] == "ours"]) == len(payload["rows"])

