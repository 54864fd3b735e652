"""A 2-D NHWC convolution whose input gradient stays fast inside `lax.scan` on XLA:CPU.

Why: JAX differentiates `lax.conv_general_dilated` w.r.t. its input with another convolution
whose kernel is the flipped forward kernel read with input/output features swapped (`01oi`).
XLA:CPU hands a convolution to its fast library only in the canonical `01io` kernel layout; in
the entry computation a layout pass makes the swap a physical transpose, but inside a while
loop (the body of the engine's `lax.scan` over frames) the `01oi` convolution is emitted as a
generic loop nest instead. Measured on 2 CPU cores, the scanned PITTA step at 320x96 took
443 ms/frame with JAX's rule and 170 ms/frame with this one (`benchmarks/step.py`).

The fix is a `jax.custom_vjp` whose backward builds the input gradient from an explicitly
flipped and transposed kernel, already in canonical HWIO, with the same padding and dilation
JAX's own transpose rule uses. The kernel gradient has the same problem (JAX's rule is a
convolution in swapped layouts; inside the loop a 3x3 64->64 kernel gradient at 32x48 took
1.37 s for 4 frames instead of 0.023 s): it is written as a convolution of the input, features
and batch swapped, with the cotangent as a canonical HWIO kernel, or, for the image input of a
single frame, as a matrix product of the input's patches (`_kernel_grad`). Values and gradients
are those of `lax.conv_general_dilated` (tests/test_conv_vjp.py). Flax's `nn.Conv` takes it
through its `conv_general_dilated` attribute (`models.layers.Conv`).

The forward of a stride-1 convolution to a single output feature (a disparity head) is a
matrix product and a sum of shifted planes (`_single_output_conv`): XLA:CPU's convolution
library does not take it, and its generic loop nest was 2.6x slower. A convolution (forward or
input gradient) whose input is smaller than the kernel, and in float64 one whose output is
larger than its input, is one matrix product of the input's patches (`_small_input_conv`):
XLA:CPU runs both through slow generic code. So is one with few output pixels and many
features (ResNet's last stage), where the product is ~25% faster than XLA's convolution; its
input gradient is then the transposed product, scattered back tap by tap
(`_patches_input_grad`), which needs no transposed copy of the kernel.
"""

from __future__ import annotations

import functools
from typing import Any, Sequence

import jax
import jax.numpy as jnp
from jax import lax

NHWC_HWIO = ("NHWC", "HWIO", "NHWC")
Pairs = tuple[tuple[int, int], ...]


def _dilated_size(size: int, dilation: int) -> int:
  return 0 if size == 0 else 1 + dilation * (size - 1)


def _single_output_conv(x: jax.Array, k: jax.Array, padding: Pairs, precision: Any) -> jax.Array:
  """A stride-1 convolution to one output feature, as a matrix product and a sum of shifts.

  x (N, H, W, C), k (kh, kw, C, 1) -> (N, H', W', 1). Why: XLA:CPU's fast convolution path does
  not take a single output feature; MonoDepth2's disparity head (3x3, 16 -> 1 at full
  resolution) ran as a generic loop nest, 3.7 ms for a forward that is 35 MFLOP. Here every
  pixel's C features are contracted with all kh * kw taps at once (one matrix product, (N H W,
  C) @ (C, kh kw)), and output pixel (i, j) adds tap (a, b)'s value at (i + a, j + b): 1.4 ms
  (640x192, 2 CPU cores). The product reads x as it lies: with the taps first, (kh kw, C) @
  (C, N H W), XLA:CPU copied x into a transposed layout first (1.9 ms at 640x192 with 16
  features; the head's forward + input gradient inside a scan 9.4 -> 8.1 ms best with the
  pixels first, 2 vCPUs AMD EPYC Zen 4). Used when the kh * kw taps are no more than the
  input's C features (the product then writes no more than it reads); the padding is applied to
  the taps. Same sums, in another order (float rounding).
  """
  kh, kw, c, _ = k.shape
  taps = lax.dot_general(x, k.reshape(kh * kw, c), (((3,), (1,)), ((), ())),
                         precision=precision)  # (N, H, W, kh * kw)
  if any(p for pair in padding for p in pair):
    taps = lax.pad(taps, jnp.zeros((), taps.dtype),
                   ((0, 0, 0), *((lo, hi, 0) for lo, hi in padding), (0, 0, 0)))
  ho, wo = taps.shape[1] - kh + 1, taps.shape[2] - kw + 1
  return sum(taps[:, a:a + ho, b:b + wo, a * kw + b:a * kw + b + 1]
             for a in range(kh) for b in range(kw))  # (N, Ho, Wo, 1)


