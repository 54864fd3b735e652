"""Mask2Former's pixel decoder: multi-scale deformable attention encoder + FPN path, NHWC.

Implements upstream facebookresearch/Mask2Former `pixel_decoder/msdeformattn.py`
(`MSDeformAttnPixelDecoder`, `MSDeformAttnTransformerEncoderOnly`) and the deformable
attention of Deformable DETR (Zhu et al. 2021, `MSDeformAttn` and its PyTorch reference
`ms_deform_attn_core_pytorch`), plus two helpers the whole model shares:

- `position_embedding_sine`: DETR's normalised sine embedding (`PositionEmbeddingSine`,
  normalize=True, scale 2 pi, temperature 10000), a constant of the feature map size.
- `resize_bilinear`: `F.interpolate(mode="bilinear", align_corners=False)` (no antialiasing),
  separable two-tap gathers with PyTorch's source index rule.

Deformable attention samples the value maps bilinearly with explicit gathers, matching
`F.grid_sample(mode="bilinear", padding_mode="zeros", align_corners=False)`: a sampling
location (x, y) in [0, 1] reads pixel coordinates (x W - 0.5, y H - 0.5); corners outside the
map contribute zero.

The encoder runs on res3..res5 (levels ordered 1/32, 1/16, 1/8 as upstream, `input_proj[0]`
and `level_embed[0]` belong to 1/32); the FPN adds res2 with a lateral 1x1 conv + GroupNorm
and a 3x3 conv + GroupNorm + ReLU after the bilinearly upsampled coarser level, and
`mask_features` (1x1 conv) gives the per-pixel embeddings at 1/4.
Numerics as PyTorch: LayerNorm and GroupNorm(32) with eps 1e-5 and the two-pass variance.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax.models.mask2former.swin import layer_norm


def group_norm(name: str, groups: int = 32) -> nn.GroupNorm:
  """`torch.nn.GroupNorm(groups, C)` numerics (eps 1e-5) over (H, W, C // groups) per group."""
  return nn.GroupNorm(num_groups=groups, epsilon=1e-5, use_fast_variance=False, name=name)


def position_embedding_sine(height: int, width: int, num_pos_feats: int = 128,
                            temperature: float = 10000.0) -> np.ndarray:
  """(H, W, 2 * num_pos_feats) float32: [y features, x features], each sin/cos interleaved.

  Upstream `PositionEmbeddingSine(normalize=True)` without a padding mask: cumulative
  coordinates 1..H (1..W) divided by (H + 1e-6) and scaled by 2 pi, float32 throughout.
  """
  f32 = np.float32
  scale = f32(2 * math.pi)
  y = (np.arange(1, height + 1, dtype=f32) / (f32(height) + f32(1e-6))) * scale  # (H,)
  x = (np.arange(1, width + 1, dtype=f32) / (f32(width) + f32(1e-6))) * scale  # (W,)
  i = np.arange(num_pos_feats, dtype=f32)
  dim_t = np.power(f32(temperature), f32(2) * np.floor(i / f32(2)) / f32(num_pos_feats))

  def encode(coord: np.ndarray) -> np.ndarray:  # (N,) -> (N, num_pos_feats)
    pos = coord[:, None] / dim_t
    return np.stack([np.sin(pos[:, 0::2]), np.cos(pos[:, 1::2])], axis=-1).reshape(len(coord), -1)

  pos_y = np.broadcast_to(encode(y)[:, None, :], (height, width, num_pos_feats))
  pos_x = np.broadcast_to(encode(x)[None, :, :], (height, width, num_pos_feats))
  return np.concatenate([pos_y, pos_x], axis=-1).astype(f32)


def _linear_taps(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Indices i0, i1 (out,) int32 and weight of i1 (out,) float32 of PyTorch's bilinear resize.

  `area_pixel_compute_source_index`: src = (dst + 0.5) * in / out - 0.5, clamped at 0;
  i1 = i0 + 1 unless i0 is the last pixel.
  """
  scale = np.float32(in_size) / np.float32(out_size)
  src = np.maximum(scale * (np.arange(out_size, dtype=np.float32) + np.float32(0.5))
                   - np.float32(0.5), np.float32(0))
  i0 = src.astype(np.int32)
  i1 = np.minimum(i0 + 1, in_size - 1).astype(np.int32)
  return i0, i1, (src - i0).astype(np.float32)


def _resize_axis(x: jax.Array, size: int, axis: int) -> jax.Array:
  if x.shape[axis] == size:
    return x
  i0, i1, lam = _linear_taps(x.shape[axis], size)
  shape = [1] * x.ndim
  shape[axis] = size
  lam = jnp.asarray(lam).reshape(shape)
  return jnp.take(x, i0, axis=axis) * (1 - lam) + jnp.take(x, i1, axis=axis) * lam


def resize_bilinear(x: jax.Array, size: tuple[int, int], axes: tuple[int, int] = (1, 2)
                    ) -> jax.Array:
  """`F.interpolate(x, size, mode="bilinear", align_corners=False)` over `axes` (H, W)."""
  return _resize_axis(_resize_axis(x, size[0], axes[0]), size[1], axes[1])


def ms_deform_attn_core(value: jax.Array, shapes: tuple[tuple[int, int], ...],
                        locations: jax.Array, weights: jax.Array) -> jax.Array:
  """Multi-scale deformable attention sampling (Deformable DETR's `ms_deform_attn_core`).

  Args:
    value: (B, S, M, D) values of all levels flattened row-major, S = sum H_l W_l.
    shapes: static ((H_0, W_0), ...) of the L levels in the order of `value`.
    locations: (B, Lq, M, L, P, 2) sampling points (x, y) in [0, 1] per level.
    weights: (B, Lq, M, L, P) attention weights (softmax over L * P).

  Returns:
    (B, Lq, M * D): per head the weighted sum of bilinear samples (zero outside the maps).
  """
  b, _, m, d = value.shape
  lq = locations.shape[1]
  size = np.array(shapes, np.float32)  # (L, 2) as (H, W)
  starts = np.concatenate([[0], np.cumsum([h * w for h, w in shapes])[:-1]]).astype(np.int32)
  x = locations[..., 0] * size[None, None, None, :, None, 1] - 0.5  # (B, Lq, M, L, P)
  y = locations[..., 1] * size[None, None, None, :, None, 0] - 0.5
  x0, y0 = jnp.floor(x), jnp.floor(y)
  fx, fy = x - x0, y - y0
  hs = jnp.asarray(size[:, 0])[None, None, None, :, None]
  ws = jnp.asarray(size[:, 1])[None, None, None, :, None]
  start = jnp.asarray(starts)[None, None, None, :, None]
  idx, wgt = [], []
  for dy, wy in ((0, 1 - fy), (1, fy)):
    for dx, wx in ((0, 1 - fx), (1, fx)):
      xi, yi = x0 + dx, y0 + dy
      valid = (xi >= 0) & (xi < ws) & (yi >= 0) & (yi < hs)
      flat = jnp.clip(yi, 0, hs - 1) * ws + jnp.clip(xi, 0, ws - 1)
      idx.append(start + flat.astype(jnp.int32))
      wgt.append(jnp.where(valid, wy * wx, 0.0) * weights)
  idx = jnp.stack(idx, -1).transpose(0, 2, 1, 3, 4, 5).reshape(b, m, lq, -1)  # (B, M, Lq, K)
  wgt = jnp.stack(wgt, -1).transpose(0, 2, 1, 3, 4, 5).reshape(b, m, lq, -1)
  v = value.transpose(0, 2, 1, 3)  # (B, M, S, D)
  k = idx.shape[-1]
  take_rows = jax.vmap(jax.vmap(lambda table, rows: jnp.take(table, rows, axis=0)))
  gathered = take_rows(v, idx.reshape(b, m, lq * k)).reshape(b, m, lq, k, d)
  out = jnp.einsum("bmqk,bmqkd->bqmd", wgt, gathered)
  return out.reshape(b, lq, m * d)


class MSDeformAttn(nn.Module):
  """Deformable attention (`MSDeformAttn`): per query, M heads x L levels x P points.

  Params: `sampling_offsets`, `attention_weights`, `value_proj`, `output_proj` (Dense).
  """
  d_model: int = 256
  n_levels: int = 3
  n_heads: int = 8
  n_points: int = 4

  @nn.compact
  def __call__(self, query: jax.Array, reference_points: jax.Array, value_in: jax.Array,
               shapes: tuple[tuple[int, int], ...]) -> jax.Array:
    """query: (B, Lq, C); reference_points: (B | 1, Lq, L, 2); value_in: (B, S, C) -> (B, Lq, C)."""
    b, lq, _ = query.shape
    m, lv, p = self.n_heads, self.n_levels, self.n_points
    value = nn.Dense(self.d_model, name="value_proj")(value_in)
    value = value.reshape(b, value.shape[1], m, self.d_model // m)
    offsets = nn.Dense(m * lv * p * 2, name="sampling_offsets")(query).reshape(b, lq, m, lv, p, 2)
    attn = nn.Dense(m * lv * p, name="attention_weights")(query).reshape(b, lq, m, lv * p)
    attn = jax.nn.softmax(attn, axis=-1).reshape(b, lq, m, lv, p)
    normalizer = jnp.asarray([[w, h] for h, w in shapes], jnp.float32)  # (L, 2) as (W, H)
    locations = (reference_points[:, :, None, :, None, :]
                 + offsets / normalizer[None, None, None, :, None, :])
    out = ms_deform_attn_core(value, shapes, locations, attn)
    return nn.Dense(self.d_model, name="output_proj")(out)


class MSDeformEncoderLayer(nn.Module):
  """Post-norm deformable self-attention + ReLU FFN (`MSDeformAttnTransformerEncoderLayer`)."""
  d_model: int = 256
  d_ffn: int = 1024
  n_levels: int = 3
  n_heads: int = 8
  n_points: int = 4

  @nn.compact
  def __call__(self, src: jax.Array, pos: jax.Array, reference_points: jax.Array,
               shapes: tuple[tuple[int, int], ...]) -> jax.Array:
    """src, pos: (B, S, C); reference_points: (1, S, L, 2) -> (B, S, C)."""
    attn = MSDeformAttn(self.d_model, self.n_levels, self.n_heads, self.n_points,
                        name="self_attn")(src + pos, reference_points, src, shapes)
    src = layer_norm("norm1")(src + attn)
    y = nn.Dense(self.d_model, name="linear2")(nn.relu(nn.Dense(self.d_ffn, name="linear1")(src)))
    return layer_norm("norm2")(src + y)


def encoder_reference_points(shapes: tuple[tuple[int, int], ...]) -> np.ndarray:
  """(1, S, L, 2) pixel-centre reference points (x, y) in [0, 1] of every level, no padding."""
  refs = []
  for h, w in shapes:
    ry, rx = np.meshgrid((np.arange(h, dtype=np.float32) + np.float32(0.5)) / np.float32(h),
                         (np.arange(w, dtype=np.float32) + np.float32(0.5)) / np.float32(w),
                         indexing="ij")
    refs.append(np.stack([rx.reshape(-1), ry.reshape(-1)], -1))
  ref = np.concatenate(refs, 0)  # (S, 2)
  return np.broadcast_to(ref[None, :, None, :], (1, len(ref), len(shapes), 2)).copy()


class MSDeformPixelDecoder(nn.Module):
  """`MSDeformAttnPixelDecoder`: deformable encoder on the 3 coarsest maps + FPN to stride 4.

  Submodules: `input_proj{l}_conv/_norm` (l = 0 is the coarsest level), param `level_embed`
  (L, C), `encoder_layer{k}`, `adapter{i}_conv/_norm` and `layer{i}_conv/_norm` for the FPN
  levels (i = 1 is res2, as upstream's `adapter_1` / `layer_1`), `mask_features`.
  """
  conv_dim: int = 256
  mask_dim: int = 256
  num_layers: int = 6
  n_heads: int = 8
  n_points: int = 4
  d_ffn: int = 1024
  num_transformer_levels: int = 3  # res3, res4, res5
  num_groups: int = 32

  @nn.compact
  def __call__(self, features: list[jax.Array]) -> tuple[jax.Array, list[jax.Array]]:
    """features: backbone maps res2..res5 [(B, H/4, W/4, C0), ..., (B, H/32, W/32, C3)].

    Returns:
      mask_features (B, H/4, W/4, mask_dim) and the multi-scale features
      [(B, H/32, W/32, C), (B, H/16, W/16, C), (B, H/8, W/8, C)] for the transformer decoder.
    """
    nl = self.num_transformer_levels
    c = self.conv_dim
    level_embed = self.param("level_embed", nn.initializers.normal(1.0), (nl, c), jnp.float32)
    srcs = features[::-1][:nl]  # coarse to fine: res5, res4, res3
    shapes = tuple((f.shape[1], f.shape[2]) for f in srcs)
    b = srcs[0].shape[0]
    flat, pos = [], []
    for lvl, f in enumerate(srcs):
      y = nn.Conv(c, (1, 1), name=f"input_proj{lvl}_conv")(f)
      y = group_norm(f"input_proj{lvl}_norm", self.num_groups)(y)
      flat.append(y.reshape(b, -1, c))
      pe = position_embedding_sine(f.shape[1], f.shape[2], c // 2).reshape(1, -1, c)
      pos.append(jnp.asarray(pe) + level_embed[lvl][None, None, :])
    src, pos = jnp.concatenate(flat, 1), jnp.concatenate(pos, 1)  # (B, S, C), (1, S, C)
    ref = jnp.asarray(encoder_reference_points(shapes))
    for k in range(self.num_layers):
      src = MSDeformEncoderLayer(c, self.d_ffn, nl, self.n_heads, self.n_points,
                                 name=f"encoder_layer{k}")(src, pos, ref, shapes)
    outs, start = [], 0
    for h, w in shapes:
      outs.append(src[:, start:start + h * w].reshape(b, h, w, c))
      start += h * w
    num_fpn = len(features) - nl  # res2 only, for strides (4, 8, 16, 32) and common stride 4
    for i in range(num_fpn, 0, -1):  # coarse to fine; upstream's index idx + 1
      f = features[i - 1]
      lateral = nn.Conv(c, (1, 1), use_bias=False, name=f"adapter{i}_conv")(f)
      lateral = group_norm(f"adapter{i}_norm", self.num_groups)(lateral)
      y = lateral + resize_bilinear(outs[-1], lateral.shape[1:3])
      y = nn.Conv(c, (3, 3), padding=((1, 1), (1, 1)), use_bias=False, name=f"layer{i}_conv")(y)
      outs.append(nn.relu(group_norm(f"layer{i}_norm", self.num_groups)(y)))
    mask_features = nn.Conv(self.mask_dim, (1, 1), name="mask_features")(outs[-1])
    return mask_features, outs[:nl]
