"""Where the wall time of a whole run goes: `pitta-jax demo` or one experiments table, end to end.

    python benchmarks/whole_run.py demo                      # the demo's defaults, source cached
    python benchmarks/whole_run.py demo --demo.methods none,bn,pitta,actmad,cotta
    python benchmarks/whole_run.py experiment table4 --quick # any `pitta-jax experiment` command

Runs the command in this process (the same code path as the CLI: `pitta_jax.cli.main`) with
timers around the project's functions, and prints JSON lines:
- one per part of the run, exclusive wall seconds (a part's time minus that of the parts it
  calls) and its share: source model (load or train), method resources (ActMAD's source
  statistics), data (frame generation / reading), host inputs (resizing and stacking frames
  into chunks), initial state, compiles (tracing, lowering, XLA; from `jax.monitoring`), steps
  (the compiled chunks, computed to completion), device-to-host copies of their outputs,
  metrics, figures and files, and the rest (Python, progress bars);
- one per compiled chunk runner: its compile seconds (tracing + lowering + XLA, the first call)
  and its steady ms per frame;
- the totals: wall seconds, frames stepped, step ms per frame, and the load average.
The timers are installed for this process only (nothing in the library changes); a part is
wrapped wherever the function is bound (`from ... import` copies included).
"""

from __future__ import annotations

import collections
import functools
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import numpy as np  # noqa: E402

import bench_common as bc  # noqa: E402

# part name -> (module, function name) of the functions timed as that part
PARTS = {
    "source model (load or train)": [("pitta_jax.source_model", "load_or_train_source")],
    "method resources (source statistics)": [("pitta_jax.sources", "method_resources")],
    "data: frames (generate / read)": [("pitta_jax.data.synthetic", "generate_sequence"),
                                       ("pitta_jax.data.readers", "open_dataset")],
    "host inputs: resize and stack into chunks": [("pitta_jax.adapt.inputs", "chunks")],
    "initial state (split, copies)": [("pitta_jax.adapt.engine", "init_state")],
    "metrics": [("pitta_jax.metrics", "depth_metrics"), ("pitta_jax.metrics", "mean_metrics")],
    "figures and files": [("pitta_jax.plots", "per_frame_figure"), ("pitta_jax.plots", "save_figure"),
                          ("pitta_jax.report", "write_results"), ("pitta_jax.viz", "grid"),
                          ("pitta_jax.data.image_io", "write_image")],
}
COMPILE = "compiles (trace, lower, XLA)"
STEPS = "steps (compiled chunks)"
TRANSFERS = "device-to-host copies of step outputs"
OTHER = "rest (Python, progress bars, checkpoints)"
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                  "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")


class Timers:
  """Exclusive wall time per part: a part's time minus that of the parts running inside it."""

  def __init__(self):
    self.total = collections.Counter()
    self.stack: list[list] = []  # [part, start, time in nested parts]

  def enter(self, part: str) -> None:
    self.stack.append([part, time.perf_counter(), 0.0])

  def leave(self) -> float:
    part, start, nested = self.stack.pop()
    spent = time.perf_counter() - start
    self.total[part] += spent - nested
    if self.stack:
      self.stack[-1][2] += spent
    return spent

  def add_nested(self, part: str, seconds: float) -> None:
    """Time measured elsewhere (compile events) inside the current part."""
    self.total[part] += seconds
    if self.stack:
      self.stack[-1][2] += seconds

  def wrap(self, part: str, fn: Callable) -> Callable:
    @functools.wraps(fn)
    def timed(*args, **kwargs):
      self.enter(part)
      try:
        out = fn(*args, **kwargs)
      finally:
        self.leave()
      if hasattr(out, "__next__"):  # a generator: time every item it produces
        return self.wrap_iter(part, out)
      return out
    return timed

  def wrap_iter(self, part: str, it):
    while True:
      self.enter(part)
      try:
        item = next(it)
      except StopIteration:
        self.leave()
        return
      self.leave()
      yield item


