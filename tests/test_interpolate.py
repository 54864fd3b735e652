"""`pitta_jax.models.interpolate` against PyTorch's `F.interpolate` (values and input gradients)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pitta_jax.models import interpolate

CASES = [((5, 7), (12, 9)), ((8, 8), (3, 5)), ((37, 37), (16, 24)), ((1, 4), (3, 8)),
         ((6, 9), (6, 14)), ((5, 7), (5, 7)),  # one axis, both axes at their own size
         ((4, 6), (1, 3))]                      # an output of one row


def _torch(x: np.ndarray, size, mode: str, align_corners):
  t = torch.from_numpy(x).permute(0, 3, 1, 2).double().requires_grad_(True)
  kw = {} if mode == "nearest" else {"align_corners": align_corners}
  y = F.interpolate(t, size=size, mode=mode, **kw)
  w = torch.from_numpy(np.random.default_rng(1).normal(size=y.shape))
  (y * w).sum().backward()
  return y.detach().permute(0, 2, 3, 1).numpy(), t.grad.permute(0, 2, 3, 1).numpy(), w


MODES = [("bilinear", False), ("bilinear", True), ("bicubic", False), ("bicubic", True),
         ("nearest", None)]


@pytest.mark.parametrize("mode,align_corners", MODES)
@pytest.mark.parametrize("src,dst", CASES)
def test_matches_torch_interpolate(mode, align_corners, src, dst):
  x = np.random.default_rng(0).normal(size=(2, *src, 3))
  want, want_grad, w = _torch(x, dst, mode, align_corners)
  fn = {"bilinear": lambda a: interpolate.resize_bilinear(a, dst, align_corners),
        "bicubic": lambda a: interpolate.resize_bicubic(a, dst, align_corners),
        "nearest": lambda a: interpolate.resize_nearest(a, dst)}[mode]
  got = fn(jnp.asarray(x, jnp.float32))
  np.testing.assert_allclose(np.asarray(got), want, atol=2e-6)
  wj = jnp.asarray(w.permute(0, 2, 3, 1).numpy(), jnp.float32)
  grad = jax.grad(lambda a: jnp.sum(fn(a) * wj))(jnp.asarray(x, jnp.float32))
  np.testing.assert_allclose(np.asarray(grad), want_grad, atol=2e-5)


@pytest.mark.parametrize("mode,align_corners", [("bilinear", False), ("bilinear", True),
                                                ("bicubic", True)])
def test_float64_resize_matches_torch_in_float64(mode, align_corners):
  """A float64 input is resized in float64, as F.interpolate resizes a double tensor: the
  interpolation weights were float32 constants, so a float64 resize was only float32-accurate
  (5e-8 from torch's, at 5x7 -> 12x9)."""
  x = np.random.default_rng(0).normal(size=(1, 5, 7, 2))
  want, want_grad, w = _torch(x, (12, 9), mode, align_corners)
  fn = {"bilinear": interpolate.resize_bilinear, "bicubic": interpolate.resize_bicubic}[mode]
  with jax.enable_x64(True):
    got = fn(jnp.asarray(x), (12, 9), align_corners)
    assert got.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-13)
    grad = jax.grad(lambda a: jnp.sum(fn(a, (12, 9), align_corners)
                                      * jnp.asarray(w.permute(0, 2, 3, 1).numpy())))(jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(grad), want_grad, rtol=0, atol=1e-12)
