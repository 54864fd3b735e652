"""The online adaptation engine: one pure `adapt_step`, scanned over frames in chunks.

Per frame (predict-then-adapt, as every TTA paper evaluates): the method's loss is evaluated on
the frame; the depth returned for evaluation comes from that same forward pass, i.e. *before* the
update the frame causes; then the method updates its state (paper eq. 11 for PITTA). A method
whose original evaluates after its update (`Method.report_after_update`, Ada-Depth) gets one
more forward pass with the updated parameters, and that depth is returned instead. A
sequence is `jax.lax.scan(adapt_step, state, frames)`; long sequences stream through one compiled
scan of `chunk_size` frames at a time, so memory does not grow with the sequence length, and the
state can be checkpointed (orbax) after any frame and resumed with bitwise identical results.

Everything random derives from `jax.random.fold_in(state.rng, state.step)`: same config + same
inputs => bitwise the same depths and parameters.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from pitta_jax import trainable as trainable_lib
from pitta_jax.prng import seed_key
from pitta_jax.adapt.config import AdaptConfig
from pitta_jax.adapt.hoist import hoist_invariants
from pitta_jax.adapt.xla_cpu import step_compiler_options
from pitta_jax.methods.base import Method, predict

Tree = Any


class StepInput(NamedTuple):
  """One frame as the compiled step sees it (static shapes; stack on a leading axis to scan).

  image:        (H, W, 3) float32 RGB in [0, 1] at the network's input size.
  panoptic:     (H, W) int32 segment ids at the same size (0 = void).
  seg_ids:      (S,) int32 segment ids present in the frame, padded.
  seg_classes:  (S,) int32 COCO category ids of those segments.
  seg_valid:    (S,) bool, False for padding.
  valid:        () bool, False for a padding frame at the end of the last chunk (no-op step).
  intrinsics:   (3, 3) float32 camera matrix K at the network's input size (zeros if unknown).
  has_intrinsics: () bool, whether the dataset gave K for this frame.
  starts_recording: () bool, True for the first frame of a recording that follows another
                (`Frame.starts_recording`): methods that pair a frame with the frames before it
                (CoMoDa, Ada-Depth) forget those; ActMAD's ring keeps them (its stand-in for a
                batch of images, which upstream draws independently).
  """
  image: jax.Array
  panoptic: jax.Array
  seg_ids: jax.Array
  seg_classes: jax.Array
  seg_valid: jax.Array
  valid: jax.Array
  intrinsics: jax.Array
  has_intrinsics: jax.Array
  starts_recording: jax.Array


class Consts(NamedTuple):
  """The network's weights that do not adapt: an argument of the compiled chunk, not carried.

  frozen: the parameters outside the selector; batch_stats: BN running statistics (PITTA and
  the baselines leave them untouched: batch statistics are used, not accumulated).
  """
  frozen: Tree
  batch_stats: Tree


@struct.dataclass
class AdaptState:
  """The scan carry: only what changes from frame to frame."""
  trainable: Tree      # the adapted parameters (differentiated and updated)
  opt_state: Tree
  method_state: Tree   # method-specific (lambda for PITTA, an EMA teacher, a frame ring, ...)
  source: Tree         # the trainable parameters at the start, for the reset policy
  step: jax.Array      # () int32, frames processed
  rng: jax.Array       # base PRNG key; per frame: fold_in(rng, step)
  n_skipped: jax.Array  # () int32, updates skipped by the non-finite guard


class StepOutput(NamedTuple):
  """Per-frame measurements returned by the step (stacked by the scan)."""
  depth: jax.Array        # (H, W) depth predicted before this frame's update (after it with
                          # Method.report_after_update)
  loss: jax.Array         # () the method's loss (0 for `none`)
  logs: dict              # () scalars: the method's own terms (PITTA: loss_d, loss_e, n_instances)
  skipped: jax.Array      # () bool, an update of the frame was skipped (non-finite): with
                          # several steps per frame, any of them (`n_skipped` counts each)
  grad_norm: jax.Array    # () global norm of the gradient w.r.t. the trainable tree
  update_norm: jax.Array  # () global norm of the applied update


def make_optimizer(cfg: AdaptConfig, method: Method | None = None
                   ) -> optax.GradientTransformation:
  """The method's own optimiser when it has one (`Method.optimizer`), else Adam (default) or SGD
  with the configured learning rate (paper eq. 11: theta -= alpha grad)."""
  if method is not None and method.optimizer is not None:
    return method.optimizer(cfg)
  if cfg.optimizer == "adam":
    return optax.adam(cfg.lr)
  return optax.sgd(cfg.lr, momentum=cfg.momentum or None)


def init_state(variables: Tree, method: Method, cfg: AdaptConfig,
               tx: optax.GradientTransformation, model: Any = None,
               resources: dict[str, Any] | None = None) -> tuple[AdaptState, Consts]:
  """Splits the variables with the configured selector: the initial carry and the constants.

  model: the `Network` (passed to `method.init`); resources: host-side inputs of the method.
  """
  method.check(cfg)
  selector = trainable_lib.parse_selector(cfg.selector)
  order = model.forward_order() if model is not None and selector.kind == "fraction" else None
  parts = trainable_lib.split(variables, selector,
                              encoder=model.spec.encoder if model is not None else "encoder",
                              order=order)
  # private copies: the runner donates the carry, which must never alias the caller's arrays
  to_jnp = functools.partial(jax.tree_util.tree_map, lambda x: jnp.array(x, copy=True))
  tr = to_jnp(parts.trainable)
  state = AdaptState(
      trainable=tr, opt_state=tx.init(tr),
      method_state=method.init(model, parts, cfg, dict(resources or {})),
      source=jax.tree_util.tree_map(jnp.copy, tr),  # distinct buffers: the carry is donated
      step=jnp.zeros((), jnp.int32), rng=seed_key(cfg.seed),
      n_skipped=jnp.zeros((), jnp.int32))
  consts = Consts(jax.tree_util.tree_map(jnp.asarray, parts.frozen),
                  jax.tree_util.tree_map(jnp.asarray, parts.batch_stats))
  return state, consts


def _same_shape_groups(tree: Tree) -> list[list[jax.Array]]:
  """The inexact leaves of `tree`, grouped by (shape, dtype): elementwise work on a group
  followed by one reduction is one XLA kernel where a reduction per leaf is one kernel each."""
  groups: dict[tuple, list[jax.Array]] = {}
  for x in jax.tree_util.tree_leaves(tree):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
      groups.setdefault((x.shape, x.dtype), []).append(x)
  return list(groups.values())


def all_finite(tree: Tree) -> jax.Array:
  """() bool: every leaf of `tree` is finite (integers and booleans always are).

  Leaves of one shape and dtype are summed elementwise as 0-or-NaN flags before one reduction
  per shape: a reduction per leaf is a separate XLA kernel, and the guard of an Adam step on
  MonoDepth2's 88 parameter leaves (gradients, parameters, both moments) compiled 831 of them
  (6.3 s; grouped: 4 s). A leaf's flag is `x * 0` (0 where x is finite, NaN where it is
  infinite or NaN; no sum of flags can overflow): XLA:CPU fuses the product into the
  reduction, where `where(isfinite(x), 0, nan)` was one more full-size kernel per leaf. That
  guard on MonoDepth2's parameters: 666 -> 550 kernels, 300 -> 110-129 ms per step alone (one
  vCPU); Ada-Depth's step at 640x192: 3625 -> 3469 kernels, compile 82.5 -> 78.7 s, 2314 ->
  2284 ms/frame best of 5 interleaved on a busy host. The predicate is sqrt of the total so
  that XLA computes it once: an `and` of per-leaf flags is a chain of cheap scalar ops that
  XLA's fusion copies into every consumer, i.e. into each guarded leaf's select (with hundreds
  of leaves, minutes of compile time and a 100 MB program); sqrt is an op it does not duplicate.
  """
  groups = _same_shape_groups(tree)
  if not groups:
    return jnp.array(True)
  nan_if_any = sum(jnp.sum(sum(x * 0 for x in group)) for group in groups)
  return jnp.isfinite(jnp.sqrt(nan_if_any))


def tree_norm(tree: Tree) -> jax.Array:
  """() the global L2 norm of `tree`'s inexact leaves (`optax.tree.norm`'s value), with one
  reduction per leaf shape (see `all_finite`): the engine logs the gradient's and the update's
  norm every step, and per leaf that is two kernels per parameter leaf."""
  groups = _same_shape_groups(tree)
  if not groups:
    return jnp.zeros(())
  return jnp.sqrt(sum(jnp.sum(sum(x * x for x in group)) for group in groups))


def select(pred: jax.Array, on_true: Tree, on_false: Tree) -> Tree:
  """Leafwise `where(pred, on_true, on_false)` of two trees of the same structure.

  Not a `lax.cond`: that compiles fewer kernels (a guarded Adam step on MonoDepth2's parameters:
  1.2 s less), but Ada-Depth's step took 9% longer with it (320x96, interleaved: 1066 vs 957
  ms/frame)."""
  return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


def optax_update(state: AdaptState, grads: Tree, loss: jax.Array, tx: optax.GradientTransformation,
                 cfg: AdaptConfig) -> tuple[AdaptState, jax.Array, jax.Array]:
  """One optimiser step on the trainable tree, with the non-finite guard.

  Returns (state, skipped, update_norm). The guard rejects a step whose loss, gradient, new
  parameters or new optimiser state is not finite: trainable and optimiser state then stay
  exactly as they were and `n_skipped` counts it.
  """
  updates, new_opt = tx.update(grads, state.opt_state, state.trainable)
  new_tr = optax.apply_updates(state.trainable, updates)
  if cfg.skip_nonfinite:
    ok = jnp.isfinite(loss) & all_finite((grads, new_tr, new_opt))
    new_tr = select(ok, new_tr, state.trainable)
    new_opt = select(ok, new_opt, state.opt_state)
    skipped = ~ok
  else:
    skipped = jnp.array(False)
  unorm = jnp.where(skipped, 0.0, tree_norm(updates))
  state = state.replace(trainable=new_tr, opt_state=new_opt,
                        n_skipped=state.n_skipped + skipped.astype(jnp.int32))
  return state, skipped, unorm


def adapt_step(state: AdaptState, frame: StepInput, consts: Consts, *, model: Any,
               method: Method, cfg: AdaptConfig, tx: optax.GradientTransformation
               ) -> tuple[AdaptState, StepOutput]:
  """One frame: predict, compute the method's loss, update (pure; `lax.scan`-able).

  Bind the keyword arguments with `functools.partial` (see `make_step`).
  """
  rng = jax.random.fold_in(state.rng, state.step)
  before = state
  if cfg.reset_every > 0:
    reset = (state.step > 0) & (state.step % cfg.reset_every == 0)
    restored = select(reset, (state.source, tx.init(state.source)),
                      (state.trainable, state.opt_state))
    state = state.replace(trainable=restored[0], opt_state=restored[1])
    if method.reset is not None:
      state = state.replace(method_state=select(
          reset, method.reset(state.method_state, state.source), state.method_state))

  def update(state, grads, loss, aux, key):
    if method.update is None:
      return optax_update(state, grads, loss, tx, cfg)
    return method.update(state, grads, loss, aux, key, tx, cfg)

  outputs, skipped_any = None, jnp.array(False)
  for k in range(cfg.steps_per_frame if method.adapts else 1):
    # each inner step draws afresh (CoTTA's augmented views, as upstream's `steps` loop); the
    # first uses the frame's key itself, the update keys are fold_in(rng, 0 .. steps - 1)
    loss_rng = rng if k == 0 else jax.random.fold_in(rng, cfg.steps_per_frame + k)
    loss_fn = functools.partial(method.loss, state=state, consts=consts, frame=frame,
                                rng=loss_rng, model=model, cfg=cfg, mcfg=method.config)
    if method.adapts:
      (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.trainable)
      gnorm = tree_norm(grads)
      state, skipped, unorm = update(state, grads, loss, aux, jax.random.fold_in(rng, k))
    else:
      loss, aux = loss_fn(state.trainable)
      gnorm = unorm = jnp.zeros(())
      skipped = jnp.array(False)
    skipped_any = skipped_any | skipped
    if k == 0 or method.report_last_step:  # the first pass (predict-then-adapt), or the last
      outputs = StepOutput(aux.depth, loss, aux.logs, skipped, gnorm, unorm)
  # a frame's later inner step skipped is the frame's too (its log agrees with `n_skipped`)
  outputs = outputs._replace(skipped=skipped_any)
  if method.report_after_update:  # adapt-then-predict: the depth after the last update
    outputs = outputs._replace(depth=predict(state.trainable, consts, frame, model, cfg))
  state = state.replace(step=state.step + 1)
  # a padding frame leaves the state untouched
  state = select(frame.valid, state, before)
  return state, outputs


def make_step(model: Any, method: Method, cfg: AdaptConfig,
              tx: optax.GradientTransformation | None = None):
  """`adapt_step` with its static arguments bound: `step(state, frame, consts)`."""
  return functools.partial(adapt_step, model=model, method=method, cfg=cfg,
                           tx=tx or make_optimizer(cfg, method))


def make_method_runner(model: Any, method: Method, cfg: AdaptConfig,
                       tx: optax.GradientTransformation | None = None):
  """The compiled chunk runner of `method`'s step under `cfg`, as every command compiles it:
  `make_chunk_runner(make_step(...))` with the step's XLA options (`xla_cpu.step_compiler_options`:
  the convolution library of `cfg.conv_library`). tx: the optimiser that `init_state` got
  (default `make_optimizer(cfg, method)`)."""
  return make_chunk_runner(make_step(model, method, cfg, tx), step_compiler_options(cfg, method))


def make_chunk_runner(step, compiler_options: dict[str, Any] | None = None):
  """jit(lax.scan(step)) over a chunk of frames, carry donated:
  `(state, frames, consts) -> (state, outputs)`; `consts` is an ordinary (not donated) input.

  The step's work that depends on `consts` alone (e.g. the frozen convolutions' input-gradient
  kernels) runs once per chunk, before the scan (`hoist.hoist_invariants`).
  compiler_options: XLA options for this program alone (`jax.jit`'s), e.g.
  `{"xla_backend_optimization_level": 0}` for a run too short to repay a full compile.

  Called with traced arguments (inside the caller's own `jax.jit`, `jax.vmap`, ...), the runner
  is the same scan jitted without `compiler_options`, which JAX takes on a top-level `jax.jit`
  only: the caller's program compiles with its own options (a speed choice, `xla_cpu`)."""
  def scan_chunk(state, frames, consts):
    one = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), frames)
    body, _ = hoist_invariants(lambda c, s, f: step(s, f, c), consts, state, one)
    return jax.lax.scan(body, state, frames)

  run_chunk = jax.jit(scan_chunk, donate_argnums=0, compiler_options=compiler_options)
  if not compiler_options:
    return run_chunk

  traced = jax.jit(scan_chunk, donate_argnums=0)

  @functools.wraps(scan_chunk)
  def runner(state, frames, consts):
    if any(isinstance(x, jax.core.Tracer)
           for x in jax.tree_util.tree_leaves((state, frames, consts))):
      return traced(state, frames, consts)
    return run_chunk(state, frames, consts)

  runner._cache_size = run_chunk._cache_size  # `run._compile_count` reads it
  runner.lower = run_chunk.lower
  return runner


