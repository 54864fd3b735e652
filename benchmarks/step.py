"""Time one PITTA adaptation step: the JAX engine vs a PyTorch eager reference, same process.

    python benchmarks/step.py                           # 640x192, N = 8 instances, s = 5
    python benchmarks/step.py --sweep-instances 1,8,32  # N side by side
    python benchmarks/step.py --quick                   # 320x96, fewer repetitions

Prints JSON lines: one per implementation and configuration (`impl`, `H`, `W`, `instances`,
`window`, `threads`, `ms_per_frame`), a `ratio` line (torch ms / jax ms) per configuration, a
loss-parity line (both start from the same random weights and see the same frames, so their
losses must agree), a sweep summary, and a profile: XLA's FLOP count of the step
(`jax.jit(...).lower(...).compile().cost_analysis()`), a FLOP floor at this machine's measured
matmul/conv rate, and the time of the parts (network forward only, forward + backward, loss
with its gradient w.r.t. the depth only, whole step) in both frameworks.

JAX timing: the engine's compiled chunk runner (`make_chunk_runner`: jit of a `lax.scan` of
`adapt_step` over `--frames` frames, carry donated), steady state (after compile and one warm-up
chunk), ms per frame = chunk time / chunk length, median over `--reps` chunks. PyTorch timing:
the same frames, one `TorchPitta.step` each after warm-up, median over `--reps` chunks.
Both use every core (`--threads` sets PyTorch's; XLA's CPU backend uses all cores).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import bench_common as bc  # noqa: E402
import torch_reference as tr  # noqa: E402
from pitta_jax import trainable as trainable_lib  # noqa: E402
from pitta_jax.adapt import (AdaptConfig, StepInput, init_state, make_chunk_runner,  # noqa: E402
                             make_optimizer, make_step)
from pitta_jax.methods import build  # noqa: E402
from pitta_jax.methods.depth_refining import DepthRefiningConfig, frame_loss  # noqa: E402
from pitta_jax.methods.pitta import PittaConfig  # noqa: E402


def engine_config(instances: int, window: int, frames: int) -> tuple[AdaptConfig, PittaConfig]:
  """The engine's and PITTA's default configs; the instance table grows only beyond its default
  32 rows."""
  base, ld = AdaptConfig(), DepthRefiningConfig()
  cfg = AdaptConfig(chunk_size=frames, max_segments=max(base.max_segments, instances + 2))
  pitta = PittaConfig(ld=DepthRefiningConfig(window=window,
                                             max_instances=max(ld.max_instances, instances)))
  return cfg, pitta


class JaxBench:
  """The engine's compiled chunk runner, one per config (shapes), reused across frame sets."""

  def __init__(self, variables, configs: tuple[AdaptConfig, PittaConfig],
               conv_rule: str = "loop_friendly"):
    self.variables = variables
    self.cfg, self.pitta = configs
    self.model, self.method = bc.depth_network(conv_rule), build("pitta", self.pitta)
    self.tx = make_optimizer(self.cfg)
    self.step = make_step(self.model, self.method, self.cfg, self.tx)
    self.runner = make_chunk_runner(self.step)
    self.consts = None
    self.compile_s = None

  def fresh_state(self):
    """A fresh carry (private copies: the runner donates it); the constants are kept."""
    state, consts = init_state(self.variables, self.method, self.cfg, self.tx, self.model)
    if self.consts is None:
      self.consts = consts
    return state

  def run(self, chunk: StepInput, reps: int) -> dict:
    state = self.fresh_state()
    first_s, outs, med, best, _ = bc.timed_chunks(self.runner, state, chunk, self.consts, reps)
    if self.compile_s is None:
      self.compile_s = first_s
    n = int(np.asarray(chunk.valid).sum())
    return {"ms_per_frame": 1e3 * med / n, "min_ms_per_frame": 1e3 * best / n,
            "compile_s": round(self.compile_s, 2), "first_losses": np.asarray(outs.loss).tolist()}


