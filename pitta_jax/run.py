"""One adaptation run, evaluated: a method over a frame sequence -> per-frame metrics and logs.

This is what `pitta-jax adapt`, `pitta-jax evaluate`, the demo and the experiments call. The
compiled chunk runner is cached per (network, config, input size), so the same compile serves
every sequence of a sweep (e.g. the four weather shifts of the demo).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm import tqdm

from pitta_jax import metrics as metrics_lib
from pitta_jax.adapt import (AdaptConfig, StepOutput, adapt_stream, init_state,
                             make_chunk_runner, make_optimizer, make_step, monodepth2_model)
from pitta_jax.adapt.inputs import chunks
from pitta_jax.adapt.methods import get_method
from pitta_jax.checkpoint import MonoDepth2Weights
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """MonoDepth2 evaluation protocol (SPEC "Evaluation")."""
  min_depth: float = 1e-3
  max_depth: float = 80.0
  median_scaling: bool = True   # monocular models: per-image median scaling
  garg_crop: bool = False       # KITTI Eigen split only


@dataclasses.dataclass
class RunResult:
  """Everything one run produced (host NumPy)."""
  name: str
  per_frame: list[dict[str, float]]    # 7 metrics per frame (frames with ground truth)
  mean: dict[str, float]               # averaged over frames
  logs: dict[str, np.ndarray]          # per frame: loss, loss_d, loss_e, n_instances, skipped...
  frame_names: list[str]
  seconds: float
  kept_depths: dict[int, np.ndarray]   # frame index -> predicted depth (network size)
  n_skipped: int = 0

  @property
  def fps(self) -> float:
    return len(self.frame_names) / self.seconds if self.seconds > 0 else float("nan")


@functools.lru_cache(maxsize=16)
def _runner(num_layers: int, cfg: AdaptConfig):
  model, method = monodepth2_model(num_layers), get_method(cfg.method)
  tx = make_optimizer(cfg)
  return model, method, tx, make_chunk_runner(make_step(model, method, cfg, tx))


def run_sequence(weights: MonoDepth2Weights, frames: Sequence[Frame], cfg: AdaptConfig,
                 eval_cfg: EvalConfig = EvalConfig(), name: str = "", quiet: bool = False,
                 keep: Sequence[int] = (), checkpoint_dir: str | Path | None = None,
                 checkpoint_every: int = 0) -> RunResult:
  """Runs `cfg.method` online over `frames` (predict-then-adapt) and evaluates each prediction
  against the frame's ground truth (when it has one).

  Args:
    weights: the network to adapt (its config gives the input size).
    frames: the sequence, any length; read lazily chunk by chunk.
    keep: frame indices whose predicted depth is returned (for figures).
  """
  if len(frames) == 0:
    raise DataError(name or "sequence", "no frames to adapt on")
  h, w = weights.config.height, weights.config.width
  model, method, tx, runner = _runner(weights.config.num_layers, cfg)
  state = init_state(weights.depth, method, cfg, tx)
  per_frame, names, kept, logs = [], [], {}, []
  keep = set(keep)
  bar = tqdm(total=len(frames), desc=name or cfg.method, unit="frame", disable=quiet)
  t0 = time.perf_counter()
  # a sequence shorter than a chunk is one chunk of its own length (no padded steps)
  stream = chunks(frames, h, w, min(cfg.chunk_size, len(frames)), cfg.max_segments)
  chunk_frames: list[list[Frame]] = []

  def inputs():
    for chunk, originals in stream:
      chunk_frames.append(originals)
      yield chunk

  index = 0
  for state, out in adapt_stream(state, inputs(), runner, checkpoint_dir, checkpoint_every):
    originals = chunk_frames.pop(0)
    for k, frame in enumerate(originals):
      depth = out.depth[k]
      if index in keep:
        kept[index] = depth
      if frame.depth is not None:
        per_frame.append(metrics_lib.depth_metrics(
            depth, frame.depth, min_depth=eval_cfg.min_depth, max_depth=eval_cfg.max_depth,
            median_scaling=eval_cfg.median_scaling, garg_crop=eval_cfg.garg_crop))
      names.append(frame.name)
      index += 1
    logs.append(out)
    running = np.mean([m["abs_rel"] for m in per_frame]) if per_frame else float("nan")
    bar.update(len(originals))
    bar.set_postfix(abs_rel=f"{running:.4f}", loss=f"{float(np.mean(out.loss)):.3g}")
  bar.close()
  seconds = time.perf_counter() - t0
  log_arrays = {f: np.concatenate([getattr(o, f) for o in logs]) for f in StepOutput._fields
                if f != "depth"}
  mean = metrics_lib.mean_metrics(per_frame) if per_frame else {}
  return RunResult(name=name, per_frame=per_frame, mean=mean, logs=log_arrays,
                   frame_names=names, seconds=seconds, kept_depths=kept,
                   n_skipped=int(state.n_skipped))
