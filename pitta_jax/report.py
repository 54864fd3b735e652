"""Results to files: results.json, results.csv, table.md (the 7 Eigen metrics per row). Used by
the CLI, the demo and the experiments; the figures are `pitta_jax.plots`'.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pitta_jax.metrics import METRIC_NAMES
from pitta_jax.outputs import atomic_write_files, json_safe
from pitta_jax.text import first_and_count

RESULT_FILES = ("results.json", "results.csv", "table.md")  # what `write_results` writes
# what an experiment table NAME writes beside results.json: NAME.md, NAME.csv, NAME.tex
TABLE_SUFFIXES = (".md", ".csv", ".tex")
HIGHER_IS_BETTER = ("a1", "a2", "a3")  # threshold accuracies; the errors are lower-is-better
HEADERS = {"abs_rel": "AbsRel ↓", "sq_rel": "SqRel ↓", "rmse": "RMSE ↓", "rmse_log": "RMSElog ↓",
           "a1": "δ<1.25 ↑", "a2": "δ<1.25² ↑", "a3": "δ<1.25³ ↑"}


@dataclasses.dataclass
class Row:
  """One line of a results table: a (group, method) pair and its mean metrics."""
  group: str           # e.g. the weather shift or dataset
  method: str
  metrics: dict[str, float]
  extra: dict[str, Any] = dataclasses.field(default_factory=dict)  # fps, seconds, n_skipped...
  status: str = "ok"   # else why there are no metrics (e.g. "diverged: ..."), shown instead


def markdown_table(rows: Sequence[Row], group_title: str = "Shift") -> str:
  """The paper's table layout: group, method, 7 metrics (3 decimals; best per group in bold).

  The best is found on the values as printed (3 decimals), as the paper marks them and as the
  experiments' tables do (`experiments.render.ranks`): cells that print the same number are
  both bold or neither (0.1004 and 0.1001 both print 0.100), and a group whose values all
  print alike has no best to mark."""
  head = f"| {group_title} | Method | " + " | ".join(HEADERS[m] for m in METRIC_NAMES) + " |"
  lines = [head, "|" + "---|" * (len(METRIC_NAMES) + 2)]
  for group in dict.fromkeys(r.group for r in rows):
    members = [r for r in rows if r.group == group]
    best = {}
    for m in METRIC_NAMES:
      vals = {round(float(r.metrics[m]), 3) for r in members
              if r.status == "ok" and m in r.metrics and np.isfinite(r.metrics[m])}
      if len(vals) > 1:
        best[m] = max(vals) if m in HIGHER_IS_BETTER else min(vals)
    for r in members:
      if r.status != "ok":
        lines.append(f"| {group} | {r.method} | {r.status} |" + " — |" * (len(METRIC_NAMES) - 1))
        continue
      cells = []
      for m in METRIC_NAMES:
        v = r.metrics.get(m, float("nan"))
        text = f"{v:.3f}"
        cells.append(f"**{text}**" if m in best and np.isfinite(v) and round(float(v), 3)
                     == best[m] else text)
      lines.append(f"| {group} | {r.method} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def write_results(out_dir: str | Path, rows: Sequence[Row], meta: dict[str, Any],
                  group_title: str = "Shift") -> str:
  """Writes results.json (meta + rows), results.csv (one line per row: group, method, status,
  the 7 metrics, the extras) and table.md, each atomically; returns the markdown. results.json
  is valid JSON: a non-finite value is written as null and counted in its "non_finite_values"
  entry."""
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  table = markdown_table(rows, group_title)
  payload = {**meta, "rows": [dataclasses.asdict(r) for r in rows]}
  payload = json.loads(json.dumps(payload, default=_jsonable))  # plain types
  payload, n_bad = json_safe(payload)
  payload["non_finite_values"] = n_bad
  buffer = io.StringIO(newline="")
  writer = csv.writer(buffer)
  extra_keys = sorted({k for r in rows for k in r.extra})
  # the row's status beside its numbers, as results.json and table.md give it: a diverged
  # run's means cover only its finite frames (`pitta-jax adapt`), which table.md does not show
  # and a CSV without it passed off as an ok row's
  writer.writerow([group_title.lower(), "method", "status", *METRIC_NAMES, *extra_keys])
  for r in rows:
    writer.writerow([r.group, r.method, r.status, *(f"{r.metrics.get(m, float('nan')):.6f}"
                                                    for m in METRIC_NAMES),
                     *(r.extra.get(k, "") for k in extra_keys)])
  texts = (json.dumps(payload, indent=2, allow_nan=False) + "\n", buffer.getvalue(), table)
  atomic_write_files(out, dict(zip(RESULT_FILES, texts)))
  return table


def clear_earlier_results(out_dir: str | Path, patterns: Sequence[str] = (),
                          files: Sequence[str] = RESULT_FILES) -> list[str]:
  """Removes what an earlier run of the same command left in `out_dir`: its result `files`
  (default `RESULT_FILES`) and the files matching `patterns` (globs relative to `out_dir`, e.g.
  the demo's figures), with one warning naming them. A run calls it once its inputs are checked
  and before its first step, so that a run killed (or failing) on the way leaves no earlier
  results beside its own checkpoints that could pass for its own, and a rerun with fewer shifts
  keeps no figures of the others. No other file is touched. Returns the removed paths, relative
  to `out_dir`."""
  out = Path(out_dir)
  found = [out / name for name in files if (out / name).is_file()]
  found += sorted(p for pattern in patterns for p in out.glob(pattern) if p.is_file())
  for path in found:
    path.unlink(missing_ok=True)
  names = [str(p.relative_to(out)) for p in found]
  if names:
    print(f"warning: {out}: removed an earlier run's results ({first_and_count(names, 6)}); "
          f"this run writes its own when it ends", file=sys.stderr)
  return names


# commands whose results.json another command may replace, because it writes every file they
# wrote: adapt and evaluate write `RESULT_FILES`, the demo those and its figures
REPLACES = {"adapt": ("adapt", "evaluate"), "evaluate": ("adapt", "evaluate"),
            "demo": ("adapt", "evaluate", "demo")}


def results_owner(out_dir: str | Path) -> tuple[str, list[str]] | None:
  """Which command wrote `out_dir`/results.json, and the files that go with it: ("adapt" |
  "evaluate" | "demo" | "experiment NAME", [file names]); None when there is no results.json or
  it is not one of ours (unreadable, another program's), which a run replaces as before."""
  out = Path(out_dir)
  try:
    payload = json.loads((out / "results.json").read_text())
  except (OSError, UnicodeDecodeError, ValueError):
    return None
  if not isinstance(payload, dict):
    return None
  table, command = payload.get("table"), payload.get("command")
  if isinstance(table, str) and table:
    return f"experiment {table}", ["results.json"] + [
        f"{table}{s}" for s in TABLE_SUFFIXES if (out / f"{table}{s}").is_file()]
  if command in ("adapt", "evaluate") or (command is None and isinstance(payload.get("demo"),
                                                                         dict)):
    owner = command or "demo"
    return owner, [n for n in RESULT_FILES if (out / n).is_file()] + (
        ["figures/"] if owner == "demo" and (out / "figures").is_dir() else [])
  return None


def check_results_owner(out_dir: str | Path, owner: str, what: str = "--out") -> None:
  """DataError, before any work, when `out_dir` holds the results of another command that
  `owner` (as `results_owner` names commands) would leave half replaced: both write
  results.json, and the other's own files (a table's NAME.md, the demo's figures) would stay
  beside results that are not theirs."""
  from pitta_jax.data.errors import DataError
  found = results_owner(out_dir)
  if found is None or found[0] == owner or found[0] in REPLACES.get(owner, ()):
    return
  earlier, files = found
  raise DataError(None, f"{what} {out_dir}: holds the results of `pitta-jax {earlier}` "
                        f"({', '.join(files)}), which `pitta-jax {owner}` would replace in "
                        f"part; give another {what} or remove them")


def _jsonable(x):
  if isinstance(x, (np.floating, np.integer)):
    return x.item()
  if isinstance(x, np.ndarray):
    return x.tolist()
  if dataclasses.is_dataclass(x):
    return dataclasses.asdict(x)
  if isinstance(x, Path):
    return str(x)
  raise TypeError(f"not JSON serialisable: {type(x).__name__}")
