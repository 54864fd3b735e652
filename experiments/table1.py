"""Table 1: MonoDepth2 (ResNet-18) adapted online to DrivingStereo's weather (Foggy, Rainy, All)
by every method of the paper's comparison; each baseline with PITTA's L_d added (paper Sec. 4.1).

    pitta-jax experiment table1 [--quick] [--dataset drivingstereo --root DIR --weights DIR ...]
    python -m experiments.table1 ...
"""

from __future__ import annotations

from typing import Sequence

from experiments import common
from experiments.common import RowSpec

CASES = ("Foggy", "Rainy", "All")
# (our label, method, network, paper's label). Ours, not the paper's: "BN batch stats" (the
# source model with the frame's BN statistics and no update, which separates their effect from
# PITTA's loss) and each baseline as published, without L_d ("(no L_d)": ld_weight 0), which
# separates the method from the loss the paper adds to it
ROWS = (
    RowSpec("No adaptation", "none", paper="No adaptation"),
    RowSpec("BN batch stats", "none", adapt=(("bn_stats", "batch"),)),
    RowSpec("CoMoDa + L_d", "comoda", paper="CoMoDA"),
    RowSpec("CoMoDa (no L_d)", "comoda", method_config=(("ld_weight", 0.0),)),
    RowSpec("CoTTA + L_d", "cotta", paper="CoTTA"),
    RowSpec("CoTTA (no L_d)", "cotta", method_config=(("ld_weight", 0.0),)),
    RowSpec("ActMAD + L_d", "actmad", paper="ActMAD"),
    RowSpec("ActMAD (no L_d)", "actmad", method_config=(("ld_weight", 0.0),)),
    RowSpec("Ada-Depth + L_d", "adadepth", paper="Ada-Depth"),
    RowSpec("Ada-Depth (no L_d)", "adadepth", method_config=(("ld_weight", 0.0),)),
    RowSpec("Depth Anything V2", "none", model="depth_anything_v2", paper="DepthAnythingV2"),
    RowSpec("PITTA", "pitta", paper="PITTA (ours)"),
)
TITLE = ("MonoDepth2 ResNet-18 adapted online; every baseline with PITTA's L_d "
         "(paper Sec. 4.1). Bold: best, underlined: second, per test case, among the paper's "
         "methods (our added rows, BN batch stats and the baselines without L_d, are not "
         "ranked).")


def run(args, runners=None) -> int:
  from experiments.figures import per_frame_figures
  from experiments.tables import publish, rows_table
  ctx = common.context(args, "table1", runners)
  elapsed = common.timer()
  entries = rows_table(ctx, ROWS, CASES, table=1)
  caption = f"{TITLE} Dataset: {_dataset_caption(ctx)}."
  per_frame_figures(ctx.out, "table1", entries, ctx.quick,
                    check=lambda: common.check_out(ctx))
  return publish(ctx, "table1", entries, elapsed(), layout="rows", caption=caption,
                 group_title="Weather", row_title="Method")


def _dataset_caption(ctx) -> str:
  if ctx.dataset == "synthetic":
    return common.SYNTHETIC_CAPTION["drivingstereo"] + f", {ctx.frames} frames per part"
  return f"DrivingStereo at {ctx.root}"


def main(argv: Sequence[str] | None = None, runners=None) -> int:
  p = common.parser("table1", __doc__.split("\n\n")[0])
  return common.main_wrapper(run, p, argv, runners)


if __name__ == "__main__":  # as python -m experiments: signals and library logs handled
  from pitta_jax.cli import exit_with, interruptible
  exit_with(interruptible(main))
