"""Derivatives at non-smooth points against native PyTorch ops (the convention we follow).

Each case evaluates the JAX function and `torch.autograd` of the PyTorch op a PyTorch user
writes (`Tensor.abs`, `torch.clamp`, `F.relu`, `F.elu`, `torch.maximum`, `Tensor.max`,
`nn.BatchNorm2d`) on inputs placed exactly on the kinks and ties, and compares the gradients.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import torch
import torch.nn.functional as F

from pitta_jax.models.layers import BatchNorm
from pitta_jax.nonsmooth import absolute, clamp

X = np.array([-2.0, -1.0, -0.5, 0.0, 0.0, 0.5, 1.0, 1.0, 2.0], np.float32)  # kinks at 0, +-1
W = np.linspace(0.5, 1.5, X.size).astype(np.float32)  # a weighted sum: no accidental symmetry


def _torch_grad(fn, x=X):
  t = torch.from_numpy(x.copy()).requires_grad_(True)
  (fn(t) * torch.from_numpy(W)).sum().backward()
  return t.grad.numpy()


def _jax_grad(fn, x=X):
  return np.asarray(jax.grad(lambda a: jnp.sum(fn(a) * W))(jnp.asarray(x)))


def test_absolute_has_torch_abs_derivative_zero_at_zero():
  np.testing.assert_array_equal(_jax_grad(absolute), _torch_grad(lambda t: t.abs()))
  np.testing.assert_array_equal(np.asarray(absolute(jnp.asarray(X))), np.abs(X))
  assert _jax_grad(absolute)[3] == 0.0 and _jax_grad(jnp.abs)[3] == W[3]  # why it exists
  # a Python number, as jnp.abs takes it (the rule called .astype on a bool)
  assert [float(jax.grad(absolute)(v)) for v in (0.0, 2.0, -2.0)] == [0.0, 1.0, -1.0]


def test_clamp_passes_the_gradient_at_the_bounds_as_torch_clamp():
  np.testing.assert_array_equal(_jax_grad(lambda a: clamp(a, -1.0, 1.0)),
                                _torch_grad(lambda t: torch.clamp(t, -1.0, 1.0)))
  np.testing.assert_array_equal(_jax_grad(lambda a: clamp(a, lo=0.0)),
                                _torch_grad(lambda t: torch.clamp(t, min=0.0)))
  np.testing.assert_array_equal(_jax_grad(lambda a: clamp(a, hi=0.5)),
                                _torch_grad(lambda t: torch.clamp(t, max=0.5)))


def test_clamp_with_array_bounds_routes_gradients_as_torch():
  lo = np.full_like(X, -1.0)
  hi = np.full_like(X, 1.0)

  def jax_grads():
    return jax.grad(lambda a, b, c: jnp.sum(clamp(a, b, c) * W), argnums=(0, 1, 2))(
        jnp.asarray(X), jnp.asarray(lo), jnp.asarray(hi))

  ts = [torch.from_numpy(v.copy()).requires_grad_(True) for v in (X, lo, hi)]
  (torch.clamp(ts[0], ts[1], ts[2]) * torch.from_numpy(W)).sum().backward()
  for g, t in zip(jax_grads(), ts):
    np.testing.assert_array_equal(np.asarray(g), t.grad.numpy())


def test_clamp_with_crossed_or_equal_bounds_routes_gradients_as_torch():
  """lo >= hi (the result is hi): torch gives the bound gradient to hi where hi < lo and never
  to lo; lo == hi passes x's own gradient at the tie. A Python float x has a gradient too."""
  x = np.array([-1.0, 0.5, -1.0, 0.0, 2.0, 0.7], np.float32)
  lo = np.array([0.0, 1.0, 0.0, 0.0, 1.0, 0.7], np.float32)
  hi = np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.7], np.float32)
  w = np.linspace(0.5, 1.5, x.size).astype(np.float32)
  got = jax.grad(lambda a, b, c: jnp.sum(clamp(a, b, c) * w), argnums=(0, 1, 2))(
      jnp.asarray(x), jnp.asarray(lo), jnp.asarray(hi))
  ts = [torch.from_numpy(v.copy()).requires_grad_(True) for v in (x, lo, hi)]
  (torch.clamp(ts[0], ts[1], ts[2]) * torch.from_numpy(w)).sum().backward()
  for g, t in zip(got, ts):
    np.testing.assert_array_equal(np.asarray(g), t.grad.numpy())
  assert float(jax.grad(lambda a: clamp(a, 0.0, 1.0))(0.5)) == 1.0


