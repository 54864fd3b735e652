"""The decoder's fast layer forms (`models.layers`) against their plain definitions.

- `reflect_pad` equals NumPy's `np.pad(mode="reflect")` (what `nn.ReflectionPad2d` does),
  and on maps of 1 pixel NumPy's rule (our extension: `nn.ReflectionPad2d` raises there, so
  upstream MonoDepth2 cannot run an input whose 1/32 map is 1 pixel, e.g. 32 pixels wide);
- `reflect_conv3x3` (the zero-padded conv corrected at the ring, or VALID) equals the VALID conv
  of the reflection-padded map, values and gradients, in both forms of the `ring_form_pays`
  rule (forced on small maps); `ReflectConv3x3` has `nn.Conv`'s parameter tree;
- `upsample_reflect_conv3x3` (four 2x2 phase convs at low resolution, or the direct form below
  `phase_form_pays`' threshold) and `UpConv3x3` equal the composition upstream writes (nearest
  2x upsampling with `np.repeat`, concatenation, reflection padding, VALID 3x3 conv, bias),
  value and input gradients, within float32 rounding, on even, odd and 1-pixel maps;
  `UpConv3x3` has `nn.Conv`'s parameter tree.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from pitta_jax.models import layers

NHWC = ("NHWC", "HWIO", "NHWC")


def plain_reflect_conv(x, k):
  xp = jnp.asarray(np.pad(np.asarray(x), ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect"))
  return lax.conv_general_dilated(xp, k, (1, 1), "VALID", dimension_numbers=NHWC,
                                  precision=lax.Precision.HIGHEST)


def differentiable_reflect_conv(x, k):
  """`plain_reflect_conv` with jnp.pad's reflection, for JAX's own autodiff of it."""
  xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect")
  return lax.conv_general_dilated(xp, k, (1, 1), "VALID", dimension_numbers=NHWC,
                                  precision=lax.Precision.HIGHEST)


@pytest.mark.parametrize("h, w", [(1, 1), (1, 4), (2, 3), (5, 7), (12, 40)])
def test_reflect_pad_is_numpy_reflect(h, w):
  x = np.random.default_rng(0).standard_normal((2, h, w, 3)).astype(np.float32)
  np.testing.assert_array_equal(np.asarray(jax.jit(layers.reflect_pad)(x)),
                                np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect"))


@pytest.mark.parametrize("ring", [True, False])
@pytest.mark.parametrize("h, w", [(2, 2), (2, 5), (3, 3), (6, 20), (48, 160)])
def test_reflect_conv3x3_is_the_valid_conv_of_the_padded_map(h, w, ring, monkeypatch):
  """Both forms (the ring form forced on small maps): value, input and kernel gradients
  against JAX's own autodiff of the VALID conv of NumPy's reflection padding, batch 2."""
  monkeypatch.setattr(layers, "RING_FORM_MAX_SHARE", 1e9 if ring else -1.0)
  monkeypatch.setattr(layers, "RING_FORM_MIN_ELEMENTS", 0)
  assert layers.ring_form_pays(h, w, 8) == ring
  rng = np.random.default_rng(h * 1000 + w)
  x = jnp.asarray(rng.standard_normal((2, h, w, 8)).astype(np.float32))
  k = jnp.asarray(rng.standard_normal((3, 3, 8, 5)).astype(np.float32))
  # a fresh function to trace: jit's cache does not see the monkeypatched threshold
  got, vjp = jax.vjp(jax.jit(lambda x, k: layers.reflect_conv3x3(x, k)), x, k)
  want, ref_vjp = jax.vjp(differentiable_reflect_conv, x, k)
  np.testing.assert_allclose(np.asarray(got), np.asarray(plain_reflect_conv(x, k)),
                             rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-5)
  g = jnp.asarray(rng.standard_normal(got.shape).astype(np.float32))
  for a, r in zip(vjp(g), ref_vjp(g)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(r), rtol=1e-5, atol=1e-4)


def test_ring_form_under_vmap_and_x64(monkeypatch):
  """The ring form (forced) batched by vmap (as the engine's streams run it) and in float64:
  values and input gradients against JAX's autodiff of the VALID conv of the padded map."""
  monkeypatch.setattr(layers, "RING_FORM_MIN_ELEMENTS", 0)
  monkeypatch.setattr(layers, "RING_FORM_MAX_SHARE", 1e9)
  rng = np.random.default_rng(11)
  with jax.enable_x64(True):
    x = jnp.asarray(rng.standard_normal((3, 1, 4, 6, 2)))                    # (streams, B, H, W, C)
    k = jnp.asarray(rng.standard_normal((3, 3, 2, 3)))

    def loss(f, x):
      return jnp.sum(jnp.sin(f(x, k)))
    ours = jax.jit(jax.vmap(jax.value_and_grad(
        lambda x: loss(lambda x, k: layers.reflect_conv3x3(x, k), x))))(x)
    ref = jax.vmap(jax.value_and_grad(lambda x: loss(differentiable_reflect_conv, x)))(x)
    for a, r in zip(ours, ref):
      assert a.dtype == jnp.float64
      np.testing.assert_allclose(np.asarray(a), np.asarray(r), rtol=1e-12, atol=1e-12)


def test_monodepth2_decoder_takes_the_ring_form_on_its_largest_maps():
  """At 640x192: upconv_0_0 (320x96, 32 features), upconv_1_1's skip (320x96, 64) and the heads
  at 320x96 and 640x192 take the ring form; the other reflection-padded convs and every phase
  of the upsample-then-convolve layers (x at most 320x96 with 16 features) do not."""
  sizes = {"upconv_0_0": (96, 320, 32), "skip_1": (96, 320, 64), "dispconv_0": (192, 640, 16),
           "dispconv_1": (96, 320, 32), "upconv_1_0": (48, 160, 64), "skip_2": (48, 160, 64),
           "dispconv_2": (48, 160, 64), "upconv_2_0": (24, 80, 128), "skip_3": (24, 80, 128),
           "upconv_3_0": (12, 40, 256), "skip_4": (12, 40, 256), "upconv_4_0": (6, 20, 512),
           "phases_0": (96, 320, 16), "phases_1": (48, 160, 32)}
  ring = {name for name, hwc in sizes.items() if layers.ring_form_pays(*hwc)}
  assert ring == {"upconv_0_0", "skip_1", "dispconv_0", "dispconv_1"}


def test_reflect_conv3x3_module_has_nn_conv_parameters():
  """`ReflectConv3x3`: `nn.Conv(features, (3, 3))`'s tree, and bias added to the conv."""
  rng = np.random.default_rng(7)
  x = jnp.asarray(rng.standard_normal((1, 5, 6, 3)).astype(np.float32))
  variables = layers.ReflectConv3x3(4).init(jax.random.PRNGKey(0), x)
  ref_vars = nn.Conv(4, (3, 3)).init(jax.random.PRNGKey(0), x)
  assert jax.tree_util.tree_map(jnp.shape, variables) == jax.tree_util.tree_map(jnp.shape, ref_vars)
  k = jnp.asarray(rng.standard_normal((3, 3, 3, 4)).astype(np.float32))
  b = jnp.asarray(rng.standard_normal((4,)).astype(np.float32))
  got = layers.ReflectConv3x3(4).apply({"params": {"kernel": k, "bias": b}}, x)
  np.testing.assert_allclose(np.asarray(got), np.asarray(plain_reflect_conv(x, k) + b),
                             rtol=1e-5, atol=1e-5)


def upstream_upconv(x, skip, k, b):
  """nearest 2x (np.repeat), concat, ReflectionPad2d(1), VALID conv, bias."""
  u = jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)
  if skip is not None:
    u = jnp.concatenate([u, skip], axis=-1)
  xp = jnp.pad(u, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect")
  return lax.conv_general_dilated(xp, k, (1, 1), "VALID", dimension_numbers=NHWC,
                                  precision=lax.Precision.HIGHEST) + b


@pytest.mark.parametrize("phase_form, bordered", [(True, True), (True, False), (False, True),
                                                  (False, False)])
@pytest.mark.parametrize("h, w, skip_channels", [(1, 1, 0), (1, 3, 2), (3, 5, 0), (4, 6, 3),
                                                 (7, 9, 4)])
def test_upconv_equals_upsample_concat_reflect_conv(h, w, skip_channels, phase_form, bordered,
                                                    monkeypatch):
  """Every form of `upsample_reflect_conv3x3` and of the skip's `reflect_conv3x3` (the
  thresholds set to take the ones asked for: phase or direct form; with or without the
  padding's border as `bordered_conv` terms)."""
  monkeypatch.setattr(layers, "PHASE_FORM_MIN_MACS", 0 if phase_form else 2 ** 62)
  monkeypatch.setattr(layers, "RING_FORM_MAX_SHARE", 1e9 if bordered else -1.0)
  monkeypatch.setattr(layers, "RING_FORM_MIN_ELEMENTS", 0)
  assert layers.phase_form_pays(h, w, 3, 4) == phase_form
  assert layers.ring_form_pays(h, w, 3) == bordered
  rng = np.random.default_rng(h * 100 + w)
  c, o = 3, 4
  x = jnp.asarray(rng.standard_normal((2, h, w, c)).astype(np.float32))
  skip = (jnp.asarray(rng.standard_normal((2, 2 * h, 2 * w, skip_channels)).astype(np.float32))
          if skip_channels else None)
  layer = layers.UpConv3x3(o)
  variables = layer.init(jax.random.PRNGKey(0), x, skip)
  ref_vars = nn.Conv(o, (3, 3)).init(jax.random.PRNGKey(0), jnp.zeros((1, 4, 4, c + skip_channels)))
  assert jax.tree_util.tree_map(jnp.shape, variables) == jax.tree_util.tree_map(jnp.shape, ref_vars)
  k = jnp.asarray(rng.standard_normal((3, 3, c + skip_channels, o)).astype(np.float32))
  b = jnp.asarray(rng.standard_normal((o,)).astype(np.float32))
  params = {"params": {"kernel": k, "bias": b}}
  got = jax.jit(lambda x, s: layer.apply(params, x, s))(x, skip)
  want = jax.jit(upstream_upconv)(x, skip, k, b)
  assert got.shape == (2, 2 * h, 2 * w, o)
  np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-5)

  g = jnp.asarray(rng.standard_normal(got.shape).astype(np.float32))
  ours = jax.vjp(lambda x, s: layer.apply(params, x, s), x, skip)[1](g)
  theirs = jax.vjp(lambda x, s: upstream_upconv(x, s, k, b), x, skip)[1](g)
  for a, r in zip(ours, theirs):
    if r is not None:
      np.testing.assert_allclose(np.asarray(a), np.asarray(r), rtol=1e-5, atol=1e-5)


