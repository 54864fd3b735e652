"""ResNet encoder of MonoDepth2 (Godard et al. 2019, `networks/resnet_encoder.py`), NHWC.

torchvision's ResNet-18/34 (BasicBlock) and ResNet-50 (Bottleneck, stride on the 3x3 conv as in
torchvision >= 0.2 "v1.5"), without the classifier, returning the 5 feature maps MonoDepth2's
decoders consume: after conv1+bn1+relu (1/2), and after layer1..layer4 (1/4 .. 1/32).
`num_input_images > 1` widens the first convolution to 3 * n channels (the pose encoder takes
two stacked frames). The input normalisation `(x - 0.45) / 0.225` happens inside, as upstream;
`input_mean`/`input_std` replace it for networks that normalise otherwise (SGDepth: torchvision's
per-channel ImageNet statistics).

Parameter names mirror torchvision's with `layer1.0.conv1` -> `layer1_0/conv1` and
`downsample.0/1` -> `downsample_conv` / `downsample_bn`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import flax.linen as nn
import numpy as np

from pitta_jax.models.layers import BatchNorm, Conv, ModuleDef, conv, max_pool_3x3_s2

# depth -> (block kind, blocks per stage)
RESNET_SPECS: dict[int, tuple[str, tuple[int, int, int, int]]] = {
    18: ("basic", (2, 2, 2, 2)),
    34: ("basic", (3, 4, 6, 3)),
    50: ("bottleneck", (3, 4, 6, 3)),
}
STAGE_WIDTHS = (64, 128, 256, 512)
MONODEPTH2_MEAN, MONODEPTH2_STD = 0.45, 0.225  # MonoDepth2's input normalisation
IMAGENET_MEAN = (0.485, 0.456, 0.406)  # torchvision's Normalize statistics, RGB
IMAGENET_STD = (0.229, 0.224, 0.225)


def encoder_channels(num_layers: int) -> tuple[int, ...]:
  """Channels of the 5 feature maps (`num_ch_enc` upstream)."""
  kind, _ = RESNET_SPECS[num_layers]
  expansion = 4 if kind == "bottleneck" else 1
  return (64,) + tuple(w * expansion for w in STAGE_WIDTHS)


class BasicBlock(nn.Module):
  """torchvision BasicBlock: 3x3 conv -> BN -> ReLU -> 3x3 conv -> BN, + (downsampled) input."""
  features: int
  stride: int
  downsample: bool
  conv: ModuleDef = Conv

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    y = conv(self.features, 3, self.stride, 1, name="conv1", module=self.conv)(x)
    y = nn.relu(BatchNorm(name="bn1")(y, train))
    y = conv(self.features, 3, 1, 1, name="conv2", module=self.conv)(y)
    y = BatchNorm(name="bn2")(y, train)
    if self.downsample:
      x = conv(self.features, 1, self.stride, 0, name="downsample_conv", module=self.conv)(x)
      x = BatchNorm(name="downsample_bn")(x, train)
    return nn.relu(y + x)


class Bottleneck(nn.Module):
  """torchvision Bottleneck (v1.5): 1x1 -> 3x3 (stride) -> 1x1 (x4 channels), + shortcut."""
  features: int
  stride: int
  downsample: bool
  conv: ModuleDef = Conv

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    y = nn.relu(BatchNorm(name="bn1")(conv(self.features, 1, name="conv1", module=self.conv)(x), train))
    y = nn.relu(BatchNorm(name="bn2")(conv(self.features, 3, self.stride, 1, name="conv2", module=self.conv)(y), train))
    y = BatchNorm(name="bn3")(conv(self.features * 4, 1, name="conv3", module=self.conv)(y), train)
    if self.downsample:
      x = conv(self.features * 4, 1, self.stride, 0, name="downsample_conv", module=self.conv)(x)
      x = BatchNorm(name="downsample_bn")(x, train)
    return nn.relu(y + x)


class ResnetEncoder(nn.Module):
  """MonoDepth2's `ResnetEncoder`.

  Attributes:
    num_layers: 18, 34 or 50.
    num_input_images: frames stacked along channels (1 for depth, 2 for the pose encoder).
    input_mean, input_std: `(x - mean) / std` on the RGB input, one value or one per channel
      (repeated for each stacked frame).
  """
  num_layers: int = 18
  num_input_images: int = 1
  conv: ModuleDef = Conv  # the convolution class of every layer
  input_mean: float | tuple[float, ...] = MONODEPTH2_MEAN
  input_std: float | tuple[float, ...] = MONODEPTH2_STD

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> list[jax.Array]:
    """images: (B, H, W, 3 * num_input_images) RGB in [0, 1] -> 5 maps, (B, H/2, W/2, 64) ...
    (B, H/32, W/32, C4)."""
    if self.num_layers not in RESNET_SPECS:
      raise ValueError(f"num_layers must be one of {sorted(RESNET_SPECS)}, got {self.num_layers}")
    expected_c = 3 * self.num_input_images
    if images.ndim != 4 or images.shape[-1] != expected_c:
      raise ValueError(f"encoder input must be (B, H, W, {expected_c}) NHWC, got {images.shape}")
    kind, blocks = RESNET_SPECS[self.num_layers]
    block_cls = Bottleneck if kind == "bottleneck" else BasicBlock
    expansion = 4 if kind == "bottleneck" else 1

    # one value, or one per RGB channel repeated for each stacked frame
    mean, std = (jnp.tile(jnp.asarray(v, images.dtype), self.num_input_images if np.ndim(v) else 1)
                 for v in (self.input_mean, self.input_std))
    x = (images - mean) / std
    x = conv(64, 7, 2, 3, name="conv1", module=self.conv)(x)
    x = nn.relu(BatchNorm(name="bn1")(x, train))
    features = [x]
    x = max_pool_3x3_s2(x)
    in_ch = 64
    for stage, (width, n_blocks) in enumerate(zip(STAGE_WIDTHS, blocks)):
      for b in range(n_blocks):
        stride = 2 if (stage > 0 and b == 0) else 1
        downsample = b == 0 and (stride != 1 or in_ch != width * expansion)
        x = block_cls(width, stride, downsample, self.conv, name=f"layer{stage + 1}_{b}")(x, train)
        in_ch = width * expansion
      features.append(x)
    return features
