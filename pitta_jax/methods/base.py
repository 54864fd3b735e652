"""The method API: what a test-time adaptation method gives the engine.

A method is a `Method` value built from its own config dataclass (`pitta_jax.methods.build`):

  init(model, parts, cfg, resources) -> method_state
      Anything the method carries from frame to frame besides the adapted parameters: an EMA
      teacher, source statistics, a ring of previous frames (`ring_init`/`ring_push`), a
      per-stream loss weight. `parts` is the trainable/frozen/batch_stats split of the source
      network, `resources` optional host-side inputs loaded before the run (source
      statistics, a replay set), keyed by name; `resources[INPUT_SIZE]` is the frames' (H, W)
      (e.g. for a ring of previous images).
  loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg) -> (loss, Aux)
      Differentiable in `trainable`. It also produces the depth that is evaluated for this
      frame (predict-then-adapt: the depth before this frame's update) and an open dict of
      scalar logs (PITTA logs L, L_d, L_e, N; another method logs its own terms).
  update(state, grads, loss, aux, rng, tx, cfg) -> (state, skipped, update_norm)   [optional]
      Replaces the default single optimiser step (`engine.optax_update`), e.g. to also move an
      EMA teacher or restore weights stochastically; it must keep the non-finite guard.
      `aux.carry` brings it what the loss computed for it (e.g. activations for a frame ring).
  reset(method_state, source) -> method_state   [optional]
      What `AdaptConfig.reset_every` does to the method state when the engine puts the adapted
      parameters and the optimiser back to the source (`source`: the trainable leaves at the
      start), e.g. CoTTA's teacher copied from the source again; without it the method state
      carries on.
  optimizer(cfg) -> optax.GradientTransformation   [optional]
      The method's own optimiser (e.g. ActMAD's SGD with Nesterov momentum and weight decay),
      used by `engine.make_optimizer` instead of AdaptConfig's optimizer/lr/momentum.
  adapts: False for a method that never updates (no gradient is computed).
  prepare(model, variables, source: SourceData) -> resources   [optional]
      Host-side inputs computed once before the run from source-domain data (ActMAD's source
      statistics from `source.batches()`, CoMoDa's replay set from `source.sequences`).
  needs: what the method needs besides a frame's image and panoptic input, checked before any
      work: "pose" (the weights' pose network, given as resources["pose"] = PoseNet(module,
      variables)), "intrinsics" (every frame's K), "previous_frame" (consecutive frames).
  cpu_conv_library: what `AdaptConfig.conv_library = "auto"` means for this method's step
      on a CPU (`adapt.xla_cpu`): "auto" (Eigen's convolutions, every method measured so far),
      or "eigen" / "default" where a method's step was measured faster with that library.
  metres: the method's constants are in metres: it multiplies the network's depth by its
      config's `depth_scale`, else by the weights' factor to metres (resources["metric_factor"],
      `run.metric_factor`), else 1 (the CLI notes that case).
  report_after_update: the frame's evaluated depth is the adapted network's prediction *after*
      the frame's update (`predict` with the new trainable leaves, one more forward pass) instead
      of `Aux.depth` (e.g. Ada-Depth, whose official code evaluates the student after its step).
  report_last_step: with `AdaptConfig.steps_per_frame` > 1, the frame's outputs (Aux.depth,
      loss, logs) are those of the last inner step instead of the first (CoTTA, whose official
      `forward` returns what its last pass of the `steps` loop computed); False keeps the first
      forward pass, before any update of the frame (predict-then-adapt: PITTA).

The engine (`pitta_jax.adapt.engine`) knows only this interface, never a method's name.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from pitta_jax import trainable as trainable_lib

Tree = Any


NEEDS = ("pose", "intrinsics", "previous_frame")
POSE = "pose"  # the resources key of the weights' pose network
INPUT_SIZE = "input_size"  # the resources key of the frames' (H, W) (`run.run_sequence` gives it)
# the resources key of the factor from the network's depth to metres where the weights give one,
# else None (`run.metric_factor`; `run.run_sequence` gives it)
METRIC_FACTOR = "metric_factor"


class PoseNet(NamedTuple):
  """The source weights' pose network: a Flax module (frame pair (B, H, W, 6) ->
  (axisangle, translation), each (B, F, 1, 3)) and its variables."""
  module: Any
  variables: Tree


@dataclasses.dataclass(frozen=True)
class SourceData:
  """Source-domain data a method's `prepare` may use, all at the network's input size.

  images: single frames (H, W, 3) float32 in [0, 1] (e.g. for activation statistics).
  sequences: runs of consecutive frames (`data.Frame`, with `intrinsics` when known), e.g. a
    replay set of frame pairs or triplets; empty when only unordered images were given.
  """
  images: tuple[Any, ...] = ()
  sequences: tuple[tuple[Any, ...], ...] = ()
  progress: str | None = None  # a progress bar's title for `batches()`; None: no bar

  def batches(self, size: int = 4):
    """`images` as stacked batches (B, H, W, 3) of at most `size`, read one batch at a time
    (a real source set need not fit in memory), with a progress bar titled `progress`."""
    import numpy as np
    from tqdm import tqdm
    starts = range(0, len(self.images), size)
    for i in tqdm(starts, desc=self.progress, unit="batch", disable=self.progress is None):
      yield np.stack(self.images[i:i + size])


class Aux(NamedTuple):
  """What a method's loss returns beside the scalar (all stop-gradient)."""
  depth: jax.Array               # (H, W) the evaluated depth of this frame
  logs: dict[str, jax.Array]     # () scalars, the method's own per-frame measurements
  carry: Any = None              # for the method's own `update` only (never output per frame)


