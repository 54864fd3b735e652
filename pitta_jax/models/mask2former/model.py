"""Mask2Former (Cheng et al. 2022) for COCO panoptic segmentation, inference only, NHWC.

The frozen instance segmenter of PITTA (paper Sec. 3.1, eq. 3). Implements upstream
facebookresearch/Mask2Former: `MultiScaleMaskedTransformerDecoder`
(`transformer_decoder/mask2former_transformer_decoder.py`) on top of the Swin backbone
(`swin.py`) and the deformable-attention pixel decoder (`msdeform.py`), and the inference path
of `MaskFormer.forward` (`maskformer_model.py`): detectron2's preprocessing (RGB 0-255, mean/std,
shortest-edge resize, zero padding to a multiple of 32), mask logits upsampled to the padded
input, cropped and resized back to the image (`sem_seg_postprocess`).

The transformer decoder: 100 learnable queries (features `query_feat`, positions
`query_embed`); 9 post-norm layers of masked cross-attention -> self-attention -> FFN, the
cross-attention of layer i reading level i mod 3 (1/32, 1/16, 1/8) of the pixel decoder plus
a sine position embedding and a level embedding. Its attention mask is the previous prediction
resized to that level: a pixel is blocked where sigmoid(mask logit) < 0.5, and a query whose
pixels are all blocked attends everywhere. Heads (`decoder_norm` -> `class_embed` 133 + 1
and a 3-layer `mask_embed` MLP dotted with the 1/4 mask features) run on the initial queries
and after every layer: 10 predictions, the last being the output (detectron2's `pred_logits`
and `pred_masks`, the first 9 its `aux_outputs`).
"""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax.models.mask2former.msdeform import (MSDeformPixelDecoder, position_embedding_sine,
                                       resize_bilinear)
from pitta_jax.models.mask2former.swin import SwinConfig, SwinTransformer, layer_norm

# detectron2 cfg.MODEL.PIXEL_MEAN / PIXEL_STD of the Swin configs, RGB order, 0-255 pixels.
PIXEL_MEAN = (123.675, 116.28, 103.53)
PIXEL_STD = (58.395, 57.12, 57.375)


@dataclasses.dataclass(frozen=True)
class Mask2FormerConfig:
  """Architecture; defaults = `maskformer2_swin_tiny_bs16_50ep.yaml` (COCO panoptic)."""
  swin: SwinConfig = SwinConfig()
  num_classes: int = 133  # COCO panoptic: 80 things + 53 stuff
  num_queries: int = 100
  hidden_dim: int = 256
  num_heads: int = 8
  dim_feedforward: int = 2048
  dec_layers: int = 9  # cfg DEC_LAYERS 10 = 9 layers + the prediction on the initial queries
  mask_dim: int = 256
  conv_dim: int = 256
  enc_layers: int = 6  # deformable encoder of the pixel decoder
  enc_dim_feedforward: int = 1024
  enc_n_points: int = 4
  num_groups: int = 32

  def to_dict(self) -> dict:
    return dataclasses.asdict(self)

  @classmethod
  def from_dict(cls, d: dict) -> "Mask2FormerConfig":
    d = dict(d)
    swin = d.pop("swin", {})
    swin = SwinConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in swin.items()})
    return cls(swin=swin, **d)


class Attention(nn.Module):
  """`nn.MultiheadAttention` (batch first): separate `q_proj`, `k_proj`, `v_proj`, `out_proj`."""
  dim: int
  num_heads: int

  @nn.compact
  def __call__(self, q: jax.Array, k: jax.Array, v: jax.Array,
               blocked: jax.Array | None = None) -> jax.Array:
    """q: (B, Lq, C), k, v: (B, Lk, C), blocked: (B, Lq, Lk) bool, True = not attended."""
    b, lq, c = q.shape
    h, hd = self.num_heads, c // self.num_heads
    q = nn.Dense(c, name="q_proj")(q).reshape(b, lq, h, hd) * hd**-0.5
    k = nn.Dense(c, name="k_proj")(k).reshape(b, -1, h, hd)
    v = nn.Dense(c, name="v_proj")(v).reshape(b, -1, h, hd)
    logits = jnp.einsum("bqhd,bkhd->bhqk", q, k)
    if blocked is not None:
      logits = jnp.where(blocked[:, None], -jnp.inf, logits)
    attn = jax.nn.softmax(logits, axis=-1)
    out = jnp.einsum("bhqk,bkhd->bqhd", attn, v).reshape(b, lq, c)
    return nn.Dense(c, name="out_proj")(out)


