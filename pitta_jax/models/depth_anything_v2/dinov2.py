"""DINOv2 ViT encoder of Depth Anything V2 (`depth_anything_v2/dinov2.py`, `dinov2_layers/*`), NHWC.

The `DinoVisionTransformer` as Depth Anything V2 builds it (`DINOv2(model_name)`): a 14x14
patch embedding (a stride-14 convolution), a class token, learned position embeddings for a
37x37 patch grid (518x518 inputs), `depth` pre-norm Transformer blocks (LayerNorm eps 1e-6,
multi-head self-attention with a fused qkv projection, LayerScale, exact-GELU MLP, LayerScale),
and the final LayerNorm `norm`, which `get_intermediate_layers(..., norm=True)` applies to every
returned block output. The encoder returns those normalised patch tokens of the blocks
`layer_idx` as (B, H/14, W/14, C) maps; the class token is dropped (Depth Anything V2 runs its
DPT head with `use_clstoken=False`).

Position embeddings for another patch grid (gh, gw) are resized bicubically (a = -0.75,
align_corners=False, no antialiasing) exactly as each upstream does it:

* upstream DINOv2 / Depth Anything V2 (`interpolate_offset=0.1`): `F.interpolate` with
  `scale_factor = ((gh + 0.1) / g, (gw + 0.1) / g)`; PyTorch then maps output index i to the
  source coordinate (i + 0.5) * g / (gh + 0.1) - 0.5 (the scale factor, not the size ratio);
* Hugging Face `Dinov2Embeddings.interpolate_pos_encoding`: `size=(gh, gw)`, i.e. the source
  coordinate (i + 0.5) * g / gh - 0.5, which is the formula above with offset 0. That is
  current transformers (the tests' reference); its older releases added 0.1 and passed a scale
  factor, as upstream does, so a model run there matches `pos_offset` 0.1 instead.

Both skip the interpolation when the grid is the stored g x g one. `pos_offset` selects the rule.

Parameter names follow upstream with `blocks.i` -> `blocks_i` and `patch_embed.proj` ->
`patch_embed`; upstream's fused `attn.qkv` (q, k, v stacked on the output axis) is kept.
"""

from __future__ import annotations

from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax.models import interpolate
from pitta_jax.models.layers import conv

PATCH_SIZE = 14
LN_EPS = 1e-6  # upstream's norm_layer = partial(nn.LayerNorm, eps=1e-6)
OFFICIAL_POS_OFFSET = 0.1  # DINOv2(..., interpolate_offset=0.1) in Depth Anything V2
HF_POS_OFFSET = 0.0  # transformers resizes to the target size


class ViTVariant(NamedTuple):
  """One DINOv2 size as Depth Anything V2 uses it (its DPT head's widths included)."""
  embed_dim: int
  depth: int
  num_heads: int
  layer_idx: tuple[int, ...]  # DepthAnythingV2.intermediate_layer_idx
  features: int  # DPT head width (model_configs in upstream run.py)
  out_channels: tuple[int, ...]


# upstream `vit_small/base/large` and `model_configs` of run.py; vitg (SwiGLU FFN) is not supported
VIT_VARIANTS: dict[str, ViTVariant] = {
    "vits": ViTVariant(384, 12, 6, (2, 5, 8, 11), 64, (48, 96, 192, 384)),
    "vitb": ViTVariant(768, 12, 12, (2, 5, 8, 11), 128, (96, 192, 384, 768)),
    "vitl": ViTVariant(1024, 24, 16, (4, 11, 17, 23), 256, (256, 512, 1024, 1024)),
}
DEFAULT_VARIANT = "vits"
MLP_RATIO = 4.0
POS_GRID = 37  # img_size 518 / patch 14


def layer_norm(name: str) -> nn.LayerNorm:
  """`nn.LayerNorm(dim, eps=1e-6)` numerics: variance as E[(x - mean)^2], as PyTorch."""
  return nn.LayerNorm(epsilon=LN_EPS, use_fast_variance=False, name=name)


def pos_embed_matrix(n_in: int, n_out: int, offset: float) -> np.ndarray:
  """(n_out, n_in) float32 weights of upstream's 1-D bicubic position-embedding resize.

  Source coordinate (i + 0.5) * n_in / (n_out + offset) - 0.5: PyTorch's rule for
  `scale_factor = (n_out + offset) / n_in`; offset 0 is PyTorch's rule for `size=n_out`, for
  which `interpolate.cubic_matrix` is used as it is.
  """
  if offset == 0.0:
    return interpolate.cubic_matrix(n_in, n_out, align_corners=False)
  x = (np.arange(n_out, dtype=np.float64) + 0.5) * (n_in / (n_out + offset)) - 0.5
  base = np.floor(x).astype(np.int64)
  w = interpolate._cubic_weights(x - base, interpolate.CUBIC_A)  # (n_out, 4), taps -1..2
  m = np.zeros((n_out, n_in), np.float64)
  for k in range(4):  # border taps replicate the edge, as PyTorch's clamped access
    np.add.at(m, (np.arange(n_out), np.clip(base - 1 + k, 0, n_in - 1)), w[:, k])
  return m.astype(np.float32)