def test_jax_natives_already_follow_torch():
  """relu and elu at 0, maximum and max at ties: JAX's own rules equal PyTorch's."""
  np.testing.assert_array_equal(_jax_grad(jax.nn.relu), _torch_grad(F.relu))
  np.testing.assert_allclose(_jax_grad(jax.nn.elu), _torch_grad(F.elu), rtol=1e-6)  # exp rounding
  np.testing.assert_array_equal(_jax_grad(lambda a: jnp.maximum(a, 1.0)),
                                _torch_grad(lambda t: torch.maximum(t, torch.tensor(1.0))))
  np.testing.assert_array_equal(_jax_grad(lambda a: jnp.minimum(a, 0.0)),
                                _torch_grad(lambda t: torch.minimum(t, torch.tensor(0.0))))
  np.testing.assert_allclose(_jax_grad(lambda a: jnp.max(a) * jnp.ones_like(a)),
                             _torch_grad(lambda t: t.max() * torch.ones_like(t)), rtol=1e-6)


def test_batch_norm_at_zero_variance_matches_torch():
  """A constant channel (variance 0): train-mode BN output and gradients as nn.BatchNorm2d."""
  rng = np.random.default_rng(0)
  x = rng.normal(size=(1, 4, 5, 3)).astype(np.float32)
  x[..., 1] = 0.7  # constant channel
  g = rng.normal(size=x.shape).astype(np.float32)
  scale = np.array([1.5, 0.5, 2.0], np.float32)
  bias = np.array([0.1, -0.2, 0.3], np.float32)

  bn = torch.nn.BatchNorm2d(3)
  with torch.no_grad():
    bn.weight.copy_(torch.from_numpy(scale)), bn.bias.copy_(torch.from_numpy(bias))
  xt = torch.from_numpy(x).permute(0, 3, 1, 2).clone().requires_grad_(True)
  y = bn.train()(xt)
  (y * torch.from_numpy(g).permute(0, 3, 1, 2)).sum().backward()

  variables = {"params": {"scale": jnp.asarray(scale), "bias": jnp.asarray(bias)},
               "batch_stats": {"mean": jnp.zeros(3), "var": jnp.ones(3)}}

  def f(params, x):
    out = BatchNorm().apply({**variables, "params": params}, x, True)
    return jnp.sum(out * g), out

  (_, out), (gp, gx) = jax.value_and_grad(f, argnums=(0, 1), has_aux=True)(
      variables["params"], jnp.asarray(x))
  out, ref = np.asarray(out), y.detach().permute(0, 2, 3, 1).numpy()
  varying = [0, 2]
  np.testing.assert_allclose(out[..., varying], ref[..., varying], atol=1e-5)
  # The constant channel: x - mean is 0 up to the rounding of the mean, which PyTorch's CPU
  # kernel leaves at one or more ulps of 0.7 depending on the instruction set and threads (seen
  # on AVX2); normalisation multiplies it by scale / sqrt(eps) = 158. Bound: the float32
  # summation error of the 20 values, (n - 1) u sum|x| / n, times that factor.
  n = x.shape[0] * x.shape[1] * x.shape[2]
  amplified = (n - 1) * 2.0**-24 * 0.7 * scale[1] / np.sqrt(1e-5)
  np.testing.assert_allclose(out[..., 1], bias[1], atol=amplified)
  np.testing.assert_allclose(ref[..., 1], bias[1], atol=amplified)
  np.testing.assert_allclose(np.asarray(gx), xt.grad.permute(0, 2, 3, 1).numpy(), atol=1e-4)
  np.testing.assert_allclose(np.asarray(gp["scale"]), bn.weight.grad.numpy(), atol=1e-4)
  np.testing.assert_allclose(np.asarray(gp["bias"]), bn.bias.grad.numpy(), atol=1e-5)


def test_absolute_derivative_at_nan_is_torchs_zero():
  """torch.abs's derivative is sgn(x), 0 at NaN as at 0: a NaN that a `where` masks out leaves
  the gradient finite in PyTorch. jnp.sign(NaN) is NaN, and 0 * NaN poisoned the gradient of
  the masked-out entry (and everything summed with it)."""
  x = np.float32([np.nan, -1.0, 0.0, 2.0])
  keep = np.array([False, True, True, True])
  got = jax.grad(lambda a: jnp.sum(jnp.where(keep, absolute(a), 0.0)))(jnp.asarray(x))
  t = torch.from_numpy(x.copy()).requires_grad_(True)
  torch.where(torch.from_numpy(keep), t.abs(), torch.zeros(())).sum().backward()
  np.testing.assert_array_equal(np.asarray(got), t.grad.numpy())
