"""MonoDepth2's depth decoder (`networks/depth_decoder.py`) and the depth network, NHWC.

Decoder: from the 1/32 feature map up to full resolution, five stages i = 4..0, each
`upconv_i_0` (3x3 conv, reflection padding, ELU), nearest x2 upsampling, concatenation with the
encoder skip `features[i - 1]` (i > 0), `upconv_i_1` (3x3 conv, reflection padding, ELU); the
last three steps run as one layer (`layers.UpConv3x3`, which from 320x96 inputs never builds
the upsampled map: `layers.phase_form_pays`).
Channels (16, 32, 64, 128, 256). A sigmoid disparity head `dispconv_s` (3x3 conv, reflection
padding) at scales s = 0..3, scale s at 1/2**s of the input resolution.

`DepthNet` = `ResnetEncoder` (name "encoder") + `DepthDecoder` (name "decoder"); its variables
are what `weights_convert monodepth2` writes. `disp_to_depth` is MonoDepth2's.
"""

from __future__ import annotations

import jax
import flax.linen as nn

from pitta_jax.models.layers import Conv, ModuleDef, ReflectConv3x3, UpConv3x3
from pitta_jax.models.resnet import ResnetEncoder, encoder_channels

DECODER_CHANNELS = (16, 32, 64, 128, 256)
SCALES = (0, 1, 2, 3)
MIN_DEPTH, MAX_DEPTH = 0.1, 100.0  # MonoDepth2's defaults


def conv3x3_reflect(x: jax.Array, features: int, name: str, module: ModuleDef = Conv) -> jax.Array:
  """MonoDepth2's `Conv3x3(use_refl=True)`: ReflectionPad2d(1) then a 3x3 conv with bias,
  (B, H, W, C) -> (B, H, W, features), as `layers.ReflectConv3x3` named `name` (parameters of
  `nn.Conv`); `module` is the network's conv class."""
  return ReflectConv3x3(features, module, name=name)(x)


class DepthDecoder(nn.Module):
  """MonoDepth2's `DepthDecoder(num_ch_enc, scales=range(4), num_output_channels=1, use_skips=True)`."""
  scales: tuple[int, ...] = SCALES
  num_output_channels: int = 1
  conv: ModuleDef = Conv  # the convolution class of every layer

  @nn.compact
  def __call__(self, features: list[jax.Array]) -> tuple[jax.Array, ...]:
    """features: the encoder's 5 maps -> disparities, one per scale in `scales` order,
    each (B, H / 2**s, W / 2**s, num_output_channels) in (0, 1)."""
    x = features[-1]
    disps = {}
    for i in range(4, -1, -1):
      x = nn.elu(conv3x3_reflect(x, DECODER_CHANNELS[i], f"upconv_{i}_0", self.conv))
      # upconv_i_1 of concat([upsample_nearest2x(x), features[i - 1]]), as one layer
      skip = features[i - 1] if i > 0 else None
      x = nn.elu(UpConv3x3(DECODER_CHANNELS[i], self.conv, name=f"upconv_{i}_1")(x, skip))
      if i in self.scales:
        disps[i] = nn.sigmoid(conv3x3_reflect(x, self.num_output_channels, f"dispconv_{i}", self.conv))
    return tuple(disps[s] for s in self.scales)


class DepthNet(nn.Module):
  """MonoDepth2 depth network: `encoder` + `decoder`.

  Attributes:
    num_layers: ResNet depth of the encoder (18, 34, 50).
  """
  num_layers: int = 18
  conv: ModuleDef = Conv  # the convolution class of every layer (benchmarks swap it)

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array, ...]:
    """images: (B, H, W, 3) RGB in [0, 1], H and W multiples of 32 -> 4 disparity maps
    (B, H / 2**s, W / 2**s, 1), s = 0..3.

    train: use the batch's BN statistics (PyTorch train mode); the running estimates are
    updated only when `batch_stats` is passed as mutable.
    """
    check_input_size(images.shape[1], images.shape[2])
    features = ResnetEncoder(self.num_layers, 1, self.conv, name="encoder")(images, train)
    return DepthDecoder(conv=self.conv, name="decoder")(features)


def check_input_size(height: int, width: int) -> None:
  """MonoDepth2's U-Net needs sides divisible by 32 (five stride-2 stages, exact skip sizes)."""
  if height % 32 or width % 32 or height <= 0 or width <= 0:
    raise ValueError(
        f"input size {width}x{height} (WxH) is not supported: MonoDepth2 needs width and height "
        f"that are positive multiples of 32 (e.g. 640x192, 320x96); resize the images first")


def scaled_disparity(disp: jax.Array, min_depth: float = MIN_DEPTH,
                     max_depth: float = MAX_DEPTH) -> jax.Array:
  """Sigmoid disparity -> MonoDepth2's scaled disparity in [1 / max_depth, 1 / min_depth] (the
  first value of its `disp_to_depth`, what `test_simple.py` saves as `_disp.npy`)."""
  min_disp, max_disp = 1.0 / max_depth, 1.0 / min_depth
  return min_disp + (max_disp - min_disp) * disp


def disp_to_depth(disp: jax.Array, min_depth: float = MIN_DEPTH,
                  max_depth: float = MAX_DEPTH) -> jax.Array:
  """Sigmoid disparity -> depth, MonoDepth2's `disp_to_depth`.

  depth = 1 / (1 / max_depth + (1 / min_depth - 1 / max_depth) * disp).
  """
  return 1.0 / scaled_disparity(disp, min_depth, max_depth)


__all__ = ["DepthNet", "DepthDecoder", "disp_to_depth", "scaled_disparity", "check_input_size",
           "encoder_channels", "DECODER_CHANNELS", "SCALES"]