def patch_everywhere(original: Callable, replacement: Callable) -> None:
  """Rebinds `original` to `replacement` in every loaded module that holds it."""
  for module in list(sys.modules.values()):
    for name, value in list(getattr(module, "__dict__", {}).items()):
      if value is original:
        setattr(module, name, replacement)


class RunnerStats:
  """Per compiled chunk runner: compile seconds and step seconds / frames."""

  def __init__(self, timers: Timers):
    self.timers = timers
    self.runners: list[dict] = []
    self.compiling: dict | None = None

  def on_event(self, event: str, seconds: float, **_: Any) -> None:
    if event in COMPILE_EVENTS:
      self.timers.add_nested(COMPILE, seconds)
      if self.compiling is not None:
        self.compiling["compile_s"] += seconds

  def wrap_factory(self, make_chunk_runner: Callable) -> Callable:
    @functools.wraps(make_chunk_runner)
    def make(step, compiler_options=None):
      runner = make_chunk_runner(step, compiler_options)
      stats = {"runner": len(self.runners), "method": getattr(
          getattr(step, "keywords", {}).get("method"), "name", "?"), "compile_s": 0.0,
               "step_s": 0.0, "frames": 0, "chunks": 0}
      self.runners.append(stats)

      def run(state, frames, consts):
        self.compiling = stats
        self.timers.enter(STEPS)
        try:
          state, outs = runner(state, frames, consts)
          jax.block_until_ready(outs)
        finally:
          spent = self.timers.leave()
          self.compiling = None
        if stats["chunks"]:  # steady state: the first call compiles
          stats["step_s"] += spent
          stats["frames"] += int(np.asarray(frames.valid).sum())
        stats["chunks"] += 1
        self.timers.enter(TRANSFERS)
        outs = jax.device_get(outs)  # what adapt_stream's np.asarray would copy
        self.timers.leave()
        return state, outs
      return run
    return make


def install(timers: Timers, stats: RunnerStats) -> None:
  import importlib
  import pitta_jax.cli  # noqa: F401  (loads the modules the commands bind names from)
  for part, places in PARTS.items():
    for module_name, fn_name in places:
      try:
        module = importlib.import_module(module_name)
      except ImportError:
        continue
      original = getattr(module, fn_name, None)
      if original is not None:
        patch_everywhere(original, timers.wrap(part, original))
  from pitta_jax.adapt import engine
  patch_everywhere(engine.make_chunk_runner, stats.wrap_factory(engine.make_chunk_runner))
  jax.monitoring.register_event_duration_secs_listener(stats.on_event)


def main(argv=None) -> None:
  argv = list(sys.argv[1:] if argv is None else argv)
  if not argv or argv[0] in ("-h", "--help"):
    print(__doc__)
    return
  import experiments  # noqa: F401  (so that its bindings are patched too)
  from pitta_jax import cli
  timers, stats = Timers(), RunnerStats(Timers())
  stats.timers = timers
  install(timers, stats)
  bc.emit({"start": "whole_run", "command": argv, "load": bc.load()})
  t0 = time.perf_counter()
  timers.enter(OTHER)
  code = cli.main(argv)
  timers.leave()
  wall = time.perf_counter() - t0
  for part, seconds in sorted(timers.total.items(), key=lambda kv: -kv[1]):
    bc.emit({"part": part, "seconds": round(seconds, 2), "share": round(seconds / wall, 3)})
  for r in stats.runners:
    bc.emit({"runner": r["runner"], "method": r["method"], "compile_s": round(r["compile_s"], 2),
             "chunks": r["chunks"], "steady_ms_per_frame":
                 round(1e3 * r["step_s"] / r["frames"], 1) if r["frames"] else None})
  frames = sum(r["frames"] for r in stats.runners)
  step_s = sum(r["step_s"] for r in stats.runners)
  bc.emit({"command": argv, "exit_code": code, "wall_s": round(wall, 2),
           "steady_frames": frames, "steady_step_ms_per_frame":
               round(1e3 * step_s / frames, 1) if frames else None,
           "max_compile_s": round(max((r["compile_s"] for r in stats.runners), default=0.0), 2),
           "load": bc.load(), "cpus": os.cpu_count()})


if __name__ == "__main__":
  main()
