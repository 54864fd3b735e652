"""Edge maps, eqs. 5-6: against literal NumPy loops, hand values (clamped, not reflected), and
properties."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pitta_jax import edges
from reference_numpy import channel_mean_loop, laplacian_edge_loop

SHAPE = (6, 8)


@pytest.fixture(scope="module")
def em():
  return jax.jit(edges.edge_map)


@pytest.fixture(scope="module")
def iem():
  return jax.jit(edges.image_edge_map)


def maps(shape=SHAPE, lo=-10.0, hi=10.0):
  return hnp.arrays(np.float32, shape,
                    elements=st.floats(lo, hi, width=32, allow_subnormal=False))


def test_hand_computed_clamped_not_reflected(em):
  # Hand values, 1x3 row [0, 0, 1]: the vertical neighbours clamp to the pixel itself.
  # y=0: 0+0 + 0+0 - 0 = 0; y=1: 0+0 + 1+0 - 0 = 1; y=2: 1+1 + 1+0 - 4 = -1 -> 1.
  # (Reflect padding would give |1+1 + 0+0 - 4| = 2 at y=2.)
  x = np.array([[0, 0, 1]], np.float32)
  np.testing.assert_array_equal(np.asarray(em(x, None)), [[0, 1, 1]])
  # 2x2 [[1, 2], [3, 5]]: (0,0): 3+1+2+1-4 = 3; (0,1): 5+2+2+1-8 = 2;
  # (1,0): 3+1+5+3-12 = 0; (1,1): 5+2+5+3-20 = -5 -> 5.
  x = np.array([[1, 2], [3, 5]], np.float32)
  np.testing.assert_array_equal(np.asarray(em(x, None)), [[3, 2], [0, 5]])


@pytest.mark.parametrize("shape", [(6, 8), (1, 1), (1, 5), (4, 1)])
def test_matches_loop(em, shape):
  # Reference: literal NumPy loop of eq. 6 with clamped indices; weights None, scalar, (H, W).
  rng = np.random.default_rng(shape[0] * 10 + shape[1])
  x = rng.standard_normal(shape).astype(np.float32)
  w = rng.random(shape).astype(np.float32)
  for weight in (None, np.float32(0.7), w):
    got = np.asarray(em(x, weight))
    want = laplacian_edge_loop(x, weight)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


def test_image_edge_map_matches_loop(iem):
  # Reference: eq. 5 = loop Laplacian of the loop channel mean I_bar, weights U.
  rng = np.random.default_rng(1)
  image = rng.random(SHAPE + (3,)).astype(np.float32)
  u = rng.random(SHAPE).astype(np.float32)
  want = laplacian_edge_loop(channel_mean_loop(image), u)
  np.testing.assert_allclose(np.asarray(iem(image, u)), want, rtol=1e-5, atol=1e-6)


def test_rejects_bad_shapes():
  with pytest.raises(ValueError, match="H, W"):
    edges.edge_map(jnp.zeros((2, 3, 3)))
  with pytest.raises(ValueError, match="H, W, C"):
    edges.image_edge_map(jnp.zeros((2, 3)))


@settings(max_examples=15, deadline=None)
@given(c=st.floats(-1e3, 1e3, width=32, allow_subnormal=False))
def test_vanishes_on_constants(em, c):
  # Property: the Laplacian of a constant is exactly 0 (neighbours summed in pairs).
  np.testing.assert_array_equal(np.asarray(em(np.full(SHAPE, c, np.float32), None)), 0.0)


@settings(max_examples=20, deadline=None)
@given(x=maps(), c=st.floats(-50, 50, width=32, allow_subnormal=False))
def test_ignores_added_constant(em, x, c):
  # Property: d(X + c) = dX, up to the float rounding of adding c (|X|, |c| <= 50 -> 1e-4).
  np.testing.assert_allclose(np.asarray(em(x + np.float32(c), None)),
                             np.asarray(em(x, None)), atol=2e-4)


@settings(max_examples=20, deadline=None)
@given(x=maps(), a=st.floats(0.0, 4.0, width=32, allow_subnormal=False))
def test_nonnegative_and_weight_linear(em, x, a):
  # Properties: dX >= 0, and dX scales with a scalar weight: d_a = a * d_1. XLA:CPU flushes
  # subnormal results to zero (NumPy keeps them), so products below float32's smallest normal
  # number may read 0 on our side: atol = that number (hypothesis found a = 2^-126, d_1 = 0.5).
  d1 = np.asarray(em(x, None))
  assert (d1 >= 0).all()
  np.testing.assert_allclose(np.asarray(em(x, np.float32(a))), np.float32(a) * d1, rtol=1e-6,
                             atol=float(np.finfo(np.float32).tiny))


@settings(max_examples=25, deadline=None)
@given(image=hnp.arrays(np.float32, (5, 7, 3), elements=st.floats(-50, 50, width=32).filter(
    lambda v: v == 0 or abs(v) > 1e-30)))  # no subnormal mean (see below)
def test_channel_mean_is_torchs_bit_for_bit_under_jit(image):
  """I_bar (eq. 5) is torch.mean(image, -1) exactly, compiled: ties of eq. 9 (dI = dD) stay
  ties, where PyTorch's |.| has gradient 0. jnp.mean under jit differs in the last bit at
  about half the pixels (XLA's summation order and reciprocal product). Subnormal results
  aside: XLA:CPU flushes them to 0, PyTorch does not."""
  import torch
  want = torch.from_numpy(image.copy()).mean(-1).numpy()
  np.testing.assert_array_equal(np.asarray(_jit_channel_mean(jnp.asarray(image))), want)


_jit_channel_mean = jax.jit(edges.channel_mean)
