"""Many adaptation streams in one compiled call: `jax.vmap` of `adapt_step`, and its sharding.

A *multi-stream state* is an `AdaptState` whose per-stream fields carry a leading stream axis K
(trainable parameters, optimiser state, method state, source parameters, step, rng, skip counter)
while the `shared` fields (by default `frozen` and `batch_stats`: the network's frozen weights
and running statistics, the same for every stream) are held once, without that axis. Keeping the
frozen convolution kernels unbatched is what makes the vmapped network a batch-K network with one
set of kernels (convolutions with batch K), instead of K sets of kernels (grouped convolutions).
Shared fields are constants of the run: any change a method would make to them is discarded
(PITTA and `none` never change them: the engine only passes them through). With
`AdaptConfig.reset_every > 0` the engine's reset select covers the whole state, which makes the
frozen kernels per-stream inside the step: still correct, but the convolutions become grouped.

Two uses:

- K independent streams (`make_multi_stream_step`, `init_streams`): each stream sees its own
  frames, chunks stacked time-major `(T, K, ...)` (`stack_stream_inputs`), and owns its
  parameters and optimiser state. Stream k of the result equals a single-stream engine run on
  stream k's frames, up to float rounding (XLA rounds a batch-K convolution differently from K
  batch-1 ones: depths agree to ~1e-6 relative).
- One stream, many loss weights (`make_lambda_sweep_step`, `init_lambda_sweep`): the paper's
  Table 4 sweeps lambda of eq. 10 over `TABLE4_LAMBDAS`; all streams see the same frames
  (shared, `(T, ...)`), and lambda is a traced per-stream value read from
  `state.method_state["lam"]` by the `PITTA_LAMBDA` method (inf = L_e only). Stream k equals the
  plain engine with `AdaptConfig(lam=lams[k])`.

Sharding: `stream_mesh` builds a 1-D device mesh with axis "streams"; `shard_streams` /
`shard_stream_inputs` place the per-stream axis over it (shared fields replicated), and
`make_sharded_chunk_runner` compiles the scanned chunk with those input and output shardings, so
each device runs K / devices streams and the carry stays where it is between chunks.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from pitta_jax import trainable as trainable_lib
from pitta_jax.adapt.config import AdaptConfig
from pitta_jax.adapt.engine import (AdaptState, DepthModel, LossAux, Method, StepInput,
                                    init_state, make_optimizer, make_step)
from pitta_jax.adapt.methods import forward_and_loss

Tree = Any

# Fields of AdaptState that every stream shares (no stream axis); see the module docstring.
SHARED_FIELDS: tuple[str, ...] = ("frozen", "batch_stats")
STREAM_AXIS = "streams"
# Paper Table 4: lambda of eq. 10 in {0, 0.1, ..., 1.0, inf} (inf = L_e only).
TABLE4_LAMBDAS: tuple[float, ...] = tuple(round(0.1 * i, 1) for i in range(11)) + (math.inf,)


def _field_names() -> list[str]:
  return [f.name for f in dataclasses.fields(AdaptState)]


def _check_shared(shared: Sequence[str]) -> tuple[str, ...]:
  unknown = set(shared) - set(_field_names())
  if unknown:
    raise ValueError(f"unknown AdaptState fields {sorted(unknown)}; fields: {_field_names()}")
  return tuple(shared)


def state_axes(shared: Sequence[str] = SHARED_FIELDS) -> AdaptState:
  """The `vmap` axes of a multi-stream state: None for the shared fields, 0 for the others."""
  shared = _check_shared(shared)
  return AdaptState(**{f: (None if f in shared else 0) for f in _field_names()})


# ----------------------------------------------------------------------------- building states


def stack_streams(states: Sequence[AdaptState], shared: Sequence[str] = SHARED_FIELDS
                  ) -> AdaptState:
  """K single-stream states -> one multi-stream state (per-stream fields stacked on axis 0).

  The shared fields are copied from `states[0]`; they must be the same in every state (not
  checked leaf by leaf: they are the network's frozen weights, built once).
  """
  shared = _check_shared(shared)
  if not states:
    raise ValueError("no state to stack")
  fields = {}
  for name in _field_names():
    parts = [getattr(s, name) for s in states]
    if name in shared:
      # a copy: the chunk runners donate the whole carry, and these are often the caller's
      # network variables (`init_state` does not copy them)
      fields[name] = jax.tree_util.tree_map(jnp.copy, parts[0])
    else:
      fields[name] = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *parts)
  return AdaptState(**fields)


def stream_state(states: AdaptState, k: int, shared: Sequence[str] = SHARED_FIELDS
                 ) -> AdaptState:
  """Stream k of a multi-stream state, as a plain single-stream `AdaptState`."""
  shared = _check_shared(shared)
  return AdaptState(**{
      name: (getattr(states, name) if name in shared
             else jax.tree_util.tree_map(lambda x: x[k], getattr(states, name)))
      for name in _field_names()})


def num_streams(states: AdaptState) -> int:
  """K, from the per-stream `step` counter (shape (K,))."""
  return int(np.shape(states.step)[0])


def init_streams(variables: Tree, method: Method, cfg: AdaptConfig, num: int,
                 tx: optax.GradientTransformation | None = None,
                 seeds: Sequence[int] | None = None) -> AdaptState:
  """K streams starting from the same network, each with its own optimiser state and PRNG seed.

  Args:
    variables: Flax variables {"params", "batch_stats"} of the source network.
    method, cfg, tx: as `engine.init_state` (tx defaults to `make_optimizer(cfg)`).
    num: number of streams K.
    seeds: K seeds (default cfg.seed + k); only methods that draw random numbers see them.

  Returns:
    multi-stream AdaptState (per-stream fields (K, ...), `SHARED_FIELDS` unbatched).
  """
  tx = tx or make_optimizer(cfg)
  seeds = list(seeds) if seeds is not None else [cfg.seed + k for k in range(num)]
  if len(seeds) != num:
    raise ValueError(f"{len(seeds)} seeds for {num} streams")
  base = init_state(variables, method, cfg, tx)
  states = [base.replace(rng=jax.random.PRNGKey(s)) for s in seeds]
  return stack_streams(states)


def stack_stream_inputs(inputs: Sequence[StepInput]) -> StepInput:
  """K chunks of frames, (T, ...) each -> one time-major multi-stream chunk (T, K, ...).

  All chunks need the same T and shapes (pad with `inputs.stack`, `valid=False` frames).
  """
  if not inputs:
    raise ValueError("no stream to stack")
  return StepInput(*(np.stack([np.asarray(x) for x in field], axis=1) for field in zip(*inputs)))


# ----------------------------------------------------------------------------- the vmapped step


def make_multi_stream_step(model: DepthModel, method: Method, cfg: AdaptConfig,
                           tx: optax.GradientTransformation | None = None, *,
                           shared_frames: bool = False,
                           shared: Sequence[str] = SHARED_FIELDS):
  """`adapt_step` vmapped over the streams: `step(states, frames) -> (states, outputs)`.

  Args:
    model, method, cfg, tx: as `engine.make_step` (the same for every stream).
    shared_frames: False: `frames` holds one frame per stream, (K, ...) per field; True: every
      stream sees the same frame, (...) per field (e.g. a lambda sweep).
    shared: AdaptState fields without a stream axis (constants of the run).

  Returns:
    step(states, frames) -> (states, StepOutput with a leading K axis); scan it over time with
    `engine.make_chunk_runner` (chunks (T, K, ...), or (T, ...) with shared frames) or
    `make_sharded_chunk_runner`.
  """
  shared = _check_shared(shared)
  single = make_step(model, method, cfg, tx)

  def one(state: AdaptState, frame: StepInput):
    new, out = single(state, frame)
    # shared fields stay the unbatched inputs (the engine's valid-frame select would otherwise
    # broadcast them over the streams)
    return new.replace(**{f: getattr(state, f) for f in shared}), out

  axes = state_axes(shared)
  return jax.vmap(one, in_axes=(axes, None if shared_frames else 0), out_axes=(axes, 0))


# ----------------------------------------------------------------------------- lambda sweep


def lambda_loss(trainable: Tree, *, state: AdaptState, frame: StepInput, rng: jax.Array,
                model: DepthModel, cfg: AdaptConfig) -> tuple[jax.Array, LossAux]:
  """PITTA's eq. 10 with lambda read from `state.method_state["lam"]` (a traced scalar).

  Same forward pass and loss terms as the `pitta` method; only `cfg.lam` is replaced, so that
  lambda can differ between vmapped streams. lambda = inf means L_e only (Table 4).
  """
  del rng
  return forward_and_loss(trainable, state, frame, model, cfg, lam=state.method_state["lam"])


def _lambda_init(split: trainable_lib.Split, cfg: AdaptConfig) -> dict[str, jax.Array]:
  return {"lam": jnp.asarray(cfg.lam, jnp.float32)}


# PITTA with lambda as state: method_state = {"lam": () float32}, initialised from cfg.lam.
PITTA_LAMBDA = Method("pitta_lambda", init=_lambda_init, loss=lambda_loss)


def init_lambda_sweep(variables: Tree, lams: Sequence[float], cfg: AdaptConfig,
                      tx: optax.GradientTransformation | None = None) -> AdaptState:
  """One stream per lambda, all from the same network and seed (method `PITTA_LAMBDA`).

  Returns:
    multi-stream AdaptState with method_state {"lam": (K,) float32}.
  """
  tx = tx or make_optimizer(cfg)
  base = init_state(variables, PITTA_LAMBDA, cfg, tx)
  states = [base.replace(method_state={"lam": jnp.asarray(lam, jnp.float32)}) for lam in lams]
  return stack_streams(states)


def make_lambda_sweep_step(model: DepthModel, cfg: AdaptConfig,
                           tx: optax.GradientTransformation | None = None):
  """The vmapped PITTA step over per-stream lambdas, every stream on the same frames.

  Frames are (...) per field (scan chunks (T, ...)), states from `init_lambda_sweep`.
  """
  return make_multi_stream_step(model, PITTA_LAMBDA, cfg, tx, shared_frames=True)


# ----------------------------------------------------------------------------- sharding


def stream_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
  """A 1-D mesh with axis "streams" over `devices` (default: all of `jax.devices()`)."""
  devices = list(devices) if devices is not None else jax.devices()
  return Mesh(np.array(devices), (STREAM_AXIS,))


def state_shardings(mesh: Mesh, shared: Sequence[str] = SHARED_FIELDS) -> AdaptState:
  """Per-field shardings of a multi-stream state: stream axis over the mesh, shared replicated.

  An AdaptState of `NamedSharding`s (a pytree prefix of the state, for `jax.device_put` and
  `jax.jit`'s in/out shardings).
  """
  shared = _check_shared(shared)
  by_stream = NamedSharding(mesh, PartitionSpec(STREAM_AXIS))
  replicated = NamedSharding(mesh, PartitionSpec())
  return AdaptState(**{f: (replicated if f in shared else by_stream) for f in _field_names()})


def input_sharding(mesh: Mesh, shared_frames: bool = False) -> NamedSharding:
  """Sharding of a chunk: (T, K, ...) split on K, or replicated when the frames are shared."""
  if shared_frames:
    return NamedSharding(mesh, PartitionSpec())
  return NamedSharding(mesh, PartitionSpec(None, STREAM_AXIS))


def _check_divisible(k: int, mesh: Mesh) -> None:
  if k % mesh.size:
    raise ValueError(f"{k} streams cannot be split evenly over {mesh.size} devices; use a "
                     f"multiple of {mesh.size} streams (or fewer devices)")


def shard_streams(states: AdaptState, mesh: Mesh, shared: Sequence[str] = SHARED_FIELDS
                  ) -> AdaptState:
  """Places a multi-stream state on the mesh (stream axis split, shared fields replicated)."""
  _check_divisible(num_streams(states), mesh)
  return jax.device_put(states, state_shardings(mesh, shared))


def shard_stream_inputs(frames: StepInput, mesh: Mesh, shared_frames: bool = False) -> StepInput:
  """Places a chunk on the mesh: (T, K, ...) split on K, or (T, ...) replicated if shared."""
  if not shared_frames:
    _check_divisible(int(np.shape(frames.valid)[1]), mesh)
  return jax.device_put(frames, input_sharding(mesh, shared_frames))


def make_sharded_chunk_runner(multi_step, mesh: Mesh, *, shared_frames: bool = False,
                              shared: Sequence[str] = SHARED_FIELDS):
  """jit(lax.scan(multi_step)) with the stream axis sharded over `mesh`, carry donated.

  `(states, frames) -> (states, outputs)`; outputs are (T, K, ...) split on K. Inputs placed by
  `shard_streams` / `shard_stream_inputs` stay where they are; others are moved on the call.
  """
  st = state_shardings(mesh, shared)
  out = NamedSharding(mesh, PartitionSpec(None, STREAM_AXIS))

  def run_chunk(states, frames):
    return jax.lax.scan(multi_step, states, frames)

  return jax.jit(run_chunk, in_shardings=(st, input_sharding(mesh, shared_frames)),
                 out_shardings=(st, out), donate_argnums=0)


__all__ = ["SHARED_FIELDS", "STREAM_AXIS", "TABLE4_LAMBDAS", "PITTA_LAMBDA", "state_axes",
           "stack_streams", "stream_state", "num_streams", "init_streams", "stack_stream_inputs",
           "make_multi_stream_step", "lambda_loss", "init_lambda_sweep", "make_lambda_sweep_step",
           "stream_mesh", "state_shardings", "input_sharding", "shard_streams",
           "shard_stream_inputs", "make_sharded_chunk_runner"]
