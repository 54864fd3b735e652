"""No adaptation: the network as it is, one forward pass per frame, nothing updated.

With `AdaptConfig.bn_stats="running"` this is the released model ("No adaptation" row); with
"batch" it uses each frame's BatchNorm statistics and no loss, which separates the effect of
batch statistics from the effect of a method's loss.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from pitta_jax.methods.base import Aux, Method, predict


@dataclasses.dataclass(frozen=True)
class NoneConfig:
  """No knobs: `none` only predicts."""


def loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg):
  del state, rng, mcfg
  depth = jax.lax.stop_gradient(predict(trainable, consts, frame, model, cfg))
  return jnp.zeros((), depth.dtype), Aux(depth, {})


def build(config: NoneConfig = NoneConfig()) -> Method:
  # "No adaptation" evaluates the source model as it is: BN with its running statistics
  # (with --bn-stats batch the same method gives the "BN batch stats" row)
  return Method("none", config, init=lambda model, parts, cfg, resources: {}, loss=loss,
                adapts=False, setting=(("bn_stats", "running"),))
