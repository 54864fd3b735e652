"""The ResNet stem's max pool: values and gradient against PyTorch's `max_pool2d(3, 2, 1)`,
ties included (PyTorch sends the gradient to the first maximal tap; so must we)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
import torch

from pitta_jax.models.layers import max_pool_3x3_s2


@pytest.fixture(scope="module")
def pool_vjp():
  @jax.jit
  def run(x, g):
    y, vjp = jax.vjp(max_pool_3x3_s2, x)
    return y, vjp(g)[0]
  return run


@pytest.mark.parametrize("shape", [(1, 17, 23, 4), (2, 16, 20, 3), (1, 5, 6, 2), (1, 1, 1, 1),
                                   (1, 2, 3, 1)])
@pytest.mark.parametrize("values", ["continuous", "ties"])
def test_matches_torch(pool_vjp, shape, values):
  rng = np.random.default_rng(sum(shape))
  if values == "continuous":
    x = rng.standard_normal(shape).astype(np.float32)
  else:  # few distinct values: most windows hold tied maxima
    x = rng.integers(0, 3, shape).astype(np.float32)
  b, h, w, c = shape
  g = rng.standard_normal((b, (h + 1) // 2, (w + 1) // 2, c)).astype(np.float32)
  y, dx = pool_vjp(x, g)
  xt = torch.from_numpy(x).permute(0, 3, 1, 2).clone().requires_grad_(True)
  yt = torch.nn.functional.max_pool2d(xt, 3, 2, 1)
  yt.backward(torch.from_numpy(g).permute(0, 3, 1, 2))
  np.testing.assert_array_equal(np.asarray(y), yt.detach().permute(0, 2, 3, 1).numpy())
  np.testing.assert_allclose(np.asarray(dx), xt.grad.permute(0, 2, 3, 1).numpy(), rtol=0,
                             atol=1e-6)
