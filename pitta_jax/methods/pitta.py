"""PITTA (the paper's method): L = L_d + lambda L_e (eq. 10) on the frame's depth, one optimiser
step per frame on the selected parameters (eq. 11; encoder BN gamma/beta by default).

lambda lives in `method_state["lam"]` (initialised from the config), so that many streams of one
compiled call can each have their own (Table 4's sweep, `pitta_jax.adapt.streams`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from pitta_jax.configs import check, check_types, is_number, option
from pitta_jax.dtypes import tree_dtype
from pitta_jax.losses import LAMBDA
from pitta_jax.methods.base import Aux, Method, predict
from pitta_jax.methods.depth_refining import DepthRefiningConfig, frame_loss


@dataclasses.dataclass(frozen=True)
class PittaConfig:
  """PITTA's own knobs (eqs. 3-10); the optimiser and the adapted parameters are AdaptConfig's."""
  lam: float = option(LAMBDA, "lambda of eq. 10 (paper Table 4's best); inf = L_e only")
  ld: DepthRefiningConfig = DepthRefiningConfig()

  def __post_init__(self):
    check_types(self)
    check(is_number(self.lam) and not math.isnan(self.lam) and self.lam >= 0,
          f"lam must be >= 0 (inf allowed), got {self.lam!r}")


def loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg: PittaConfig):
  """Eq. 10 on the frame's depth; lambda from the method state (rng unused: deterministic)."""
  del rng
  depth = predict(trainable, consts, frame, model, cfg)  # (H, W)
  parts = frame_loss(depth, frame, mcfg.ld, state.method_state["lam"])
  logs = {"loss_d": parts.l_d, "loss_e": parts.l_e, "n_instances": parts.n}
  return parts.total, Aux(jax.lax.stop_gradient(depth), jax.lax.stop_gradient(logs))


def build(config: PittaConfig = PittaConfig()) -> Method:
  """PITTA with `config` bound; method_state = {"lam": () of the parameters' float type}."""
  def init(model, parts, cfg, resources):
    del model, cfg, resources
    # the parameters' float type: float64 runs (x64 gradient checks) keep lambda exact
    return {"lam": jnp.asarray(config.lam, tree_dtype(parts.trainable))}
  return Method("pitta", config, init=init, loss=loss)
