"""Throughput of many adaptation streams in one compiled call (`pitta_jax.adapt.streams`).

    python benchmarks/streams.py                 # 640x192, K = 1, 4, 12 and the lambda sweep
    python benchmarks/streams.py --quick         # 320x96

Prints JSON lines:
- `impl: engine`: the plain single-stream engine (`make_method_runner`);
- `impl: vmap`, K = 1, 4, 12 independent streams (own frames, parameters and Adam state), one
  `jax.vmap`-ed step scanned over a chunk: total frames/s = K * T / chunk time;
- `impl: lambda_sweep`: the 12 lambdas of the paper's Table 4 ({0, 0.1, ..., 1.0, inf}) as 12
  streams on the same frames in one call, vs the same 12 runs one after another (one compiled
  single-stream runner, reused), and the speedup.
Steady state: compile and one warm-up chunk first, then the median over `--reps` chunks.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dataclasses  # noqa: E402
import math  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import bench_common as bc  # noqa: E402
from pitta_jax.adapt import (AdaptConfig, init_state, make_chunk_runner,  # noqa: E402
                             make_method_runner, make_optimizer)
from pitta_jax.adapt import streams  # noqa: E402
from pitta_jax.adapt.xla_cpu import step_compiler_options  # noqa: E402
from pitta_jax.methods import build  # noqa: E402
from pitta_jax.methods.pitta import PittaConfig  # noqa: E402

# the lambdas of eq. 10 in the paper's Table 4 (inf = L_e only)
TABLE4_LAMBDAS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, math.inf)


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--height", type=int, default=192)
  p.add_argument("--width", type=int, default=640)
  p.add_argument("--instances", type=int, default=8)
  p.add_argument("--ks", default="1,4,12", help="numbers of independent streams")
  p.add_argument("--frames", type=int, default=4, help="frames per chunk (per stream)")
  p.add_argument("--reps", type=int, default=2)
  p.add_argument("--quick", action="store_true", help="320x96")
  args = p.parse_args(argv)
  try:
    ks = [int(x) for x in args.ks.split(",")]
  except ValueError:
    p.error(f"--ks: expected a comma list of integers, got {args.ks!r}")
  if min(ks) < 1 or args.frames < 1 or args.reps < 1:
    p.error("--ks, --frames and --reps must be >= 1")
  if args.quick:
    args.height, args.width = 96, 320
  common = {"H": args.height, "W": args.width, "instances": args.instances,
            "frames_per_chunk": args.frames, "devices": len(jax.devices()),
            "device": jax.devices()[0].platform}
  cfg, pitta = AdaptConfig(chunk_size=args.frames), PittaConfig()
  model, method = bc.depth_network(), build("pitta", pitta)
  tx = make_optimizer(cfg)
  options = step_compiler_options(cfg, method)  # as `pitta-jax adapt` compiles the step
  variables = bc.jax_variables(seed=0)
  t = args.frames

  def chunk(seed: int):
    return bc.step_inputs(bc.synthetic_frames(t, args.height, args.width, args.instances, seed),
                          cfg.max_segments)

  def copy(state):
    return jax.tree_util.tree_map(jnp.copy, state)

  # plain engine, one stream
  runner = make_method_runner(model, method, cfg, tx)
  state, consts = init_state(variables, method, cfg, tx, model)
  first, _, med, _, _ = bc.timed_chunks(runner, state, chunk(0), consts, args.reps)
  base_fps = t / med
  bc.emit({"impl": "engine", "streams": 1, **common, "frames_per_s": base_fps,
           "ms_per_frame": 1e3 * med / t, "first_chunk_s": round(first, 1), "load": bc.load()})

  # K independent streams
  multi = make_chunk_runner(streams.make_multi_stream_step(model, method, cfg, tx), options)
  for k in ks:
    frames = streams.stack_stream_inputs([chunk(100 + i) for i in range(k)])
    states, consts = streams.init_streams(variables, method, cfg, k, tx, model=model)
    first, _, med, _, _ = bc.timed_chunks(multi, states, frames, consts, args.reps)
    bc.emit({"impl": "vmap", "streams": k, **common, "frames_per_s": k * t / med,
             "speedup_vs_engine": k * t / med / base_fps, "first_chunk_s": round(first, 1),
             "load": bc.load()})

  # Table 4: 12 lambdas, same frames; one call vs one after another
  lams = TABLE4_LAMBDAS
  shared = chunk(7)
  sweep = make_chunk_runner(streams.make_lambda_sweep_step(model, cfg, tx, pitta=pitta), options)
  states, consts = streams.init_lambda_sweep(variables, lams, cfg, tx, pitta=pitta, model=model)
  first, _, med_sweep, _, _ = bc.timed_chunks(sweep, states, shared, consts, args.reps)
  # the sequential reference: the plain engine with PittaConfig(lam=lam), one run per lambda.
  # lambda is a method-state value, so all 12 share one compiled runner (PittaConfig(lam=0.2)'s);
  # each run's state comes from its own method (method_state {"lam": lam})
  one = make_method_runner(model, method, cfg, tx)
  singles = [init_state(variables, build("pitta", dataclasses.replace(pitta, lam=lam)), cfg, tx,
                        model) for lam in lams]
  consts = singles[0][1]
  jax.block_until_ready(one(copy(singles[0][0]), shared, consts))  # compile
  holder = [copy(s) for s, _ in singles]
  for i in range(len(lams)):  # warm-up, as for the sweep
    holder[i], _ = one(holder[i], shared, consts)

  def sequential():
    for i in range(len(lams)):
      holder[i], o = one(holder[i], shared, consts)
      jax.block_until_ready(o)
  med_seq, _ = bc.median_time(sequential, args.reps)
  n = len(lams) * t
  bc.emit({"impl": "lambda_sweep", "streams": len(lams), **common,
           "lambdas": [str(x) for x in lams],
           "one_call_frames_per_s": n / med_sweep, "sequential_frames_per_s": n / med_seq,
           "speedup": med_seq / med_sweep, "first_chunk_s": round(first, 1), "load": bc.load()})


if __name__ == "__main__":
  main()
