"""Lite-Mono's encoder in NHWC (Zhang et al., CVPR 2023; upstream `networks/depth_encoder.py`).

A CNN/transformer hybrid at three resolutions (1/4, 1/8, 1/16 of the input):

* stem: three 3x3 convolutions with BatchNorm + exact GELU (upstream `Conv(bn_act=True)`, the
  first one stride 2), then `stem2`, a stride-2 3x3 convolution without BN or activation whose
  input is the stem output concatenated with the normalised image average-pooled once;
* stage i (dims[i] channels, depths[i] blocks): `DilatedConv` blocks (a dilated depthwise 3x3
  convolution, BatchNorm, an inverted-bottleneck MLP with exact GELU, a layer scale `gamma`,
  a residual) and, as the last block, one `LGFI` block (cross-covariance attention XCA over
  the LayerNorm-ed tokens, a Fourier positional encoding in stage 0 only, then a LayerNorm +
  MLP whose result is added to the *block input*, as upstream does);
* between stages, `downsample_layers_i`: a stride-2 3x3 convolution of the concatenation
  [previous downsampling output, stage output, image average-pooled i + 1 times].

Upstream's AvgPool2d(3, 2, 1) counts the zero padding (count_include_pad=True), so every window
divides by 9. Stochastic depth (DropPath) is an identity here: it is off at inference, and the
adaptation is deterministic. Every BatchNorm is `layers.BatchNorm` (params scale/bias and
batch_stats mean/var), every LayerNorm a flax `nn.LayerNorm` (eps 1e-6, params only).

Flax names follow the PyTorch module paths with list indices joined by "_":
`downsample_layers.0.1.bn_gelu.bn` -> `downsample_layers_0_1/bn`, `stages.2.9.xca.qkv` ->
`stages_2_9/xca/qkv`, `stages.0.0.ddwconv.conv` -> `stages_0_0/ddwconv`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import flax.linen as nn
import numpy as np

from pitta_jax.models.layers import BatchNorm, Conv, conv
from pitta_jax.nonsmooth import clamp, norm

SQRT_HALF = 0.7071067811865476  # 1 / sqrt(2), for the exact GELU
LN_EPS = 1e-6          # upstream LayerNorm(eps=1e-6) everywhere in the encoder
IMAGE_MEAN, IMAGE_STD = 0.45, 0.225  # upstream forward_features' input normalisation
NORMALIZE_EPS = 1e-12  # F.normalize's default eps (XCA's q/k normalisation)
POS_HIDDEN = 32        # PositionalEncodingFourier(hidden_dim=32)
POS_TEMPERATURE = 10000.0
POS_EPS = 1e-6
# upstream layer_scale_init_value of the `gamma` / `gamma_xca` layer scales (weights replace it)
LAYER_SCALE_INIT = nn.initializers.constant(1e-6)


class Variant(NamedTuple):
  """Widths and block counts of one Lite-Mono model size (upstream `LiteMono.__init__`)."""
  dims: tuple[int, int, int]
  depths: tuple[int, int, int]


VARIANTS: dict[str, Variant] = {
    "lite-mono": Variant((48, 80, 128), (4, 4, 10)),
    "lite-mono-small": Variant((48, 80, 128), (4, 4, 7)),
    "lite-mono-tiny": Variant((32, 64, 128), (4, 4, 7)),
    "lite-mono-8m": Variant((64, 128, 224), (4, 4, 10)),
}

# Dilation rates of the DilatedConv blocks, chosen upstream by the training size (H, W); the last
# block of each stage is an LGFI block, so each list has depths[i] - 1 entries.
_D192_DEEP = ((1, 2, 3), (1, 2, 3), (1, 2, 3, 1, 2, 3, 2, 4, 6))
_D192_SHALLOW = ((1, 2, 3), (1, 2, 3), (1, 2, 3, 2, 4, 6))
DILATIONS: dict[tuple[str, int, int], tuple[tuple[int, ...], ...]] = {
    ("lite-mono", 192, 640): _D192_DEEP,
    ("lite-mono", 320, 1024): ((1, 2, 5), (1, 2, 5), (1, 2, 5, 1, 2, 5, 2, 4, 10)),
    ("lite-mono-small", 192, 640): _D192_SHALLOW,
    ("lite-mono-small", 320, 1024): ((1, 2, 5), (1, 2, 5), (1, 2, 5, 2, 4, 10)),
    ("lite-mono-tiny", 192, 640): _D192_SHALLOW,
    ("lite-mono-tiny", 320, 1024): ((1, 2, 5), (1, 2, 5), (1, 2, 5, 2, 4, 10)),
    ("lite-mono-8m", 192, 640): _D192_DEEP,
    ("lite-mono-8m", 320, 1024): _D192_DEEP,  # upstream uses the 640x192 rates for 8m at 1024x320
}

HEADS = (8, 8, 8)                  # XCA heads per stage
USE_POS_EMBD = (True, False, False)  # Fourier positional encoding in stage 0's LGFI only
EXPAN_RATIO = 6                    # inverted-bottleneck expansion
GLOBAL_BLOCKS = (1, 1, 1)          # LGFI blocks at the end of each stage


def dilations_for(model: str, height: int, width: int) -> tuple[tuple[int, ...], ...]:
  """The DilatedConv rates of `model` trained at height x width (ValueError if upstream
  defines none)."""
  if model not in VARIANTS:
    raise ValueError(f"unknown Lite-Mono model {model!r}; one of {sorted(VARIANTS)}")
  key = (model, height, width)
  if key not in DILATIONS:
    sizes = sorted(f"{w}x{h}" for m, h, w in DILATIONS if m == model)
    raise ValueError(f"{model} defines dilation rates only for training sizes {sizes} (WxH), "
                     f"not {width}x{height}")
  return DILATIONS[key]


def gelu(x: jax.Array) -> jax.Array:
  """PyTorch's nn.GELU(), exact, in PyTorch's own formula x / 2 * (1 + erf(x / sqrt 2)).

  Same function as `nn.gelu(x, approximate=False)`, which XLA:CPU evaluates through erfc ~6x
  slower (5.8 vs 0.9 ms on the stage-0 MLP activations at 640x192, 2 cores); GELU runs on the
  6x-expanded MLP activations of all 18 blocks.
  """
  return 0.5 * x * (1.0 + jax.lax.erf(x * SQRT_HALF))


def avg_pool_3x3_s2(x: jax.Array) -> jax.Array:
  """`nn.AvgPool2d(3, stride=2, padding=1)` (zero padding counted, divisor 9) on NHWC:
  (B, H, W, C) -> (B, ceil(H/2), ceil(W/2), C)."""
  pad = ((0, 0), (1, 1), (1, 1), (0, 0))
  summed = jax.lax.reduce_window(x, jnp.zeros((), x.dtype), jax.lax.add, (1, 3, 3, 1),
                                 (1, 2, 2, 1), pad)
  return summed / 9.0


class ConvLayer(nn.Module):
  """Upstream `Conv`: a bias-free 3x3 convolution (padding 1), then BatchNorm + GELU if bn_act."""
  features: int
  stride: int
  bn_act: bool

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    x = conv(self.features, 3, self.stride, 1, name="conv")(x)
    if self.bn_act:
      x = gelu(BatchNorm(name="bn")(x, train))
    return x


class DepthwiseConv3x3(nn.Module):
  """Upstream `CDilated(C, C, 3, d=dilation, groups=C)`: `nn.Conv2d(C, C, 3, padding=d,
  dilation=d, groups=C, bias=False)`, computed as the sum of 9 shifted, per-channel scaled
  copies of the zero-padded input.

  Why not `layers.Conv(feature_group_count=C)`: XLA:CPU runs grouped convolutions as generic
  loops, ~60x slower forward and ~6x slower with its gradient (stage 0 at 640x192, 2 cores:
  16 vs 0.26 ms forward, 31 vs 5.5 ms value+gradient); the shifted sum is the same function,
  its gradient pads and slices. The parameter is a Conv's `kernel`, HWIO (3, 3, 1, C), so the
  layer looks like any depthwise convolution to the converter and the selectors.
  """
  features: int
  dilation: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, H, W, C) -> (B, H, W, C)."""
    kernel = self.param("kernel", nn.initializers.lecun_normal(), (3, 3, 1, self.features),
                        jnp.float32)
    d, (h, w) = self.dilation, x.shape[1:3]
    xp = jnp.pad(x, ((0, 0), (d, d), (d, d), (0, 0)))  # (B, H + 2d, W + 2d, C)
    out = xp[:, :h, :w] * kernel[0, 0, 0]
    for i in range(3):
      for j in range(3):
        if i or j:
          out = out + xp[:, i * d:i * d + h, j * d:j * d + w] * kernel[i, j, 0]
    return out


