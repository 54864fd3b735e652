"""A MonoDepth2-shaped depth network small enough that the engine's programs compile in seconds.

Why: the engine's own behaviour (predict-then-adapt, chunking, resume, the guard, resets, many
streams, the lambda sweep, sharding) does not depend on the network's size, but a PITTA chunk
runner on ResNet-18 compiles for 15-20 s on 2 vCPUs, once per configuration. This network is
built from the same layers as MonoDepth2 (`models.layers.Conv` with its custom gradient,
`BatchNorm`, the custom-gradient 3x3 max pool, a ResNet `BasicBlock` with a downsample, the
decoder's reflection-padded convs and `UpConv3x3` with skips, ELU and sigmoid heads), with an
`encoder` whose BatchNorms the default selector adapts, and four sigmoid disparities, full
resolution first: what the engine sees of MonoDepth2, through the same `Network` seam. The
networks themselves are tested against PyTorch in their own files.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import jax
import jax.numpy as jnp
import flax.linen as nn

from pitta_jax.models.depth_decoder import conv3x3_reflect
from pitta_jax.models.layers import BatchNorm, UpConv3x3, conv, max_pool_3x3_s2
from pitta_jax.models.random_init import random_variables
from pitta_jax.models.registry import MODELS, Network
from pitta_jax.models.resnet import BasicBlock
from pitta_jax.models.spec import ModelSpec


class TinyEncoder(nn.Module):
  """(B, H, W, 3) -> maps at 1/2 (8 ch), 1/4 (8 ch), 1/8 (16 ch)."""

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> list[jax.Array]:
    x = nn.relu(BatchNorm(name="bn1")(conv(8, 3, 2, 1, name="conv1")((images - 0.45) / 0.225),
                                      train))
    f1 = BasicBlock(8, 1, False, name="layer1_0")(max_pool_3x3_s2(x), train)
    f2 = BasicBlock(16, 2, True, name="layer2_0")(f1, train)
    return [x, f1, f2]


class TinyDecoder(nn.Module):
  """The encoder's maps -> sigmoid disparities at scales 0..3, each (B, H / 2**s, W / 2**s, 1)."""

  @nn.compact
  def __call__(self, features: list[jax.Array]) -> tuple[jax.Array, ...]:
    x = features[-1]
    disps = [nn.sigmoid(conv3x3_reflect(x, 1, "dispconv_3"))]
    for i, (skip, width) in enumerate(zip((features[1], features[0], None), (8, 8, 4))):
      x = nn.elu(UpConv3x3(width, name=f"upconv_{2 - i}")(x, skip))
      disps.insert(0, nn.sigmoid(conv3x3_reflect(x, 1, f"dispconv_{2 - i}")))
    return tuple(disps)


class TinyDepthNet(nn.Module):
  """`encoder` + `decoder`, called as `DepthNet` is: images (B, H, W, 3), H and W multiples of 8."""

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array, ...]:
    return TinyDecoder(name="decoder")(TinyEncoder(name="encoder")(images, train))


class TinyPoseNet(nn.Module):
  """Two frames (B, H, W, 6) -> (axis-angle, translation), each (B, 2, 1, 3), as MonoDepth2's
  `PoseNet` returns them: two strided convolutions with BatchNorm, a 1x1 conv to 12 values,
  the spatial mean times 0.01 (MonoDepth2's pose decoder's scaling)."""

  @nn.compact
  def __call__(self, frame_pair: jax.Array, train: bool = False) -> tuple[jax.Array, jax.Array]:
    x = nn.relu(BatchNorm(name="bn1")(conv(8, 3, 2, 1, name="conv1")(frame_pair - 0.45), train))
    x = nn.relu(conv(16, 3, 2, 1, use_bias=True, name="conv2")(x))
    x = conv(12, 1, use_bias=True, name="pose")(x)
    x = 0.01 * jnp.mean(x, axis=(1, 2)).reshape(-1, 2, 1, 6)
    return x[..., :3], x[..., 3:]


SPEC = ModelSpec(name="tiny", build=lambda config: TinyDepthNet(), output="sigmoid_disparity",
                 size_multiple=8, default_size=(64, 96), build_pose=lambda config: TinyPoseNet())
TINY = Network(SPEC, TinyDepthNet())


@contextlib.contextmanager
def registered() -> Iterator[None]:
  """The tiny network registered as a user registers one (`MODELS[spec.name] = spec`) while the
  block runs, so that its weights load and the commands take them; the registry as it was
  after."""
  before = MODELS.get(SPEC.name)
  MODELS[SPEC.name] = SPEC
  try:
    yield
  finally:
    if before is None:
      del MODELS[SPEC.name]
    else:
      MODELS[SPEC.name] = before


def tiny_variables(seed: int) -> dict:
  """Random {"params", "batch_stats"} whose activations stay O(1) (`random_variables`)."""
  return random_variables(TinyDepthNet(), seed, jnp.zeros((1, 64, 96, 3)))


def tiny_pose_variables(seed: int) -> dict:
  """`TinyPoseNet`'s random variables, drawn as `tiny_variables`."""
  return random_variables(TinyPoseNet(), seed, jnp.zeros((1, 64, 96, 6)))
