"""Layers whose numerics must match PyTorch exactly (for checkpoint parity).

- `BatchNorm`: PyTorch `nn.BatchNorm2d` semantics, which Flax's `nn.BatchNorm` does not have:
  normalisation uses the *biased* batch variance, the running estimate receives the *unbiased*
  one, momentum 0.1 means `running = 0.9 * running + 0.1 * batch`, eps 1e-5.
- `Conv`: `flax.linen.Conv` with the loop-friendly input gradient of `conv_vjp` (fast inside
  the engine's `lax.scan` on CPU); `conv`: one with explicit PyTorch-style symmetric padding
  (Flax's 'SAME' pads asymmetrically for stride-2 convolutions).
- `max_pool_3x3_s2`: the ResNet stem's max pool, with a gradient that is fast on CPU.
- `reflect_pad`, `upsample_nearest2x`: MonoDepth2's `ReflectionPad2d(1)` and
  `F.interpolate(scale_factor=2, mode="nearest")`.
- `reflect_conv3x3` (`ReflectConv3x3` with bias), `upsample_reflect_conv3x3`, `UpConv3x3`:
  MonoDepth2's `Conv3x3(use_refl)` on a map, on its nearest-2x upsampling (computed at the low
  resolution), and on the decoder's concatenation of both, written for XLA:CPU's fast paths
  (same sums, up to float rounding).
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax import lax
import flax.linen as nn

from pitta_jax.models import conv_vjp

# Every convolution of the adapted networks: same parameters and values as nn.Conv. Networks
# take it as their `conv` attribute (flax's ModuleDef pattern), so a caller can swap it.
Conv = functools.partial(nn.Conv, conv_general_dilated=conv_vjp.conv_general_dilated)
ModuleDef = Any


def _channel_sum(x: jax.Array) -> jax.Array:
  """(B, H, W, C) -> (C,): the sum over pixels in two stages, rows first (see `BatchNorm`)."""
  rows = jax.lax.optimization_barrier(jnp.sum(x, axis=2))  # (B, H, C)
  return jnp.sum(rows, axis=(0, 1))


def _channel_broadcast(v: jax.Array, shape: tuple[int, ...]) -> jax.Array:
  """(C,) -> `shape` (B, H, W, C) in two stages: its transpose (the gradient) is `_channel_sum`'s
  staged sum."""
  rows = jax.lax.optimization_barrier(jnp.broadcast_to(v, (shape[0], shape[1], v.shape[-1])))
  return jnp.broadcast_to(rows[:, :, None, :], shape)


# BatchNorm's steps are jitted so that an un-jitted `apply` runs each as one program, not op by op
@jax.jit
def _centre(x: jax.Array, mean: jax.Array) -> jax.Array:
  """x (B, H, W, C) minus the per-channel mean (C,)."""
  return x - _channel_broadcast(mean, x.shape)


@jax.jit
def _batch_moments(x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
  """x (B, H, W, C) -> (x - mean, mean, biased variance), the moments (C,) over pixels."""
  n = x.size // x.shape[-1]
  mean = _channel_sum(x) / n
  centred = _centre(x, mean)
  return centred, mean, _channel_sum(jnp.square(centred)) / n


@jax.jit
def _normalize(centred: jax.Array, var: jax.Array, scale: jax.Array, bias: jax.Array,
               epsilon: jax.Array) -> jax.Array:
  """(x - mean) / sqrt(var + eps) * gamma + beta over (B, H, W, C), per-channel (C,) inputs."""
  inv = jax.lax.rsqrt(var + epsilon) * scale
  return centred * _channel_broadcast(inv, centred.shape) + _channel_broadcast(bias, centred.shape)


class BatchNorm(nn.Module):
  """BatchNorm over the channel (last) axis with PyTorch semantics.

  Variables: params `scale` (gamma) and `bias` (beta); batch_stats `mean` and `var`.

  The per-channel sums over pixels (the batch mean and variance, and in the gradient those of
  gamma, beta and the normalisation) are taken in two stages, each row's pixels and then the
  rows, behind an optimisation barrier so that XLA does not merge them back into one reduction.
  A one-stage float32 sum over a whole image accumulates its rounding error linearly in the
  pixel count (PyTorch's CPU kernels accumulate these sums in float64): MonoDepth2's encoder BN
  gradient at 640x192 was 2.5e-3 (one thread) to 1.3e-2 (two) of each leaf's largest component
  off the float64 gradient, PyTorch's float32 gradient 7.9e-4; staged, JAX's is as close as
  PyTorch's (tests/test_pitta_torch.py).

  Attributes:
    momentum: PyTorch convention (weight of the new batch statistic), 0.1 by default.
    epsilon: added to the variance, 1e-5 as in PyTorch.
  """
  momentum: float = 0.1
  epsilon: float = 1e-5

  @nn.compact
  def __call__(self, x: jax.Array, use_batch_stats: bool) -> jax.Array:
    """Normalises `x` (B, H, W, C).

    Args:
      x: (B, H, W, C) activations.
      use_batch_stats: True = PyTorch train mode (normalise with the batch's statistics, and
        update the running estimate if the `batch_stats` collection is mutable); False = eval
        mode (normalise with the running estimate).
    """
    features = x.shape[-1]
    scale = self.param("scale", nn.initializers.ones, (features,), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros, (features,), jnp.float32)
    ra_mean = self.variable("batch_stats", "mean", lambda: jnp.zeros((features,), jnp.float32))
    ra_var = self.variable("batch_stats", "var", lambda: jnp.ones((features,), jnp.float32))

    if use_batch_stats:
      centred, mean, var = _batch_moments(x)  # var biased, as PyTorch normalises
      if not self.is_initializing() and self.is_mutable_collection("batch_stats"):
        n = x.size // features
        unbiased = var * (n / max(n - 1, 1))  # PyTorch stores the unbiased estimate
        m = self.momentum
        ra_mean.value = (1.0 - m) * ra_mean.value + m * jax.lax.stop_gradient(mean)
        ra_var.value = (1.0 - m) * ra_var.value + m * jax.lax.stop_gradient(unbiased)
    else:
      centred = _centre(x, ra_mean.value)
      var = ra_var.value
    return _normalize(centred, var, scale, bias, jnp.asarray(self.epsilon, x.dtype))


def conv(features: int, kernel: int, stride: int = 1, padding: int = 0, use_bias: bool = False,
         name: str | None = None, module: ModuleDef = Conv) -> nn.Conv:
  """A PyTorch-equivalent `Conv2d(k, stride, padding)` in NHWC (kernel stored as HWIO).

  module: the convolution class (a network's `conv` attribute; default `Conv`).
  """
  return module(features, (kernel, kernel), strides=(stride, stride),
                 padding=((padding, padding), (padding, padding)), use_bias=use_bias, name=name)


def _pool_views(x: jax.Array) -> list[jax.Array]:
  """The 9 strided (stride 2) views of the -inf-padded x, taps in row-major order."""
  b, h, w, c = x.shape
  ho, wo = (h + 1) // 2, (w + 1) // 2
  xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), constant_values=-jnp.inf)
  return [jax.lax.slice(xp, (0, i, j, 0), (b, i + 2 * ho - 1, j + 2 * wo - 1, c), (1, 2, 2, 1))
          for i in range(3) for j in range(3)]


@jax.custom_vjp
def max_pool_3x3_s2(x: jax.Array) -> jax.Array:
  """`nn.MaxPool2d(3, stride=2, padding=1)` on NHWC: (B, H, W, C) -> (B, ceil(H/2), ceil(W/2), C).

  Forward: the maximum of the 9 strided views of the -inf-padded input. Backward: PyTorch's
  rule (the whole gradient to the first maximal tap in row-major order) written as 4 parity
  planes of the input, each a sum of at most 4 masked output gradients, instead of XLA's
  select-and-scatter, which XLA:CPU runs ~10x slower (22 ms at 640x192 in the PITTA step).
  """
  return _max_pool_fwd(x)[0]


def _max_pool_fwd(x):
  views = _pool_views(x)
  best, arg = views[0], jnp.zeros(views[0].shape, jnp.int8)
  for t, v in enumerate(views[1:], start=1):
    take = v > best  # strict: ties keep the first tap, as PyTorch
    best = jnp.where(take, v, best)
    arg = jnp.where(take, jnp.int8(t), arg)
  return best, (arg, x.shape)


def _max_pool_bwd(res, g):
  arg, (b, h, w, c) = res
  ho, wo = g.shape[1], g.shape[2]

  def part(tap: int, dy: int, dx: int) -> jax.Array:
    """Gradient of output (m + dy, n + dx) through `tap`, on the (m, n) grid (zero past the end)."""
    contrib = jnp.where(arg == tap, g, 0.0)
    contrib = contrib[:, dy:, dx:]
    return jnp.pad(contrib, ((0, 0), (0, dy), (0, dx), (0, 0)))

  # input (2m + r, 2n + q) is tap (r + 1, q + 1) of output (m, n), and for r = 1 (q = 1) also
  # tap (0, .) of output (m + 1, n) (tap (., 0) of output (m, n + 1))
  ee = part(4, 0, 0)
  eo = part(5, 0, 0) + part(3, 0, 1)
  oe = part(7, 0, 0) + part(1, 1, 0)
  oo = part(8, 0, 0) + part(6, 0, 1) + part(2, 1, 0) + part(0, 1, 1)
  rows_e = jnp.stack([ee, eo], axis=3).reshape(b, ho, 2 * wo, c)  # interleave columns
  rows_o = jnp.stack([oe, oo], axis=3).reshape(b, ho, 2 * wo, c)
  full = jnp.stack([rows_e, rows_o], axis=2).reshape(b, 2 * ho, 2 * wo, c)  # interleave rows
  return (full[:, :h, :w].astype(g.dtype),)


max_pool_3x3_s2.defvjp(_max_pool_fwd, _max_pool_bwd)


def reflect_pad(x: jax.Array, pad: int = 1) -> jax.Array:
  """`nn.ReflectionPad2d(pad)` on an NHWC tensor (edge pixel not repeated).

  Written as one concatenation per axis of the mirrored border slices: the same values as
  `jnp.pad(mode="reflect")`, whose XLA:CPU lowering takes more passes over the tensor, forward
  and backward (about 10% of a decoder convolution's time at 640x192).
  """
  h, w = x.shape[1], x.shape[2]
  if pad == 0 or pad >= h or pad >= w:  # NumPy's rule (repeats at size 1); torch's raises
    return jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="reflect")
  return _mirror(_mirror(x, 1, pad), 2, pad)


def _mirror(x: jax.Array, axis: int, pad: int) -> jax.Array:
  """x with its `pad` pixels next to each end of `axis` mirrored beyond it (pad < size)."""
  n = x.shape[axis]
  ends = (lax.slice_in_dim(x, 1, pad + 1, axis=axis),
          lax.slice_in_dim(x, n - pad - 1, n - 1, axis=axis))
  return jnp.concatenate([jnp.flip(ends[0], axis), x, jnp.flip(ends[1], axis)], axis)


def upsample_nearest2x(x: jax.Array) -> jax.Array:
  """`F.interpolate(x, scale_factor=2, mode="nearest")` on an NHWC tensor."""
  return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)


# The border forms (`ring_form_pays`) where the padding's ring, 2H + 2W + 4 pixels, is at most
# this share of the map's H W, and the map holds at least this many values per image.
RING_FORM_MAX_SHARE = 0.15
RING_FORM_MIN_ELEMENTS = 2 ** 19


def ring_form_pays(height: int, width: int, channels: int) -> bool:
  """Whether a conv of an (H, W, C) map skips building its padded map (`bordered_conv`: the
  ring form of `reflect_conv3x3`, the phases of `upsample_reflect_conv3x3`): when the padding's
  ring adds at most `RING_FORM_MAX_SHARE` to the map's pixels and the map has at least
  `RING_FORM_MIN_ELEMENTS` values.

  Why both: the border terms are a fixed number of small kernels (about 20 more loop kernels
  per layer, forward and backward, for XLA to compile) whose gain, the padding pass, grows with
  the map. MonoDepth2's decoder at 640x192 (forward + input gradient, best ms; see
  `ring_reflect_conv3x3`): 3-4 ms saved per layer on the 1-2 M-value maps at 320x96 and
  640x192, 0.3-0.9 ms on the 0.25-0.5 M-value maps at 160x48 and 80x24, a loss on the small
  maps at 40x12 and 20x6. The ring form everywhere it saved time made the PITTA step's
  program 295 loop kernels larger (1014 -> 1309) and its compile 20-25% longer, as for the
  other methods' steps (CoTTA 22.6 -> 27.5 s); from 2^19 values only the layers on the largest
  maps take it (at 640x192: upconv_0_0, upconv_1_1's skip and the heads at 320x96 and 640x192).
  """
  return ((height + 2) * (width + 2) <= (1 + RING_FORM_MAX_SHARE) * height * width
          and height * width * channels >= RING_FORM_MIN_ELEMENTS)


def conv_function(module: ModuleDef) -> Callable:
  """The `conv_general_dilated` a conv module class uses: `conv_vjp`'s for `Conv`, JAX's own
  for `flax.linen.Conv` (the benchmarks swap them)."""
  return getattr(module, "keywords", {}).get("conv_general_dilated", jax.lax.conv_general_dilated)


def _conv(x: jax.Array, kernel: jax.Array, padding, conv_general_dilated: Callable) -> jax.Array:
  return conv_general_dilated(x, kernel, (1, 1), padding,
                              dimension_numbers=("NHWC", "HWIO", "NHWC"))


def reflect_conv3x3(x: jax.Array, kernel: jax.Array,
                    conv_general_dilated: Callable = conv_vjp.conv_general_dilated) -> jax.Array:
  """`Conv3x3(use_refl=True)` of MonoDepth2 without bias: ReflectionPad2d(1), then a 3x3 conv.

  x: (B, H, W, C), kernel: (3, 3, C, O) -> (B, H, W, O). Upstream convolves the padded map
  (a VALID conv); where `ring_form_pays` this runs `ring_reflect_conv3x3` instead, which never
  builds the padded map, forward or backward.
  """
  h, w = x.shape[1], x.shape[2]
  if ring_form_pays(h, w, x.shape[3]):
    return ring_reflect_conv3x3(x, kernel, conv_general_dilated)
  return _conv(reflect_pad(x), kernel, ((0, 0), (0, 0)), conv_general_dilated)


# A border term of `bordered_conv`: (axis, src, out, tap). The strip of x at index `src` along
# `axis` (1 rows, 2 columns; negative from the end) is what the padding puts next to output
# index `out` along that axis, read by the kernel's tap `tap` along it.
Border = tuple[int, int, int, int]


def _index(i: int, n: int) -> int:
  """Index i (negative: from the end) of an axis of n."""
  return i % n


def _strip(a: jax.Array, axis: int, index: int) -> jax.Array:
  """a's one-pixel strip at `index` (negative: from the end) along `axis` (1 or 2)."""
  i = _index(index, a.shape[axis])
  return lax.slice_in_dim(a, i, i + 1, axis=axis)


def _border_strips(x: jax.Array, borders: tuple[Border, ...]) -> tuple[jax.Array, ...]:
  """The strips of x the border terms read: (B, 1, W, C) rows, (B, H, 1, C) columns."""
  return tuple(_strip(x, ax, src) for ax, src, _, _ in borders)


def _border_terms(strips: tuple[jax.Array, ...], kernel: jax.Array, padding: conv_vjp.Pairs,
                  borders: tuple[Border, ...], mode: str, conv_general_dilated: Callable
                  ) -> tuple[jax.Array, ...]:
  """What the padding's border adds to the outputs of the zero-padded conv next to it.

  A row strip is padded along the width as the map is (`mode`, `padding[1]`: its own ends, the
  corners, are the row's share) and convolved (VALID) with the kernel's row `tap`: (B, 1, W',
  O). A column strip is zero padded along the height (`padding[0]`) and convolved with the
  kernel's column `tap`: (B, H', 1, O).
  """
  terms = []
  for strip, (ax, _, _, tap) in zip(strips, borders):
    if ax == 1:
      row = jnp.pad(strip, ((0, 0), (0, 0), padding[1], (0, 0)), mode=mode)
      terms.append(_conv(row, kernel[tap:tap + 1], ((0, 0), (0, 0)), conv_general_dilated))
    else:
      terms.append(_conv(strip, kernel[:, tap:tap + 1], (padding[0], (0, 0)),
                         conv_general_dilated))
  return tuple(terms)


def _add_at(a: jax.Array, v: jax.Array, axis: int, index: int) -> jax.Array:
  """a with v added to its block at `index` along `axis` (1 or 2): a dynamic update slice, which
  XLA runs in place."""
  start = [0, 0, 0, 0]
  start[axis] = _index(index, a.shape[axis])
  return lax.dynamic_update_slice(a, lax.dynamic_slice(a, start, v.shape) + v, start)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4, 5))
def bordered_conv(x: jax.Array, kernel: jax.Array, padding: conv_vjp.Pairs,
                  borders: tuple[Border, ...], mode: str,
                  conv_general_dilated: Callable = conv_vjp.conv_general_dilated) -> jax.Array:
  """The stride-1 conv of x padded with `mode` ("reflect" or "edge") by `padding`, without the
  padded map: the conv of x with zero padding, plus the border's terms added in place.

  x: (B, H, W, C), kernel: (kh, kw, C, O) -> (B, H', W', O). `padding` is one pixel wide where
  `borders` (`Border`) name the strips of x that the padding repeats there; where it is zero on
  a side, no term.

  Why: building the padded map is a full pass over it (two concatenations), and its gradient
  another. The terms are one-pixel-wide convolutions of the few rows and columns the padding
  repeats, and the gradient (`_bordered_bwd`) is the zero-padded conv's plus those strips' own,
  added in place. The interior outputs are the padded map's sums; the border outputs add the
  border's taps last (float rounding).
  """
  y = _conv(x, kernel, padding, conv_general_dilated)
  terms = _border_terms(_border_strips(x, borders), kernel, padding, borders, mode,
                        conv_general_dilated)
  for term, (ax, _, out, _) in zip(terms, borders):
    y = _add_at(y, term, ax, out)
  return y


def _bordered_fwd(x, kernel, padding, borders, mode, conv_general_dilated):
  return bordered_conv(x, kernel, padding, borders, mode, conv_general_dilated), (x, kernel)


def _bordered_bwd(padding, borders, mode, conv_general_dilated, residuals, g):
  """The zero-padded conv's gradients, plus the border terms' (input gradients of the strips,
  added in place; kernel gradients dropped by XLA where the kernel is not differentiated)."""
  x, kernel = residuals
  dx, dk = jax.vjp(lambda x, k: _conv(x, k, padding, conv_general_dilated), x, kernel)[1](g)
  g_terms = tuple(_strip(g, ax, out) for ax, _, out, _ in borders)
  d_strips, dk_terms = jax.vjp(
      lambda s, k: _border_terms(s, k, padding, borders, mode, conv_general_dilated),
      _border_strips(x, borders), kernel)[1](g_terms)
  for d, (ax, src, _, _) in zip(d_strips, borders):
    dx = _add_at(dx, d, ax, src)
  return dx, dk + dk_terms


bordered_conv.defvjp(_bordered_fwd, _bordered_bwd)

# ReflectionPad2d(1): output row 0 reads the ring row -1, i.e. row 1; row H - 1 reads row H - 2;
# columns likewise (the ring's corners are the rows' share)
REFLECT_RING: tuple[Border, ...] = ((1, 1, 0, 0), (1, -2, -1, 2), (2, 1, 0, 0), (2, -2, -1, 2))


def ring_reflect_conv3x3(x: jax.Array, kernel: jax.Array,
                         conv_general_dilated: Callable = conv_vjp.conv_general_dilated
                         ) -> jax.Array:
  """`reflect_conv3x3` as a 3x3 conv of x itself with zero padding of 1, the reflected ring's
  contribution then added to the border outputs: `bordered_conv` with `REFLECT_RING`.

  x: (B, H, W, C), H, W >= 2; kernel: (3, 3, C, O) -> (B, H, W, O).

  Why: the form before this one padded the map, convolved it with a zero ring on top (the
  VALID conv of the padded map is 1.3-2x slower on XLA:CPU than one with its own zero padding)
  and sliced the output ring off; its gradient padded the cotangent back. Forward + input
  gradient inside a scan (eight frames, Eigen's convolutions, 2 vCPUs AMD EPYC Zen 4, best ms),
  MonoDepth2's decoder at 640x192: 32 -> 16 at 320x96 6.8 -> 5.3, 64 -> 32 at 320x96 20.2 ->
  17.0, 16 -> 1 at 640x192 12.5 -> 8.4, 128 -> 64 at 80x24 4.3 -> 3.9; 256 -> 128 at 40x12 3.8
  -> 3.9 and 512 -> 256 at 20x6 4.8 -> 5.4, hence `ring_form_pays`.
  """
  return bordered_conv(x, kernel, ((1, 1), (1, 1)), REFLECT_RING, "reflect",
                       conv_general_dilated)


# `upsample_reflect_conv3x3` takes its phase form from this many multiply-adds of the direct form.
PHASE_FORM_MIN_MACS = 2 ** 25


def phase_form_pays(h: int, w: int, c: int, o: int) -> bool:
  """Whether `upsample_reflect_conv3x3` of a (h, w, c) map to o features uses its phase form:
  when the direct form's 2h * 2w * 9 * c * o multiply-adds reach `PHASE_FORM_MIN_MACS`.

  Why a threshold: the phase form saves 20 of every 36 multiply-adds and the upsampled map, but
  it is four convolutions with their slices, folded kernels and interleaving, forward and
  backward: ~30 more kernels for XLA to compile per layer and network pass. MonoDepth2's
  decoder halves the channels where it doubles the resolution, so all five of its upconv_i_1
  layers do the same work: 70.8 M multiply-adds each at 320x96, where the phase form is
  1.0-1.7x faster per layer (forward + backward, best of 9) and the PITTA step 132 against
  148 ms/frame, and 14.2 M at 64x96, where the step ran as fast either way (66.8 against 66.2)
  and compiled in 18.0 s directly against 24.3 s (813 against 966 loop kernels). Best of 5,
  interleaved, 2 vCPUs (Intel Xeon, 2026-12-03, a busy host). 2^25 sits between the two sizes.
  """
  return 4 * h * w * 9 * c * o >= PHASE_FORM_MIN_MACS


def upsample_reflect_conv3x3(x: jax.Array, kernel: jax.Array,
                             conv_general_dilated: Callable = conv_vjp.conv_general_dilated
                             ) -> jax.Array:
  """`reflect_conv3x3(upsample_nearest2x(x), kernel)`, computed at x's resolution where that
  pays (`phase_form_pays`), else literally.

  x: (B, h, w, C), kernel: (3, 3, C, O) -> (B, 2h, 2w, O).

  Why: on the nearest-2x upsampled map a 3x3 window covers only 2x2 distinct pixels of x, so
  each of the four output phases (row parity a, column parity b) is a 2x2 conv of x with the
  kernel's taps summed where they read the same pixel: along an axis, phase 0 reads pixels
  (i - 1, i) with taps (k0, k1 + k2), phase 1 reads (i, i + 1) with (k0 + k1, k2). The
  reflection padding of the upsampled map reads, at the border, the pixel itself, i.e. the edge
  (replicate) padding of x. 4 * 4 instead of 9 * 4 multiply-adds per 2x2 output block, and
  the upsampled map is never built, forward or backward: 2-3x faster on XLA:CPU. Where
  `ring_form_pays` for x, neither is x's edge padding: each phase is a `bordered_conv` of x.
  The same sums up to float rounding (the pairs of taps are added first).
  """
  b, h, w, c = x.shape
  o = kernel.shape[-1]
  if not phase_form_pays(h, w, c, o):
    return reflect_conv3x3(upsample_nearest2x(x), kernel, conv_general_dilated)
  bordered = ring_form_pays(h, w, c)
  if not bordered:
    xe = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")  # (B, h + 2, w + 2, C)

  def taps(k: jax.Array, phase: int) -> jax.Array:
    """The 3 taps of axis 0 of k folded into the 2 that phase `phase` reads."""
    return jnp.stack([k[0], k[1] + k[2]] if phase == 0 else [k[0] + k[1], k[2]])

  rows = []
  for a in (0, 1):
    ka = taps(kernel, a)  # (2, 3, C, O)
    cols = []
    for q in (0, 1):
      kab = jnp.moveaxis(taps(jnp.moveaxis(ka, 1, 0), q), 0, 1)  # (2, 2, C, O)
      if bordered:  # phase a reads row -1 (a = 0, tap 0) or row h (a = 1, tap 1): edge rows
        y = bordered_conv(x, kab, (PHASE_PADDING[a], PHASE_PADDING[q]),
                          ((1, -a, -a, a), (2, -q, -q, q)), "edge", conv_general_dilated)
      else:
        y = _conv(xe[:, a:a + h + 1, q:q + w + 1], kab, ((0, 0), (0, 0)), conv_general_dilated)
      cols.append(y)  # (B, h, w, O)
    rows.append(jnp.stack(cols, axis=3))  # (B, h, w, 2, O)
  return jnp.stack(rows, axis=2).reshape(b, 2 * h, 2 * w, o)  # interleave the phases


# the padding of x that phase 0 (pixels i - 1, i) and phase 1 (i, i + 1) read along an axis
PHASE_PADDING = ((1, 0), (0, 1))


class _Conv3x3Layer(nn.Module):
  """A decoder layer with `nn.Conv(features, (3, 3))`'s parameters (`kernel` (3, 3, in,
  features) and `bias`, float32, with its initialisers), so checkpoints are unchanged.

  Attributes:
    features: output channels.
    conv: the network's conv module class (`Conv` or `flax.linen.Conv`), whose
      `conv_general_dilated` is used.
  """
  features: int
  conv: ModuleDef = Conv

  def promoted(self, *inputs: jax.Array | None
               ) -> tuple[tuple[jax.Array | None, ...], jax.Array, jax.Array]:
    """The inputs (None: absent) and the parameters, kernel (3, 3, the inputs' channels
    together, features) and bias (features,), all in one dtype, as flax's Conv promotes
    (float32 weights on float64 features under x64)."""
    present = [a for a in inputs if a is not None]
    kernel = self.param("kernel", nn.initializers.lecun_normal(),
                        (3, 3, sum(a.shape[-1] for a in present), self.features), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
    dtype = jnp.result_type(*present, kernel)
    return (tuple(None if a is None else a.astype(dtype) for a in inputs),
            kernel.astype(dtype), bias.astype(dtype))


class ReflectConv3x3(_Conv3x3Layer):
  """MonoDepth2's `Conv3x3(use_refl=True)` with bias, (B, H, W, C) -> (B, H, W, features):
  `reflect_conv3x3` plus the bias."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    (x,), kernel, bias = self.promoted(x)
    return reflect_conv3x3(x, kernel, conv_function(self.conv)) + bias


class UpConv3x3(_Conv3x3Layer):
  """MonoDepth2's decoder layer `upconv_i_1` on its two inputs: `Conv3x3(use_refl=True)` with
  bias of concat([upsample_nearest2x(x), skip]).

  x: (B, h, w, C), skip: (B, 2h, 2w, S) or None -> (B, 2h, 2w, features). The parameters are
  those of the conv over the C + S concatenated channels (kernel (3, 3, C + S, features)); the
  conv is split along its input channels: `upsample_reflect_conv3x3` on x and
  `reflect_conv3x3` on the skip.
  """

  @nn.compact
  def __call__(self, x: jax.Array, skip: jax.Array | None = None) -> jax.Array:
    c = x.shape[-1]
    (x, skip), kernel, bias = self.promoted(x, skip)
    fn = conv_function(self.conv)
    y = upsample_reflect_conv3x3(x, kernel[:, :, :c], fn)
    if skip is not None:
      y = y + reflect_conv3x3(skip, kernel[:, :, c:], fn)
    return y + bias
