"""Where does PITTA's loss matter? A sweep on the synthetic benchmark.

    pitta-jax experiment sensitivity [--quick] [--frames N] [--out DIR]
    python -m experiments.sensitivity ...

PITTA (eqs. 3-11) changes two things at once with respect to the source model: BatchNorm uses
the frame's statistics (train-mode BN, as in TENT), and the loss moves the BN scale/shift. The
"BN batch stats" row (no update) isolates the first; every number here is PITTA minus that row
(negative = the loss helps) on the same frames, swept over:

  learning rate (1e-5 .. 1e-2) x steps per frame (1, 3, 5), lambda of eq. 10 (Table 4's 12
  values, one vmapped run),
  the BN mode while adapting (running statistics: against No adaptation, the source model with
  its running statistics and no update), the sequence length (the mean over
  the first N frames of one long run), and the traffic density (more dynamic instances means
  more pixels under L_d).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from experiments import common
from experiments.common import Entry, RowSpec
from experiments.table4 import LAMBDAS

CASE = {"domain": "fog", "seed": common.TARGET_SEED}
DENSE = {**CASE, "n_cars": 16.0, "n_pedestrians": 16.0, "n_cyclists": 4.0, "n_lead_cars": 2}
LRS = (1e-5, 1e-4, 1e-3, 1e-2)
STEPS = (1, 3, 5)
LENGTHS = (10, 25, 50, 100)
# --quick: one setting per study (the default PITTA row and BN running)
QUICK = dict(lrs=(1e-4,), steps=(1,), lengths=(1, 2, 4))
REFERENCE = RowSpec("BN batch stats", "none", adapt=(("bn_stats", "batch"),))
# the BN-mode study's reference: running statistics, no update (the source model as it is)
RUNNING_REFERENCE = RowSpec("No adaptation", "none")


def grid(quick: bool) -> list[tuple[str, str, RowSpec, dict]]:
  """(study, setting label, row, case part) of every run besides the lambda sweep."""
  lrs, steps = (QUICK["lrs"], QUICK["steps"]) if quick else (LRS, STEPS)
  runs = [("reference", "BN batch stats", REFERENCE, CASE)]
  for lr in lrs:
    for k in steps:
      runs.append(("lr x steps", f"lr {lr:g}, {k} step{'s' * (k > 1)}",
                   RowSpec(f"PITTA lr {lr:g} x{k}", "pitta",
                           adapt=(("lr", lr), ("steps_per_frame", k))), CASE))
  runs.append(("BN mode", "running: reference", RUNNING_REFERENCE, CASE))
  runs.append(("BN mode", "running statistics",
               RowSpec("PITTA BN running", "pitta", adapt=(("bn_stats", "running"),)), CASE))
  runs.append(("traffic", "dense: reference", REFERENCE, DENSE))
  runs.append(("traffic", "dense: PITTA", RowSpec("PITTA", "pitta"), DENSE))
  return runs


def run(args, runners=None) -> int:
  from tqdm import tqdm
  from experiments.render import write_table
  from experiments.table4 import label, lambda_sweep
  ctx = common.context(args, "sensitivity", runners)
  if ctx.dataset != "synthetic":
    raise ValueError("--dataset: the sensitivity study runs on the synthetic benchmark")
  elapsed = common.timer()
  lengths = QUICK["lengths"] if ctx.quick else LENGTHS
  ctx.frames = max(ctx.frames, max(lengths)) if not args.frames else ctx.frames
  runs = [(study, setting, row, "fog" if part is CASE else "fog, dense traffic", (part,))
          for study, setting, row, part in grid(ctx.quick)]
  # what the runs need, before any work and before the earlier study's files go: flags it
  # cannot use (--weights of another network), the weights themselves
  common.check_flags_used(ctx, [row for _, _, row, _, _ in runs])
  common.check_rows(ctx, [(case, parts, row) for _, _, row, case, parts in runs])
  common.clear_earlier_table(ctx)
  shared, resources, results = common.runners(ctx), {}, []
  for study, setting, row, case, parts in tqdm(runs, desc="runs", unit="run",
                                               disable=ctx.quiet):
    results.append((study, setting, common.run_row(ctx, row, case, parts, shared, resources)))
  weights = common.weights_for(ctx, "monodepth2")
  lams = LAMBDAS  # Table 4's 12, one vmapped run
  row = RowSpec("lambda sweep", "pitta", method_config=(("lam", lams),))
  key = common.row_key(ctx, row, "fog", (CASE,), common.weights_identity(ctx, "monodepth2",
                                                                          weights))
  sweep = common.cached(ctx, key, lambda: {"sweep": lambda_sweep(
      weights, common.case_frames(ctx, (CASE,), weights.height, weights.width), lams,
      ctx.quiet, ctx.quick, shared, common.checkpoints(ctx, key, f"fog: {row.label}"),
      ctx.evaluation(),
      lambda: common.check_out(ctx))},
      field="sweep", length=len(lams))["sweep"]
  common.remove_checkpoints(ctx, key)
  ref = results[0][2]
  dense_ref = next(e for s, n, e in results if n == "dense: reference")
  running_ref = next(e for s, n, e in results if n == "running: reference")
  entries = []
  for study, setting, e in results:
    if study == "reference" or setting.endswith(": reference"):
      continue
    base = {"traffic": dense_ref, "BN mode": running_ref}.get(study, ref)
    entries.append(_delta(study, setting, e, base))
  for lam, r in zip(lams, sweep):
    entries.append(_delta("lambda", f"λ = {label(lam)}",
                          Entry("fog", "", r["metrics"], status=r.get("status", "ok")), ref))
  default = next(e for s, n, e in results if n.startswith("lr 0.0001, 1 step"))
  for n in [n for n in lengths if n <= ctx.frames]:  # a mean over frames the run has
    failed = next((e for e in (default, ref) if e.status != "ok"), None)
    if failed is not None:  # its per-frame values are the frames it scored, not the first n
      entries.append(Entry("sequence length", f"first {n} frame{'s' * (n > 1)}", {},
                           status=f"{failed.label}: {failed.status}"))
      continue
    # NaN (null when served from the row cache): a frame not scored
    a = np.nanmean(np.asarray(default.extra["abs_rel_per_frame"][:n], np.float64))
    b = np.nanmean(np.asarray(ref.extra["abs_rel_per_frame"][:n], np.float64))
    entries.append(Entry("sequence length", f"first {n} frame{'s' * (n > 1)}",
                         {"abs_rel": float(a - b)}))
  md = write_table(ctx.out, "sensitivity", entries, layout="rows",
                   caption=("PITTA minus 'BN batch stats' (the same frames, no update) on "
                            f"synthetic fog, {ctx.frames} frames: negative AbsRel / positive "
                            "δ = the loss helps. Reference AbsRel "
                            f"{_abs_rel(ref)}; the BN-mode row is PITTA with "
                            "running statistics minus No adaptation (running statistics, no "
                            f"update: AbsRel {_abs_rel(running_ref)}); the traffic "
                            "row is against BN batch stats on the dense street. "
                            + common.caption_notes(ctx)).strip(),
                   group_title="Study", row_title="Setting", seconds=elapsed(), decimals=4,
                   meta={**common.meta(ctx), "reference": ref.metrics,
                         "dense_reference": dense_ref.metrics,
                         "running_reference": running_ref.metrics, "verdict": verdict(entries)})
  if not ctx.quiet:
    print(md)
    print(verdict(entries))
  return 0


def _delta(study: str, setting: str, ours: Entry, ref: Entry) -> Entry:
  """`ours` minus `ref`; where either has no metrics (diverged, not scored), its status."""
  failed = next((e for e in (ours, ref) if e.status != "ok"), None)
  if failed is not None:
    return Entry(study, setting, {}, status=failed.status if failed is ours
                 else f"reference {failed.label}: {failed.status}")
  return Entry(study, setting, {m: ours.metrics[m] - ref.metrics[m] for m in ours.metrics
                                if m in ref.metrics})


def _abs_rel(e: Entry) -> str:
  return f"{e.metrics['abs_rel']:.4f}" if e.status == "ok" else e.status


def verdict(entries: Sequence[Entry], noise: float = 0.002) -> str:
  """One sentence per study: the best and worst AbsRel change, and whether it beats `noise`."""
  lines = []
  for study in dict.fromkeys(e.group for e in entries):
    vals = [(e.metrics["abs_rel"], e.label) for e in entries if e.group == study
            and math.isfinite(e.metrics.get("abs_rel", math.nan))]
    if not vals:
      continue
    best, worst = min(vals), max(vals)
    word = "helps" if best[0] < -noise else "hurts" if worst[0] > noise and best[0] > -noise \
        else "is within noise"
    lines.append(f"{study}: the loss {word} (best {best[0]:+.4f} at {best[1]}, worst "
                 f"{worst[0]:+.4f} at {worst[1]})")
  return "\n".join(lines)


def main(argv: Sequence[str] | None = None, runners=None) -> int:
  p = common.parser("sensitivity", __doc__.split("\n\n")[0], datasets=("synthetic",),
                    rows=False, frames=max(LENGTHS), quick_frames=max(QUICK["lengths"]))
  return common.main_wrapper(run, p, argv, runners)


if __name__ == "__main__":  # as python -m experiments: signals and library logs handled
  from pitta_jax.cli import exit_with, interruptible
  exit_with(interruptible(main))
