"""PyTorch's `F.interpolate` on NHWC arrays: bilinear and bicubic, both align_corners modes.

Each axis is resized by a constant (out, in) interpolation matrix built with NumPy from
PyTorch's source-coordinate rule, then applied with one einsum per axis; the matrices are
constants of the compiled program, and the gradient w.r.t. the input is exact.

Source coordinate of output index i (scale = in / out, PyTorch's rule when no scale_factor is
given):
  align_corners=True:  x = i * (in - 1) / (out - 1)   (0 when out == 1)
  align_corners=False: x = (i + 0.5) * scale - 0.5, clamped at 0 for bilinear (not for bicubic)
Bilinear: linear weights between floor(x) and floor(x) + 1 (index clamped to in - 1).
Bicubic: Keys' cubic convolution with a = -0.75 (PyTorch's constant) over the 4 neighbours
floor(x) - 1 .. floor(x) + 2, indices clamped to [0, in - 1] (border replication).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

CUBIC_A = -0.75  # PyTorch's bicubic constant (OpenCV uses the same)


def _source_coords(n_in: int, n_out: int, align_corners: bool) -> np.ndarray:
  i = np.arange(n_out, dtype=np.float64)
  if align_corners:
    return i * ((n_in - 1) / (n_out - 1)) if n_out > 1 else np.zeros(n_out)
  return (i + 0.5) * (n_in / n_out) - 0.5


def linear_matrix(n_in: int, n_out: int, align_corners: bool,
                  dtype: type = np.float32) -> np.ndarray:
  """(n_out, n_in) weights of PyTorch's 1-D linear interpolation, float32 (or `dtype`)."""
  x = _source_coords(n_in, n_out, align_corners)
  if not align_corners:
    x = np.maximum(x, 0.0)
  lo = np.minimum(np.floor(x).astype(np.int64), n_in - 1)
  hi = np.minimum(lo + 1, n_in - 1)
  frac = x - lo
  m = np.zeros((n_out, n_in), np.float64)
  np.add.at(m, (np.arange(n_out), lo), 1.0 - frac)
  np.add.at(m, (np.arange(n_out), hi), frac)
  return m.astype(dtype)


def _cubic_weights(t: np.ndarray, a: float) -> np.ndarray:
  """Weights of the neighbours at offsets -1, 0, 1, 2 for fractional position t, (n, 4)."""
  def near(d):  # |d| <= 1
    return ((a + 2) * d - (a + 3)) * d * d + 1
  def far(d):  # 1 < |d| < 2
    return ((a * d - 5 * a) * d + 8 * a) * d - 4 * a
  return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], axis=-1)


def cubic_matrix(n_in: int, n_out: int, align_corners: bool, a: float = CUBIC_A,
                 dtype: type = np.float32) -> np.ndarray:
  """(n_out, n_in) weights of PyTorch's 1-D bicubic interpolation, float32 (or `dtype`)."""
  x = _source_coords(n_in, n_out, align_corners)
  base = np.floor(x).astype(np.int64)
  w = _cubic_weights(x - base, a)  # (n_out, 4)
  m = np.zeros((n_out, n_in), np.float64)
  for k in range(4):
    idx = np.clip(base - 1 + k, 0, n_in - 1)
    np.add.at(m, (np.arange(n_out), idx), w[:, k])
  return m.astype(dtype)


def _resize(x: jax.Array, size: tuple[int, int], matrix) -> jax.Array:
  """Each axis through its matrix; an axis whose matrix is the identity (same size: every
  mode's source coordinates are then the pixels themselves) is left as it is, so a resize to
  the input's own size (e.g. MonoDepth2's loss upsampling scale 0) costs nothing and puts no
  (H, H) constant into the program."""
  h, w = x.shape[-3], x.shape[-2]
  # float64 weights for a float64 input (as F.interpolate on a double tensor), float32 otherwise
  dtype = np.float64 if x.dtype == jnp.float64 else np.float32
  mh = matrix(h, size[0], dtype)  # (H', H)
  mw = matrix(w, size[1], dtype)  # (W', W)
  hp = jax.lax.Precision.HIGHEST
  if not _is_identity(mh):
    x = jnp.einsum("ph,...hwc->...pwc", jnp.asarray(mh), x, precision=hp)
  if not _is_identity(mw):
    x = jnp.einsum("qw,...pwc->...pqc", jnp.asarray(mw), x, precision=hp)
  return x


def _is_identity(m: np.ndarray) -> bool:
  return m.shape[0] == m.shape[1] and np.array_equal(m, np.eye(m.shape[0], dtype=m.dtype))


def resize_bilinear(x: jax.Array, size: tuple[int, int], align_corners: bool) -> jax.Array:
  """`F.interpolate(x, size, mode="bilinear", align_corners=...)` on (..., H, W, C)."""
  return _resize(x, size, lambda i, o, dtype: linear_matrix(i, o, align_corners, dtype=dtype))


def resize_bicubic(x: jax.Array, size: tuple[int, int], align_corners: bool) -> jax.Array:
  """`F.interpolate(x, size, mode="bicubic", align_corners=...)` on (..., H, W, C), a = -0.75."""
  return _resize(x, size, lambda i, o, dtype: cubic_matrix(i, o, align_corners, dtype=dtype))


def resize_nearest(x: jax.Array, size: tuple[int, int]) -> jax.Array:
  """`F.interpolate(x, size, mode="nearest")` on (..., H, W, C): source index floor(i * in / out)."""
  h, w = x.shape[-3], x.shape[-2]
  rows = np.minimum(np.floor(np.arange(size[0]) * (h / size[0])).astype(np.int64), h - 1)
  cols = np.minimum(np.floor(np.arange(size[1]) * (w / size[1])).astype(np.int64), w - 1)
  return x[..., rows, :, :][..., cols, :]
