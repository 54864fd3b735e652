"""Test-time adaptation methods for the engine: a registry of `Method`s.

- `pitta`: the paper's method. Loss L = L_d + lambda L_e (eqs. 3-10) on the frame's depth,
  gradient w.r.t. the selected parameters (encoder BN gamma/beta by default), one optimiser step
  per frame (eq. 11).
- `none`: no adaptation; the network as it is. With `bn_stats="running"` this is the released
  model ("No adaptation" row); with `bn_stats="batch"` it isolates the effect of batch statistics
  from the effect of the loss (SPEC step 10).
The loss terms are still computed for `none`, so that the logs of both rows are comparable.
Later baselines (CoTTA, ActMAD, CoMoDa, Ada-Depth) register here too.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pitta_jax import losses, masks
from pitta_jax import trainable as trainable_lib
from pitta_jax.adapt.config import AdaptConfig
from pitta_jax.adapt.engine import DepthModel, LossAux, Method, StepInput


def frame_loss(depth: jax.Array, frame: StepInput, cfg: AdaptConfig,
               lam: float | jax.Array | None = None) -> losses.PittaLoss:
  """Eqs. 3-10 on one frame: dynamic-instance index map from the panoptic input, then L.

  lam: lambda of eq. 10 when it is not `cfg.lam` (a traced per-stream value in a lambda sweep).
  """
  inst_ids, inst_valid = masks.instance_table(
      frame.seg_ids, frame.seg_classes, frame.seg_valid,
      jnp.asarray(cfg.dynamic_classes, jnp.int32), cfg.max_instances)
  index_map = masks.instance_index_map(frame.panoptic, inst_ids, inst_valid)  # (H, W)
  n = jnp.sum(inst_valid.astype(jnp.int32))
  return losses.pitta_loss_from_index(
      frame.image, depth, index_map, n, s=cfg.window, lam=cfg.lam if lam is None else lam, mode=cfg.mask_mode,
      impl=cfg.loss_impl, n_max=cfg.max_instances)


def forward_and_loss(trainable, state, frame: StepInput, model: DepthModel, cfg: AdaptConfig,
                     lam: float | jax.Array | None = None) -> tuple[jax.Array, LossAux]:
  """The frame's depth (one forward pass, BN statistics per `cfg.bn_stats`) and its loss L."""
  variables = trainable_lib.merge(trainable, state.frozen, state.batch_stats)
  depth = model.depth(variables, frame.image[None], cfg.bn_stats == "batch")[0]  # (H, W)
  parts = frame_loss(depth, frame, cfg, lam)
  aux = LossAux(jax.lax.stop_gradient(depth), jax.lax.stop_gradient(parts.l_d),
                jax.lax.stop_gradient(parts.l_e), parts.n)
  return parts.total, aux


def pitta_loss(trainable, *, state, frame, rng, model, cfg):
  """PITTA's objective, eq. 10, for the engine (rng unused: PITTA is deterministic)."""
  del rng
  return forward_and_loss(trainable, state, frame, model, cfg)


def none_loss(trainable, *, state, frame, rng, model, cfg):
  del rng
  total, aux = forward_and_loss(trainable, state, frame, model, cfg)
  return jax.lax.stop_gradient(total), aux


def _no_state(split, cfg):
  return {}


METHODS: dict[str, Method] = {
    "pitta": Method("pitta", init=_no_state, loss=pitta_loss),
    "none": Method("none", init=_no_state, loss=none_loss, adapts=False),
}


def get_method(name: str) -> Method:
  if name not in METHODS:
    raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(METHODS))}")
  return METHODS[name]
