"""PyTorch's derivative conventions at the non-smooth points of the differentiated path.

A loss built from |.|, clamps and maxima is not differentiable everywhere, and at those points
the frameworks choose different subgradients. The points are not rare in depth TTA: a pixel
that equals its median-filtered pseudo label (eq. 7) gives |D~ - D~'| = 0 exactly (a median of
a locally symmetric window *is* its centre), and on a smooth depth map that is most pixels; a
planar region has a Laplacian (eqs. 5-6) of exactly 0. The paper's method, its baselines and
their public code are PyTorch, so the project follows PyTorch's choices everywhere a gradient
flows:

  |x| at 0                      d/dx = 0         (torch.abs: sgn(0) = 0; jnp.abs gives +1)
  clamp(x, lo, hi) at a bound   d/dx = 1         (torch.clamp passes lo <= x <= hi;
                                                  jnp.clip gives 1/2 there)
  relu(x) at 0                  d/dx = 0         (jax.nn.relu already agrees)
  maximum(a, b) / max at ties   split evenly     (jnp.maximum, jnp.max agree with torch.maximum,
                                                  amax and max(); torch.max(x, dim) sends it
                                                  all to the returned index)
  elu(x) at 0                   d/dx = 1         (jax.nn.elu already agrees)
  the L2 norm ||x|| at x = 0    d/dx = 0         (torch.norm; jnp.linalg.norm gives NaN: the
                                                  pose net's axis-angle at rest, `norm`)
  the stem's 3x3/2 max pool     first maximum    (`models.layers.max_pool_3x3_s2`)
  a median's middle values      one element      (torch.sort; `median.median_filter`, never
    at ties                     per slot          differentiated in PITTA: pseudo labels are
                                                  constants)

`absolute`, `clamp` and `norm` below are the three that differ; every loss uses them instead of
jnp.abs / jnp.clip / jnp.linalg.norm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


@jax.custom_jvp
def absolute(x: Array) -> Array:
  """|x| with PyTorch's derivative sign(x) (0 at x = 0), any shape."""
  return jnp.abs(x)


@absolute.defjvp
def _absolute_jvp(primals, tangents):
  (x,), (t,) = primals, tangents
  # torch's sgn(x) = (0 < x) - (x < 0): 0 at 0 and at NaN (jnp.sign(NaN) is NaN, and a NaN
  # derivative poisons the gradient of an entry that a `where` masks out, 0 * NaN = NaN)
  x = jnp.asarray(x)  # (a Python number too)
  sgn = (x > 0).astype(x.dtype) - (x < 0).astype(x.dtype)
  return jnp.abs(x), sgn * t


def norm(x: Array, axis: int = -1, keepdims: bool = False) -> Array:
  """The L2 norm of `x` along `axis`, with PyTorch's derivative x / ||x|| and 0 where ||x|| = 0
  (jnp.linalg.norm's is NaN there: 0 / 0). A vector whose squares underflow counts as 0."""
  squares = jnp.sum(x * x, axis=axis, keepdims=True)
  positive = squares > 0
  # the sqrt never sees a 0 (its derivative there is inf, and inf * 0 is NaN)
  n = jnp.where(positive, jnp.sqrt(jnp.where(positive, squares, 1.0)), 0.0)
  return n if keepdims else jnp.squeeze(n, axis)


def clamp(x: Array, lo: float | Array | None = None, hi: float | Array | None = None) -> Array:
  """`torch.clamp(x, lo, hi)`: the gradient passes where lo <= x <= hi, bounds included."""
  return _clamp(x, -jnp.inf if lo is None else lo, jnp.inf if hi is None else hi)


@jax.custom_jvp
def _clamp(x: Array, lo: Array | float, hi: Array | float) -> Array:
  return jnp.minimum(jnp.maximum(x, lo), hi)


@_clamp.defjvp
def _clamp_jvp(primals, tangents):
  x, lo, hi = primals
  tx, tlo, thi = tangents
  y = jnp.minimum(jnp.maximum(x, lo), hi)
  inside = (x >= lo) & (x <= hi)
  # torch routes the gradient to a tensor bound only where x is strictly past it; with lo >= hi
  # (the result is hi everywhere) hi takes it wherever hi < lo, and lo never (autograd's
  # clamp_backward_min_max)
  t = jnp.where(inside, tx, 0.0)
  t = (t + jnp.where((x < lo) & (lo < hi), _as(tlo, x), 0.0)
       + jnp.where((x > hi) | (hi < lo), _as(thi, x), 0.0))
  return y, t


def _as(t, like):
  like = jnp.asarray(like)
  return jnp.broadcast_to(jnp.asarray(t, like.dtype), like.shape)
