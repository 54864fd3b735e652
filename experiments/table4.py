"""Table 4: PITTA's lambda (eq. 10) from 0 to 1 and infinity on Waymo, all 12 values as one
vmapped run (`pitta_jax.adapt.streams`: one stream per lambda, the same frames).

    pitta-jax experiment table4 [--quick] [--dataset waymo --root DIR --weights DIR ...]
    python -m experiments.table4 ...
"""

from __future__ import annotations

import dataclasses

import json
import math
from typing import Sequence

import numpy as np

from experiments import common
from experiments.common import Entry, RowSpec

LAMBDAS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, math.inf)


def label(lam: float) -> str:
  """The paper's column label: 0, 0.1, ..., 0.9, 1.0, ∞."""
  return "∞" if math.isinf(lam) else "1.0" if lam == 1 else f"{lam:g}"


def lambda_sweep(weights, frames, lams: Sequence[float], quiet: bool = True,
                 quick: bool = False, runners=None, checkpoint_dir=None,
                 eval_cfg=None, check_out=None) -> list[dict]:
  """PITTA with each lambda of `lams` over `frames`, as one vmapped run; per lambda
  {"metrics": mean of the 7, "abs_rel_per_frame": [...] (every frame, NaN where not scored),
  "frames": n, "status": "ok" or why there are no metrics, "metrics_before_divergence"}: a
  lambda whose depth stops being finite is that lambda's divergence, as a table row's
  (`run.RunResult.status`), not the sweep's failure; its frames from there are not scored.
  runners: a `run.Runners` that keeps the compiled sweep for later calls. checkpoint_dir: the
  sweep's states and results so far are saved there every `common.CHECKPOINT_EVERY` frames (and
  on Ctrl-C), and a sweep interrupted before resumes from its newest checkpoint (one of another
  sweep is removed, with a warning), with the result of an uninterrupted one. eval_cfg: the
  `run.EvalConfig` each frame is scored with (None: its defaults). check_out: called before
  each checkpoint save, it raises to stop the sweep where the folder of `checkpoint_dir` was
  removed or replaced (`run.run_sequence`'s check_out; None: no check)."""
  from pathlib import Path
  from tqdm import tqdm
  from pitta_jax import metrics as metrics_lib
  from pitta_jax.adapt import streams
  from pitta_jax.adapt.engine import wait_for_chunk
  from pitta_jax.adapt.inputs import chunks
  from pitta_jax.methods import build
  from pitta_jax.methods.depth_refining import dynamic_classes
  from pitta_jax.outputs import check_passes
  from pitta_jax.run import (EvalConfig, Runners, check_aspect, checkpoint_chunk_size,
                             frame_metrics, frame_names, input_size, load_resume_point,
                             model_alignment, note_compile, record_marks, run_fingerprint,
                             run_status, save_checkpoint, truncate_record)
  cfg = common.adapt_config("pitta", quick=quick)
  pitta = build("pitta")  # every lambda's method but for lambda (the vmapped axis)
  every = common.CHECKPOINT_EVERY if checkpoint_dir is not None else 0
  cfg = dataclasses.replace(cfg, chunk_size=checkpoint_chunk_size(cfg.chunk_size, every))
  key = ("lambda_sweep", weights.spec.name, json.dumps(weights.config, sort_keys=True,
                                                       default=str), cfg, len(lams))
  model, tx, runner = (runners or Runners()).custom(key, lambda: _sweep_runner(weights, cfg))
  states, consts = streams.init_lambda_sweep(weights.depth, lams, cfg, tx, model=model)
  ev = eval_cfg if eval_cfg is not None else EvalConfig()
  names = frame_names(frames)  # (not read: a dataset's frames are read as the sweep runs)
  # per lambda: the scored frames' metrics, the frames whose depth is not finite, and AbsRel
  # of every frame (None where not scored: the curves' x is the frame index)
  record = {"names": [], "per_frame": [[] for _ in lams], "nonfinite": [[] for _ in lams],
            "abs_rel": [[] for _ in lams], "fingerprint": None}
  directory = Path(checkpoint_dir) if checkpoint_dir is not None else None
  if directory is not None:
    if check_out is not None:
      check_out()
    directory.parent.mkdir(parents=True, exist_ok=True)  # (e.g. --out/rows: made now, as
    # run_sequence does, never by a save: a save refuses a folder gone while the run went on)
    record["fingerprint"] = run_fingerprint(weights, pitta, cfg, ev,
                                            [*names, f"lambdas {list(lams)}"])
    found = load_resume_point(directory, record["fingerprint"], names, states, strict=False,
                              template=record)
    if found is not None:
      states, record = found
  start = len(record["names"])
  h, w = input_size(weights, frames)
  bar = tqdm(total=len(frames), initial=start, desc="lambda sweep", unit="frame",
             disable=quiet)
  note_compile(bar, runner)
  done = (states, record_marks(record))  # the newest states whose frames are all in `record`
  last_saved = start  # frames in the newest checkpoint (or resumed from)
  try:
    for chunk, originals in chunks(frames[start:], h, w,
                                   min(cfg.chunk_size, max(len(frames) - start, 1)),
                                   cfg.max_segments, weights.spec.image_resize,
                                   dynamic_classes(pitta.config)):
      for frame in originals:  # the prediction is resized onto the ground truth, as in
        check_aspect(frame)    # `run.run_sequence`: refused before the chunk runs
      states, out = runner(states, chunk, consts)
      held = wait_for_chunk((states, out))  # an interrupt meanwhile: raised once it is recorded
      depth = np.asarray(out.depth)                                     # (T, K, H, W)
      for t, frame in enumerate(originals):
        for k in range(len(lams)):
          if not np.isfinite(depth[t, k]).all():
            record["nonfinite"][k].append(len(record["names"]))
            record["abs_rel"][k].append(None)
            continue
          if frame.depth is None:  # no ground truth (e.g. --option depth=false): not scored,
            record["abs_rel"][k].append(None)  # as `run.run_sequence` leaves such a frame
            continue
          try:
            m = frame_metrics(depth[t, k], frame.depth, ev, model_alignment(weights))
          except metrics_lib.NoValidPixels:
            record["abs_rel"][k].append(None)
            continue
          record["per_frame"][k].append(m)
          record["abs_rel"][k].append(m["abs_rel"])
        record["names"].append(frame.name)
      n = len(record["names"])
      done = (states, record_marks(record))
      if every and n < len(frames) and n % every == 0:
        save_checkpoint(directory, states, record, check_out)
        last_saved = n
      bar.set_postfix_str("", refresh=False)
      bar.update(len(originals))
      if held is not None:
        raise held
  except KeyboardInterrupt:
    done_states, marks = done
    n = marks["names"][0]
    # the last whole chunk is not lost, nor one whose save the Ctrl-C cut (the save removes
    # what it wrote)
    if every and n > last_saved and check_passes(check_out):
      truncate_record(record, marks)
      save_checkpoint(directory, done_states, record, check_out)
    raise
  finally:
    bar.close()
  # a checkpoint's JSON holds NaN as null
  per_frame = [[{k: float("nan") if v is None else v for k, v in m.items()} for m in p]
               for p in record["per_frame"]]
  results = []
  for p, bad, series in zip(per_frame, record["nonfinite"], record["abs_rel"]):
    mean = metrics_lib.mean_metrics(p) if p else {}
    status = run_status(bad, len(frames), len(p))
    results.append({"metrics": mean if status == "ok" else {}, "status": status,
                    "metrics_before_divergence": mean if bad else None, "frames": len(frames),
                    "abs_rel_per_frame": [float("nan") if v is None else v for v in series]})
  return results


