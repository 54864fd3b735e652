"""The tables' figures (matplotlib, through `pitta_jax.plots`): per-frame AbsRel curves of each
test case (one line per row) and Table 4's lambda curve, ours beside the paper's."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

from experiments.common import Entry

QUICK_TITLE = "\n--quick: random networks, not results"


def per_frame_figures(out: Path, name: str, entries: Sequence[Entry], quick: bool = False,
                      check: Callable[[], Any] | None = None) -> list[Path]:
  """out/figures/NAME_<group>_abs_rel.png for each group with per-frame values; `quick`: the
  title says the curves are a --quick run's. check: called before each figure (the command's
  `common.check_out`: --out removed or replaced stops it)."""
  from pitta_jax import plots
  written = []
  for group in dict.fromkeys(e.group for e in entries):
    series = {e.label: e.extra["abs_rel_per_frame"] for e in entries
              if e.group == group and e.extra.get("abs_rel_per_frame")}
    if series:
      slug = "".join(c if c.isalnum() else "_" for c in group).strip("_").lower()
      if check is not None:
        check()
      written += plots.save_figure(
          plots.per_frame_figure(series, "abs_rel", f"{name}: {group}, per-frame AbsRel"
                                  + (QUICK_TITLE if quick else "")),
          out / "figures" / f"{name}_{slug}_abs_rel.png")
  return written


def lambda_figure(out: Path, name: str, entries: Sequence[Entry], quick: bool = False,
                  check: Callable[[], Any] | None = None) -> list[Path]:
  """out/figures/NAME_lambda.png: AbsRel and delta<1.25 against lambda (ours, `quick`: titled
  as a --quick run's; the paper's as printed in a second figure). check: as
  `per_frame_figures`'."""
  from pitta_jax import plots
  written = []
  if check is not None:
    check()
  ours = [e for e in entries if e.status == "ok"]
  if ours:
    lams = [e.extra["lambda"] for e in ours]
    written += plots.save_figure(plots.lambda_figure(
        lams, {m: [e.metrics[m] for e in ours] for m in ("abs_rel", "a1")},
        f"{name}: ours, lambda of eq. 10" + (QUICK_TITLE if quick else "")),
        out / "figures" / f"{name}_lambda.png")
  paper = [e for e in entries if e.paper]
  if paper:
    written += plots.save_figure(plots.lambda_figure(
        [e.extra["lambda"] for e in paper], {m: [e.paper[m] for e in paper]
                                             for m in ("abs_rel", "a1")},
        f"{name}: the paper's numbers as printed"), out / "figures" / f"{name}_lambda_paper.png")
  return written


__all__ = ["per_frame_figures", "lambda_figure"]
