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
  return jnp.asarray(weight, mag.dtype) * mag


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
  return edge_map(jnp.mean(image, axis=-1), weight)  # I_bar: (H, W)
