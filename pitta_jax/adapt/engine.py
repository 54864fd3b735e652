"""The online adaptation engine: one pure `adapt_step`, scanned over frames in chunks.

Per frame (predict-then-adapt, SPEC "The method"): the method's loss is evaluated on the
frame; the depth returned for evaluation comes from that same forward pass, i.e. *before* the
update the frame causes; then the method updates its state (paper eq. 11 for PITTA). A
sequence is `jax.lax.scan(adapt_step, state, frames)`; long sequences stream through one compiled
scan of `chunk_size` frames at a time, so memory does not grow with the sequence length, and the
state can be checkpointed (orbax) after any frame and resumed with bitwise identical results.

Everything random derives from `jax.random.fold_in(state.rng, state.step)`: same config + same
inputs => bitwise the same depths and parameters.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from pitta_jax import trainable as trainable_lib
from pitta_jax.adapt.config import AdaptConfig

Tree = Any


class StepInput(NamedTuple):
  """One frame as the compiled step sees it (static shapes; stack on a leading axis to scan).

  image:        (H, W, 3) float32 RGB in [0, 1] at the network's input size.
  panoptic:     (H, W) int32 segment ids at the same size (0 = void).
  seg_ids:      (S,) int32 segment ids present in the frame, padded.
  seg_classes:  (S,) int32 COCO category ids of those segments.
  seg_valid:    (S,) bool, False for padding.
  valid:        () bool, False for a padding frame at the end of the last chunk (no-op step).
  """
  image: jax.Array
  panoptic: jax.Array
  seg_ids: jax.Array
  seg_classes: jax.Array
  seg_valid: jax.Array
  valid: jax.Array


@struct.dataclass
class AdaptState:
  """The scan carry. `trainable` alone is differentiated and updated by the optimiser."""
  trainable: Tree
  frozen: Tree
  batch_stats: Tree
  opt_state: Tree
  method_state: Tree   # method-specific (e.g. an EMA teacher); {} for PITTA
  source: Tree         # the trainable parameters at the start, for the reset policy
  step: jax.Array      # () int32, frames processed
  rng: jax.Array       # base PRNG key; per frame: fold_in(rng, step)
  n_skipped: jax.Array  # () int32, updates skipped by the non-finite guard


class StepOutput(NamedTuple):
  """Per-frame measurements returned by the step (stacked by the scan)."""
  depth: jax.Array        # (H, W) depth predicted before this frame's update
  loss: jax.Array         # () L (eq. 10), or the method's loss
  loss_d: jax.Array       # () L_d (eq. 8)
  loss_e: jax.Array       # () L_e (eq. 9)
  n_instances: jax.Array  # () int32 N
  skipped: jax.Array      # () bool, the update was skipped (non-finite)
  grad_norm: jax.Array    # () global norm of the gradient w.r.t. the trainable tree
  update_norm: jax.Array  # () global norm of the applied update


@dataclasses.dataclass(frozen=True)
class DepthModel:
  """A depth network as the engine sees it: variables + images -> depth.

  apply_disp: (variables, images (B, H, W, 3), use_batch_stats) -> scale-0 disparity (B, H, W).
  """
  apply_disp: Callable[[Tree, jax.Array, bool], jax.Array]
  min_depth: float = 0.1   # MonoDepth2's disp_to_depth range (SPEC step 1)
  max_depth: float = 100.0

  def depth(self, variables: Tree, images: jax.Array, use_batch_stats: bool) -> jax.Array:
    from pitta_jax.models.depth_decoder import disp_to_depth
    return disp_to_depth(self.apply_disp(variables, images, use_batch_stats),
                         self.min_depth, self.max_depth)


def monodepth2_model(num_layers: int = 18) -> DepthModel:
  """The MonoDepth2 `DepthNet` wrapped for the engine (scale 0 only, as the loss uses)."""
  from pitta_jax.models.depth_decoder import DepthNet
  net = DepthNet(num_layers)

  def apply_disp(variables, images, use_batch_stats):
    return net.apply(variables, images, train=use_batch_stats)[0][..., 0]
  return DepthModel(apply_disp)


class LossAux(NamedTuple):
  """What a method's loss returns beside the scalar (all stop-gradient)."""
  depth: jax.Array        # (H, W)
  loss_d: jax.Array
  loss_e: jax.Array
  n_instances: jax.Array


