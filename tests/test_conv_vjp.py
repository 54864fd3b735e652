"""The loop-friendly convolution: JAX's own values and gradients, and canonical kernels in a scan."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import flax.linen as nn
from jax import lax

from pitta_jax.models import conv_vjp
from pitta_jax.models.layers import Conv
from xla_options import RUN_OPTIMIZED

NHWC = ("NHWC", "HWIO", "NHWC")

# (input H, W, kernel, stride, padding (lo, hi) per axis, kernel dilation)
CASES = [
    ((17, 23), 3, (1, 1), ((1, 1), (1, 1)), (1, 1)),
    ((17, 23), 3, (2, 2), ((1, 1), (1, 1)), (1, 1)),
    ((16, 20), 7, (2, 2), ((3, 3), (3, 3)), (1, 1)),
    ((15, 9), 1, (2, 2), ((0, 0), (0, 0)), (1, 1)),
    ((13, 14), 3, (3, 2), ((0, 2), (1, 0)), (1, 1)),
    ((12, 12), 3, (1, 2), ((2, 2), (1, 1)), (2, 2)),
    ((8, 9), 3, (1, 1), ((0, 0), (0, 0)), (1, 1)),
    ((13, 14), 3, (1, 1), ((0, 2), (1, 0)), (1, 1)),
    ((6, 7), 5, (1, 1), ((2, 1), (0, 0)), (1, 1)),
    # inputs smaller than the kernel (a product of patches; for the strided ones only the input
    # gradient, whose stride-dilated cotangent is smaller than the kernel)
    ((2, 3), 3, (1, 1), ((1, 1), (1, 1)), (1, 1)),
    ((1, 5), 3, (1, 1), ((1, 1), (1, 1)), (1, 1)),
    ((4, 3), 3, (2, 2), ((1, 1), (1, 0)), (1, 1)),
    ((3, 5), 3, (1, 2), ((2, 2), (2, 1)), (2, 2)),
    ((2, 2), 5, (2, 1), ((2, 2), (1, 2)), (1, 1)),
    # strided by 2: the kernel gradient per stride phase (uneven padding, an even kernel, a
    # kernel no larger than the stride)
    ((13, 10), 3, (2, 2), ((0, 1), (1, 0)), (1, 1)),
    ((11, 9), 4, (2, 1), ((1, 2), (2, 1)), (1, 1)),
    ((8, 10), 2, (2, 2), ((0, 0), (0, 0)), (1, 1)),
]


def _both_rules(x, k, strides, padding, dilation=(1, 1)):
  """(value, input grad, kernel grad) of lax's convolution and of conv_vjp's, both pulled back
  with the same cotangent (not all ones)."""
  def run(fn, ct=None):
    def f(x, k):
      return fn(x, k, strides, padding, rhs_dilation=dilation, dimension_numbers=NHWC)
    y, vjp = jax.vjp(f, x, k)
    ct = jnp.cos(3.0 * y) if ct is None else ct
    return (y, *vjp(ct)), ct
  ref, ct = run(lax.conv_general_dilated)
  return ref, run(conv_vjp.conv_general_dilated, ct)[0]


# out = 1 with 12 input features: the stride-1 undilated cases with at most 12 taps take the
# single-output path (a product and shifted sums), the 5x5 one does not, and the kernel gradient
# is a convolution; one image of 5 input features (at most PATCHES_MAX_INPUT_FEATURES, an
# image's): the kernel gradient as a product of the input's patches; the same features in a
# batch of 2, and 64 -> 64 features in a batch of 2: a convolution with the padding inside; one
# image of 12 features (to 7, and to 1 as a disparity head): a convolution of the padded input
@pytest.mark.parametrize("out,cin,batch", [(7, 5, 1), (7, 5, 2), (1, 12, 2), (64, 64, 2),
                                           (7, 12, 1), (1, 12, 1)])
@pytest.mark.parametrize("size,ksize,strides,padding,dilation", CASES)
def test_values_and_both_gradients_match_jax_rule(size, ksize, strides, padding, dilation, out,
                                                  cin, batch):
  # the cases reach both forms of the kernel gradient
  assert 5 <= conv_vjp.PATCHES_MAX_INPUT_FEATURES < 12
  rng = np.random.default_rng(sum(size) + ksize)
  x = rng.standard_normal((batch, *size, cin), np.float32)
  k = rng.standard_normal((ksize, ksize, cin, out), np.float32)

  ref, got = jax.jit(lambda x, k: _both_rules(x, k, strides, padding, dilation),
                     compiler_options=RUN_OPTIMIZED)(x, k)
  for name, a, b in zip(("value", "input grad", "kernel grad"), ref, got):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, name
    err = float(np.max(np.abs(a - b)) / (np.max(np.abs(a)) + 1e-12))
    print(f"{name}: max rel diff {err:.2e}")
    assert err < 1e-6, name


@pytest.mark.parametrize("strides,padding,size", [((1, 1), ((1, 1), (1, 1)), (6, 20)),
                                                 ((2, 2), ((1, 1), (1, 1)), (12, 40)),
                                                 ((2, 2), ((1, 1), (1, 1)), (8, 14)),
                                                 ((2, 1), ((2, 0), (1, 1)), (7, 9))])
def test_few_pixels_many_features_take_patches_and_match_jax_rule(strides, padding, size):
  """A 3x3 convolution of FEW_PIXELS_MIN_FEATURES features with at most FEW_PIXELS_MAX_OUTPUT
  output pixels (ResNet's last stage at 640x192: 6x20) is a product of patches, with JAX's
  values and gradients to float32 rounding; in float64 it stays a convolution. Where the input
  has that few pixels too (6x20; 8x14 and 7x9, strided, uneven padding), the input gradient is
  the transposed product scattered back by tap (`_patches_input_grad`); 12x40 is a convolution."""
  c = conv_vjp.FEW_PIXELS_MIN_FEATURES
  assert size[0] * size[1] // (strides[0] * strides[1]) <= conv_vjp.FEW_PIXELS_MAX_OUTPUT
  rng = np.random.default_rng(3)
  x = rng.standard_normal((1, *size, c), np.float32)
  k = rng.standard_normal((3, 3, c, c), np.float32) / 48.0
  def forward(x, k) -> str:  # the lowered forward program
    return jax.jit(lambda x, k: conv_vjp.conv_general_dilated(
        x, k, strides, padding, dimension_numbers=NHWC)).lower(x, k).as_text()
  text = forward(x, k)
  assert "convolution" not in text and "dot_general" in text
  with jax.enable_x64(True):
    assert "convolution" in forward(x.astype(np.float64), k.astype(np.float64))
  ref, got = jax.jit(lambda x, k: _both_rules(x, k, strides, padding),
                     compiler_options=RUN_OPTIMIZED)(x, k)
  # each value is a float32 sum of 9c products, which the two forms (and XLA:CPU's convolution
  # libraries) add in different orders: they agree to about eps * sqrt(9c) of the largest value
  # (8e-6 at c = 512; measured 1.5e-6 with YNNPACK on an AMD Zen 3, < 1e-6 on an Intel Xeon)
  tol = float(np.finfo(np.float32).eps * np.sqrt(9 * c))
  for name, a, b in zip(("value", "input grad", "kernel grad"), ref, got):
    a, b = np.asarray(a), np.asarray(b)
    err = float(np.max(np.abs(a - b)) / np.max(np.abs(a)))
    assert err < tol, (name, err, tol)


def test_float64_growing_convolutions_match_jax_rule():
  """float64 convolutions whose output is larger than the input (padding past the kernel's
  half width: the input gradient of an unpadded convolution) take the product of patches;
  values and both gradients as JAX's rule, to float64 rounding."""
  rng = np.random.default_rng(7)
  with jax.enable_x64(True):
    for size, padding, strides in [((5, 7), ((2, 2), (2, 2)), (1, 1)),
                                   ((6, 4), ((3, 1), (2, 3)), (2, 1))]:
      x = jnp.asarray(rng.standard_normal((2, *size, 6)))
      k = jnp.asarray(rng.standard_normal((3, 3, 6, 5)))
      ref, got = _both_rules(x, k, strides, padding)
      assert any(m > n for m, n in zip(ref[0].shape[1:3], size))  # the output grows
      for a, b in zip(ref, got):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-12)


