"""Swin Transformer backbone (Liu et al. 2021) as Mask2Former's `D2SwinTransformer`, NHWC.

Implements upstream facebookresearch/Mask2Former `mask2former/modeling/backbone/swin.py`
(itself the Swin-Transformer-Semantic-Segmentation backbone): a 4x4 patch embedding with
LayerNorm, four stages of Swin blocks (window multi-head self-attention with a relative position
bias; every second block cyclically shifts the windows by `window // 2` and masks attention
between regions that were not adjacent before the shift with -100), patch merging between
stages, and a LayerNorm on each stage output (`norm0..norm3`). Feature maps not divisible by the
window are zero-padded after `norm1` (the padded tokens are attended to, not masked, as
upstream); odd sizes are zero-padded before patch merging.

Numerics as PyTorch: LayerNorm eps 1e-5 with the two-pass variance, exact (erf) GELU.
Parameter names follow upstream with `layers.i.blocks.j` -> `stage{i}_block{j}`,
`layers.i.downsample` -> `stage{i}_downsample`, `patch_embed.proj/norm` -> `patch_embed_proj/norm`.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class SwinConfig:
  """Swin-T as Mask2Former's COCO panoptic config (`maskformer2_swin_tiny_bs16_50ep.yaml`)."""
  patch_size: int = 4
  embed_dim: int = 96
  depths: tuple[int, ...] = (2, 2, 6, 2)
  num_heads: tuple[int, ...] = (3, 6, 12, 24)
  window_size: int = 7
  mlp_ratio: float = 4.0

  @property
  def channels(self) -> tuple[int, ...]:
    """Channels of the stage outputs res2..res5."""
    return tuple(self.embed_dim * 2**i for i in range(len(self.depths)))


def layer_norm(name: str) -> nn.LayerNorm:
  """`torch.nn.LayerNorm` numerics: eps 1e-5, variance as E[(x - mean)^2]."""
  return nn.LayerNorm(epsilon=1e-5, use_fast_variance=False, name=name)


def relative_position_index(window: int) -> np.ndarray:
  """(window^2, window^2) int32 index into the ((2w-1)^2, heads) bias table, as upstream."""
  coords = np.stack(np.meshgrid(np.arange(window), np.arange(window), indexing="ij"))  # (2, w, w)
  coords = coords.reshape(2, -1)
  rel = (coords[:, :, None] - coords[:, None, :]).transpose(1, 2, 0) + (window - 1)  # (N, N, 2)
  return (rel[..., 0] * (2 * window - 1) + rel[..., 1]).astype(np.int32)


