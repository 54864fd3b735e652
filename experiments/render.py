"""A table's files: NAME.md (ours and the paper's, labelled), NAME.csv (every metric, ours and
the paper's, one line per row), NAME.tex (booktabs, best per group in bold and second
underlined, as the paper typesets it) and results.json (every row's config and metrics).

Two layouts, as in the paper: "rows" (Tables 1-3: group, row, the 7 metrics) and "columns"
(Tables 4-5: one column per setting, AbsRel and delta<1.25 as lines; the CSV keeps all seven).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from pathlib import Path
from typing import Any, Sequence

from experiments.common import Entry
from pitta_jax.metrics import METRIC_NAMES
from pitta_jax.outputs import atomic_write_files, json_safe
from pitta_jax.report import HEADERS, HIGHER_IS_BETTER

TEX_HEADERS = {"abs_rel": r"AbsRel $\downarrow$", "sq_rel": r"SqRel $\downarrow$",
               "rmse": r"RMSE $\downarrow$", "rmse_log": r"RMSElog $\downarrow$",
               "a1": r"$\delta<1.25$ $\uparrow$", "a2": r"$\delta<1.25^2$ $\uparrow$",
               "a3": r"$\delta<1.25^3$ $\uparrow$"}


def _fmt(v: float | None, decimals: int = 3) -> str:
  """`v` at `decimals`; a value that rounds to zero is "0.000", whichever its sign ("-0.000"
  beside "0.000" read as two values, and `ranks` ties them)."""
  if v is None or not math.isfinite(v):
    return "—"
  text = f"{v:.{decimals}f}"
  return text[1:] if text.startswith("-") and float(text) == 0 else text


def ranks(entries: Sequence[Entry], metric: str, which: str = "ours",
          marked: bool = True, decimals: int = 3) -> dict[int, int]:
  """{entry index: 1 (best) or 2 (second)} within each group, on the values rounded to the
  `decimals` shown (ties share; a group whose values all tie is not marked: every cell bold
  said nothing);
  for the paper's numbers, the marks as the paper prints them.

  Ours are ranked among the rows the paper compares (those with a paper label) when the table
  has such rows, as the paper marks its own methods: our extra rows (BN batch stats, the
  baselines without L_d) are shown unmarked. `marked` False: no marks on ours (a table whose
  groups do not compare methods, e.g. Table 3's test cases of one network)."""
  out: dict[int, int] = {}
  if which == "paper":
    for i, e in enumerate(entries):
      marks = e.paper_marks or {}
      if metric in marks.get("bold", ()):
        out[i] = 1
      elif metric in marks.get("underline", ()):
        out[i] = 2
    return out
  if not marked:
    return out
  compared = [e.spec is not None and bool(e.spec.paper) for e in entries]
  compared = compared if any(compared) else [True] * len(entries)
  for group in dict.fromkeys(e.group for e in entries):
    vals = []
    for i, e in enumerate(entries):
      v = e.metrics.get(metric)
      if e.group == group and compared[i] and v is not None and math.isfinite(v):
        vals.append((i, round(v, decimals)))
    distinct = sorted({v for _, v in vals}, reverse=metric in HIGHER_IS_BETTER)
    if len(distinct) < 2:
      continue
    for i, v in vals:
      r = distinct.index(v) + 1
      if r <= 2 and len(vals) > 1:
        out[i] = r
  return out


def _mark_md(text: str, rank: int | None) -> str:
  return f"**{text}**" if rank == 1 else f"<u>{text}</u>" if rank == 2 else text


def markdown(entries: Sequence[Entry], layout: str, group_title: str, row_title: str,
             metrics: Sequence[str], marked: bool = True, decimals: int = 3) -> str:
  """Ours, then the paper's, each as its own labelled block."""
  blocks = []
  for which, title in (("ours", "Ours"), ("paper", "Paper")):
    if which == "paper" and not any(e.paper for e in entries):
      continue
    blocks.append(f"**{title}**\n\n" + (
        _md_rows(entries, which, group_title, row_title, marked, decimals) if layout == "rows"
        else _md_columns(entries, which, row_title, metrics, marked, decimals)))
  return "\n".join(blocks)


def _label(e: Entry, which: str) -> str:
  """The row's label; in the paper's block the paper's name of the method (`RowSpec.paper`:
  e.g. CoMoDA, PITTA (ours); spelled correctly where the paper misprints it, "DetphAnythingV2")."""
  return e.spec.paper if which == "paper" and e.spec is not None and e.spec.paper else e.label


def _md_rows(entries, which, group_title, row_title, marked=True, decimals=3) -> str:
  head = f"| {group_title} | {row_title} | " + " | ".join(HEADERS[m] for m in METRIC_NAMES) + " |"
  lines = [head, "|" + "---|" * (len(METRIC_NAMES) + 2)]
  rk = {m: ranks(entries, m, which, marked, decimals) for m in METRIC_NAMES}
  for i, e in enumerate(entries):
    values = e.metrics if which == "ours" else e.paper
    if which == "paper" and not values:
      continue
    if which == "ours" and e.status != "ok":
      cells = [e.status] + [""] * (len(METRIC_NAMES) - 1)
    else:
      cells = [_mark_md(_fmt(values.get(m), decimals), rk[m].get(i)) for m in METRIC_NAMES]
    lines.append(f"| {e.group} | {_label(e, which)} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def _md_columns(entries, which, row_title, metrics, marked=True, decimals=3) -> str:
  shown = [e for e in entries if which == "ours" or e.paper]
  head = f"| {row_title} | " + " | ".join(_label(e, which) for e in shown) + " |"
  lines = [head, "|" + "---|" * (len(shown) + 1)]
  for m in metrics:
    rk = ranks(shown, m, which, marked, decimals)
    cells = []
    for i, e in enumerate(shown):
      if which == "ours" and e.status != "ok":
        cells.append(e.status)
        continue
      values = e.metrics if which == "ours" else e.paper
      cells.append(_mark_md(_fmt(values.get(m), decimals), rk.get(i)))
    lines.append(f"| {HEADERS[m]} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


# text-mode LaTeX of each character that is not itself there: the specials, the symbols of the
# captions and labels, and "<", ">" (text mode's default OT1 encoding prints them as "¡", "¿")
TEX_TEXT = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#",
            "$": r"\$", "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}",
            "^": r"\textasciicircum{}", "<": r"\textless{}", ">": r"\textgreater{}",
            "λ": r"$\lambda$", "∞": r"$\infty$", "δ": r"$\delta$", "↑": r"$\uparrow$",
            "↓": r"$\downarrow$", "²": r"$^2$", "³": r"$^3$", "—": "---"}


def _tex_escape(text: str) -> str:
  """`text` as LaTeX prints it; a "-" before another "-" is kept apart ("--quick", "--weights":
  LaTeX joins "--" into an en dash)."""
  return "".join("-{}" if c == "-" and text[i + 1:i + 2] == "-" else TEX_TEXT.get(c, c)
                 for i, c in enumerate(text))


def _mark_tex(text: str, rank: int | None) -> str:
  return rf"\textbf{{{text}}}" if rank == 1 else rf"\underline{{{text}}}" if rank == 2 else text


def latex(entries: Sequence[Entry], layout: str, group_title: str, row_title: str,
          metrics: Sequence[str], caption: str, label: str, marked: bool = True,
          decimals: int = 3) -> str:
  """Our numbers as a booktabs table in the paper's layout (needs \\usepackage{booktabs})."""
  lines = [r"\begin{table}[t]", r"\centering", rf"\caption{{{_tex_escape(caption)}}}",
           rf"\label{{{label}}}"]
  if layout == "rows":
    lines += [r"\begin{tabular}{ll" + "c" * len(METRIC_NAMES) + "}", r"\toprule",
              f"{_tex_escape(group_title)} & {_tex_escape(row_title)} & "
              + " & ".join(TEX_HEADERS[m] for m in METRIC_NAMES) + r" \\", r"\midrule"]
    rk = {m: ranks(entries, m, marked=marked, decimals=decimals) for m in METRIC_NAMES}
    groups = list(dict.fromkeys(e.group for e in entries))
    for g, group in enumerate(groups):
      for i, e in enumerate(entries):
        if e.group != group:
          continue
        if e.status != "ok":
          cells = [rf"\multicolumn{{{len(METRIC_NAMES)}}}{{c}}{{{_tex_escape(e.status)}}}"]
        else:
          cells = [_mark_tex(_fmt(e.metrics.get(m), decimals), rk[m].get(i))
                   for m in METRIC_NAMES]
        lines.append(f"{_tex_escape(group)} & {_tex_escape(e.label)} & " + " & ".join(cells)
                     + r" \\")
      if g < len(groups) - 1:
        lines.append(r"\midrule")
  else:
    lines += [r"\begin{tabular}{l" + "c" * len(entries) + "}", r"\toprule",
              f"{_tex_escape(row_title)} & " + " & ".join(_tex_escape(e.label) for e in entries)
              + r" \\", r"\midrule"]
    for m in metrics:
      rk = ranks(entries, m, marked=marked, decimals=decimals)
      cells = [_mark_tex(_fmt(e.metrics.get(m), decimals), rk.get(i)) if e.status == "ok"
               else "--"
               for i, e in enumerate(entries)]
      lines.append(f"{TEX_HEADERS[m]} & " + " & ".join(cells) + r" \\")
  lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
  return "\n".join(lines) + "\n"


def csv_text(entries: Sequence[Entry], table: str, quick: bool = False) -> str:
  """One line per row and source; `quick`: our rows are a --quick run's (random networks, a
  few frames), which their "quick" column says, as the caption does in the .md and .tex."""
  buffer = io.StringIO(newline="")
  writer = csv.writer(buffer)
  writer.writerow(["table", "group", "row", "source", "status", *METRIC_NAMES, "frames",
                   "seconds", "quick"])
  for e in entries:
    writer.writerow([table, e.group, e.label, "ours", e.status,
                     *(f"{e.metrics[m]:.6f}" if e.metrics.get(m) is not None else ""
                       for m in METRIC_NAMES),
                     e.extra.get("frames", ""), e.extra.get("seconds", ""),
                     "true" if quick else "false"])
    if e.paper:
      writer.writerow([table, e.group, e.label, "paper", "ok",
                       *(f"{e.paper[m]:.3f}" if e.paper.get(m) is not None else ""
                         for m in METRIC_NAMES), "", "", ""])
  return buffer.getvalue()


def write_table(out: Path, name: str, entries: Sequence[Entry], *, layout: str, caption: str,
                group_title: str, row_title: str, metrics: Sequence[str] = METRIC_NAMES,
                seconds: float, meta: dict[str, Any], marked: bool = True,
                decimals: int = 3, paper_notes: Sequence[str] = ()) -> str:
  """Writes NAME.md/.csv/.tex and results.json atomically; returns the markdown.
  marked: bold / underline the best and second (`ranks`); decimals: of our values in .md and
  .tex (the paper prints 3; the sensitivity study's differences need 4); paper_notes: what the
  paper's numbers need said (`experiments/paper/tableN.json` notes: misprints, missing marks),
  listed under the paper's block. Every file is rendered and written
  to a synced temporary file before the first rename (`outputs.atomic_write_files`)."""
  out.mkdir(parents=True, exist_ok=True)
  title = f"Table {name[len('table'):]}" if name.startswith("table") else name.capitalize()
  md = (f"### {title}\n\n{caption}\n\n"
        + markdown(entries, layout, group_title, row_title, metrics, marked, decimals)
        + "".join(f"\n- Paper: {note}" for note in paper_notes) + ("\n" if paper_notes else "")
        + f"\nWall time: {seconds:.0f} s ({meta.get('load', '')}).\n")
  payload = {"table": name, "caption": caption, "seconds": round(seconds, 1), **meta,
             "rows": [dataclasses.asdict(e) for e in entries]}
  payload, n_bad = json_safe(json.loads(json.dumps(payload, default=str)))
  # a per-frame series' NaN is a frame not scored (a gap, null), not a non-finite value: not
  # counted, as it is not when the row comes back from the row cache (null there already)
  gaps = sum(isinstance(v, float) and not math.isfinite(v) for e in entries
             for v in (e.extra.get("abs_rel_per_frame") or ()))
  payload["non_finite_values"] = n_bad - gaps
  files = {f"{name}.md": md, f"{name}.csv": csv_text(entries, name, bool(meta.get("quick"))),
           f"{name}.tex": latex(entries, layout, group_title, row_title, metrics, caption,
                                f"tab:{name}", marked, decimals),
           "results.json": json.dumps(payload, indent=1, allow_nan=False) + "\n"}
  atomic_write_files(out, files)
  return md