def test_other_forms_fall_back_to_lax():
  """Grouped / input-dilated / SAME convolutions are passed through unchanged."""
  rng = np.random.default_rng(0)
  x = rng.standard_normal((1, 9, 9, 4), np.float32)
  for kwargs, cin in (({"feature_group_count": 2}, 2), ({"lhs_dilation": (2, 2)}, 4)):
    k = rng.standard_normal((3, 3, cin, 4), np.float32)

    @jax.jit
    def both(x, k):
      return [fn(x, k, (1, 1), ((1, 1), (1, 1)), dimension_numbers=NHWC, **kwargs)
              for fn in (lax.conv_general_dilated, conv_vjp.conv_general_dilated)]
    a, b = both(x, k)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _kernel_layouts(conv_fn, argnums=0) -> list[str]:
  """dim_labels of every convolution XLA compiles for the gradient of a 3-step scan."""
  def loss(x, k):
    def body(c, _):
      y = conv_fn(c, k, (2, 2), ((1, 1), (1, 1)), dimension_numbers=NHWC)
      return c, jnp.sum(jnp.tanh(y))
    return jnp.sum(lax.scan(body, x, None, length=3)[1])
  x, k = jnp.ones((1, 16, 16, 8)), jnp.ones((3, 3, 8, 8))
  text = jax.jit(jax.grad(loss, argnums)).lower(x, k).compile().as_text()
  return re.findall(r"dim_labels=([a-z0-9_>-]+)", text)


