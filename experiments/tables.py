"""The loop every table shares: rows x test cases, cached, with one progress bar."""

from __future__ import annotations

import sys

from typing import Sequence

from tqdm import tqdm

from experiments.common import Context, Entry, RowSpec, run_row, runners


def run_grid(ctx: Context, rows: Sequence[RowSpec], cases: Sequence[str],
             skip: Sequence[tuple[str, str]] = ()) -> list[Entry]:
  """Each row on each test case (case-major, the paper's order); (case, label) pairs in `skip`
  are not run. One compile cache serves the whole table."""
  from experiments.common import check_flags_used, check_rows, check_selection
  todo = [(case, parts, row) for case, parts in ctx.cases(cases) for row in rows
          if (case, row.label) not in skip and ctx.wants(row.label, row.method, row.model, case)]
  check_selection(ctx, todo, [row.label for row in rows],
                  [(row.label, row.method, row.model, case) for case in cases for row in rows])
  check_flags_used(ctx, rows, [row for _, _, row in todo])
  check_rows(ctx, todo)
  shared = runners(ctx)
  resources: dict = {}
  entries = []
  bar = tqdm(todo, desc="rows", unit="row", disable=ctx.quiet, position=0)
  for case, parts, row in bar:
    bar.set_postfix_str(f"{case}: {row.label}")
    entries.append(run_row(ctx, row, case, parts, shared, resources))
  bar.close()
  return entries


def rows_table(ctx: Context, rows: Sequence[RowSpec], cases: Sequence[str], table: int,
               with_case: bool = True) -> list[Entry]:
  """`run_grid`, with the paper's numbers of Table `table` attached (matched on method, network
  and, `with_case`, the test case)."""
  from experiments.common import attach_paper, paper_fields
  entries = run_grid(ctx, rows, cases)
  attach_paper(entries, table, lambda e: paper_fields(e, with_case))
  return entries


def publish(ctx: Context, name: str, entries: Sequence[Entry], elapsed: float,
            **layout) -> int:
  """Writes the table's files (`render.write_table`, `layout` its keyword arguments) with the
  run's metadata, prints the markdown unless --quiet; the command's exit status (0)."""
  from experiments.common import caption_notes, check_out, evaluation_note, meta, units_note
  from experiments.render import write_table
  notes = " ".join(n for n in (evaluation_note(ctx.evaluation()), units_note(ctx, entries),
                               caption_notes(ctx)) if n)
  layout = {**layout, "caption": f"{layout.get('caption', '')} {notes}".strip()}
  if name.startswith("table") and any(e.paper for e in entries):  # e.g. Table 4's misprint
    from experiments.paper import load_paper_table
    layout = {**layout, "paper_notes": tuple(load_paper_table(int(name[5:])).get("notes", ()))}
  check_out(ctx)  # --out still the command's: the files would re-make it, or go to another's
  md = write_table(ctx.out, name, entries, seconds=elapsed, meta=meta(ctx), **layout)
  if not ctx.quiet:
    print(md)
  print(f"wrote {ctx.out / name}.md, .csv, .tex and results.json", file=sys.stderr)
  return 0