def test_upconv_promotes_float32_weights_on_float64_features():
  """Under x64, float32 weights (shipped, converted) on float64 features compute in float64,
  as flax's Conv promotes; the layer handed float32 kernels to the convolution with float64
  inputs, which lax refuses."""
  rng = np.random.default_rng(5)
  with jax.enable_x64(True):
    x = jnp.asarray(rng.standard_normal((1, 3, 4, 2)))                       # float64
    skip = jnp.asarray(rng.standard_normal((1, 6, 8, 3)))
    k = jnp.asarray(rng.standard_normal((3, 3, 5, 4)).astype(np.float32))
    b = jnp.asarray(rng.standard_normal((4,)).astype(np.float32))
    got = layers.UpConv3x3(4).apply({"params": {"kernel": k, "bias": b}}, x, skip)
    want = upstream_upconv(x, skip, k.astype(jnp.float64), b.astype(jnp.float64))
    assert got.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=1e-12)


def test_monodepth2_decoder_takes_the_phase_form_from_320x96():
  """Every upconv_i_1 of MonoDepth2's decoder (x: 2 ** -(i + 1) of the input, C = O = its
  channels) does the same work, so one side of the threshold per input size."""
  channels = (16, 32, 64, 128, 256)
  for (height, width), want in [((64, 96), False), ((96, 320), True), ((192, 640), True)]:
    got = {layers.phase_form_pays(height >> (i + 1), width >> (i + 1), channels[i], channels[i])
           for i in range(5)}
    assert got == {want}, (height, width, got)
