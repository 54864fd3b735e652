"""Many adaptation streams in one compiled call: `jax.vmap` of `adapt_step`, and its sharding.

A *multi-stream state* is an `AdaptState` whose every field carries a leading stream axis K
(trainable parameters, optimiser state, method state, source parameters, step, rng, skip
counter). The network's constants (`engine.Consts`: frozen weights and running statistics) are
not part of the carry and are passed once, unbatched, to every stream: the vmapped network is a
batch-K network with one set of kernels (convolutions with batch K), not K sets of kernels
(grouped convolutions).

Two uses:

- K independent streams (`make_multi_stream_step`, `init_streams`): each stream sees its own
  frames, chunks stacked time-major `(T, K, ...)` (`stack_stream_inputs`), and owns its
  parameters and optimiser state. Stream k of the result equals a single-stream engine run on
  stream k's frames, up to float rounding (XLA rounds a batch-K convolution differently from K
  batch-1 ones: depths agree to ~1e-6 relative).
- One stream, many loss weights (`make_lambda_sweep_step`, `init_lambda_sweep`): Table 4 sweeps
  lambda of eq. 10; all streams see the same frames (shared, `(T, ...)`), and lambda is PITTA's
  per-stream `method_state["lam"]` (inf = L_e only). Stream k equals the plain engine with
  `PittaConfig(lam=lams[k])`.

Sharding: `stream_mesh` builds a 1-D device mesh with axis "streams"; `shard_streams` /
`shard_stream_inputs` place the stream axis over it (constants replicated), and
`make_sharded_chunk_runner` compiles the scanned chunk with those shardings, so each device runs
K / devices streams and the carry stays where it is between chunks.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from pitta_jax.adapt.config import AdaptConfig
from pitta_jax.adapt.engine import (AdaptState, Consts, StepInput, init_state, make_optimizer,
                                    make_step)
from pitta_jax.methods import build as build_method
from pitta_jax.methods.base import Method
from pitta_jax.methods.pitta import PittaConfig
from pitta_jax.prng import seed_key

Tree = Any

STREAM_AXIS = "streams"


# ----------------------------------------------------------------------------- building states


def stack_streams(states: Sequence[AdaptState]) -> AdaptState:
  """K single-stream states -> one multi-stream state (every field stacked on axis 0)."""
  if not states:
    raise ValueError("no state to stack")
  return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *states)


def stream_state(states: AdaptState, k: int) -> AdaptState:
  """Stream k of a multi-stream state, as a plain single-stream `AdaptState`."""
  return jax.tree_util.tree_map(lambda x: x[k], states)


def num_streams(states: AdaptState) -> int:
  """K, from the per-stream `step` counter (shape (K,))."""
  return int(np.shape(states.step)[0])


def init_streams(variables: Tree, method: Method, cfg: AdaptConfig, num: int,
                 tx: optax.GradientTransformation | None = None,
                 seeds: Sequence[int] | None = None, model: Any = None,
                 resources: dict | None = None) -> tuple[AdaptState, Consts]:
  """K streams starting from the same network, each with its own optimiser state and PRNG seed.

  Args:
    variables: Flax variables {"params", "batch_stats"} of the source network.
    method, cfg, tx, model, resources: as `engine.init_state` (tx defaults to
      `make_optimizer(cfg, method)`; resources: what `method.needs`, e.g. Ada-Depth's pose
      network, shared by the streams).
    num: number of streams K.
    seeds: K seeds (default cfg.seed + k); only methods that draw random numbers see them.

  Returns:
    (multi-stream AdaptState with (K, ...) fields, the shared Consts).
  """
  tx = tx or make_optimizer(cfg, method)
  seeds = list(seeds) if seeds is not None else [cfg.seed + k for k in range(num)]
  if len(seeds) != num:
    raise ValueError(f"{len(seeds)} seeds for {num} streams")
  base, consts = init_state(variables, method, cfg, tx, model, resources)
  return stack_streams([base.replace(rng=seed_key(s)) for s in seeds]), consts


def stack_stream_inputs(inputs: Sequence[StepInput]) -> StepInput:
  """K chunks of frames, (T, ...) each -> one time-major multi-stream chunk (T, K, ...).

  All chunks need the same T and shapes (pad with `inputs.stack`, `valid=False` frames).
  """
  if not inputs:
    raise ValueError("no stream to stack")
  return StepInput(*(np.stack([np.asarray(x) for x in field], axis=1) for field in zip(*inputs)))


# ----------------------------------------------------------------------------- the vmapped step


def make_multi_stream_step(model: Any, method: Method, cfg: AdaptConfig,
                           tx: optax.GradientTransformation | None = None, *,
                           shared_frames: bool = False):
  """`adapt_step` vmapped over the streams: `step(states, frames, consts)`.

  Args:
    model, method, cfg, tx: as `engine.make_step` (the same for every stream).
    shared_frames: False: `frames` holds one frame per stream, (K, ...) per field; True: every
      stream sees the same frame, (...) per field (e.g. a lambda sweep).

  Returns:
    step(states, frames, consts) -> (states, StepOutput with a leading K axis); scan it over
    time with `engine.make_chunk_runner` (chunks (T, K, ...), or (T, ...) with shared frames)
    or `make_sharded_chunk_runner`. `consts` are shared by every stream (no stream axis).
  """
  single = make_step(model, method, cfg, tx)
  return jax.vmap(single, in_axes=(0, None if shared_frames else 0, None))


# ----------------------------------------------------------------------------- lambda sweep


def init_lambda_sweep(variables: Tree, lams: Sequence[float], cfg: AdaptConfig,
                      tx: optax.GradientTransformation | None = None,
                      pitta: PittaConfig = PittaConfig(), model: Any = None
                      ) -> tuple[AdaptState, Consts]:
  """One PITTA stream per lambda, all from the same network and seed.

  Returns:
    (multi-stream AdaptState with method_state {"lam": (K,)}, the shared Consts).
  """
  lams = list(np.asarray(lams, dtype=object).reshape(-1)) if np.ndim(lams) == 1 else None
  if not lams:
    raise ValueError("lams must be a non-empty 1-D sequence of lambdas, one per stream")
  # a 0-d array (jnp.asarray(0.1), a NumPy scalar array) is its number, as a NumPy array of
  # lambdas gives its elements
  lams = [lam.item() if isinstance(lam, (jax.Array, np.ndarray)) and np.ndim(lam) == 0
          and not isinstance(lam, jax.core.Tracer) else lam for lam in lams]
  for lam in lams:  # each stream is PITTA at that lambda: a lambda its config refuses is refused
    dataclasses.replace(pitta, lam=lam)
  tx = tx or make_optimizer(cfg)
  base, consts = init_state(variables, build_method("pitta", pitta), cfg, tx, model)
  dtype = base.method_state["lam"].dtype  # the parameters' float type
  states = [base.replace(method_state={"lam": jnp.asarray(lam, dtype)}) for lam in lams]
  return stack_streams(states), consts


def make_lambda_sweep_step(model: Any, cfg: AdaptConfig,
                           tx: optax.GradientTransformation | None = None,
                           pitta: PittaConfig = PittaConfig()):
  """The vmapped PITTA step over per-stream lambdas, every stream on the same frames.

  Frames are (...) per field (scan chunks (T, ...)), states from `init_lambda_sweep`.
  """
  return make_multi_stream_step(model, build_method("pitta", pitta), cfg, tx,
                                shared_frames=True)


# ----------------------------------------------------------------------------- sharding


def stream_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
  """A 1-D mesh with axis "streams" over `devices` (default: all of `jax.devices()`)."""
  devices = list(devices) if devices is not None else jax.devices()
  return Mesh(np.array(devices), (STREAM_AXIS,))


def state_shardings(mesh: Mesh) -> AdaptState:
  """Per-field shardings of a multi-stream state: the stream axis over the mesh.

  An AdaptState of `NamedSharding`s (a pytree prefix of the state, for `jax.device_put` and
  `jax.jit`'s in/out shardings).
  """
  by_stream = NamedSharding(mesh, PartitionSpec(STREAM_AXIS))
  return AdaptState(**{f.name: by_stream for f in dataclasses.fields(AdaptState)})


def input_sharding(mesh: Mesh, shared_frames: bool = False) -> NamedSharding:
  """Sharding of a chunk: (T, K, ...) split on K, or replicated when the frames are shared."""
  if shared_frames:
    return NamedSharding(mesh, PartitionSpec())
  return NamedSharding(mesh, PartitionSpec(None, STREAM_AXIS))


def _check_divisible(k: int, mesh: Mesh) -> None:
  if k % mesh.size:
    raise ValueError(f"{k} streams cannot be split evenly over {mesh.size} devices; use a "
                     f"multiple of {mesh.size} streams (or fewer devices)")


def shard_streams(states: AdaptState, mesh: Mesh) -> AdaptState:
  """Places a multi-stream state on the mesh (stream axis split)."""
  _check_divisible(num_streams(states), mesh)
  return jax.device_put(states, state_shardings(mesh))


def replicate(consts: Consts, mesh: Mesh) -> Consts:
  """Places the shared constants on every device of the mesh."""
  return jax.device_put(consts, NamedSharding(mesh, PartitionSpec()))


def shard_stream_inputs(frames: StepInput, mesh: Mesh, shared_frames: bool = False) -> StepInput:
  """Places a chunk on the mesh: (T, K, ...) split on K, or (T, ...) replicated if shared."""
  if not shared_frames:
    _check_divisible(int(np.shape(frames.valid)[1]), mesh)
  return jax.device_put(frames, input_sharding(mesh, shared_frames))


def make_sharded_chunk_runner(multi_step, mesh: Mesh, *, shared_frames: bool = False):
  """jit(lax.scan(multi_step)) with the stream axis sharded over `mesh`, carry donated.

  `(states, frames, consts) -> (states, outputs)`; outputs are (T, K, ...) split on K; consts
  replicated. Inputs placed by `shard_streams` / `shard_stream_inputs` / `replicate` stay where
  they are; others are moved on the call.
  """
  st = state_shardings(mesh)
  out = NamedSharding(mesh, PartitionSpec(None, STREAM_AXIS))
  replicated = NamedSharding(mesh, PartitionSpec())

  def run_chunk(states, frames, consts):
    return jax.lax.scan(lambda s, f: multi_step(s, f, consts), states, frames)

  return jax.jit(run_chunk, in_shardings=(st, input_sharding(mesh, shared_frames), replicated),
                 out_shardings=(st, out), donate_argnums=0)


__all__ = ["STREAM_AXIS", "stack_streams", "stream_state", "num_streams", "init_streams",
           "stack_stream_inputs", "make_multi_stream_step", "init_lambda_sweep",
           "make_lambda_sweep_step", "stream_mesh", "state_shardings", "input_sharding",
           "shard_streams", "replicate", "shard_stream_inputs", "make_sharded_chunk_runner"]