def _tap_planes(xp: jax.Array, axes: tuple[int, int], kernel_size: tuple[int, int],
                strides: tuple[int, int], rhs_dilation: tuple[int, int],
                out_size: tuple[int, int]) -> list[jax.Array]:
  """The kh * kw strided views of the padded input xp that kernel tap (a, b) reads, taps in
  row-major order; `axes` are xp's two spatial axes. Each view is out_size along them."""
  views = []
  for a in range(kernel_size[0]):
    for b in range(kernel_size[1]):
      start, limit, step = [0] * xp.ndim, list(xp.shape), [1] * xp.ndim
      for ax, tap, s, d, m in zip(axes, (a, b), strides, rhs_dilation, out_size):
        start[ax], limit[ax], step[ax] = tap * d, tap * d + s * (m - 1) + 1, s
      views.append(lax.slice(xp, start, limit, step))
  return views


def _small_input_conv(x: jax.Array, k: jax.Array, strides: tuple[int, int], padding: Pairs,
                      lhs_dilation: tuple[int, int], rhs_dilation: tuple[int, int],
                      precision: Any) -> jax.Array:
  """A convolution as one matrix product of the input's patches: (N Ho Wo, kh kw C) @ (kh kw C, O).

  x (N, H, W, C), k (kh, kw, C, O) -> (N, Ho, Wo, O). Why: XLA:CPU gives a convolution to its
  library only when the (input-dilated, unpadded) input is at least as large as the kernel's
  extent; otherwise it runs a generic loop nest. That is the deepest ResNet stage of a small
  image (a 64x96 input leaves 2x3 pixels): a 3x3 512 -> 512 convolution of a 2x3 input took
  24 ms in float32 and float64 alike, as a product of its patches 0.9 ms (2 vCPUs). In float64
  the convolutions whose output is larger than the input (the input gradient of an unpadded
  convolution: MonoDepth2's reflection-padded decoder) run in a fallback at 0.1-1 GFLOP/s:
  (1, 12, 40, 256) -> (1, 14, 42, 256) took 584 ms, as patches 8 ms. The patches are a kh * kw
  times larger copy of the input, cheap for these. Same sums, in another order (float
  rounding). Measured in one process on 2 vCPUs (Intel, AVX-512); Ada-Depth's float64 step at
  64x96 (its parity test) 1.95 -> 0.96 s.
  """
  kh, kw, c, o = k.shape
  xp = lax.pad(x, jnp.zeros((), x.dtype),
               ((0, 0, 0), *((lo, hi, d - 1) for (lo, hi), d in zip(padding, lhs_dilation)),
                (0, 0, 0)))                                                     # (N, Hp, Wp, C)
  out = tuple((n - _dilated_size(kn, d)) // s + 1
              for n, kn, d, s in zip(xp.shape[1:3], (kh, kw), rhs_dilation, strides))
  cols = jnp.concatenate(_tap_planes(xp, (1, 2), (kh, kw), strides, rhs_dilation, out),
                         axis=-1)                                               # (N, Ho, Wo, kh kw C)
  return lax.dot_general(cols, k.reshape(kh * kw * c, o), (((3,), (0,)), ((), ())),
                         precision=precision)                                   # (N, Ho, Wo, O)


# a convolution (forward or input gradient) with at most this many output pixels, all images
# together, and at least this many features on both sides is a product of patches (`_conv`)
FEW_PIXELS_MAX_OUTPUT = 128
FEW_PIXELS_MIN_FEATURES = 256


def _few_pixels(images: int, out: Sequence[int], k_shape: tuple[int, ...], dtype: Any) -> bool:
  """A float32 kh x kw > 1 convolution to at most `FEW_PIXELS_MAX_OUTPUT` output pixels (all
  images) with at least `FEW_PIXELS_MIN_FEATURES` features on both sides (`_conv`)."""
  return (dtype == jnp.float32 and images * out[0] * out[1] <= FEW_PIXELS_MAX_OUTPUT
          and k_shape[0] * k_shape[1] > 1 and min(k_shape[2:]) >= FEW_PIXELS_MIN_FEATURES)