class DecoderLayer(nn.Module):
  """Masked cross-attention -> self-attention -> FFN, each residual + post LayerNorm."""
  dim: int
  num_heads: int
  dim_feedforward: int

  @nn.compact
  def __call__(self, x: jax.Array, query_pos: jax.Array, memory: jax.Array,
               memory_pos: jax.Array, blocked: jax.Array) -> jax.Array:
    """x, query_pos: (B, Q, C); memory, memory_pos: (B, HW, C); blocked: (B, Q, HW)."""
    y = Attention(self.dim, self.num_heads, name="cross_attn")(
        x + query_pos, memory + memory_pos, memory, blocked)
    x = layer_norm("cross_norm")(x + y)
    qk = x + query_pos
    y = Attention(self.dim, self.num_heads, name="self_attn")(qk, qk, x)
    x = layer_norm("self_norm")(x + y)
    y = nn.Dense(self.dim_feedforward, name="linear1")(x)
    y = nn.Dense(self.dim, name="linear2")(nn.relu(y))
    return layer_norm("ffn_norm")(x + y)


class MaskedTransformerDecoder(nn.Module):
  """`MultiScaleMaskedTransformerDecoder` (mask classification, 3 levels, no input projection).

  Params: `query_feat`, `query_embed` (Q, C), `level_embed` (3, C); submodules `layer{i}`,
  `decoder_norm`, `class_embed`, `mask_embed_{0,1,2}`.
  """
  config: Mask2FormerConfig = Mask2FormerConfig()

  def setup(self):
    cfg = self.config
    c = cfg.hidden_dim
    self.query_feat = self.param("query_feat", nn.initializers.normal(1.0),
                                 (cfg.num_queries, c), jnp.float32)
    self.query_embed = self.param("query_embed", nn.initializers.normal(1.0),
                                  (cfg.num_queries, c), jnp.float32)
    self.level_embed = self.param("level_embed", nn.initializers.normal(1.0), (3, c), jnp.float32)
    self.layers = [DecoderLayer(c, cfg.num_heads, cfg.dim_feedforward, name=f"layer{i}")
                   for i in range(cfg.dec_layers)]
    self.decoder_norm = layer_norm("decoder_norm")
    self.class_embed = nn.Dense(cfg.num_classes + 1, name="class_embed")
    self.mask_embed = [nn.Dense(c, name="mask_embed_0"), nn.Dense(c, name="mask_embed_1"),
                       nn.Dense(cfg.mask_dim, name="mask_embed_2")]

  def heads(self, x: jax.Array, mask_features: jax.Array, target: tuple[int, int]
            ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Predictions of queries x (B, Q, C) and the attention mask for a level of size `target`.

    Returns: class logits (B, Q, K + 1), mask logits (B, Q, H/4, W/4), blocked (B, Q, h * w).
    """
    y = self.decoder_norm(x)
    logits = self.class_embed(y)
    e = nn.relu(self.mask_embed[0](y))
    e = self.mask_embed[2](nn.relu(self.mask_embed[1](e)))  # (B, Q, mask_dim)
    masks = jnp.einsum("bqc,bhwc->bqhw", e, mask_features)
    small = resize_bilinear(masks, target, axes=(2, 3))  # (B, Q, h, w)
    blocked = jax.lax.stop_gradient(jax.nn.sigmoid(small.reshape(*small.shape[:2], -1)) < 0.5)
    return logits, masks, blocked

  def __call__(self, multi_scale: list[jax.Array], mask_features: jax.Array
               ) -> tuple[jax.Array, jax.Array, list[jax.Array]]:
    """Runs the decoder.

    Args:
      multi_scale: [(B, H/32, W/32, C), (B, H/16, W/16, C), (B, H/8, W/8, C)].
      mask_features: (B, H/4, W/4, mask_dim).

    Returns:
      class logits (L + 1, B, Q, K + 1) and mask logits (L + 1, B, Q, H/4, W/4), from the
      initial queries and after each of the L layers (the last entry is the model output),
      and the L attention masks (B, Q, h_l * w_l) bool (True = blocked) as predicted for
      layer l, before all-blocked rows are opened.
    """
    b = mask_features.shape[0]
    c = self.config.hidden_dim
    sizes = [(f.shape[1], f.shape[2]) for f in multi_scale]
    memory, memory_pos = [], []
    for i, f in enumerate(multi_scale):
      pe = position_embedding_sine(f.shape[1], f.shape[2], c // 2).reshape(1, -1, c)
      memory_pos.append(jnp.asarray(pe))
      memory.append(f.reshape(b, -1, c) + self.level_embed[i][None, None])
    query_pos = jnp.broadcast_to(self.query_embed[None], (b,) + self.query_embed.shape)
    x = jnp.broadcast_to(self.query_feat[None], (b,) + self.query_feat.shape)
    logits, masks, blocked = self.heads(x, mask_features, sizes[0])
    all_logits, all_masks, attention_masks = [logits], [masks], []
    for i, layer in enumerate(self.layers):
      lvl = i % 3
      attention_masks.append(blocked)
      everything = jnp.all(blocked, axis=-1, keepdims=True)
      blocked = blocked & ~everything  # a query with nothing to attend attends everywhere
      x = layer(x, query_pos, memory[lvl], memory_pos[lvl], blocked)
      logits, masks, blocked = self.heads(x, mask_features, sizes[(i + 1) % 3])
      all_logits.append(logits)
      all_masks.append(masks)
    return jnp.stack(all_logits), jnp.stack(all_masks), attention_masks


class Mask2Former(nn.Module):
  """Backbone -> pixel decoder -> masked transformer decoder.

  Submodules: `backbone` (SwinTransformer), `pixel_decoder`, `predictor`.
  """
  config: Mask2FormerConfig = Mask2FormerConfig()

  @nn.compact
  def __call__(self, images: jax.Array, return_features: bool = False) -> dict[str, jax.Array]:
    """images: (B, H, W, 3) normalised ((rgb255 - mean) / std), H and W multiples of 32.

    Returns a dict with `pred_logits` (L + 1, B, Q, K + 1) and `pred_masks`
    (L + 1, B, Q, H/4, W/4) (see `MaskedTransformerDecoder`), and with `return_features` also
    `backbone` (res2..res5), `multi_scale` (1/32, 1/16, 1/8) and `mask_features` (1/4), NHWC,
    and the decoder's `attention_masks` (L of (B, Q, h_l * w_l) bool).
    """
    cfg = self.config
    feats = SwinTransformer(cfg.swin, name="backbone")(images)
    mask_features, multi_scale = MSDeformPixelDecoder(
        conv_dim=cfg.conv_dim, mask_dim=cfg.mask_dim, num_layers=cfg.enc_layers,
        n_heads=cfg.num_heads, n_points=cfg.enc_n_points, d_ffn=cfg.enc_dim_feedforward,
        num_groups=cfg.num_groups, name="pixel_decoder")(feats)
    logits, masks, attention_masks = MaskedTransformerDecoder(cfg, name="predictor")(
        multi_scale, mask_features)
    out = {"pred_logits": logits, "pred_masks": masks}
    if return_features:
      out.update(backbone=feats, multi_scale=multi_scale, mask_features=mask_features,
                 attention_masks=attention_masks)
    return out


# ------------------------------------------------------------------------------ inference


@dataclasses.dataclass(frozen=True)
class InferenceConfig:
  """detectron2's test-time settings for Mask2Former COCO panoptic.

  input_size: (H, W) to resize every image to (e.g. the frame size, no resize), or None for
  `ResizeShortestEdge(min_size, max_size)`.
  """
  min_size: int = 800  # cfg.INPUT.MIN_SIZE_TEST
  max_size: int = 1333  # cfg.INPUT.MAX_SIZE_TEST
  input_size: tuple[int, int] | None = None
  size_divisibility: int = 32
  object_mask_threshold: float = 0.8  # cfg.MODEL.MASK_FORMER.TEST.OBJECT_MASK_THRESHOLD
  overlap_threshold: float = 0.8  # cfg.MODEL.MASK_FORMER.TEST.OVERLAP_THRESHOLD


def resized_shape(height: int, width: int, cfg: InferenceConfig) -> tuple[int, int]:
  """Network input size before padding: `cfg.input_size`, or detectron2's ResizeShortestEdge."""
  if cfg.input_size is not None:
    return tuple(cfg.input_size)
  scale = cfg.min_size / min(height, width)
  new_h, new_w = (cfg.min_size, scale * width) if height < width else (scale * height, cfg.min_size)
  if max(new_h, new_w) > cfg.max_size:
    s = cfg.max_size / max(new_h, new_w)
    new_h, new_w = new_h * s, new_w * s
  size = int(new_h + 0.5), int(new_w + 0.5)
  if min(size) < 1:  # an extreme aspect: the short edge rounds to nothing (upstream fails too)
    raise ValueError(f"a {height}x{width} image resized to at most {cfg.max_size} pixels a side "
                     f"is {size[0]}x{size[1]}: too thin for the detectron2 resize; give an "
                     f"input size instead")
  return size


def preprocess(image: jax.Array, size: tuple[int, int], divisibility: int = 32) -> jax.Array:
  """image (H, W, 3) RGB in [0, 1] -> (1, Hp, Wp, 3) normalised, zero-padded network input.

  Resizing (when `size` differs from the image) is linear with antialiasing on 0-255 values,
  close to the PIL bilinear resize detectron2 applies (PIL also rounds to uint8; we do not).
  Padding happens after normalisation (detectron2's `ImageList.from_tensors` pads with 0).
  """
  x = image.astype(jnp.float32) * 255.0
  if tuple(image.shape[:2]) != tuple(size):
    x = jax.image.resize(x, (*size, 3), method="linear", antialias=True)
  x = (x - jnp.asarray(PIXEL_MEAN)) / jnp.asarray(PIXEL_STD)
  ph, pw = (-size[0]) % divisibility, (-size[1]) % divisibility
  return jnp.pad(x, ((0, ph), (0, pw), (0, 0)))[None]


def mask_logits_to_image(masks: jax.Array, size: tuple[int, int], image_hw: tuple[int, int],
                         divisibility: int = 32) -> jax.Array:
  """(Q, H/4, W/4) logits -> (Q, H0, W0): upsample to the padded input, crop, resize to image.

  detectron2: `F.interpolate` to the padded size, then `sem_seg_postprocess` (crop to the
  resized image, bilinear to the original size), all bilinear with align_corners=False.
  """
  padded = (size[0] + (-size[0]) % divisibility, size[1] + (-size[1]) % divisibility)
  x = resize_bilinear(masks, padded, axes=(1, 2))[:, :size[0], :size[1]]
  return resize_bilinear(x, image_hw, axes=(1, 2))


@functools.partial(jax.jit, static_argnums=0)
def network(module: Mask2Former, variables, images: jax.Array) -> dict[str, jax.Array]:
  """`module.apply(variables, images, return_features=True)`, jitted: one compile per module
  and input shape, shared by every caller (`predict`, `segment`, the parity tests)."""
  return module.apply(variables, images, return_features=True)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _preprocess(image: jax.Array, size: tuple[int, int], divisibility: int) -> jax.Array:
  return preprocess(image, size, divisibility)


@functools.partial(jax.jit, static_argnums=(2, 3, 4))
def _final_prediction(logits: jax.Array, masks: jax.Array, size: tuple[int, int],
                      image_hw: tuple[int, int], divisibility: int) -> tuple[jax.Array, jax.Array]:
  return logits[-1, 0], mask_logits_to_image(masks[-1, 0], size, image_hw, divisibility)


def predict(module: Mask2Former, variables, image, cfg: InferenceConfig = InferenceConfig()
            ) -> tuple[jax.Array, jax.Array]:
  """image (H, W, 3) float32 RGB in [0, 1] -> class logits (Q, K + 1), mask logits (Q, H, W).

  The output of the last decoder layer (detectron2's `pred_logits`, `pred_masks`), the masks
  resized back to the image. Three jitted steps (preprocess, `network`, resize), each
  compiled once per shape.
  """
  image = jnp.asarray(image, jnp.float32)
  image_hw = tuple(image.shape[:2])
  size = resized_shape(*image_hw, cfg)
  out = network(module, variables, _preprocess(image, size, cfg.size_divisibility))
  return _final_prediction(out["pred_logits"], out["pred_masks"], size, image_hw,
                           cfg.size_divisibility)


def segment(module: Mask2Former, variables, image, cfg: InferenceConfig = InferenceConfig(),
            is_thing: np.ndarray | None = None, contiguous_to_id: np.ndarray | None = None):
  """Panoptic segmentation of one image (the PITTA integration API, paper Sec. 3.1).

  Args:
    module, variables: from `pitta_jax.models.mask2former.load_mask2former(dir)`.
    image: (H, W, 3) float32 RGB in [0, 1].
    cfg: preprocessing and post-processing thresholds.
    is_thing: (K,) bool per contiguous class; default COCO panoptic's (`coco.is_thing_table`).
    contiguous_to_id: (K,) category id per contiguous class; default COCO panoptic's ids.

  Returns:
    id_map (H, W) int32 (0 = void, segments numbered from 1) and a tuple of
    `pitta_jax.data.frame.Segment(id, category_id, isthing)` with COCO category ids, the
    format of `Frame.panoptic` / `Frame.segments`.
  """
  from pitta_jax import panoptic
  logits, masks = predict(module, variables, image, cfg)
  id_map, segments = panoptic.panoptic_inference(
      np.asarray(logits), np.asarray(masks), is_thing=is_thing,
      object_mask_threshold=cfg.object_mask_threshold, overlap_threshold=cfg.overlap_threshold)
  return id_map, panoptic.to_frame_segments(segments, contiguous_to_id)