@dataclasses.dataclass(frozen=True)
class Method:
  """A test-time adaptation method plugged into the engine.

  init: (split: trainable.Split, cfg) -> method_state pytree.
  loss: (trainable, state, frame, rng, model, cfg) -> (scalar loss, LossAux); differentiable in
        `trainable`. Also produces the evaluated depth.
  update: (state, grads, loss, aux, rng, tx, cfg) -> (state, skipped, update_norm); None = the
        default `optax_update` (one optimiser step with the non-finite guard).
  adapts: False for methods that never update (no gradient is computed).
  """
  name: str
  init: Callable[..., Tree]
  loss: Callable[..., tuple[jax.Array, LossAux]]
  update: Callable[..., AdaptState] | None = None
  adapts: bool = True


def make_optimizer(cfg: AdaptConfig) -> optax.GradientTransformation:
  """Adam (default) or SGD with the configured learning rate (paper eq. 11: theta -= alpha grad)."""
  if cfg.optimizer == "adam":
    return optax.adam(cfg.lr)
  return optax.sgd(cfg.lr, momentum=cfg.momentum or None)


def init_state(variables: Tree, method: Method, cfg: AdaptConfig,
               tx: optax.GradientTransformation) -> AdaptState:
  """Splits the variables with the configured selector and builds the initial carry."""
  parts = trainable_lib.split(variables, trainable_lib.parse_selector(cfg.selector))
  # private copies: the runner donates the carry, which must never alias the caller's arrays
  to_jnp = functools.partial(jax.tree_util.tree_map, lambda x: jnp.array(x, copy=True))
  tr = to_jnp(parts.trainable)
  return AdaptState(
      trainable=tr, frozen=to_jnp(parts.frozen), batch_stats=to_jnp(parts.batch_stats),
      opt_state=tx.init(tr), method_state=method.init(parts, cfg),
      source=jax.tree_util.tree_map(jnp.copy, tr),  # distinct buffers: the carry is donated
      step=jnp.zeros((), jnp.int32), rng=jax.random.PRNGKey(cfg.seed),
      n_skipped=jnp.zeros((), jnp.int32))


def _all_finite(tree: Tree) -> jax.Array:
  leaves = jax.tree_util.tree_leaves(tree)
  return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.array(True)


def _select(pred: jax.Array, on_true: Tree, on_false: Tree) -> Tree:
  return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


def optax_update(state: AdaptState, grads: Tree, loss: jax.Array, tx: optax.GradientTransformation,
                 cfg: AdaptConfig) -> tuple[AdaptState, jax.Array, jax.Array]:
  """One optimiser step on the trainable tree, with the non-finite guard.

  Returns (state, skipped, update_norm). When the guard trips, trainable and optimiser state stay
  exactly as they were and `n_skipped` counts it.
  """
  updates, new_opt = tx.update(grads, state.opt_state, state.trainable)
  new_tr = optax.apply_updates(state.trainable, updates)
  if cfg.skip_nonfinite:
    ok = jnp.isfinite(loss) & _all_finite(grads)
    new_tr = _select(ok, new_tr, state.trainable)
    new_opt = _select(ok, new_opt, state.opt_state)
    skipped = ~ok
  else:
    skipped = jnp.array(False)
  unorm = jnp.where(skipped, 0.0, optax.tree.norm(updates))
  state = state.replace(trainable=new_tr, opt_state=new_opt,
                        n_skipped=state.n_skipped + skipped.astype(jnp.int32))
  return state, skipped, unorm