def interleaved_ratio(variables, benches: dict, n_lo: int, n_hi: int, args) -> dict:
  """JAX ms/frame at N = n_lo and n_hi, chunks alternated (lo, hi, hi, lo) `args.reps` times on
  warm runners: the sequential sweep above is exposed to drift of a shared machine's load."""
  runs = {}
  for n in (n_lo, n_hi):
    configs = engine_config(n, args.window, args.frames)
    bench = benches.get(configs) or benches.setdefault(configs, JaxBench(variables, configs))
    chunk = bc.step_inputs(bc.synthetic_frames(args.frames, args.height, args.width, n, seed=1),
                           configs[0].max_segments)
    state = bench.fresh_state()
    state, outs = bench.runner(state, chunk, bench.consts)  # compiled already: warm-up
    jax.block_until_ready(outs)
    runs[n] = [bench, chunk, state, []]
  for _ in range(args.reps):
    for n in (n_lo, n_hi, n_hi, n_lo):
      run = runs[n]
      t0 = time.perf_counter()
      run[2], outs = run[0].runner(run[2], run[1], run[0].consts)
      jax.block_until_ready(outs)
      run[3].append(1e3 * (time.perf_counter() - t0) / args.frames)
  lo, hi = np.median(runs[n_lo][3]), np.median(runs[n_hi][3])
  return {"check": "N sweep, interleaved", "instances": [n_lo, n_hi],
          "jax_ms_per_frame": [float(lo), float(hi)], "ratio_max_vs_min_N": float(hi / lo)}


def torch_frames(frames: list[bc.BenchFrame]) -> list[tuple]:
  return [(torch.from_numpy(f.image).permute(2, 0, 1)[None].contiguous(),
           torch.from_numpy(f.panoptic), list(f.segments)) for f in frames]


def torch_run(encoder_state, decoder_state, frames: list[bc.BenchFrame], window: int,
              reps: int) -> dict:
  enc, dec = tr.build()
  enc.load_state_dict(encoder_state)
  dec.load_state_dict(decoder_state)
  model = tr.TorchPitta(enc, dec, window=window)
  inputs = torch_frames(frames)
  first_losses = [model.step(*x)[1] for x in inputs]  # warm-up; losses from the fresh weights

  def one():
    for x in inputs:
      model.step(*x)
  med, best = bc.median_time(one, reps)
  return {"ms_per_frame": 1e3 * med / len(inputs), "min_ms_per_frame": 1e3 * best / len(inputs),
          "first_losses": first_losses}


