"""One optimiser update of whole networks: the engine's Adam step against PyTorch's Adam.

    python benchmarks/optimizer.py                    # MonoDepth2 depth + pose (Ada-Depth's U)
    python benchmarks/optimizer.py --tree depth       # the depth network (CoTTA's student)

Why: the baselines that adapt every weight (CoTTA, CoMoDa, Ada-Depth's self-supervised branch)
update 14-28 M parameters per frame, which is memory traffic, not arithmetic, and the engine
adds a non-finite guard that PyTorch's optimisers do not have. This times the update alone.

JAX (each inside one compiled loop of `--steps` updates, state donated):
- `optax`: `tx.update` + `optax.apply_updates` on the parameter tree, leaf by leaf;
- `optax+guard`: the engine's `optax_update` (`pitta_jax.adapt.engine`): the same plus the
  guard, which checks loss, gradient, new parameters and new Adam state for non-finite values
  and keeps the old ones if it finds any (one `where` per leaf).
PyTorch (`torch.optim.Adam` on the same shapes, `--threads` threads): the default for-loop
implementation on CPU tensors, `foreach=True`, and `fused=True`.

Per implementation: median and best ms per update over `--reps` rounds, interleaved (rotated
order), with the load average.
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
import optax  # noqa: E402
import torch  # noqa: E402

import bench_common as bc  # noqa: E402
from pitta_jax.adapt import AdaptConfig  # noqa: E402
from pitta_jax.adapt.engine import AdaptState, optax_update  # noqa: E402
from pitta_jax.models.pose import PoseNet  # noqa: E402

TREES = ("depth", "depth+pose")
TORCH_VARIANTS = {"torch-for-loop": {"foreach": False}, "torch-foreach": {"foreach": True},
                  "torch-fused": {"fused": True}}


def parameter_tree(which: str) -> dict:
  """MonoDepth2's depth network parameters (random, ResNet-18), with the pose network's when
  `which` is depth+pose."""
  _, _, variables = bc.torch_and_jax_weights(seed=0)
  tree = {"depth": variables["params"]}
  if which == "depth+pose":
    pose = bc.jit_init(PoseNet(18), jax.random.PRNGKey(2), np.zeros((1, 64, 64, 6), np.float32))
    tree["pose"] = pose["params"]
  return tree


def jax_update(tx: optax.GradientTransformation, guard: bool, steps: int):
  """jit of `steps` engine updates (`optax_update`) with a fixed gradient; state donated."""
  cfg = AdaptConfig(skip_nonfinite=guard)

  def run(state: AdaptState, grads) -> AdaptState:
    def body(_, s):
      return optax_update(s, grads, jnp.float32(1.0), tx, cfg)[0]
    return jax.lax.fori_loop(0, steps, body, state)
  return jax.jit(run, donate_argnums=0)


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--tree", choices=TREES, default="depth+pose",
                 help="which parameters: the depth network, or depth + pose (Ada-Depth's U)")
  p.add_argument("--steps", type=int, default=10, help="updates per compiled loop / timed call")
  p.add_argument("--reps", type=int, default=7, help="timed rounds, interleaved")
  p.add_argument("--lr", type=float, default=1e-5)
  p.add_argument("--threads", type=int, default=os.cpu_count(), help="PyTorch threads")
  args = p.parse_args(argv)
  if args.steps < 1 or args.reps < 1:
    p.error("--steps and --reps must be >= 1")
  torch.set_num_threads(args.threads)

  params = parameter_tree(args.tree)
  leaves = jax.tree_util.tree_leaves(params)
  n = sum(x.size for x in leaves)
  grads = jax.tree_util.tree_map(lambda x: 1e-3 * x + 1e-4, params)
  tx = optax.adam(args.lr)

  def fresh_state() -> AdaptState:
    copy = jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), params)
    return AdaptState(copy, tx.init(copy), {}, {}, jnp.int32(0), jax.random.PRNGKey(0),
                      jnp.int32(0))

  compiled, states, compile_s = {}, {}, {}
  for name, guard in (("optax", False), ("optax+guard", True)):
    t0 = time.perf_counter()
    compiled[name] = jax_update(tx, guard, args.steps).lower(fresh_state(), grads).compile()
    compile_s[name] = round(time.perf_counter() - t0, 2)
    states[name] = fresh_state()

  torch_opts = {}
  for name, kw in TORCH_VARIANTS.items():
    ps = [torch.nn.Parameter(torch.from_numpy(np.array(x))) for x in leaves]
    for x, g in zip(ps, jax.tree_util.tree_leaves(grads)):
      x.grad = torch.from_numpy(np.array(g))
    torch_opts[name] = torch.optim.Adam(ps, lr=args.lr, **kw)

  def run_jax(name):
    states[name] = compiled[name](states[name], grads)
    jax.block_until_ready(states[name])

  def run_torch(name):
    for _ in range(args.steps):
      torch_opts[name].step()

  impls = {**{k: (lambda k=k: run_jax(k)) for k in compiled},
           **{k: (lambda k=k: run_torch(k)) for k in torch_opts}}
  for fn in impls.values():  # warm-up: first steps, allocations
    fn()
  load = bc.load()
  times, _ = bc.interleaved_ms(impls, args.reps, args.steps)
  med = {k: round(float(np.median(t)), 2) for k, t in times.items()}
  bc.emit({"bench": "optimizer", "tree": args.tree, "parameters": n, "leaves": len(leaves),
           "steps": args.steps, "reps": args.reps, "threads": args.threads,
           "device": jax.devices()[0].platform, "ms_per_update": med,
           "min_ms_per_update": {k: round(float(np.min(t)), 2) for k, t in times.items()},
           "ratio_vs_torch-fused": {k: round(med[k] / med["torch-fused"], 2) for k in med},
           "jax_compile_s": compile_s,
           "load": load, "load_end": bc.load()})


if __name__ == "__main__":
  main()