def adapt_step(state: AdaptState, frame: StepInput, *, model: DepthModel, method: Method,
               cfg: AdaptConfig, tx: optax.GradientTransformation
               ) -> tuple[AdaptState, StepOutput]:
  """One frame: predict, compute the method's loss, update (pure; `lax.scan`-able).

  Bind the keyword arguments with `functools.partial` (see `make_step`).
  """
  rng = jax.random.fold_in(state.rng, state.step)
  before = state
  if cfg.reset_every > 0:
    reset = (state.step > 0) & (state.step % cfg.reset_every == 0)
    state = _select(reset, state.replace(trainable=state.source, opt_state=tx.init(state.source)),
                    state)

  def update(state, grads, loss, aux, key):
    if method.update is None:
      return optax_update(state, grads, loss, tx, cfg)
    return method.update(state, grads, loss, aux, key, tx, cfg)

  outputs = None
  for k in range(cfg.steps_per_frame if method.adapts else 1):
    loss_fn = functools.partial(method.loss, state=state, frame=frame, rng=rng, model=model,
                                cfg=cfg)
    if method.adapts:
      (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.trainable)
      gnorm = optax.tree.norm(grads)
      state, skipped, unorm = update(state, grads, loss, aux, jax.random.fold_in(rng, k))
    else:
      loss, aux = loss_fn(state.trainable)
      gnorm = unorm = jnp.zeros(())
      skipped = jnp.array(False)
    if k == 0:  # predict-then-adapt: report the first forward pass
      outputs = StepOutput(aux.depth, loss, aux.loss_d, aux.loss_e,
                           aux.n_instances.astype(jnp.int32), skipped, gnorm, unorm)
  state = state.replace(step=state.step + 1)
  # a padding frame leaves the state untouched
  state = _select(frame.valid, state, before)
  return state, outputs


def make_step(model: DepthModel, method: Method, cfg: AdaptConfig,
              tx: optax.GradientTransformation | None = None):
  """`adapt_step` with its static arguments bound: `step(state, frame) -> (state, outputs)`."""
  return functools.partial(adapt_step, model=model, method=method, cfg=cfg,
                           tx=tx or make_optimizer(cfg))


def make_chunk_runner(step):
  """jit(lax.scan(step)) over a chunk of frames, carry donated: `(state, frames) -> (state, outs)`."""
  @functools.partial(jax.jit, donate_argnums=0)
  def run_chunk(state, frames):
    return jax.lax.scan(step, state, frames)
  return run_chunk


def adapt_stream(state: AdaptState, chunks: Iterable[StepInput], run_chunk,
                 checkpoint_dir: str | Path | None = None, checkpoint_every: int = 0
                 ) -> Iterator[tuple[AdaptState, StepOutput]]:
  """Runs the compiled chunk over a stream of stacked chunks; yields (state, host outputs).

  Outputs are copied to the host per chunk (padding frames dropped), so device memory stays flat.
  With `checkpoint_dir` and `checkpoint_every > 0`, the state is saved whenever the number of
  frames processed crosses a multiple of `checkpoint_every` at a chunk end (make the chunk size
  divide `checkpoint_every` to save after exact frames), as `<dir>/state_<frames:06d>`.
  """
  last_saved = int(state.step)
  for chunk in chunks:
    # run_chunk donates the carry: work on a copy so the caller's state stays valid
    state, outs = run_chunk(jax.tree_util.tree_map(jnp.copy, state), chunk)
    valid = np.asarray(chunk.valid)
    host = StepOutput(*(np.asarray(o)[valid] for o in outs))
    done = int(state.step)
    if checkpoint_dir and checkpoint_every and done // checkpoint_every > last_saved // checkpoint_every:
      save_state(Path(checkpoint_dir) / f"state_{done:06d}", state)
      last_saved = done
    yield state, host


def save_state(path: str | Path, state: AdaptState) -> None:
  """orbax checkpoint of the carry, as a flat {index: leaf} tree (structure-agnostic)."""
  from pitta_jax.checkpoint import save_tree
  leaves = jax.tree_util.tree_leaves(state)
  save_tree(path, {f"{i:05d}": np.asarray(x) for i, x in enumerate(leaves)})


def load_state(path: str | Path, like: AdaptState) -> AdaptState:
  """Restores a carry saved by `save_state` into the structure of `like` (e.g. a fresh init)."""
  from pitta_jax.checkpoint import load_tree
  flat = load_tree(path)
  leaves, treedef = jax.tree_util.tree_flatten(like)
  if len(flat) != len(leaves):
    raise ValueError(f"{path}: {len(flat)} arrays, but this configuration's state has "
                     f"{len(leaves)}; was it saved with another method or selector?")
  restored = []
  for i, ref in enumerate(leaves):
    arr = flat[f"{i:05d}"]
    if arr.shape != np.shape(ref) or arr.dtype != np.asarray(ref).dtype:
      raise ValueError(f"{path}: array {i} has {arr.dtype}{arr.shape}, expected "
                       f"{np.asarray(ref).dtype}{np.shape(ref)}")
    restored.append(jnp.asarray(arr))
  return jax.tree_util.tree_unflatten(treedef, restored)