def shifted_window_mask(height: int, width: int, window: int, shift: int) -> np.ndarray:
  """(num_windows, window^2, window^2) float32 additive mask, 0 or -100, for padded (H, W).

  Regions [0, H - w), [H - w, H - shift), [H - shift, H) per axis (upstream's slices); two
  tokens of one window attend to each other only if they lie in the same region.
  """
  def regions(n: int) -> np.ndarray:
    idx = np.arange(n)
    return (idx >= n - window).astype(np.int32) + (idx >= n - shift).astype(np.int32)
  img = regions(height)[:, None] * 3 + regions(width)[None, :]  # (H, W)
  win = img.reshape(height // window, window, width // window, window).transpose(0, 2, 1, 3)
  win = win.reshape(-1, window * window)  # (nW, N)
  diff = win[:, None, :] - win[:, :, None]
  return np.where(diff != 0, -100.0, 0.0).astype(np.float32)


def window_partition(x: jax.Array, window: int) -> jax.Array:
  """(B, H, W, C) -> (B * nW, window^2, C), windows in row-major order."""
  b, h, w, c = x.shape
  x = x.reshape(b, h // window, window, w // window, window, c).transpose(0, 1, 3, 2, 4, 5)
  return x.reshape(-1, window * window, c)


def window_reverse(windows: jax.Array, window: int, b: int, h: int, w: int) -> jax.Array:
  """(B * nW, window^2, C) -> (B, H, W, C), inverse of `window_partition`."""
  c = windows.shape[-1]
  x = windows.reshape(b, h // window, w // window, window, window, c).transpose(0, 1, 3, 2, 4, 5)
  return x.reshape(b, h, w, c)


class WindowAttention(nn.Module):
  """Window multi-head self-attention with a relative position bias (upstream `WindowAttention`).

  Params: `qkv` (fused query/key/value, 3 * dim outputs in that order), `proj`,
  `relative_position_bias_table` ((2w - 1)^2, heads).
  """
  dim: int
  num_heads: int
  window_size: int

  @nn.compact
  def __call__(self, x: jax.Array, mask: np.ndarray | None) -> jax.Array:
    """x: (B * nW, N, C) window tokens; mask: (nW, N, N) additive or None -> (B * nW, N, C)."""
    bw, n, c = x.shape
    heads, head_dim = self.num_heads, c // self.num_heads
    w = self.window_size
    table = self.param("relative_position_bias_table", nn.initializers.truncated_normal(0.02),
                       ((2 * w - 1) ** 2, heads), jnp.float32)
    qkv = nn.Dense(3 * c, name="qkv")(x).reshape(bw, n, 3, heads, head_dim)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]  # (B * nW, N, heads, hd)
    q = q * head_dim**-0.5
    attn = jnp.einsum("bqhd,bkhd->bhqk", q, k)  # (B * nW, heads, N, N)
    bias = table[relative_position_index(w).reshape(-1)].reshape(n, n, heads)
    attn = attn + bias.transpose(2, 0, 1)[None]
    if mask is not None:
      nw = mask.shape[0]
      attn = attn.reshape(bw // nw, nw, heads, n, n) + jnp.asarray(mask)[None, :, None]
      attn = attn.reshape(bw, heads, n, n)
    attn = jax.nn.softmax(attn, axis=-1)
    out = jnp.einsum("bhqk,bkhd->bqhd", attn, v).reshape(bw, n, c)
    return nn.Dense(c, name="proj")(out)


class SwinBlock(nn.Module):
  """(Shifted-)window attention + MLP, both pre-norm residual (upstream `SwinTransformerBlock`)."""
  dim: int
  num_heads: int
  window_size: int
  shift_size: int
  mlp_ratio: float = 4.0

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, H, W, C) -> (B, H, W, C)."""
    b, h, w, c = x.shape
    ws, shift = self.window_size, self.shift_size
    y = layer_norm("norm1")(x)
    pad_b, pad_r = (-h) % ws, (-w) % ws
    y = jnp.pad(y, ((0, 0), (0, pad_b), (0, pad_r), (0, 0)))  # zeros after the norm, as upstream
    hp, wp = h + pad_b, w + pad_r
    mask = None
    if shift > 0:
      y = jnp.roll(y, (-shift, -shift), axis=(1, 2))
      mask = shifted_window_mask(hp, wp, ws, shift)
    y = WindowAttention(self.dim, self.num_heads, ws, name="attn")(window_partition(y, ws), mask)
    y = window_reverse(y, ws, b, hp, wp)  # (B, Hp, Wp, C)
    if shift > 0:
      y = jnp.roll(y, (shift, shift), axis=(1, 2))
    x = x + y[:, :h, :w]
    y = layer_norm("norm2")(x)
    y = nn.Dense(int(c * self.mlp_ratio), name="fc1")(y)
    y = nn.gelu(y, approximate=False)
    return x + nn.Dense(c, name="fc2")(y)


class PatchMerging(nn.Module):
  """2x2 neighbourhood concat (x0, x1, x2, x3 as upstream) -> LayerNorm -> linear to 2C."""
  dim: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, H, W, C) -> (B, ceil(H/2), ceil(W/2), 2C)."""
    _, h, w, _ = x.shape
    x = jnp.pad(x, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)))
    x = jnp.concatenate(
        [x[:, 0::2, 0::2], x[:, 1::2, 0::2], x[:, 0::2, 1::2], x[:, 1::2, 1::2]], axis=-1)
    x = layer_norm("norm")(x)
    return nn.Dense(2 * self.dim, use_bias=False, name="reduction")(x)


class SwinTransformer(nn.Module):
  """Swin backbone returning the normalised stage outputs res2..res5 (strides 4..32).

  Submodules: `patch_embed_proj` (conv), `patch_embed_norm`, `stage{i}_block{j}`,
  `stage{i}_downsample` (i < 3), `norm{i}` (output norms).
  """
  config: SwinConfig = SwinConfig()

  @nn.compact
  def __call__(self, x: jax.Array) -> list[jax.Array]:
    """x: (B, H, W, 3) normalised image -> [(B, H/4, W/4, C), ..., (B, H/32, W/32, 8C)]."""
    cfg = self.config
    p = cfg.patch_size
    _, h, w, _ = x.shape
    x = jnp.pad(x, ((0, 0), (0, (-h) % p), (0, (-w) % p), (0, 0)))
    x = nn.Conv(cfg.embed_dim, (p, p), strides=(p, p), padding="VALID",
                name="patch_embed_proj")(x)
    x = layer_norm("patch_embed_norm")(x)  # (B, H/4, W/4, C)
    outs = []
    for i, (depth, heads) in enumerate(zip(cfg.depths, cfg.num_heads)):
      dim = cfg.channels[i]
      for j in range(depth):
        shift = 0 if j % 2 == 0 else cfg.window_size // 2
        x = SwinBlock(dim, heads, cfg.window_size, shift, cfg.mlp_ratio,
                      name=f"stage{i}_block{j}")(x)
      outs.append(layer_norm(f"norm{i}")(x))
      if i < len(cfg.depths) - 1:
        x = PatchMerging(dim, name=f"stage{i}_downsample")(x)
    return outs