def resize_pos_embed(pos: jax.Array, grid: tuple[int, int], offset: float) -> jax.Array:
  """Patch position embeddings (1, g * g, C) -> (1, gh * gw, C) for the patch grid (gh, gw)."""
  g = int(round(pos.shape[1] ** 0.5))
  gh, gw = grid
  if (gh, gw) == (g, g):
    return pos
  table = pos.reshape(g, g, pos.shape[-1])  # (g, g, C), rows = image height
  mh = jnp.asarray(pos_embed_matrix(g, gh, offset))  # (gh, g)
  mw = jnp.asarray(pos_embed_matrix(g, gw, offset))  # (gw, g)
  hp = jax.lax.Precision.HIGHEST
  out = jnp.einsum("ph,hwc->pwc", mh, table, precision=hp)
  out = jnp.einsum("qw,pwc->pqc", mw, out, precision=hp)  # (gh, gw, C)
  return out.reshape(1, gh * gw, -1)


class Attention(nn.Module):
  """Upstream `Attention` (`MemEffAttention` without xFormers): fused `qkv`, softmax, `proj`."""
  num_heads: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, N, C) tokens -> (B, N, C)."""
    b, n, c = x.shape
    head_dim = c // self.num_heads
    qkv = nn.Dense(3 * c, name="qkv")(x).reshape(b, n, 3, self.num_heads, head_dim)
    q = qkv[:, :, 0] * head_dim**-0.5  # (B, N, heads, hd), scaled before the product as upstream
    k, v = qkv[:, :, 1], qkv[:, :, 2]
    attn = jax.nn.softmax(jnp.einsum("bqhd,bkhd->bhqk", q, k), axis=-1)  # (B, heads, N, N)
    out = jnp.einsum("bhqk,bkhd->bqhd", attn, v).reshape(b, n, c)
    return nn.Dense(c, name="proj")(out)


class Mlp(nn.Module):
  """Upstream `Mlp`: fc1 -> exact GELU -> fc2 (back to the input width)."""
  hidden: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, N, C) -> (B, N, C)."""
    dim = x.shape[-1]
    x = nn.gelu(nn.Dense(self.hidden, name="fc1")(x), approximate=False)
    return nn.Dense(dim, name="fc2")(x)


class LayerScale(nn.Module):
  """Upstream `LayerScale`: a learned per-channel factor `gamma` (init_values 1.0)."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    gamma = self.param("gamma", nn.initializers.ones, (x.shape[-1],), jnp.float32)
    return x * gamma


class Block(nn.Module):
  """Upstream `Block`: x + ls1(attn(norm1(x))), then x + ls2(mlp(norm2(x))) (no drop path)."""
  num_heads: int
  mlp_hidden: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, N, C) -> (B, N, C)."""
    x = x + LayerScale(name="ls1")(Attention(self.num_heads, name="attn")(layer_norm("norm1")(x)))
    return x + LayerScale(name="ls2")(Mlp(self.mlp_hidden, name="mlp")(layer_norm("norm2")(x)))


class DinoVisionTransformer(nn.Module):
  """Upstream `DinoVisionTransformer` + `get_intermediate_layers(x, layer_idx, norm=True)`.

  Attributes:
    embed_dim, depth, num_heads, mlp_ratio: the ViT size (ViT-S/14 by default).
    layer_idx: the blocks (0-based) whose outputs the DPT head reads.
    pos_grid: side of the stored square grid of position embeddings (37 for 518x518).
    pos_offset: position-embedding resize rule (see the module docstring): 0.1 upstream, 0 HF.
  """
  embed_dim: int = VIT_VARIANTS[DEFAULT_VARIANT].embed_dim
  depth: int = VIT_VARIANTS[DEFAULT_VARIANT].depth
  num_heads: int = VIT_VARIANTS[DEFAULT_VARIANT].num_heads
  mlp_ratio: float = MLP_RATIO
  layer_idx: tuple[int, ...] = VIT_VARIANTS[DEFAULT_VARIANT].layer_idx
  pos_grid: int = POS_GRID
  pos_offset: float = OFFICIAL_POS_OFFSET

  @nn.compact
  def __call__(self, x: jax.Array) -> list[jax.Array]:
    """x: (B, H, W, 3) ImageNet-normalised RGB, H and W multiples of 14 -> one map per
    `layer_idx` entry, each (B, H/14, W/14, embed_dim), final LayerNorm applied."""
    if sorted(set(self.layer_idx)) != list(self.layer_idx) or not (
        0 <= self.layer_idx[0] and self.layer_idx[-1] < self.depth):
      raise ValueError(f"layer_idx {self.layer_idx} must be increasing block indices below "
                       f"the depth {self.depth}")
    b, h, w, _ = x.shape
    gh, gw = h // PATCH_SIZE, w // PATCH_SIZE
    c = self.embed_dim
    tokens = conv(c, PATCH_SIZE, PATCH_SIZE, 0, use_bias=True, name="patch_embed")(x)
    tokens = tokens.reshape(b, gh * gw, c)  # (B, N, C), row-major over the grid as upstream
    cls_token = self.param("cls_token", nn.initializers.zeros, (1, 1, c), jnp.float32)
    pos_embed = self.param("pos_embed", nn.initializers.normal(0.02),
                           (1, 1 + self.pos_grid**2, c), jnp.float32)
    pos = jnp.concatenate(
        [pos_embed[:, :1], resize_pos_embed(pos_embed[:, 1:], (gh, gw), self.pos_offset)], axis=1)
    tokens = jnp.concatenate([jnp.broadcast_to(cls_token, (b, 1, c)), tokens], axis=1) + pos

    mlp_hidden = int(c * self.mlp_ratio)
    taken = []
    for i in range(self.depth):
      tokens = Block(self.num_heads, mlp_hidden, name=f"blocks_{i}")(tokens)
      if i in self.layer_idx:
        taken.append(tokens)
    norm = layer_norm("norm")
    return [norm(t)[:, 1:].reshape(b, gh, gw, c) for t in taken]  # (B, gh, gw, C) each