def test_input_gradient_kernel_is_canonical_inside_scan():
  """The reason for the module: no `01oi` (swapped-feature) kernels inside the while loop.
  JAX's own rule is checked too, so the test notices if XLA stops needing the workaround."""
  ours = _kernel_layouts(conv_vjp.conv_general_dilated)
  theirs = _kernel_layouts(lax.conv_general_dilated)
  print("lax rule:", theirs, "ours:", ours)
  assert ours and all("_01io->" in d for d in ours)
  assert any("_01oi->" in d for d in theirs), "XLA now canonicalises in loops: drop conv_vjp"


def test_kernel_gradient_is_canonical_inside_scan():
  """Adapting conv kernels (CoMoDa, ActMAD's cnn layers): the kernel gradient inside the while
  loop is made of canonical b01f x 01io convolutions too (one image, 8 features, strided: its
  stride phases' convolutions); JAX's rule is not."""
  ours = _kernel_layouts(conv_vjp.conv_general_dilated, 1)
  theirs = _kernel_layouts(lax.conv_general_dilated, 1)
  print("lax rule:", theirs, "ours:", ours)
  assert ours and all(d.startswith("b01f_01io->") for d in ours)
  assert not all(d.startswith("b01f_01io->") for d in theirs), \
      "XLA now canonicalises kernel gradients in loops: use JAX's rule"


def _kernel_grad_windows(batch: int, pad_first: bool = True) -> list[str]:
  """The window of every convolution XLA compiles for `_kernel_grad` (16 -> 1 features, 3x3,
  zero padding 1, as a disparity head) in a 2-step scan over `batch` images of 12x20."""
  def grads(x, g):
    def body(c, _):
      dk = conv_vjp._kernel_grad(jnp.tanh(x + c), g, (3, 3), (1, 1), ((1, 1), (1, 1)), (1, 1),
                                 None, pad_first=pad_first)
      return c + 1.0, dk
    return lax.scan(body, 0.0, None, length=2)[1]
  x, g = jnp.ones((batch, 12, 20, 16)), jnp.ones((batch, 12, 20, 1))
  text = jax.jit(grads).lower(x, g).compile().as_text()
  return [w for w in re.findall(r"window=\{([^}]*)\}", text) if "size=12x20" in w]


@pytest.mark.parametrize("batch", [1, 2])
def test_kernel_gradient_convolves_the_padded_input(batch):
  """The kernel gradient's convolution (a kernel the size of the output) reads the input padded
  first, one image or a batch, as XLA:CPU runs it many times faster; `pad_first=False` (the
  form before) keeps the padding inside the convolution."""
  ours, inside = _kernel_grad_windows(batch), _kernel_grad_windows(batch, pad_first=False)
  print("padded first:", ours, "padding inside:", inside)
  assert ours and all("pad" not in w for w in ours)
  assert inside and all("pad=1_1x1_1" in w for w in inside)


def test_flax_conv_uses_it_with_same_parameters():
  x = np.random.default_rng(2).standard_normal((1, 10, 12, 3), np.float32)
  ours = Conv(6, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
  plain = nn.Conv(6, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
  v = ours.init(jax.random.PRNGKey(3), x)
  assert jax.tree_util.tree_structure(v) == jax.tree_util.tree_structure(
      plain.init(jax.random.PRNGKey(3), x))
  ga, gb = jax.jit(lambda x: [jax.grad(lambda x: jnp.sum(jnp.sin(m.apply(v, x))))(x)
                               for m in (ours, plain)])(x)
  np.testing.assert_allclose(np.asarray(ga), np.asarray(gb), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("batch", [1, 4])
def test_strided_kernel_gradient_has_no_dilated_kernel(batch):
  """A stride-2 convolution's kernel gradient, one convolution per stride phase, never
  convolves with the cotangent dilated by the stride (XLA:CPU ran that up to 7x slower); the
  single-convolution form, still reachable with `phases=False`, does."""
  x, g = jnp.ones((batch, 16, 20, 12)), jnp.ones((batch, 8, 10, 10))
  def windows(phases):
    f = lambda x, g: conv_vjp._kernel_grad(x, g, (3, 3), (2, 2), ((1, 1), (1, 1)), (1, 1), None,
                                           phases=phases)
    text = jax.jit(f).lower(x, g).compile().as_text()
    return re.findall(r"window=\{([^}]*)\}", text)
  ours, single = windows(None), windows(False)
  print("phases:", ours, "one convolution:", single)
  assert ours and not any("rhs_dilate" in w for w in ours)
  assert any("rhs_dilate=2x2" in w for w in single)