@dataclasses.dataclass(frozen=True)
class Method:
  """A test-time adaptation method plugged into the engine (see the module docstring)."""
  name: str
  config: Any
  init: Callable[..., Tree]
  loss: Callable[..., tuple[jax.Array, Aux]]
  update: Callable[..., Any] | None = None
  reset: Callable[..., Tree] | None = None
  adapts: bool = True
  optimizer: Callable[..., Any] | None = None
  # (model, variables, SourceData) -> resources for `init`; None for methods that need no
  # source data. The CLI feeds it clear synthetic streets or --source-images / --replay-root.
  prepare: Callable[..., dict[str, Any]] | None = None
  # the AdaptConfig values the method needs (e.g. BN in eval mode): 0 or more
  # (field, value, reason) triples, checked before any work
  requires: tuple[tuple[str, Any, str], ...] = ()
  # data the method needs (a subset of NEEDS), checked before any work
  needs: tuple[str, ...] = ()
  # the AdaptConfig values of the method's published setting beyond `requires` (e.g. which
  # parameters adapt), as (field, value) pairs; the demo and the experiments start from them
  setting: tuple[tuple[str, Any], ...] = ()
  # evaluate the depth predicted after the frame's update instead of Aux.depth
  report_after_update: bool = False
  # with several steps per frame, report the last inner step's outputs instead of the first's
  report_last_step: bool = False
  metres: bool = False
  # `AdaptConfig.conv_library = "auto"` for this method on a CPU (see the module docstring)
  cpu_conv_library: str = "auto"

  def __post_init__(self):
    from pitta_jax.adapt.xla_cpu import check_library  # lazy: pitta_jax.adapt imports methods
    check_library(self.cpu_conv_library, f"method {self.name}: cpu_conv_library")
    unknown = set(self.needs) - set(NEEDS)
    if unknown:
      raise ValueError(f"method {self.name}: unknown needs {sorted(unknown)}; use {NEEDS}")
    for field in ("init", "loss"):
      if not callable(getattr(self, field)):
        raise ValueError(f"method {self.name}: {field} must be a function, got "
                         f"{getattr(self, field)!r}")
    from pitta_jax.adapt.config import AdaptConfig  # lazy, as above
    fields = {f.name for f in dataclasses.fields(AdaptConfig)}
    for field, _, _ in (*self.requires, *((k, v, "") for k, v in self.setting)):
      if field not in fields:
        raise ValueError(f"method {self.name}: requires/setting name {field!r}, which is no "
                         f"AdaptConfig field")

  def check(self, cfg) -> None:
    """ValueError (one line, naming every flag at once) when `cfg` contradicts `requires`."""
    unmet = [(field, value, reason) for field, value, reason in self.requires
             if getattr(cfg, field) != value]
    if unmet:
      raise ValueError(f"{self.name} {' and '.join(r for _, _, r in unmet)}: use "
                       + " ".join(f"--{f.replace('_', '-')} {v}" for f, v, _ in unmet))


def variables_of(trainable: Tree, consts) -> Tree:
  """The network's Flax variables from the adapted leaves and the run's constants."""
  return trainable_lib.merge(trainable, consts.frozen, consts.batch_stats)


def predict(trainable: Tree, consts, frame, model, cfg) -> jax.Array:
  """The frame's depth (H, W) with BN statistics per `cfg.bn_stats` (one forward pass)."""
  variables = variables_of(trainable, consts)
  return model.depth(variables, frame.image[None], cfg.bn_stats == "batch")[0]


# ----------------------------------------------------------------------------- previous frames


def ring_init(example: jax.Array, size: int) -> dict[str, jax.Array]:
  """An empty ring of the `size` most recent arrays shaped like `example` (for method_state).

  {"items": (size, *shape), "count": () int32}; `items[0]` is the most recent once filled.
  """
  return {"items": jnp.zeros((size,) + tuple(example.shape), example.dtype),
          "count": jnp.zeros((), jnp.int32)}


def ring_push(ring: dict[str, jax.Array], item: jax.Array) -> dict[str, jax.Array]:
  """The ring with `item` as the most recent entry (the oldest drops out); jittable."""
  items = jnp.concatenate([item[None].astype(ring["items"].dtype), ring["items"][:-1]], axis=0)
  return {"items": items, "count": jnp.minimum(ring["count"] + 1, ring["items"].shape[0])}


def ring_restart(ring: dict[str, jax.Array], restart: jax.Array) -> dict[str, jax.Array]:
  """The ring emptied where `restart` (() bool) holds, e.g. at a frame that starts a new
  recording (`StepInput.starts_recording`): frames of the recording before are no neighbours."""
  return {**ring, "count": jnp.where(restart, 0, ring["count"]).astype(ring["count"].dtype)}


def ring_valid(ring: dict[str, jax.Array]) -> jax.Array:
  """(size,) bool: which ring slots hold a frame (slot k = k frames ago, 0 = the last one)."""
  return jnp.arange(ring["items"].shape[0]) < ring["count"]