def _conv(x: jax.Array, k: jax.Array, strides: tuple[int, int], padding: Pairs,
          rhs_dilation: tuple[int, int], precision: Any,
          lhs_dilation: tuple[int, int] = (1, 1)) -> jax.Array:
  """The forward convolution (and the input gradient's, with `lhs_dilation`), by the fastest of
  XLA's convolution, a product of patches, and the single-output form.

  A product of patches (`_small_input_conv`) for inputs smaller than the kernel, in float64 for
  outputs larger than the input, and for a kh x kw > 1 convolution with few output pixels and
  many features (`FEW_PIXELS_*`: ResNet's last stage and the decoder's first layer at 640x192,
  6x20 pixels, 256-512 features), where XLA:CPU's convolution runs at ~70 GFLOP/s: a 3x3 512 ->
  512 convolution of a 6x20 map 8.0 ms, its patches product 5.9-6.2 ms (PyTorch's oneDNN
  7.4-7.6 ms; 2 vCPUs); the 12x40 maps of the stage before are faster as a convolution. That
  is float32 (XLA:CPU's YNNPACK path); float64 convolutions keep XLA's, whose program compiles
  faster (Ada-Depth's float64 parity step: 95 s with it, 105 s with the patches)."""
  sizes = [_dilated_size(n, d) for n, d in zip(x.shape[1:3], lhs_dilation)]
  extents = [_dilated_size(kn, d) for kn, d in zip(k.shape[:2], rhs_dilation)]
  out = [(n + lo + hi - e) // s + 1 for n, (lo, hi), e, s in zip(sizes, padding, extents, strides)]
  grows = any(m > n for m, n in zip(out, sizes))
  if any(n < e for n, e in zip(sizes, extents)) or (grows and x.dtype == jnp.float64) or \
      _few_pixels(x.shape[0], out, k.shape, x.dtype):
    return _small_input_conv(x, k, strides, padding, lhs_dilation, rhs_dilation, precision)
  fits = all(n + lo + hi >= e for n, (lo, hi), e in zip(sizes, padding, extents))
  small_taps = k.shape[0] * k.shape[1] <= k.shape[2]  # tap planes no larger than the input
  if k.shape[-1] == 1 and strides == (1, 1) and rhs_dilation == (1, 1) and fits and \
      small_taps and lhs_dilation == (1, 1) and all(p >= 0 for pair in padding for p in pair):
    return _single_output_conv(x, k, padding, precision)
  return lax.conv_general_dilated(x, k, strides, padding, lhs_dilation, rhs_dilation, NHWC_HWIO,
                                  precision=precision)


# the kernel gradient of a single image with at most this many input features (the encoders'
# first convolution) is a matrix product of the input's patches (`_kernel_grad`)
PATCHES_MAX_INPUT_FEATURES = 8


def _kernel_grad(x: jax.Array, g: jax.Array, kernel_size: tuple[int, int],
                 strides: tuple[int, int], padding: Pairs, rhs_dilation: tuple[int, int],
                 precision: Any, pad_first: bool = True,
                 phases: bool | None = None) -> jax.Array:
  """dk[a, b, c, o] = sum_{n,i,j} x_pad[n, i s + a d, j s + b d, c] g[n, i, j, o].

  x: (N, H, W, C), g: (N, Ho, Wo, O) -> (kh, kw, C, O).
  A convolution of x (features <-> batch swapped: (C, H, W, N)) with g as an HWIO kernel
  (Ho, Wo, N, O), window stride d and kernel dilation s, the rows past the kernel's extent (the
  forward convolution's unused trailing input) cut off (`kernel_grad_conv`). A convolution
  strided by 2 takes it per stride phase (`kernel_grad_phases`, below). Otherwise, for a single
  image with at most `PATCHES_MAX_INPUT_FEATURES` input features (an image, or two stacked, seen
  by a stride-1 or a patch-embedding convolution) it is one matrix product of the input's
  patches (`kernel_grad_patches`): as a convolution its "features" are the one image and its
  kernel the whole cotangent. Measured for the encoders' 7x7 stride-2 convolution before it took
  the phases, inside a compiled loop at 640x192 on 2 vCPUs (Intel, AVX-512;
  `benchmarks/kernel_grad.py`, docs/performance.md, 2026-12-05), best ms, convolution vs
  patches, batch 1: 3 -> 64 features 16.0 vs 11.7 (XLA's default library) and 18.1 vs 11.6
  (Eigen's), 6 -> 64 30.6 vs 22.2 and 32.5 vs 21.5.

  At batch 4 the convolution form is the fastest on Eigen's library for every layer shape of
  MonoDepth2 (3 -> 64: 31 ms against 50 for the patches; 64 -> 64 at 160x48: 22 against 48;
  96 -> 32 at 322x98: 76 against 423), though not on XLA's default one (66 against 48 for
  64 -> 64, 405 for 96 -> 32, where one convolution per image took 206). The only step that
  takes kernel gradients of a batch is CoMoDa's (1 + 3 replay images), and `auto` compiles it
  with Eigen's convolutions (`adapt.xla_cpu`): on that machine its step took 2742
  ms/frame this way against 3622 with XLA's default library and the patch and per-image forms
  this function used for batches before (interleaved, 4 rounds); on a 2-core AMD EPYC (Zen 3)
  a close variant (Eigen, the convolution form but the patches for the first convolutions)
  3786 against 3966 (5 rounds). Same sums, in another order (float rounding).

  The convolution form takes x zero padded first, not the padding inside the convolution
  (`pad_first`): XLA:CPU runs a padded convolution with a kernel as large as the image many
  times slower. Inside a compiled loop at 640x192 (2 vCPUs, AMD EPYC Zen 4 without
  AVX-512, `benchmarks/kernel_grad.py --forms conv,inside`), best ms, padding inside -> padded
  first: the disparity head 16 -> 1 at 640x192 28.4 -> 2.6 (XLA's default library) and 30.6 ->
  2.6 (Eigen's), 32 -> 1 at 320x96 25.7 -> 1.7, 16 -> 16 at 640x192 34.4 -> 8.7; on Eigen's
  library ResNet's 3x3 stride-1 layers 16.7 -> 4.3 (64 features at 160x48), 9.9 -> 3.8 (128),
  6.0 -> 4.3 (512 at 20x6). Whole steps, interleaved (`step.py --compare-padded-kernel-grads`): Ada-Depth on
  Eigen's library 2307 -> 1841 ms/frame, ActMAD 874 -> 733. At batch 4 (CoMoDa) the layers
  moved both ways while the strided ones were one convolution, and the step did not gain (3151
  -> 3123 ms/frame on Eigen's library); with the strided layers per stride phase (below) every
  padded layer gains there too (64 -> 64 at 160x48 25.9 -> 20.3 ms, 128 -> 128 20.7 -> 14.6, the
  disparity heads 24.7 -> 21.5 and 15.1 -> 9.3; PyTorch 17.1, 17.0, 14.0, 6.5) and so does the
  step (2982 -> 2795 ms/frame median, 4 rounds interleaved, same losses bit for bit): the input
  is padded first at every batch since 2026-12-08, 04:00 UTC. The zeros add nothing: the same
  sums. `pad_first=False` puts the padding inside (benchmarks compare).

  A stride-2 convolution's kernel gradient is the sum of its stride phases' stride-1 kernel
  gradients (`kernel_grad_phases`), at any batch: as one convolution its kernel (the cotangent)
  is dilated by the stride, which XLA:CPU runs at 15-25 GFLOP/s. `phases` given overrides that
  rule (benchmarks compare).
  """
  args = (x, g, kernel_size, strides, padding, rhs_dilation, precision)
  if _phases_pay(strides, rhs_dilation) if phases is None else phases:
    return kernel_grad_phases(*args)
  if g.shape[0] == 1 and x.shape[3] <= PATCHES_MAX_INPUT_FEATURES:
    return kernel_grad_patches(*args)
  return kernel_grad_conv(*args, pad_first=pad_first)


def kernel_grad_conv(x: jax.Array, g: jax.Array, kernel_size: tuple[int, int],
                     strides: tuple[int, int], padding: Pairs, rhs_dilation: tuple[int, int],
                     precision: Any = None, pad_first: bool = True) -> jax.Array:
  """`_kernel_grad` as a convolution of x (C, H, W, N) with g as an HWIO kernel (Ho, Wo, N, O);
  x zero padded first (`pad_first`) or the padding inside the convolution."""
  kh, kw = kernel_size
  if pad_first:
    x = lax.pad(x, jnp.zeros((), x.dtype),
                ((0, 0, 0), *((lo, hi, 0) for lo, hi in padding), (0, 0, 0)))  # (N, Hp, Wp, C)
    padding = ((0, 0), (0, 0))
  dk = lax.conv_general_dilated(jnp.transpose(x, (3, 1, 2, 0)), jnp.transpose(g, (1, 2, 0, 3)),
                                rhs_dilation, padding, None, strides, NHWC_HWIO,
                                precision=precision)                  # (C, >= kh, >= kw, O)
  return jnp.transpose(dk[:, :kh, :kw], (1, 2, 0, 3))


# the kernel gradient of a convolution strided by at most this much (and more than 1) along
# both axes is the sum of its stride phases' kernel gradients (`_kernel_grad`)
PHASES_MAX_STRIDE = 2


def _phases_pay(strides: tuple[int, int], rhs_dilation: tuple[int, int]) -> bool:
  """An undilated convolution strided by 2 along an axis, by at most `PHASES_MAX_STRIDE` along
  both (ResNet's strided 3x3, 1x1 and 7x7 convolutions)."""
  return (max(strides) > 1 and max(strides) <= PHASES_MAX_STRIDE
          and tuple(rhs_dilation) == (1, 1))


def kernel_grad_phases(x: jax.Array, g: jax.Array, kernel_size: tuple[int, int],
                       strides: tuple[int, int], padding: Pairs, rhs_dilation: tuple[int, int],
                       precision: Any = None) -> jax.Array:
  """`_kernel_grad` of a strided, undilated convolution as stride-1 kernel gradients, one per
  stride phase.

  x: (N, H, W, C), g: (N, Ho, Wo, O) -> (kh, kw, C, O). Tap (s a + r, s b + q) reads only the
  padded input's phase x_pad[:, r::s, q::s], so with p_rq that phase,
      dk[s a + r, s b + q, c, o] = sum_{n,i,j} p_rq[n, i + a, j + b, c] g[n, i, j, o]:
  the kernel gradient of a stride-1 convolution of p_rq with a ceil((kh - r) / s) x
  ceil((kw - q) / s) kernel (`kernel_grad_conv`; one matrix product over the pixels for a 1 x 1
  one), its taps then interleaved. Why: as one convolution (`kernel_grad_conv`) its kernel, the
  cotangent, is dilated by the stride, and XLA:CPU runs that at 15-25 GFLOP/s. Inside a compiled
  loop at 640x192 (2 vCPUs, AMD EPYC Zen 4, Eigen's convolutions; `benchmarks/kernel_grad.py
  --forms conv,phases`, docs/performance.md, 2026-12-08), best ms, one convolution -> phases,
  PyTorch's oneDNN in brackets: batch 1, ResNet's 3x3 64 -> 128 15.6 -> 2.8 (2.5), 128 -> 256
  7.6 -> 2.4 (2.5), 256 -> 512 5.5 -> 3.4 (2.6), 1x1 64 -> 128 5.8 -> 0.8 (0.9); batch 4: 24.4 ->
  13.5 (10.4), 17.8 -> 9.0 (9.7), 14.9 -> 9.0 (10.8), 8.6 -> 1.7 (2.0), the 7x7 3 -> 64 54.7 ->
  28.0 (18.7), the pose encoder's 6 -> 64 98.5 -> 46.1 (45.8); the 7x7 convolutions of a single
  image, which took the patches product: 14.5 -> 5.8 (4.7) and 23.4 -> 8.9 (11.5). The same
  products, summed in another order (float rounding).
  """
  kh, kw = kernel_size
  sh, sw = strides
  n, ho, wo, o = g.shape
  c = x.shape[3]
  xp = lax.pad(x, jnp.zeros((), x.dtype),
               ((0, 0, 0), *((lo, hi, 0) for lo, hi in padding), (0, 0, 0)))  # (N, Hp, Wp, C)
  parts = {}
  for r in range(min(sh, kh)):
    for q in range(min(sw, kw)):
      ka, kb = -(-(kh - r) // sh), -(-(kw - q) // sw)
      phase = lax.slice(xp, (0, r, q, 0),
                        (n, r + sh * (ho + ka - 2) + 1, q + sw * (wo + kb - 2) + 1, c),
                        (1, sh, sw, 1))                       # (N, Ho + ka - 1, Wo + kb - 1, C)
      if ka == kb == 1:
        parts[r, q] = lax.dot_general(phase, g, (((0, 1, 2), (0, 1, 2)), ((), ())),
                                      precision=precision)[None, None]  # (1, 1, C, O)
      else:
        parts[r, q] = kernel_grad_conv(phase, g, (ka, kb), (1, 1), ((0, 0), (0, 0)), (1, 1),
                                       precision)             # (ka, kb, C, O)
  taps = [parts[a % sh, b % sw][a // sh, b // sw] for a in range(kh) for b in range(kw)]
  return jnp.stack(taps).reshape(kh, kw, c, o)


def kernel_grad_patches(x: jax.Array, g: jax.Array, kernel_size: tuple[int, int],
                        strides: tuple[int, int], padding: Pairs, rhs_dilation: tuple[int, int],
                        precision: Any = None) -> jax.Array:
  """`_kernel_grad` as one product of x's patches: (kh kw C, N Ho Wo) @ (N Ho Wo, O)."""
  kh, kw = kernel_size
  n, ho, wo, o = g.shape
  c = x.shape[3]
  xt = lax.pad(jnp.transpose(x, (3, 0, 1, 2)), jnp.zeros((), x.dtype),
               ((0, 0, 0), (0, 0, 0), *((lo, hi, 0) for lo, hi in padding)))  # (C, N, Hp, Wp)
  patches = jnp.stack(_tap_planes(xt, (2, 3), kernel_size, strides, rhs_dilation,
                                  (ho, wo)))                          # (kh kw, C, N, Ho, Wo)
  dk = lax.dot_general(patches.reshape(kh * kw * c, n * ho * wo), g.reshape(n * ho * wo, o),
                       (((1,), (0,)), ((), ())), precision=precision)  # (kh kw C, O)
  return dk.reshape(kh, kw, c, o)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4, 5))
def conv_nhwc(x: jax.Array, k: jax.Array, strides: tuple[int, int], padding: Pairs,
              rhs_dilation: tuple[int, int], precision: Any = None) -> jax.Array:
  """Convolution of x (N, H, W, C) with k (kh, kw, C, O) -> (N, H', W', O); see module doc."""
  return _conv(x, k, strides, padding, rhs_dilation, precision)


def _conv_fwd(x, k, strides, padding, rhs_dilation, precision):
  return _conv(x, k, strides, padding, rhs_dilation, precision), (x, k)


def _patches_input_grad(g: jax.Array, k: jax.Array, size: tuple[int, int],
                        strides: tuple[int, int], padding: Pairs, rhs_dilation: tuple[int, int],
                        precision: Any) -> jax.Array:
  """The input gradient of a convolution as the transpose of the patches product: (N Ho Wo, O)
  @ (O, kh kw C), each tap's columns then added back where that tap read the padded input.

  g (N, Ho, Wo, O), k (kh, kw, C, O), size: the input's (H, W) -> (N, H, W, C). Why: the
  convolution form (`_conv` of g with the flipped, transposed kernel) needs that kernel as a
  copy, rebuilt each step when the kernel adapts: 7-8 ms per 3x3 512 -> 512 kernel on 2 vCPUs
  (`benchmarks/profile_step.py --method adadepth`: about a dozen per frame). The product
  contracts k's output features as they lie (a transposed right operand, no copy). Used where
  `_conv` would take the patches product for the input gradient (`_few_pixels`: ResNet's last
  stage at 640x192). Steps interleaved with the copy (`benchmarks/step.py
  --compare-patches-input-grad`, AMD EPYC Zen 4, 2026-12-08), ms/frame median: Ada-Depth 1730
  -> 1670, ActMAD 566 -> 559, PITTA 229 -> 220 (its copies were hoisted out of the scan, but
  the program is 27 kernels shorter). Same sums, in another order.
  """
  kh, kw, c, o = k.shape
  n, ho, wo, _ = g.shape
  cols = lax.dot_general(g, k.reshape(kh * kw * c, o), (((3,), (1,)), ((), ())),
                         precision=precision).reshape(n, ho, wo, kh * kw, c)  # (N, Ho, Wo, T, C)
  padded = [m + lo + hi for m, (lo, hi) in zip(size, padding)]
  dxp = None
  for t in range(kh * kw):
    pads = []
    for tap, d, s, m, full in zip(divmod(t, kw), rhs_dilation, strides, (ho, wo), padded):
      pads.append((tap * d, full - tap * d - s * (m - 1) - 1, s - 1))
    term = lax.pad(cols[:, :, :, t], jnp.zeros((), g.dtype), ((0, 0, 0), *pads, (0, 0, 0)))
    dxp = term if dxp is None else dxp + term                          # (N, Hp, Wp, C)
  return lax.pad(dxp, jnp.zeros((), g.dtype),
                 ((0, 0, 0), *((-lo, -hi, 0) for lo, hi in padding), (0, 0, 0)))


def _conv_input_grad(g: jax.Array, k: jax.Array, size: tuple[int, int],
                     strides: tuple[int, int], padding: Pairs, rhs_dilation: tuple[int, int],
                     precision: Any) -> jax.Array:
  """The input gradient as a convolution (`_conv`): the full correlation of the stride-dilated
  cotangent g (N, Ho, Wo, O) with the flipped kernel k, read as (kh, kw, O, C), canonical HWIO
  -> (N, H, W, C), size = (H, W)."""
  window = [_dilated_size(s, d) for s, d in zip(k.shape[:2], rhs_dilation)]
  lo = [w - p_lo - 1 for w, (p_lo, _) in zip(window, padding)]
  hi = [n + w - 1 - _dilated_size(m, s) - l
        for n, w, m, s, l in zip(size, window, g.shape[1:3], strides, lo)]
  k_t = jnp.transpose(jnp.flip(k, (0, 1)), (0, 1, 3, 2))  # (kh, kw, O, C), canonical HWIO
  return _conv(g, k_t, (1, 1), tuple(zip(lo, hi)), rhs_dilation, precision, lhs_dilation=strides)


def _conv_bwd(strides, padding, rhs_dilation, precision, residuals, g):
  x, k = residuals
  # kernel gradient (XLA drops it when the kernel is not differentiated)
  dk = _kernel_grad(x, g, k.shape[:2], strides, padding, rhs_dilation, precision)
  input_grad = (_patches_input_grad if _few_pixels(x.shape[0], x.shape[1:3], k.shape, x.dtype)
                else _conv_input_grad)
  return input_grad(g, k, x.shape[1:3], strides, padding, rhs_dilation, precision), dk


conv_nhwc.defvjp(_conv_fwd, _conv_bwd)


def conv_general_dilated(lhs: jax.Array, rhs: jax.Array, window_strides: Sequence[int],
                         padding: str | Sequence[tuple[int, int]],
                         lhs_dilation: Sequence[int] | None = None,
                         rhs_dilation: Sequence[int] | None = None,
                         dimension_numbers: Any = None, feature_group_count: int = 1,
                         batch_group_count: int = 1, precision: Any = None,
                         preferred_element_type: Any = None) -> jax.Array:
  """Drop-in `lax.conv_general_dilated`: plain 2-D NHWC/HWIO convolutions go to `conv_nhwc`,
  anything else (grouped, input-dilated, string padding other than VALID, other layouts) to
  `lax.conv_general_dilated` unchanged."""
  if isinstance(padding, str) and padding.upper() == "VALID":
    padding = ((0, 0),) * (lhs.ndim - 2)
  plain = (lhs.ndim == 4 and not isinstance(padding, str) and feature_group_count == 1
           and batch_group_count == 1 and preferred_element_type is None
           and tuple(lhs_dilation or (1, 1)) == (1, 1)
           and lax.conv_dimension_numbers(lhs.shape, rhs.shape, dimension_numbers)
           == lax.conv_dimension_numbers(lhs.shape, rhs.shape, NHWC_HWIO))
  if not plain:
    return lax.conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation,
                                    rhs_dilation, dimension_numbers, feature_group_count,
                                    batch_group_count, precision, preferred_element_type)
  return conv_nhwc(lhs, rhs, tuple(window_strides), tuple(tuple(p) for p in padding),
                   tuple(rhs_dilation or (1, 1)), precision)