def matmul_and_conv_rate(reps: int = 5) -> dict:
  """This machine's float32 GFLOP/s in XLA: a 1024^3 matmul and a 64->64 3x3 conv at 96x320."""
  a = jnp.ones((1024, 1024), jnp.float32)
  mm = jax.jit(lambda x: x @ x)
  mm(a).block_until_ready()
  t_mm, _ = bc.median_time(lambda: mm(a).block_until_ready(), reps)
  x = jnp.ones((1, 96, 320, 64), jnp.float32)
  k = jnp.ones((3, 3, 64, 64), jnp.float32) * 0.01
  conv = jax.jit(lambda x, k: jax.lax.conv_general_dilated(
      x, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")))
  conv(x, k).block_until_ready()
  t_conv, _ = bc.median_time(lambda: conv(x, k).block_until_ready(), reps)
  return {"matmul_gflops": 2 * 1024 ** 3 / t_mm / 1e9,
          "conv_gflops": 2 * 96 * 320 * 64 * 64 * 9 / t_conv / 1e9}


def jax_profile(bench: JaxBench, frame: StepInput, reps: int) -> dict:
  """FLOPs and time of the parts of one step (each part jitted alone, not scanned)."""
  model, method, cfg, pitta = bench.model, bench.method, bench.cfg, bench.pitta
  state = bench.fresh_state()
  consts = bench.consts

  def forward(st, image, cs):
    variables = trainable_lib.merge(st.trainable, cs.frozen, cs.batch_stats)
    return model.depth(variables, image[None], True)[0]

  def forward_backward(st, fr, cs):
    def loss_fn(t):
      return method.loss(t, state=st, consts=cs, frame=fr, rng=None, model=model, cfg=cfg,
                         mcfg=method.config)
    return jax.value_and_grad(loss_fn, has_aux=True)(st.trainable)

  def loss_only(depth, fr):
    return jax.value_and_grad(lambda d: frame_loss(d, fr, pitta.ld, pitta.lam).total)(depth)

  depth = jax.jit(forward)(state, frame.image, consts)
  parts = {"forward": (forward, (state, frame.image, consts)),
           "forward_backward": (forward_backward, (state, frame, consts)),
           "loss_and_depth_grad": (loss_only, (depth, frame)),
           "step": (bench.step, (state, frame, consts))}
  out = {}
  for name, (fn, args) in parts.items():
    compiled = jax.jit(fn).lower(*args).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    jax.block_until_ready(compiled(*args))
    med, _ = bc.median_time(lambda: jax.block_until_ready(compiled(*args)), reps)
    out[name] = {"ms": 1e3 * med, "gflop": float(cost.get("flops", float("nan"))) / 1e9}
  return out


def torch_profile(encoder_state, decoder_state, frame: bc.BenchFrame, window: int,
                  reps: int) -> dict:
  enc, dec = tr.build()
  enc.load_state_dict(encoder_state)
  dec.load_state_dict(decoder_state)
  model = tr.TorchPitta(enc, dec, window=window)
  image, pan, segs = torch_frames([frame])[0]

  def forward():
    with torch.no_grad():
      model.depth(image)

  def forward_backward():
    model.optimizer.zero_grad(set_to_none=True)
    masks = tr.instance_masks(pan, segs)
    tr.pitta_loss(image[0], model.depth(image), masks, window)[0].backward()

  with torch.no_grad():
    depth0 = model.depth(image)

  def loss_only():
    d = depth0.clone().requires_grad_(True)
    tr.pitta_loss(image[0], d, tr.instance_masks(pan, segs), window)[0].backward()

  out = {}
  for name, fn in (("forward", forward), ("forward_backward", forward_backward),
                   ("loss_and_depth_grad", loss_only),
                   ("step", lambda: model.step(image, pan, segs))):
    fn()
    out[name] = {"ms": 1e3 * bc.median_time(fn, reps)[0]}
  return out


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--height", type=int, default=192)
  p.add_argument("--width", type=int, default=640)
  p.add_argument("--instances", type=int, default=8, help="dynamic instances N per frame")
  p.add_argument("--sweep-instances", default="", help="comma list of N, e.g. 1,8,32")
  p.add_argument("--window", type=int, default=5, help="median window s")
  p.add_argument("--frames", type=int, default=8, help="frames per timed chunk")
  p.add_argument("--reps", type=int, default=3, help="timed chunks (median)")
  p.add_argument("--threads", type=int, default=os.cpu_count(), help="PyTorch threads")
  p.add_argument("--impls", default="jax,torch", help="jax,torch or one of them")
  p.add_argument("--no-profile", action="store_true", help="skip the per-part profile")
  p.add_argument("--quick", action="store_true", help="320x96, 4 frames, 2 reps")
  p.add_argument("--compare-conv-rule", action="store_true",
                 help="also time the JAX step with JAX's own convolution input-gradient rule "
                      "(what pitta_jax.models.conv_vjp replaces) and print the ratio")
  args = p.parse_args(argv)
  if args.quick:
    args.height, args.width, args.frames, args.reps = 96, 320, 4, 2
  torch.set_num_threads(args.threads)
  impls = [s.strip() for s in args.impls.split(",") if s.strip()]
  sweep = [int(n) for n in args.sweep_instances.split(",") if n.strip()] or [args.instances]

  enc, dec, variables = bc.torch_and_jax_weights(seed=0)
  enc_state, dec_state = enc.state_dict(), dec.state_dict()
  common = {"H": args.height, "W": args.width, "window": args.window, "threads": args.threads,
            "frames": args.frames, "reps": args.reps}
  benches: dict[tuple[AdaptConfig, PittaConfig], JaxBench] = {}
  results: dict[str, dict[int, float]] = {impl: {} for impl in impls}
  for n in sweep:
    frames = bc.synthetic_frames(args.frames, args.height, args.width, n, seed=1)
    configs = engine_config(n, args.window, args.frames)
    max_segments = configs[0].max_segments
    losses = {}
    for impl in impls:
      if impl == "jax":
        bench = benches.get(configs) or benches.setdefault(configs, JaxBench(variables, configs))
        r = bench.run(bc.step_inputs(frames, max_segments), args.reps)
      else:
        r = torch_run(enc_state, dec_state, frames, args.window, args.reps)
      losses[impl] = r.pop("first_losses")
      results[impl][n] = r["ms_per_frame"]
      bc.emit({"impl": impl, **common, "instances": n, **r, "load": bc.load()})
      if impl == "jax" and args.compare_conv_rule:
        r_jax_rule = JaxBench(variables, configs, conv_rule="jax").run(
            bc.step_inputs(frames, max_segments), args.reps)
        r_jax_rule.pop("first_losses")
        bc.emit({"impl": "jax", "conv_vjp": "jax_rule", **common, "instances": n, **r_jax_rule,
                 "load": bc.load()})
        bc.emit({"ratio": "jax_rule_ms / loop_friendly_ms", "instances": n, **common,
                 "value": r_jax_rule["ms_per_frame"] / r["ms_per_frame"]})
    if len(impls) == 2:
      bc.emit({"ratio": "torch_ms / jax_ms", "instances": n, **common,
               "value": results["torch"][n] / results["jax"][n]})
      a, b = np.asarray(losses["jax"]), np.asarray(losses["torch"])
      bc.emit({"check": "loss parity, frames 0..T-1 from the same weights", "instances": n,
               "max_rel_diff": float(np.max(np.abs(a - b) / np.abs(b))),
               "jax_loss_0": float(a[0]), "torch_loss_0": float(b[0])})
  if len(sweep) > 1:
    summary = {"sweep_instances": sweep,
               **{f"{impl}_ms_per_frame": [results[impl][n] for n in sweep] for impl in impls}}
    for impl in impls:
      summary[f"{impl}_ratio_max_vs_min_N"] = results[impl][max(sweep)] / results[impl][min(sweep)]
    bc.emit(summary)
    if "jax" in impls:
      bc.emit(interleaved_ratio(variables, benches, min(sweep), max(sweep), args))

  if not args.no_profile:
    n = sweep[0]
    frames = bc.synthetic_frames(1, args.height, args.width, n, seed=1)
    configs = engine_config(n, args.window, args.frames)
    bench = benches.get(configs) or JaxBench(variables, configs)
    frame = bc.step_inputs(frames, configs[0].max_segments)
    frame = StepInput(*(x[0] for x in frame))
    rates = matmul_and_conv_rate()
    prof = {"profile": "jax", "instances": n, **common, **jax_profile(bench, frame, args.reps + 2),
            **{k: round(v, 1) for k, v in rates.items()}}
    best = max(rates.values())
    prof["flop_floor_ms"] = prof["step"]["gflop"] / best * 1e3
    bc.emit(prof)
    if "torch" in impls:
      bc.emit({"profile": "torch", "instances": n, **common,
               **torch_profile(enc_state, dec_state, frames[0], args.window, args.reps + 2)})
  bc.emit({"load_end": bc.load()})


if __name__ == "__main__":
  main()