class DilatedConv(nn.Module):
  """Upstream `DilatedConv` (one layer of the consecutive dilated convolutions):
  x + gamma * pwconv2(GELU(pwconv1(BN(depthwise dilated 3x3 conv(x))))).

  Upstream also creates a LayerNorm `norm` that its forward never calls; it has no counterpart
  here (its checkpoint keys are ignored by the converter)."""
  dim: int
  dilation: int
  expan_ratio: int = EXPAN_RATIO

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    y = DepthwiseConv3x3(self.dim, self.dilation, name="ddwconv")(x)  # (B, H, W, C)
    y = BatchNorm(name="bn1")(y, train)
    y = nn.Dense(self.expan_ratio * self.dim, name="pwconv1")(y)  # (B, H, W, 6C)
    y = nn.Dense(self.dim, name="pwconv2")(gelu(y))
    gamma = self.param("gamma", LAYER_SCALE_INIT, (self.dim,), jnp.float32)
    return x + gamma * y


def fourier_positions(height: int, width: int) -> np.ndarray:
  """The (H, W, 2 * POS_HIDDEN) sine/cosine map of upstream `PositionalEncodingFourier`
  before its projection (y features first, then x), computed in float32 as upstream does."""
  f32 = np.float32
  scale = f32(2 * math.pi)
  y = np.arange(1, height + 1, dtype=f32)
  x = np.arange(1, width + 1, dtype=f32)
  y = y / (y[-1] + f32(POS_EPS)) * scale  # (H,)
  x = x / (x[-1] + f32(POS_EPS)) * scale  # (W,)
  k = np.arange(POS_HIDDEN, dtype=f32)
  dim_t = f32(POS_TEMPERATURE) ** (2 * (k // 2) / f32(POS_HIDDEN))  # (32,)

  def interleave(pos: np.ndarray) -> np.ndarray:  # (n, 32): sin of even, cos of odd, paired
    return np.stack([np.sin(pos[:, 0::2]), np.cos(pos[:, 1::2])], axis=-1).reshape(len(pos), -1)

  py = interleave(y[:, None] / dim_t)  # (H, 32)
  px = interleave(x[:, None] / dim_t)  # (W, 32)
  grid = np.concatenate([np.broadcast_to(py[:, None], (height, width, POS_HIDDEN)),
                         np.broadcast_to(px[None], (height, width, POS_HIDDEN))], axis=-1)
  return grid.astype(f32)


class PositionalEncodingFourier(nn.Module):
  """Upstream `PositionalEncodingFourier`: the fixed sine map, projected by a 1x1 conv."""
  dim: int

  @nn.compact
  def __call__(self, height: int, width: int, dtype: jnp.dtype) -> jax.Array:
    """-> (1, H, W, dim), the same for every image of the batch."""
    pos = jnp.asarray(fourier_positions(height, width), dtype)[None]  # (1, H, W, 64)
    return Conv(self.dim, (1, 1), padding=((0, 0), (0, 0)), use_bias=True,
                name="token_projection")(pos)


class XCA(nn.Module):
  """Upstream `XCA`, cross-covariance attention: per head, a (d, d) channel attention from the
  token-wise L2-normalised queries and keys, scaled by a learned per-head temperature."""
  dim: int
  num_heads: int
  qkv_bias: bool = True

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, N, C) tokens -> (B, N, C)."""
    b, n, c = x.shape
    h, d = self.num_heads, c // self.num_heads
    qkv = nn.Dense(3 * c, use_bias=self.qkv_bias, name="qkv")(x).reshape(b, n, 3, h, d)
    q, k, v = (jnp.transpose(qkv[:, :, i], (0, 2, 3, 1)) for i in range(3))  # (B, h, d, N)

    def l2_normalize(t: jax.Array) -> jax.Array:
      # F.normalize(t, dim=-1): t / norm(t).clamp_min(eps), with torch's derivatives (a norm
      # of 0, e.g. a token of zeros, has a zero gradient, not a NaN one)
      return t / clamp(norm(t, axis=-1, keepdims=True), lo=NORMALIZE_EPS)

    temperature = self.param("temperature", nn.initializers.ones, (h, 1, 1), jnp.float32)
    attn = jnp.einsum("bhdn,bhen->bhde", l2_normalize(q), l2_normalize(k)) * temperature
    attn = jax.nn.softmax(attn, axis=-1)  # (B, h, d, d)
    out = jnp.einsum("bhde,bhen->bhdn", attn, v)  # (B, h, d, N)
    out = jnp.transpose(out, (0, 3, 1, 2)).reshape(b, n, c)
    return nn.Dense(c, name="proj")(out)


class LGFI(nn.Module):
  """Upstream `LGFI` (local-global features interaction):
  t = x (+ pos) ; t = t + gamma_xca * XCA(LN(t)) ; out = x + gamma * MLP(LN(t)).
  The final residual adds the block input, not t (upstream's forward)."""
  dim: int
  num_heads: int
  use_pos_emb: bool
  expan_ratio: int = EXPAN_RATIO

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    del train  # no BatchNorm in this block
    b, hh, ww, c = x.shape
    t = x
    if self.use_pos_emb:
      t = t + PositionalEncodingFourier(self.dim, name="pos_embd")(hh, ww, x.dtype)
    t = t.reshape(b, hh * ww, c)  # (B, N, C), token n = row * W + column
    a = XCA(self.dim, self.num_heads, name="xca")(
        nn.LayerNorm(epsilon=LN_EPS, use_fast_variance=False, name="norm_xca")(t))
    gamma_xca = self.param("gamma_xca", LAYER_SCALE_INIT, (c,), jnp.float32)
    t = (t + gamma_xca * a).reshape(b, hh, ww, c)
    y = nn.LayerNorm(epsilon=LN_EPS, use_fast_variance=False, name="norm")(t)
    y = nn.Dense(self.expan_ratio * c, name="pwconv1")(y)  # (B, H, W, 6C)
    y = nn.Dense(c, name="pwconv2")(gelu(y))
    gamma = self.param("gamma", LAYER_SCALE_INIT, (c,), jnp.float32)
    return x + gamma * y


class LiteMonoEncoder(nn.Module):
  """Upstream `LiteMono` (the depth encoder).

  Attributes:
    dims, depths: a `Variant` (channels and blocks of the three stages).
    dilations: per stage, the rates of its DilatedConv blocks (`dilations_for`).
  """
  dims: tuple[int, int, int]
  depths: tuple[int, int, int]
  dilations: tuple[tuple[int, ...], ...]

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> list[jax.Array]:
    """images: (B, H, W, 3) RGB in [0, 1] -> 3 maps (B, H/4, W/4, dims[0]),
    (B, H/8, W/8, dims[1]), (B, H/16, W/16, dims[2])."""
    x = (images - IMAGE_MEAN) / IMAGE_STD
    pooled = [avg_pool_3x3_s2(x)]  # the image at 1/2, 1/4, 1/8 (upstream also builds 1/16, unused)
    for _ in range(2):
      pooled.append(avg_pool_3x3_s2(pooled[-1]))

    for k in range(3):
      x = ConvLayer(self.dims[0], 2 if k == 0 else 1, True, name=f"downsample_layers_0_{k}")(
          x, train)  # (B, H/2, W/2, dims[0])
    x = ConvLayer(self.dims[0], 2, False, name="stem2_0")(
        jnp.concatenate([x, pooled[0]], axis=-1), train)  # (B, H/4, W/4, dims[0])

    features = []
    for i in range(3):
      if i > 0:  # [downsampling output, stage output, pooled image] -> stride-2 conv
        x = ConvLayer(self.dims[i], 2, False, name=f"downsample_layers_{i}_0")(
            jnp.concatenate([entry, x, pooled[i]], axis=-1), train)
      entry = x
      n_local = self.depths[i] - GLOBAL_BLOCKS[i]
      if len(self.dilations[i]) < n_local:
        raise ValueError(f"stage {i} needs {n_local} dilation rates, got {self.dilations[i]}")
      for j in range(self.depths[i]):
        name = f"stages_{i}_{j}"
        if j < n_local:
          x = DilatedConv(self.dims[i], self.dilations[i][j], name=name)(x, train)
        else:
          x = LGFI(self.dims[i], HEADS[i], USE_POS_EMBD[i], name=name)(x, train)
      features.append(x)
    return features