POLL_SECONDS = 0.005  # how often a wait for a running chunk looks whether it has ended


def _all_ready(pending: list) -> bool:
  """Whether every array of a dispatched chunk's results in `pending` is computed; drops those
  that are, from the end (one program's outputs are ready together: a poll looks at one array,
  not at the hundreds of a carry's leaves)."""
  while pending and (not isinstance(pending[-1], jax.Array) or pending[-1].is_ready()):
    pending.pop()
  return not pending


def wait_for_chunk(tree: Any) -> KeyboardInterrupt | None:
  """Waits until the arrays of a dispatched chunk (`tree`) are computed, answering signals
  meanwhile: a blocking read holds a Ctrl-C until the chunk ends, and then the interrupt cut the
  chunk's frames from the run it had waited for.

  XLA cannot stop a running program, so the first Ctrl-C (or SIGTERM / SIGHUP, which the
  commands raise as a KeyboardInterrupt) does not end the wait: it is returned, for the caller
  to raise once the chunk's frames are recorded (and checkpointed), with a line on stderr
  saying so at once. A second one raises at once. Returns None without a signal."""
  pending = jax.tree_util.tree_leaves(tree)
  held = None
  while True:
    try:
      while not _all_ready(pending):
        time.sleep(POLL_SECONDS)
      return held
    except KeyboardInterrupt as interrupt:
      if held is not None:
        raise
      held = interrupt
      print("interrupted while a chunk runs: it cannot be cut short, so its frames are kept "
            "once it ends (interrupt again not to wait for them)", file=sys.stderr, flush=True)


