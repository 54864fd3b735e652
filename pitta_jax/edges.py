"""Weighted Laplacian edge maps (paper eqs. 5-6).

  dX(x, y) = W(x, y) * | X(min(x+1, H-1), y) + X(max(x-1, 0), y)
                         + X(x, min(y+1, W-1)) + X(x, max(y-1, 0)) - 4 X(x, y) |

Indices are clamped to the image (edge replication, not reflection). Eq. 5 applies it to the
channel mean of the image with weights U, eq. 6 to the depth with weights V.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pitta_jax.dtypes import as_float
from pitta_jax.nonsmooth import absolute

Array = jax.Array


def laplacian(x: Array) -> Array:
  """4-neighbour Laplacian with clamped indices (the inside of |.| in eqs. 5-6).

  Args:
    x: (H, W) float map.

  Returns:
    (H, W) float32 (float64 for a float64 map). The neighbours are summed as (down + up) + (right + left) so that a
    constant map gives exactly 0.
  """
  x = as_float(x)
  if x.ndim != 2:
    raise ValueError(f"expected an (H, W) map, got shape {x.shape}")
  p = jnp.pad(x, 1, mode="edge")  # (H + 2, W + 2), clamped indices
  down, up = p[2:, 1:-1], p[:-2, 1:-1]  # X(x+1, y), X(x-1, y)
  right, left = p[1:-1, 2:], p[1:-1, :-2]  # X(x, y+1), X(x, y-1)
  return (down + up) + (right + left) - 4.0 * x


def edge_map(x: Array, weight: Array | float | None = None) -> Array:
  """Edge map of a single-channel map, eq. 6 (eq. 5 on the channel-mean image).

  Args:
    x: (H, W) map (the depth D, or the channel-mean image I_bar).
    weight: nonnegative weights V (or U): None (= 1), a scalar, or an (H, W) array.

  Returns:
    (H, W) float32 `weight * |laplacian(x)|`.
  """
  mag = absolute(laplacian(x))  # (H, W); d|u|/du = 0 at u = 0, as torch.abs
  if weight is None:
    return mag
  weight = jnp.asarray(weight, mag.dtype)
  if weight.ndim != 0 and weight.shape != mag.shape:
    raise ValueError(f"weights must be a scalar or the map's {mag.shape}, got {weight.shape}")
  return weight * mag


def image_edge_map(image: Array, weight: Array | float | None = None) -> Array:
  """Edge map of an image, eq. 5: `edge_map` of the channel mean I_bar.

  Args:
    image: (H, W, C) float image.
    weight: U, None (= 1), a scalar or (H, W).

  Returns:
    (H, W) float32.
  """
  image = as_float(image)
  if image.ndim != 3:
    raise ValueError(f"expected an (H, W, C) image, got shape {image.shape}")
  return edge_map(channel_mean(image), weight)  # I_bar: (H, W)


def channel_mean(image: Array) -> Array:
  """I_bar of eq. 5: (H, W, C) -> (H, W), ((I_0 + I_1) + I_2) / C: the sum in channel order,
  then a division, as torch.mean computes it on CPU, bit for bit, compiled or not.

  Why not jnp.mean: XLA:CPU sums the channels in another order and multiplies by the rounded
  reciprocal fl(1/C), so I_bar was 1 ulp off torch's at about half the pixels of a random
  image. An image whose I_bar equals the depth (a tie |dI| = |dD| of eq. 9, where |.| has
  gradient 0) then had residuals of 1e-7 and gradients of up to +-4 per pixel in a jitted
  step, 0 in PyTorch. The divisor is a full map behind an optimisation barrier: XLA rewrites a
  division by a scalar (even an opaque one) into a product with its reciprocal."""
  if image.ndim < 1 or image.shape[-1] < 1:
    raise ValueError(f"image must have a channel axis last (..., C) with C >= 1, got shape "
                     f"{image.shape}")
  total = image[..., 0]
  for k in range(1, image.shape[-1]):
    total = total + image[..., k]  # (H, W), left to right as torch's sum over a short axis
  count = jax.lax.optimization_barrier(jnp.full(total.shape, image.shape[-1], total.dtype))
  return total / count
