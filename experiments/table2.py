"""Table 2: the methods of Table 1 on Waymo (one test case): MonoDepth2 ResNet-18 adapted online,
every baseline with PITTA's L_d (paper Sec. 4.1).

    pitta-jax experiment table2 [--quick] [--dataset waymo --root DIR --weights DIR ...]
    python -m experiments.table2 ...
"""

from __future__ import annotations

from typing import Sequence

from experiments import common
from experiments.table1 import ROWS, TITLE


def run(args, runners=None) -> int:
  from experiments.figures import per_frame_figures
  from experiments.tables import publish, rows_table
  ctx = common.context(args, "table2", runners)
  elapsed = common.timer()
  entries = rows_table(ctx, ROWS, ("Waymo",), table=2, with_case=False)
  caption = f"{TITLE} Dataset: {waymo_caption(ctx)}."
  per_frame_figures(ctx.out, "table2", entries, ctx.quick,
                    check=lambda: common.check_out(ctx))
  return publish(ctx, "table2", entries, elapsed(), layout="rows", caption=caption,
                 group_title="Dataset", row_title="Method")


def waymo_caption(ctx) -> str:
  if ctx.dataset == "synthetic":
    return common.SYNTHETIC_CAPTION["waymo"] + f", {ctx.frames} frames"
  return f"Waymo at {ctx.root}"


def main(argv: Sequence[str] | None = None, runners=None) -> int:
  p = common.parser("table2", __doc__.split("\n\n")[0], datasets=("synthetic", "waymo"))
  return common.main_wrapper(run, p, argv, runners)


if __name__ == "__main__":  # as python -m experiments: signals and library logs handled
  from pitta_jax.cli import exit_with, interruptible
  exit_with(interruptible(main))
