"""MPViT encoder of MonoViT (Zhao et al. 2022; Lee et al. 2022, "Multi-Path ViT"), NHWC.

Implements upstream zxcqlf/MonoViT `networks/mpvit.py` (`MPViT`, built by `mpvit_small`):

* stem: two `Conv2d_BN` (3x3 conv without bias, BatchNorm, Hardswish), the first with stride 2;
* per stage s: `Patch_Embed_stage`, a chain of `num_path[s]` depthwise-separable patch
  embeddings (`DWConv2d_BN`: depthwise 3x3, pointwise 1x1, BN, Hardswish; the first with
  stride 2), each path's input being the previous path's output;
* `MHCA_stage`: a local path (`ResBlock`, an inverted residual of 1x1 Conv2d_BN + Hardswish,
  depthwise 3x3, BN, Hardswish, 1x1 Conv2d_BN) on the first embedding, one transformer
  (`MHCAEncoder`) per embedding, and the aggregation of the `num_path + 1` maps by a 1x1
  Conv2d_BN + Hardswish;
* `MHCAEncoder`: `num_layers` `MHCABlock`s (pre-norm LayerNorm eps 1e-6, factorised attention
  `FactorAtt_ConvRelPosEnc`, exact-GELU MLP) that share one convolutional position encoding
  (`ConvPosEnc`, depthwise 3x3 + identity, applied at the start of every block) and one
  convolutional relative position encoding (`ConvRelPosEnc`: depthwise convs over head groups,
  window 3 for 2 heads, 5 for 3 heads, 7 for 3 heads, multiplied by the queries).

The encoder returns the stem output (1/2) and the four stage outputs (1/4 .. 1/32); channels
(64, 128, 216, 288, 288) for MPViT-small (the defaults; the layout fields also describe upstream's
mpvit_tiny/xsmall/base). There is no input normalisation: upstream feeds the
[0, 1] images to the stem as they are. Tokens are kept as (B, H, W, C) maps: every token-wise
op (LayerNorm, Linear) acts on the last axis, so no flatten/unflatten is needed around them.
Stochastic depth (drop path, rate 0.2 in training upstream) is not implemented: `train` only
selects batch statistics in the BatchNorms, which is what test-time adaptation needs.

Parameter names follow upstream with `a.i.b` -> `a_i/b` (`mhca_stages.2.mhca_blks.1.MHCA_layers.3
.factoratt_crpe.qkv` -> `mhca_stages_2/mhca_blks_1/MHCA_layers_3/factoratt_crpe/qkv`); the
trivial wrappers `DWCPatchEmbed.patch_conv` and `Conv2d_BN.act_layer` have no level of their own.
Shared modules (`cpe`, `crpe`) live once, in their `MHCAEncoder`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import flax.linen as nn

from pitta_jax.models.layers import BatchNorm, Conv

# mpvit_small in upstream's networks/mpvit.py, the layout of every MonoViT release
NUM_PATH = (2, 3, 3, 3)
NUM_LAYERS = (1, 3, 6, 3)
EMBED_DIMS = (64, 128, 216, 288)
MLP_RATIOS = (4, 4, 4, 4)
NUM_HEADS = (8, 8, 8, 8)
CRPE_WINDOW = ((3, 2), (5, 3), (7, 3))  # (window, heads) of ConvRelPosEnc, in upstream's dict order
LN_EPS = 1e-6  # MHCABlock's norm_layer = partial(nn.LayerNorm, eps=1e-6)


def conv2d(features: int, kernel: int, stride: int = 1, groups: int = 1, use_bias: bool = False,
           name: str | None = None) -> nn.Module:
  """PyTorch `Conv2d(k, stride, padding=k // 2, groups)`, NHWC (kernel HWIO)."""
  p = kernel // 2
  return Conv(features, (kernel, kernel), strides=(stride, stride), padding=((p, p), (p, p)),
              feature_group_count=groups, use_bias=use_bias, name=name)


class Conv2dBN(nn.Module):
  """Upstream `Conv2d_BN`: conv (no bias, padding k // 2) -> BatchNorm -> optional Hardswish."""
  features: int
  kernel: int = 1
  stride: int = 1
  act: bool = False

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    x = conv2d(self.features, self.kernel, self.stride, name="conv")(x)
    x = BatchNorm(name="bn")(x, train)
    return nn.hard_swish(x) if self.act else x


class DWConv2dBN(nn.Module):
  """Upstream `DWConv2d_BN` (inside `DWCPatchEmbed.patch_conv`): depthwise k x k conv (stride),
  pointwise 1x1 conv, BatchNorm, Hardswish; no biases."""
  kernel: int = 3
  stride: int = 1

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    c = x.shape[-1]
    x = conv2d(c, self.kernel, self.stride, groups=c, name="dwconv")(x)
    x = conv2d(c, 1, name="pwconv")(x)
    return nn.hard_swish(BatchNorm(name="bn")(x, train))


class PatchEmbedStage(nn.Module):
  """Upstream `Patch_Embed_stage(isPool=True)`: `num_path` chained DWCPatchEmbeds (3x3), the
  first with stride 2; returns every path's output."""
  num_path: int

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> list[jax.Array]:
    outs = []
    for i in range(self.num_path):
      x = DWConv2dBN(3, 2 if i == 0 else 1, name=f"patch_embeds_{i}")(x, train)
      outs.append(x)  # (B, H/2, W/2, C) each
    return outs


class ConvPosEnc(nn.Module):
  """Upstream `ConvPosEnc(k=3)`: x + depthwise 3x3 conv (with bias) of x."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    c = x.shape[-1]
    return conv2d(c, 3, groups=c, use_bias=True, name="proj")(x) + x


class ConvRelPosEnc(nn.Module):
  """Upstream `ConvRelPosEnc`: the values as a (h * Ch)-channel map, split into head groups, each
  group through a depthwise window x window conv (with bias); the result times the queries."""
  window: tuple[tuple[int, int], ...] = CRPE_WINDOW

  @nn.compact
  def __call__(self, q: jax.Array, v: jax.Array) -> jax.Array:
    """q, v: (B, H, W, h, Ch) -> (B, H, W, h, Ch)."""
    b, hh, ww, heads, ch = v.shape
    if sum(n for _, n in self.window) != heads:
      raise ValueError(f"ConvRelPosEnc windows {self.window} cover "
                       f"{sum(n for _, n in self.window)} heads, the attention has {heads}")
    v_img = v.reshape(b, hh, ww, heads * ch)  # channel index = head * Ch + c, as upstream
    outs, start = [], 0
    for i, (win, n_heads) in enumerate(self.window):
      width = n_heads * ch
      part = v_img[..., start:start + width]
      outs.append(conv2d(width, win, groups=width, use_bias=True, name=f"conv_list_{i}")(part))
      start += width
    conv_v = jnp.concatenate(outs, axis=-1).reshape(b, hh, ww, heads, ch)
    return q * conv_v


class FactorAttConvRelPosEnc(nn.Module):
  """Upstream `FactorAtt_ConvRelPosEnc`: scale * q (softmax_N(k)^T v) + crpe(q, v), then `proj`."""
  num_heads: int
  qkv_bias: bool = True  # MHCABlock passes qkv_bias=True

  @nn.compact
  def __call__(self, x: jax.Array, crpe: ConvRelPosEnc) -> jax.Array:
    """x: (B, H, W, C) tokens -> (B, H, W, C)."""
    b, hh, ww, c = x.shape
    ch = c // self.num_heads
    qkv = nn.Dense(3 * c, use_bias=self.qkv_bias, name="qkv")(x)
    qkv = qkv.reshape(b, hh * ww, 3, self.num_heads, ch)  # (B, N, 3, h, Ch)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]  # (B, N, h, Ch)
    k_soft = jax.nn.softmax(k, axis=1)  # over the N tokens
    kv = jnp.einsum("bnhk,bnhv->bhkv", k_soft, v)  # (B, h, Ch, Ch)
    factor_att = jnp.einsum("bnhk,bhkv->bnhv", q, kv)  # (B, N, h, Ch)
    shape5 = (b, hh, ww, self.num_heads, ch)
    rel = crpe(q.reshape(shape5), v.reshape(shape5)).reshape(b, hh * ww, self.num_heads, ch)
    y = (ch ** -0.5) * factor_att + rel
    return nn.Dense(c, name="proj")(y.reshape(b, hh, ww, c))


class Mlp(nn.Module):
  """Upstream `Mlp`: fc1 -> exact GELU -> fc2 (dropout 0)."""
  hidden: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    y = nn.gelu(nn.Dense(self.hidden, name="fc1")(x), approximate=False)
    return nn.Dense(x.shape[-1], name="fc2")(y)


class MHCABlock(nn.Module):
  """Upstream `MHCABlock`: x = cpe(x); x += att(norm1(x)); x += mlp(norm2(x)) (no drop path)."""
  num_heads: int
  mlp_ratio: int

  @nn.compact
  def __call__(self, x: jax.Array, cpe: ConvPosEnc, crpe: ConvRelPosEnc) -> jax.Array:
    """x: (B, H, W, C) -> (B, H, W, C); `cpe`/`crpe` are the encoder's shared modules."""
    c = x.shape[-1]
    x = cpe(x)  # (B, H, W, C)
    cur = nn.LayerNorm(epsilon=LN_EPS, use_fast_variance=False, name="norm1")(x)
    x = x + FactorAttConvRelPosEnc(self.num_heads, name="factoratt_crpe")(cur, crpe)
    cur = nn.LayerNorm(epsilon=LN_EPS, use_fast_variance=False, name="norm2")(x)
    return x + Mlp(c * self.mlp_ratio, name="mlp")(cur)


class MHCAEncoder(nn.Module):
  """Upstream `MHCAEncoder`: `num_layers` MHCABlocks sharing one ConvPosEnc and one
  ConvRelPosEnc."""
  num_layers: int
  num_heads: int
  mlp_ratio: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, H, W, C) -> (B, H, W, C)."""
    cpe = ConvPosEnc(name="cpe")
    crpe = ConvRelPosEnc(name="crpe")
    for i in range(self.num_layers):
      x = MHCABlock(self.num_heads, self.mlp_ratio, name=f"MHCA_layers_{i}")(x, cpe, crpe)
    return x


class ResBlock(nn.Module):
  """Upstream `ResBlock` (`InvRes`): x + conv2(Hardswish(BN(dw3x3(conv1(x))))), conv1 a 1x1
  Conv2d_BN + Hardswish, conv2 a 1x1 Conv2d_BN."""

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    c = x.shape[-1]
    feat = Conv2dBN(c, act=True, name="conv1")(x, train)
    feat = conv2d(c, 3, groups=c, name="dwconv")(feat)
    feat = nn.hard_swish(BatchNorm(name="norm")(feat, train))
    return x + Conv2dBN(c, name="conv2")(feat, train)


class MHCAStage(nn.Module):
  """Upstream `MHCA_stage`: ResBlock on the first path and one MHCAEncoder per path, concatenated
  (local first) and aggregated by a 1x1 Conv2d_BN + Hardswish to `out_dim`."""
  out_dim: int
  num_layers: int
  num_heads: int
  mlp_ratio: int

  @nn.compact
  def __call__(self, inputs: list[jax.Array], train: bool) -> jax.Array:
    outs = [ResBlock(name="InvRes")(inputs[0], train)]
    for i, x in enumerate(inputs):
      outs.append(MHCAEncoder(self.num_layers, self.num_heads, self.mlp_ratio,
                              name=f"mhca_blks_{i}")(x))
    cat = jnp.concatenate(outs, axis=-1)  # (B, H, W, C * (num_path + 1))
    return Conv2dBN(self.out_dim, act=True, name="aggregate")(cat, train)


class MPViT(nn.Module):
  """Upstream `MPViT` as MonoViT's depth encoder (defaults: `mpvit_small`).

  Returns 5 feature maps: the stem's (embed_dims[0] channels) and each stage's aggregate
  (embed_dims[s + 1] channels, the last stage keeping embed_dims[-1]).
  """
  num_path: tuple[int, ...] = NUM_PATH
  num_layers: tuple[int, ...] = NUM_LAYERS
  embed_dims: tuple[int, ...] = EMBED_DIMS
  mlp_ratios: tuple[int, ...] = MLP_RATIOS
  num_heads: tuple[int, ...] = NUM_HEADS

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> list[jax.Array]:
    """images: (B, H, W, 3) RGB in [0, 1] (not normalised, as upstream) -> for MPViT-small
    [(B, H/2, W/2, 64), (B, H/4, W/4, 128), (B, H/8, W/8, 216), (B, H/16, W/16, 288),
    (B, H/32, W/32, 288)]."""
    if images.ndim != 4 or images.shape[-1] != 3:
      raise ValueError(f"encoder input must be (B, H, W, 3) NHWC, got {images.shape}")
    dims = self.embed_dims
    x = Conv2dBN(dims[0] // 2, 3, 2, act=True, name="stem_0")(images, train)
    x = Conv2dBN(dims[0], 3, 1, act=True, name="stem_1")(x, train)
    features = [x]  # (B, H/2, W/2, dims[0])
    n = len(dims)
    for s in range(n):
      paths = PatchEmbedStage(self.num_path[s], name=f"patch_embed_stages_{s}")(x, train)
      out_dim = dims[s + 1] if s + 1 < n else dims[s]
      x = MHCAStage(out_dim, self.num_layers[s], self.num_heads[s], self.mlp_ratios[s],
                    name=f"mhca_stages_{s}")(paths, train)
      features.append(x)  # (B, H / 2**(s+2), W / 2**(s+2), out_dim)
    return features
