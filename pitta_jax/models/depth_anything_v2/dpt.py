"""Depth Anything V2 (Yang et al. 2024, `depth_anything_v2/dpt.py`, `util/blocks.py`), NHWC.

`DepthAnythingV2` = the DINOv2 ViT (`encoder`, `dinov2.DinoVisionTransformer`) + `DPTHead`
(`depth_head`), returning the affine-invariant relative inverse depth at the input resolution.

DPT head (upstream `DPTHead(use_bn=False, use_clstoken=False)`): the four token maps (1/14) are
projected by 1x1 convs `projects_i` to `out_channels[i]` and resized by `resize_layers_i` to 4x
(transposed conv, kernel = stride = 4), 2x (kernel = stride = 2), 1x (identity, no parameters)
and 1/2 (3x3 conv, stride 2, padding 1); `layer{i}_rn` (3x3, no bias) map them to `features`
channels; RefineNet fusion blocks `refinenet4..1` merge them from the coarsest up (residual conv
units: ReLU, 3x3 conv, ReLU, 3x3 conv, + input; bilinear align_corners=True upsampling to the next
map's size, 2x for the last; 1x1 `out_conv`); then `output_conv1` (3x3, features/2), bilinear
align_corners=True to (14 gh, 14 gw) = the input size, `output_conv2_0` (3x3, 32) + ReLU,
`output_conv2_2` (1x1, 1) + ReLU. Upstream applies another ReLU in `DepthAnythingV2.forward`;
ReLU twice is ReLU once (values and gradients), so it is not repeated here.

The metric models (upstream `metric_depth/depth_anything_v2/dpt.py`, `max_depth` > 0 here) have
the same layers and parameter names; their head ends in a sigmoid instead of the last ReLU, and
the output is that sigmoid times `max_depth`: depth in metres, not relative inverse depth.

Upstream's `refinenet4.resConfUnit1` exists in the checkpoints but is never called (refinenet4
gets one input): it is not created here, and the converter declares those keys ignorable.

Input normalisation: upstream's `image2tensor` divides by 255 and applies ImageNet mean/std
(`NormalizeImage`); here images come in [0, 1] and the model applies mean/std itself.
There is no BatchNorm: `train` (the engine's use-batch-statistics flag) changes nothing.
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax.models.depth_anything_v2.dinov2 import (
    DEFAULT_VARIANT, MLP_RATIO, OFFICIAL_POS_OFFSET, PATCH_SIZE, POS_GRID, VIT_VARIANTS,
    DinoVisionTransformer)
from pitta_jax.models.interpolate import resize_bilinear
from pitta_jax.models.layers import conv

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
HEAD_FEATURES = 32  # upstream's head_features_2
RESIZE_FACTORS = (4, 2, 1, 0.5)  # resize_layers 0..3 (HF: reassemble_factors)


class ConvTransposeNoOverlap(nn.Module):
  """`nn.ConvTranspose2d(c, features, kernel_size=k, stride=k, padding=0)` on NHWC.

  With kernel = stride every input pixel writes its own k x k output block, so the layer is a
  per-pixel linear map followed by a pixel shuffle (one einsum; no dilated convolution).
  Kernel stored as (k, k, features, c), i.e. PyTorch's (c, features, k, k) read as OIHW and
  moved to HWIO (the converter's "conv" kind).
  """
  features: int
  factor: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x: (B, H, W, C) -> (B, k H, k W, features)."""
    b, h, w, c = x.shape
    k = self.factor
    kernel = self.param("kernel", nn.initializers.lecun_normal(), (k, k, self.features, c),
                        jnp.float32)
    bias = self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32)
    y = jnp.einsum("bhwc,ijoc->bhiwjo", x, kernel)  # (B, H, k, W, k, F)
    return y.reshape(b, h * k, w * k, self.features) + bias