def _sweep_runner(weights, cfg):
  """(model, optimiser, the compiled chunk of the vmapped lambda-sweep step)."""
  from pitta_jax.adapt import streams
  from pitta_jax.adapt.engine import make_chunk_runner, make_optimizer
  from pitta_jax.adapt.xla_cpu import step_compiler_options
  from pitta_jax.methods import build
  model, tx = weights.network(), make_optimizer(cfg)
  options = step_compiler_options(cfg, build("pitta"))  # the sweep runs PITTA's step
  return model, tx, make_chunk_runner(streams.make_lambda_sweep_step(model, cfg, tx), options)


def run(args, runners=None) -> int:
  from experiments.figures import lambda_figure
  from experiments.table2 import waymo_caption
  from experiments.tables import publish
  ctx = common.context(args, "table4", runners)
  common.check_flags_used(ctx, [RowSpec("PITTA", "pitta")])  # the sweep: PITTA on MonoDepth2
  elapsed = common.timer()
  (case, parts), = ctx.cases(("Waymo",))
  weights = common.weights_for(ctx, "monodepth2")
  if weights is None:  # a table of 'needs weights' only is not a result (`check_rows`)
    from pitta_jax.data.errors import DataError
    raise DataError(None, f"no weights for the sweep: --weights monodepth2=DIR (on "
                          f"{ctx.dataset} no network is trained for you)")
  # the sweep's frames opened (paths only) before any work
  common.no_instances(ctx, [(case, parts, RowSpec("PITTA", "pitta"))],
                      common.check_cases(ctx, [(case, parts)]))
  common.clear_earlier_table(ctx)
  row = RowSpec("lambda sweep", "pitta", method_config=(("lam", LAMBDAS),))
  key = common.row_key(ctx, row, case, parts, common.weights_identity(ctx, "monodepth2",
                                                                      weights))

  def compute():
    frames = common.case_frames(ctx, parts, weights.height, weights.width)
    took = common.timer()
    sweep = lambda_sweep(weights, frames, LAMBDAS, ctx.quiet, ctx.quick, common.runners(ctx),
                         common.checkpoints(ctx, key, f"{case}: {row.label}"), ctx.evaluation(),
                         lambda: common.check_out(ctx))
    return {"sweep": sweep, "seconds": round(took(), 2)}
  cached = common.cached(ctx, key, compute, field="sweep", length=len(LAMBDAS))
  common.remove_checkpoints(ctx, key)
  # one vmapped run computes every lambda: each row's seconds are the whole sweep's
  # what each stream ran with (lambda_sweep's AdaptConfig, PITTA's config at that lambda)
  adapt = dataclasses.asdict(common.adapt_config("pitta", quick=ctx.quick))
  from pitta_jax.methods.pitta import PittaConfig
  pitta = PittaConfig()
  entries = [Entry(case, label(lam), r["metrics"], status=r.get("status", "ok"), extra={
      "lambda": lam, "frames": r["frames"], "seconds": cached.get("seconds"),
      "metrics_before_divergence": r.get("metrics_before_divergence"),
      "abs_rel_per_frame": r["abs_rel_per_frame"], "adapt": adapt,
      "method_config": dataclasses.asdict(dataclasses.replace(pitta, lam=lam)),
      "row_key": key})
      for lam, r in zip(LAMBDAS, cached["sweep"])]
  common.attach_paper(entries, 4, lambda e: {"lambda": e.extra["lambda"]})
  caption = (f"PITTA's lambda of eq. 10 (AbsRel, δ<1.25), 12 streams in one vmapped run (each "
             f"row's seconds are that run's). Best bold, second underlined (ours: the paper's "
             f"Table 4 marks none). Dataset: {waymo_caption(ctx)}.")
  lambda_figure(ctx.out, "table4", entries, ctx.quick,
                    check=lambda: common.check_out(ctx))
  return publish(ctx, "table4", entries, elapsed(), layout="columns", caption=caption,
                 group_title="Dataset", row_title="λ", metrics=("abs_rel", "a1"))


def main(argv: Sequence[str] | None = None, runners=None) -> int:
  p = common.parser("table4", __doc__.split("\n\n")[0], datasets=("synthetic", "waymo"),
                    rows=False)
  return common.main_wrapper(run, p, argv, runners)


if __name__ == "__main__":  # as python -m experiments: signals and library logs handled
  from pitta_jax.cli import exit_with, interruptible
  exit_with(interruptible(main))
