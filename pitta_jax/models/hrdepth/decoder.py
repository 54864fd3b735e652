"""HR-Depth's decoder (Lyu et al., AAAI 2021; shawLyu/HR-Depth `networks/HR_Depth_Decoder.py`,
`layers.py`), NHWC, for the ResNet encoders.

A nested (UNet++-style) decoder over the encoder's maps X_00 .. X_40 (X_i0 at 1/2**(i+1) of the
input). Node X_ij (row i, column j >= 1) is computed, in upstream's order 01, 11, 21, 31, 02, 12,
22, 03, 13, 04, from the node below-left, `high = X_{i+1,j-1}_Conv_0(X_{i+1,j-1})` (reflection
pad, 3x3 conv, ELU), and the nodes to its left `X_i0 .. X_i,j-1`:

* attention nodes 31, 22, 13, 04 (`X_ij_attention`, upstream's `fSEModule`): concat(nearest x2 of
  high, left nodes) -> squeeze-excite (global average, `fc.0` linear to C/16, ReLU, `fc.2` linear
  to C, sigmoid, channel-wise product) -> `conv_se` 1x1 conv with bias -> ReLU, with the channels of
  high;
* the others (upstream's `nestConv`): concat(nearest x2 of high, left nodes) -> for j > 1 the
  1x1 conv without bias `X_ij_downsample` -> `X_{i+1,j-1}_Conv_1` (reflection pad, 3x3, ELU).

Then full resolution: `X_04_Conv_0` on X_04, nearest x2, `X_04_Conv_1`. Sigmoid disparities
(reflection pad, 3x3 conv): `dispConvScale0` on that (1/1), `dispConvScale1` on X_04 (1/2),
`dispConvScale2` on X_13 (1/4), `dispConvScale3` on X_22 (1/8).

Upstream also builds X_00_Conv_0 .. X_03_Conv_0, which its forward never calls: they have no
counterpart here (the converter declares their keys unused). Layer names are upstream's
`convs` keys; the fSE linears are `fc_0` / `fc_2`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import flax.linen as nn

from pitta_jax.models.depth_decoder import DECODER_CHANNELS, conv3x3_reflect
from pitta_jax.models.layers import conv, upsample_nearest2x

# decoder nodes (row, column) in upstream's computation order; the fSE ones
NODES = ((0, 1), (1, 1), (2, 1), (3, 1), (0, 2), (1, 2), (2, 2), (0, 3), (1, 3), (0, 4))
ATTENTION_NODES = ((3, 1), (2, 2), (1, 3), (0, 4))
SE_REDUCTION = 16  # fSEModule's squeeze ratio


def conv0_features(num_ch_enc: tuple[int, ...], row: int, col: int) -> int:
  """Output channels of upstream's `X_{row}{col}_Conv_0`: half its input, which for row 0 beyond
  column 0 is half of num_ch_enc[0]."""
  n_in = num_ch_enc[row] // 2 if (row == 0 and col != 0) else num_ch_enc[row]
  return n_in // 2


class FSEModule(nn.Module):
  """Upstream's `fSEModule(high_feature_channel, low_feature_channels)`, the feature fusion
  squeeze-excitation block of the attention nodes.

  Attributes:
    features: output channels of `conv_se` (upstream: the high feature's channels).
  """
  features: int

  @nn.compact
  def __call__(self, high: jax.Array, low: list[jax.Array]) -> jax.Array:
    """high: (B, h, w, Ch) one row below; low: the row's nodes, each (B, 2h, 2w, C_k) ->
    (B, 2h, 2w, features)."""
    x = jnp.concatenate([upsample_nearest2x(high)] + low, axis=-1)  # (B, 2h, 2w, C)
    c = x.shape[-1]
    y = jnp.mean(x, axis=(1, 2))  # (B, C), AdaptiveAvgPool2d(1)
    y = nn.relu(nn.Dense(c // SE_REDUCTION, use_bias=False, name="fc_0")(y))
    y = nn.sigmoid(nn.Dense(c, use_bias=False, name="fc_2")(y))  # (B, C)
    x = x * y[:, None, None, :]
    return nn.relu(conv(self.features, 1, use_bias=True, name="conv_se")(x))


class HRDepthDecoder(nn.Module):
  """Upstream's `HRDepthDecoder(num_ch_enc, mobile_encoder=False)` with one output channel.

  Attributes:
    num_ch_enc: channels of the 5 encoder maps ((64, 64, 128, 256, 512) for ResNet-18/34).
  """
  num_ch_enc: tuple[int, ...] = (64, 64, 128, 256, 512)

  @nn.compact
  def __call__(self, features: list[jax.Array]) -> tuple[jax.Array, ...]:
    """features: the encoder's 5 maps -> 4 disparities in (0, 1), full resolution first,
    each (B, H / 2**s, W / 2**s, 1)."""
    enc, dec = self.num_ch_enc, DECODER_CHANNELS
    x = {(i, 0): f for i, f in enumerate(features)}  # node (row, col) -> (B, h_row, w_row, C)

    def conv_block(t: jax.Array, n_out: int, name: str) -> jax.Array:
      return nn.elu(conv3x3_reflect(t, n_out, name))

    for row, col in NODES:
      below = (row + 1, col - 1)
      high = conv_block(x[below], conv0_features(enc, *below), f"X_{below[0]}{below[1]}_Conv_0")
      low = [x[row, k] for k in range(col)]
      if (row, col) in ATTENTION_NODES:
        x[row, col] = FSEModule(enc[row + 1] // 2, name=f"X_{row}{col}_attention")(high, low)
      else:
        t = jnp.concatenate([upsample_nearest2x(high)] + low, axis=-1)
        if col != 1:
          t = conv(dec[row + 1] * 2, 1, name=f"X_{row}{col}_downsample")(t)
        x[row, col] = conv_block(t, dec[row + 1], f"X_{below[0]}{below[1]}_Conv_1")

    t = conv_block(x[0, 4], conv0_features(enc, 0, 4), "X_04_Conv_0")
    t = conv_block(upsample_nearest2x(t), dec[0], "X_04_Conv_1")  # (B, H, W, 16)
    sources = (t, x[0, 4], x[1, 3], x[2, 2])  # scales 0..3
    return tuple(nn.sigmoid(conv3x3_reflect(src, 1, f"dispConvScale{s}"))
                 for s, src in enumerate(sources))