class ResidualConvUnit(nn.Module):
  """Upstream `ResidualConvUnit(bn=False)`: x + conv2(relu(conv1(relu(x)))), 3x3 convs with bias."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    c = x.shape[-1]
    y = conv(c, 3, 1, 1, use_bias=True, name="conv1")(nn.relu(x))
    y = conv(c, 3, 1, 1, use_bias=True, name="conv2")(nn.relu(y))
    return y + x


class FeatureFusionBlock(nn.Module):
  """Upstream `FeatureFusionBlock(expand=False, align_corners=True)`.

  out_conv(resize(resConfUnit2(x + resConfUnit1(skip)))) with a bilinear align_corners=True
  resize to `size`, or to twice the size when `size` is None.
  """

  @nn.compact
  def __call__(self, x: jax.Array, skip: jax.Array | None = None,
               size: Sequence[int] | None = None) -> jax.Array:
    """x, skip: (B, h, w, F) -> (B, size..., F)."""
    if skip is not None:
      x = x + ResidualConvUnit(name="resConfUnit1")(skip)
    x = ResidualConvUnit(name="resConfUnit2")(x)
    h, w = x.shape[1], x.shape[2]
    x = resize_bilinear(x, tuple(size) if size is not None else (2 * h, 2 * w), align_corners=True)
    return conv(x.shape[-1], 1, 1, 0, use_bias=True, name="out_conv")(x)


class DPTHead(nn.Module):
  """Upstream `DPTHead(in_channels, features, use_bn=False, out_channels, use_clstoken=False)`."""
  features: int = VIT_VARIANTS[DEFAULT_VARIANT].features
  out_channels: tuple[int, ...] = VIT_VARIANTS[DEFAULT_VARIANT].out_channels
  head_features: int = HEAD_FEATURES
  metric: bool = False  # the metric models' head: sigmoid in place of the last ReLU

  @nn.compact
  def __call__(self, tokens: Sequence[jax.Array]) -> jax.Array:
    """tokens: 4 maps (B, gh, gw, C) -> relative inverse depth (B, 14 gh, 14 gw, 1), >= 0 (with
    `metric`, a sigmoid in (0, 1))."""
    if len(tokens) != 4 or len(self.out_channels) != 4:
      raise ValueError(f"the DPT head takes 4 feature maps and 4 out_channels, got "
                       f"{len(tokens)} and {len(self.out_channels)}")
    gh, gw = tokens[0].shape[1], tokens[0].shape[2]
    layers = []
    for i, (x, ch, factor) in enumerate(zip(tokens, self.out_channels, RESIZE_FACTORS)):
      x = conv(ch, 1, 1, 0, use_bias=True, name=f"projects_{i}")(x)
      if factor > 1:
        x = ConvTransposeNoOverlap(ch, int(factor), name=f"resize_layers_{i}")(x)
      elif factor < 1:
        x = conv(ch, 3, int(1 / factor), 1, use_bias=True, name=f"resize_layers_{i}")(x)
      layers.append(x)  # 4 gh, 2 gh, gh, ceil(gh / 2)
    rn = [conv(self.features, 3, 1, 1, name=f"layer{i + 1}_rn")(x) for i, x in enumerate(layers)]

    path = FeatureFusionBlock(name="refinenet4")(rn[3], size=rn[2].shape[1:3])
    path = FeatureFusionBlock(name="refinenet3")(path, rn[2], size=rn[1].shape[1:3])
    path = FeatureFusionBlock(name="refinenet2")(path, rn[1], size=rn[0].shape[1:3])
    path = FeatureFusionBlock(name="refinenet1")(path, rn[0])  # (B, 8 gh, 8 gw, F)

    out = conv(self.features // 2, 3, 1, 1, use_bias=True, name="output_conv1")(path)
    out = resize_bilinear(out, (gh * PATCH_SIZE, gw * PATCH_SIZE), align_corners=True)
    out = nn.relu(conv(self.head_features, 3, 1, 1, use_bias=True, name="output_conv2_0")(out))
    out = conv(1, 1, 1, 0, use_bias=True, name="output_conv2_2")(out)
    return jax.nn.sigmoid(out) if self.metric else nn.relu(out)


def check_input_size(height: int, width: int) -> None:
  """The ViT cuts 14x14 patches: both sides must be positive multiples of 14."""
  if height <= 0 or width <= 0 or height % PATCH_SIZE or width % PATCH_SIZE:
    raise ValueError(
        f"input size {width}x{height} (WxH) is not supported: Depth Anything V2 needs width and "
        f"height that are positive multiples of {PATCH_SIZE} (e.g. 518x518, 644x196); resize "
        f"the images first")


class DepthAnythingV2(nn.Module):
  """Depth Anything V2: `encoder` (DINOv2 ViT) + `depth_head` (DPT). ViT-S/14 by default.

  Attributes: the encoder's (`dinov2.DinoVisionTransformer`) and the head's (`DPTHead`).
  """
  embed_dim: int = VIT_VARIANTS[DEFAULT_VARIANT].embed_dim
  depth: int = VIT_VARIANTS[DEFAULT_VARIANT].depth
  num_heads: int = VIT_VARIANTS[DEFAULT_VARIANT].num_heads
  mlp_ratio: float = MLP_RATIO
  layer_idx: tuple[int, ...] = VIT_VARIANTS[DEFAULT_VARIANT].layer_idx
  pos_grid: int = POS_GRID
  pos_offset: float = OFFICIAL_POS_OFFSET
  features: int = VIT_VARIANTS[DEFAULT_VARIANT].features
  out_channels: tuple[int, ...] = VIT_VARIANTS[DEFAULT_VARIANT].out_channels
  head_features: int = HEAD_FEATURES
  max_depth: float = 0.0  # 0: the relative model; > 0: a metric model's depth range (metres)

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array]:
    """images: (B, H, W, 3) RGB in [0, 1], H and W multiples of 14 -> a 1-tuple with the
    relative inverse depth (B, H, W, 1) (affine-invariant, >= 0), or with `max_depth` > 0 the
    metric depth in (0, max_depth) metres (upstream's metric models).

    train: accepted for the engine's common call; the network has no BatchNorm or dropout, so
    it changes nothing.
    """
    del train
    if images.ndim != 4 or images.shape[-1] != 3:
      raise ValueError(f"input must be (B, H, W, 3) NHWC RGB, got {images.shape}")
    check_input_size(images.shape[1], images.shape[2])
    mean = np.asarray(IMAGENET_MEAN, np.float32)
    std = np.asarray(IMAGENET_STD, np.float32)
    x = (images - mean) / std
    tokens = DinoVisionTransformer(self.embed_dim, self.depth, self.num_heads, self.mlp_ratio,
                                   tuple(self.layer_idx), self.pos_grid, self.pos_offset,
                                   name="encoder")(x)
    if not (np.isfinite(self.max_depth) and self.max_depth >= 0):
      raise ValueError(f"max_depth must be >= 0 (0 = the relative model), got {self.max_depth}")
    metric = self.max_depth > 0
    depth = DPTHead(self.features, tuple(self.out_channels), self.head_features, metric,
                    name="depth_head")(tokens)
    return (depth * self.max_depth if metric else depth,)
