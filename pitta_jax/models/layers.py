"""Layers whose numerics must match PyTorch exactly (for checkpoint parity).

- `BatchNorm`: PyTorch `nn.BatchNorm2d` semantics, which Flax's `nn.BatchNorm` does not have:
  normalisation uses the *biased* batch variance, the running estimate receives the *unbiased*
  one, momentum 0.1 means `running = 0.9 * running + 0.1 * batch`, eps 1e-5.
- `Conv`: `flax.linen.Conv` with the loop-friendly input gradient of `conv_vjp` (fast inside
  the engine's `lax.scan` on CPU); `conv`: one with explicit PyTorch-style symmetric padding
  (Flax's 'SAME' pads asymmetrically for stride-2 convolutions).
- `reflect_pad`, `upsample_nearest2x`: MonoDepth2's `ReflectionPad2d(1)` and
  `F.interpolate(scale_factor=2, mode="nearest")`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import flax.linen as nn

from pitta_jax.models import conv_vjp

# Every convolution of the adapted networks: same parameters and values as nn.Conv.
Conv = functools.partial(nn.Conv, conv_general_dilated=conv_vjp.conv_general_dilated)


class BatchNorm(nn.Module):
  """BatchNorm over the channel (last) axis with PyTorch semantics.

  Variables: params `scale` (gamma) and `bias` (beta); batch_stats `mean` and `var`.

  Attributes:
    momentum: PyTorch convention (weight of the new batch statistic), 0.1 by default.
    epsilon: added to the variance, 1e-5 as in PyTorch.
  """
  momentum: float = 0.1
  epsilon: float = 1e-5

  @nn.compact
  def __call__(self, x: jax.Array, use_batch_stats: bool) -> jax.Array:
    """Normalises `x` (..., C).

    Args:
      x: (B, H, W, C) activations.
      use_batch_stats: True = PyTorch train mode (normalise with the batch's statistics, and
        update the running estimate if the `batch_stats` collection is mutable); False = eval
        mode (normalise with the running estimate).
    """
    features = x.shape[-1]
    scale = self.param("scale", nn.initializers.ones, (features,), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros, (features,), jnp.float32)
    ra_mean = self.variable("batch_stats", "mean", lambda: jnp.zeros((features,), jnp.float32))
    ra_var = self.variable("batch_stats", "var", lambda: jnp.ones((features,), jnp.float32))

    if use_batch_stats:
      axes = tuple(range(x.ndim - 1))
      mean = jnp.mean(x, axis=axes)
      var = jnp.mean(jnp.square(x - mean), axis=axes)  # biased, as PyTorch normalises
      if not self.is_initializing() and self.is_mutable_collection("batch_stats"):
        n = x.size // features
        unbiased = var * (n / max(n - 1, 1))  # PyTorch stores the unbiased estimate
        m = self.momentum
        ra_mean.value = (1.0 - m) * ra_mean.value + m * jax.lax.stop_gradient(mean)
        ra_var.value = (1.0 - m) * ra_var.value + m * jax.lax.stop_gradient(unbiased)
    else:
      mean, var = ra_mean.value, ra_var.value
    inv = jax.lax.rsqrt(var + self.epsilon) * scale
    return (x - mean) * inv + bias


def conv(features: int, kernel: int, stride: int = 1, padding: int = 0, use_bias: bool = False,
         name: str | None = None) -> nn.Conv:
  """A PyTorch-equivalent `Conv2d(k, stride, padding)` in NHWC (kernel stored as HWIO)."""
  return Conv(features, (kernel, kernel), strides=(stride, stride),
                 padding=((padding, padding), (padding, padding)), use_bias=use_bias, name=name)


def reflect_pad(x: jax.Array, pad: int = 1) -> jax.Array:
  """`nn.ReflectionPad2d(pad)` on an NHWC tensor (edge pixel not repeated)."""
  return jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="reflect")


def upsample_nearest2x(x: jax.Array) -> jax.Array:
  """`F.interpolate(x, scale_factor=2, mode="nearest")` on an NHWC tensor."""
  return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)
