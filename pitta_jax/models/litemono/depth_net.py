"""Lite-Mono's depth decoder (noahzn/Lite-Mono `networks/depth_decoder.py`) and the depth network.

Decoder: from the 1/16 feature map up, three stages i = 2, 1, 0, each `upconv_i_0` (3x3 conv,
reflection padding, ELU), bilinear x2 upsampling (align_corners=False), concatenation with the
encoder map `features[i - 1]` (i > 0), `upconv_i_1` (3x3 conv, reflection padding, ELU), with
dims[i] // 2 channels. A disparity head per scale s = 0..2: `dispconv_s` (3x3 conv, reflection
padding), bilinear x2 upsampling, sigmoid; scale s is at 1/2**s of the input resolution.

`LiteMono` = `LiteMonoEncoder` (name "encoder") + `LiteMonoDecoder` (name "decoder"); its
variables are what `weights_convert.litemono` writes. Depth = MonoDepth2's `disp_to_depth`
with (0.1, 100), as upstream's evaluation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import flax.linen as nn

from pitta_jax.models.depth_decoder import conv3x3_reflect
from pitta_jax.models.interpolate import resize_bilinear
from pitta_jax.models.litemono.encoder import VARIANTS, LiteMonoEncoder, dilations_for

SCALES = (0, 1, 2)  # upstream's default `--scales`
SIZE_MULTIPLE = 16  # three stride-2 decoder merges on a 1/4-resolution trunk: exact skip sizes


def upsample_bilinear2x(x: jax.Array) -> jax.Array:
  """Upstream `upsample(x)`: F.interpolate(scale_factor=2, mode="bilinear"), align_corners=False."""
  return resize_bilinear(x, (2 * x.shape[1], 2 * x.shape[2]), align_corners=False)


class LiteMonoDecoder(nn.Module):
  """Upstream `DepthDecoder(num_ch_enc, scales, num_output_channels=1, use_skips=True)`."""
  scales: tuple[int, ...] = SCALES
  num_output_channels: int = 1

  @nn.compact
  def __call__(self, features: list[jax.Array]) -> tuple[jax.Array, ...]:
    """features: the encoder's 3 maps -> disparities in (0, 1), one per scale in `scales`
    order, each (B, H / 2**s, W / 2**s, num_output_channels)."""
    x = features[-1]
    disps = {}
    for i in range(2, -1, -1):
      channels = features[i].shape[-1] // 2  # upstream num_ch_dec = (num_ch_enc / 2).astype(int)
      x = nn.elu(conv3x3_reflect(x, channels, f"upconv_{i}_0"))
      x = upsample_bilinear2x(x)
      if i > 0:
        x = jnp.concatenate([x, features[i - 1]], axis=-1)
      x = nn.elu(conv3x3_reflect(x, channels, f"upconv_{i}_1"))
      if i in self.scales:
        disp = conv3x3_reflect(x, self.num_output_channels, f"dispconv_{i}")
        disps[i] = nn.sigmoid(upsample_bilinear2x(disp))
    return tuple(disps[s] for s in self.scales)


class LiteMono(nn.Module):
  """Lite-Mono depth network: `encoder` + `decoder`.

  Attributes:
    model: the model size, a key of `encoder.VARIANTS` ("lite-mono" is the base model).
    height, width: the size the weights were trained at; it selects upstream's dilation rates
      (the network then runs at any size that is a multiple of `SIZE_MULTIPLE`).
  """
  model: str
  height: int
  width: int

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array, ...]:
    """images: (B, H, W, 3) RGB in [0, 1], H and W multiples of 16 -> 3 disparity maps
    (B, H / 2**s, W / 2**s, 1), s = 0..2.

    train: use the batch's BN statistics (PyTorch train mode); the running estimates are
    updated only when `batch_stats` is passed as mutable.
    """
    if images.ndim != 4 or images.shape[-1] != 3:
      raise ValueError(f"Lite-Mono input must be (B, H, W, 3) NHWC, got {images.shape}")
    check_input_size(images.shape[1], images.shape[2])
    dilations = dilations_for(self.model, self.height, self.width)  # ValueError if unknown
    variant = VARIANTS[self.model]
    features = LiteMonoEncoder(variant.dims, variant.depths, dilations, name="encoder")(
        images, train)
    return LiteMonoDecoder(name="decoder")(features)


def check_input_size(height: int, width: int) -> None:
  """Lite-Mono's skips need sides divisible by 16 (a 1/4 trunk, then two stride-2 stages
  merged back by x2 upsampling; the full-resolution output is 4x the 1/4 map)."""
  m = SIZE_MULTIPLE
  if height % m or width % m or height <= 0 or width <= 0:
    raise ValueError(
        f"input size {width}x{height} (WxH) is not supported: Lite-Mono needs width and height "
        f"that are positive multiples of {m} (e.g. 640x192, 320x96); resize the images first")
