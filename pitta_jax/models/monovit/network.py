"""MonoViT's depth network, NHWC: the HR-Depth-style decoder, and `MonoViT` = encoder + decoder.

`MonoViT` is upstream zxcqlf/MonoViT `networks/nets.py` `DeepNet('mpvitnet')`: the MPViT-small
encoder (name "encoder", `mpvit.py`) and the decoder of `networks/hr_decoder.py` (name "decoder")
on [0, 1] RGB without normalisation; the scale-0 sigmoid disparity becomes depth with MonoDepth2's
`disp_to_depth(disp, 0.1, 100)`. Inputs: H and W multiples of 32.

The decoder, upstream `DepthDecoder(ch_enc=[64, 128, 216, 288, 288], num_ch_enc=[64, 64, 128,
256, 512])`:

1. Feature fusion: encoder maps 1..4 each go through an `Attention_Module` (`f1`..`f4`): a
   squeeze-and-excitation channel attention (`ChannelAttention`, ratio 16: global average pool,
   Linear C -> C/16, ReLU, Linear C/16 -> C, sigmoid, rescale; no max-pool branch), then a 3x3
   conv (zero padding, bias) to `num_ch_enc[i]` channels and ReLU. Map 0 (the stem) is used as is.
2. HR-Depth's nested decoder: nodes X_{row}{col}, X_{i}0 = the fused maps, computed in the order
   01 11 21 31 02 12 22 03 13 04. Each node upsamples `X_{row+1}{col-1}_Conv_0(X_{row+1, col-1})`
   (3x3 reflection-padded conv + ELU, to half its channels) and combines it with all X_{row}{c<col}:
   at 31 22 13 04 by an `fSEModule` (nearest x2, concatenation, SE attention ratio 16, 1x1 conv
   with bias, ReLU); elsewhere by concatenation, a bias-free 1x1 `X_{index}_downsample` conv when
   col > 1, and `X_{row+1}{col-1}_Conv_1` (3x3 reflection conv + ELU).
3. Heads: X_04 -> `X_04_Conv_0` (ELU) -> nearest x2 -> `X_04_Conv_1` (ELU) -> `dispconv0` (full
   resolution); `dispconv1/2/3` on X_04 (1/2), X_13 (1/4), X_22 (1/8); each a 3x3 reflection conv
   and a sigmoid.

Upstream also builds `X_00_Conv_0` .. `X_03_Conv_0` in its construction loop but never uses them;
they have no Flax counterpart (the converter declares their keys ignorable).
Parameter names: `convs.<name>` -> `<name>` (ConvBlock/Conv3x3 wrappers flattened to the Conv);
`ca.fc.0`/`fc.2` -> `ca/fc_0`, `ca/fc_2`; `fc.0`/`fc.2` of an fSEModule -> `fc_0`/`fc_2`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import flax.linen as nn

from pitta_jax.models.depth_decoder import conv3x3_reflect
from pitta_jax.models.layers import conv, upsample_nearest2x
from pitta_jax.models.monovit.mpvit import (EMBED_DIMS, MLP_RATIOS, NUM_HEADS, NUM_LAYERS,
                                            NUM_PATH, MPViT)

NUM_CH_ENC = (64, 64, 128, 256, 512)  # fused feature channels (upstream's `num_ch_enc`)
NUM_CH_DEC = (16, 32, 64, 128, 256)
ALL_POSITIONS = ("01", "11", "21", "31", "02", "12", "22", "03", "13", "04")
ATTENTION_POSITIONS = ("31", "22", "13", "04")
SE_REDUCTION = 16
SIZE_MULTIPLE = 32  # five stride-2 stages; the decoder's x2 upsamplings must meet the skips exactly


def squeeze_excite(x: jax.Array) -> jax.Array:
  """Channel attention: x * sigmoid(fc_2(relu(fc_0(mean_HW(x))))), bias-free Linears C -> C/16 -> C.

  Creates Dense layers `fc_0`, `fc_2` in the calling module (upstream `fc.0`, `fc.2`).
  """
  c = x.shape[-1]
  y = jnp.mean(x, axis=(1, 2))  # (B, C), AdaptiveAvgPool2d(1)
  y = nn.relu(nn.Dense(c // SE_REDUCTION, use_bias=False, name="fc_0")(y))
  y = nn.sigmoid(nn.Dense(c, use_bias=False, name="fc_2")(y))
  return x * y[:, None, None, :]


class ChannelAttention(nn.Module):
  """Upstream `ChannelAttention` (average-pool branch only, as upstream's forward)."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    return squeeze_excite(x)


class AttentionModule(nn.Module):
  """Upstream `Attention_Module`: channel attention `ca`, 3x3 conv `conv_se` (padding 1, bias),
  ReLU."""
  features: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    x = ChannelAttention(name="ca")(x)
    return nn.relu(conv(self.features, 3, 1, 1, use_bias=True, name="conv_se")(x))


class FSEModule(nn.Module):
  """Upstream `fSEModule`: cat(upsample2x(high), *lows) -> SE attention -> 1x1 conv (bias) -> ReLU.

  The SE Linears are the module's own `fc_0`, `fc_2` (upstream `fc.0`, `fc.2`).
  """
  features: int

  @nn.compact
  def __call__(self, high: jax.Array, lows: list[jax.Array]) -> jax.Array:
    x = jnp.concatenate([upsample_nearest2x(high)] + list(lows), axis=-1)  # (B, H, W, C)
    x = squeeze_excite(x)
    return nn.relu(conv(self.features, 1, use_bias=True, name="conv_se")(x))


def conv_block(x: jax.Array, features: int, name: str) -> jax.Array:
  """Upstream `ConvBlock`: 3x3 reflection-padded conv with bias, ELU."""
  return nn.elu(conv3x3_reflect(x, features, name))


class HRDepthDecoder(nn.Module):
  """Upstream `DepthDecoder` of `networks/hr_decoder.py` (see the module docstring)."""
  num_ch_enc: tuple[int, ...] = NUM_CH_ENC
  num_ch_dec: tuple[int, ...] = NUM_CH_DEC
  num_output_channels: int = 1

  @nn.compact
  def __call__(self, features: list[jax.Array]) -> tuple[jax.Array, ...]:
    """features: the encoder's 5 maps (1/2 .. 1/32) -> disparities at scales 0..3,
    (B, H / 2**s, W / 2**s, num_output_channels) in (0, 1), full resolution first."""
    enc, dec = self.num_ch_enc, self.num_ch_dec
    nodes = {(i, 0): AttentionModule(enc[i], name=f"f{i}")(features[i]) for i in (4, 3, 2, 1)}
    nodes[(0, 0)] = features[0]
    for index in ALL_POSITIONS:
      row, col = int(index[0]), int(index[1])
      lows = [nodes[(row, c)] for c in range(col)]
      high = conv_block(nodes[(row + 1, col - 1)], enc[row + 1] // 2,
                        f"X_{row + 1}{col - 1}_Conv_0")
      if index in ATTENTION_POSITIONS:
        nodes[(row, col)] = FSEModule(enc[row + 1] // 2, name=f"X_{index}_attention")(high, lows)
      else:
        x = jnp.concatenate([upsample_nearest2x(high)] + lows, axis=-1)
        if col != 1:
          x = conv(dec[row + 1] * 2, 1, name=f"X_{index}_downsample")(x)
        nodes[(row, col)] = conv_block(x, dec[row + 1], f"X_{row + 1}{col - 1}_Conv_1")
    x = conv_block(nodes[(0, 4)], enc[0] // 4, "X_04_Conv_0")  # (B, H/2, W/2, 16)
    x = conv_block(upsample_nearest2x(x), dec[0], "X_04_Conv_1")  # (B, H, W, 16)
    heads = (x, nodes[(0, 4)], nodes[(1, 3)], nodes[(2, 2)])
    return tuple(nn.sigmoid(conv3x3_reflect(h, self.num_output_channels, f"dispconv{s}"))
                 for s, h in enumerate(heads))


def check_input_size(height: int, width: int) -> None:
  """Raises ValueError unless height and width are positive multiples of SIZE_MULTIPLE."""
  if height <= 0 or width <= 0 or height % SIZE_MULTIPLE or width % SIZE_MULTIPLE:
    raise ValueError(
        f"input size {width}x{height} (WxH) is not supported: MonoViT needs width and height that "
        f"are positive multiples of {SIZE_MULTIPLE} (e.g. 640x192, 96x64); resize the images first")


class MonoViT(nn.Module):
  """MonoViT: `MPViT` encoder + `HRDepthDecoder`, as upstream's `DeepNet('mpvitnet')`.

  The encoder layout defaults to MPViT-small, the only one MonoViT releases; the fields allow
  the other MPViT variants (upstream `mpvit_tiny/xsmall/base`), whose widths the decoder takes
  from the feature maps.
  """
  num_path: tuple[int, ...] = NUM_PATH
  num_layers: tuple[int, ...] = NUM_LAYERS
  embed_dims: tuple[int, ...] = EMBED_DIMS
  mlp_ratios: tuple[int, ...] = MLP_RATIOS
  num_heads: tuple[int, ...] = NUM_HEADS

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array, ...]:
    """images: (B, H, W, 3) RGB in [0, 1], H and W multiples of 32 -> 4 sigmoid disparities
    (B, H / 2**s, W / 2**s, 1), s = 0..3.

    train: BatchNorms use the batch's statistics (PyTorch train mode; the running estimates
    are updated only when `batch_stats` is mutable). Drop path is never applied.
    """
    check_input_size(images.shape[1], images.shape[2])
    features = MPViT(self.num_path, self.num_layers, self.embed_dims, self.mlp_ratios,
                     self.num_heads, name="encoder")(images, train)
    return HRDepthDecoder(name="decoder")(features)