def adapt_stream(state: AdaptState, consts: Consts, chunks: Iterable[StepInput], run_chunk,
                 checkpoint_dir: str | Path | None = None, checkpoint_every: int = 0
                 ) -> Iterator[tuple[AdaptState, StepOutput]]:
  """Runs the compiled chunk over a stream of stacked chunks; yields (state, host outputs).

  Outputs are copied to the host per chunk (padding frames dropped), so device memory stays flat.
  With `checkpoint_dir` and `checkpoint_every > 0`, the state is saved whenever the number of
  frames processed crosses a multiple of `checkpoint_every` at a chunk end (make the chunk size
  divide `checkpoint_every` to save after exact frames), as `<dir>/state_<frames:06d>`.
  An interrupt while a chunk runs is raised after that chunk's outputs are yielded (and saved),
  at the next iteration (`wait_for_chunk`).
  """
  last_saved = int(state.step)
  for chunk in chunks:
    # run_chunk donates the carry: work on a copy so the caller's state stays valid
    state, outs = run_chunk(jax.tree_util.tree_map(jnp.copy, state), chunk, consts)
    held = wait_for_chunk((state, outs))
    valid = np.asarray(chunk.valid)
    host = jax.tree_util.tree_map(lambda o: np.asarray(o)[valid], outs)
    done = int(state.step)
    if checkpoint_dir and checkpoint_every and done // checkpoint_every > last_saved // checkpoint_every:
      save_state(Path(checkpoint_dir) / f"state_{done:06d}", state)
      last_saved = done
    yield state, host
    if held is not None:  # the caller has recorded the chunk it waited for
      raise held


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
