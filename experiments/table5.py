"""Table 5: which parameters PITTA adapts, on Waymo: "CNN a% + BN b%" = the kernels of the last
a% of the encoder's conv layers and the scale/shift of its last b% of BN layers.

    pitta-jax experiment table5 [--quick] [--dataset waymo --root DIR --weights DIR ...]
    python -m experiments.table5 ...
"""

from __future__ import annotations

from typing import Sequence

from experiments import common
from experiments.common import RowSpec

FRACTIONS = ((0, 50), (0, 100), (20, 80), (40, 60), (60, 40))  # the paper's columns (CNN, BN)
ROWS = tuple(RowSpec(f"CNN {a}% + BN {b}%", "pitta",
                     adapt=(("selector", f"fraction(cnn={a},bn={b})"),),
                     paper=f"CNN {a}% + BN {b}%") for a, b in FRACTIONS)


def run(args, runners=None) -> int:
  from experiments.figures import per_frame_figures
  from experiments.table2 import waymo_caption
  from experiments.tables import publish, run_grid
  ctx = common.context(args, "table5", runners)
  elapsed = common.timer()
  entries = run_grid(ctx, ROWS, ("Waymo",))
  fractions = {row.label: f for row, f in zip(ROWS, FRACTIONS)}
  common.attach_paper(entries, 5, lambda e: dict(zip(("cnn_percent", "bn_percent"),
                                                     fractions[e.label])))
  caption = (f"Adapted parameters of PITTA (AbsRel, δ<1.25). Best bold, second underlined "
             f"(ours: the paper's Table 5 marks none). Dataset: {waymo_caption(ctx)}.")
  per_frame_figures(ctx.out, "table5", entries, ctx.quick, check=lambda: common.check_out(ctx))
  return publish(ctx, "table5", entries, elapsed(), layout="columns", caption=caption,
                 group_title="Dataset", row_title="fraction", metrics=("abs_rel", "a1"))


def main(argv: Sequence[str] | None = None, runners=None) -> int:
  p = common.parser("table5", __doc__.split("\n\n")[0], datasets=("synthetic", "waymo"))
  return common.main_wrapper(run, p, argv, runners)


if __name__ == "__main__":  # as python -m experiments: signals and library logs handled
  from pitta_jax.cli import exit_with, interruptible
  exit_with(interruptible(main))
