"""SGDepth's depth network (Klingner et al., ECCV 2020; ifnspaml/SGDepth `models/sgdepth.py`), NHWC.

Upstream's multi-task `SGDepth` shares a torchvision ResNet (`common.encoder`, no classifier) and
the first step(s) of a decoder (`common.decoder`) between a depth and a segmentation head; a
`ScaledSplit` then hands the shared features to `depth.decoder` (the remaining steps) and
`depth.multires` (the sigmoid disparity heads). For depth alone this is MonoDepth2's network:

* `PartialDecoder` step 2m (`PreConvBlock`: reflection pad, 3x3 conv, ELU) is MonoDepth2's
  `upconv_{4-m}_0`; step 2m+1 (`UpSkipBlock`: nearest x2, concat of the encoder skip, reflection
  pad, 3x3 conv, ELU) is `upconv_{4-m}_1`; channels (256, 128, 64, 32, 16) as MonoDepth2's. Where
  the shared part ends (`--model-split-pos`, step 1 in the released models) changes only which
  checkpoint prefix a step's weights come from, not the function.
* `MultiResDepth.convs.s` (reflection pad, 3x3 conv, sigmoid) is `dispconv_s`, scale s at 1/2**s.
* `ScaledSplit` is the identity forward; backward it multiplies the gradient reaching the shared
  part by the task's grad scale, a training-time loss weighting (upstream's evaluation and
  inference set it to 0). Here the gradient is the plain one (scale 1).

The one difference from MonoDepth2: the encoder sees torchvision's ImageNet normalisation
`(x - mean) / std` per channel (upstream's `NormalizeZeroMean` in the data loaders and
`Inference.normalize`), not `(x - 0.45) / 0.225`. So `SGDepthNet` = `ResnetEncoder` with the
ImageNet statistics (name "encoder") + MonoDepth2's `DepthDecoder` (name "decoder").
"""

from __future__ import annotations

import jax
import flax.linen as nn

from pitta_jax.models.depth_decoder import DepthDecoder
from pitta_jax.models.resnet import IMAGENET_MEAN, IMAGENET_STD, ResnetEncoder

DEPTH_RANGE = (0.1, 100.0)  # upstream --model-depth-min / --model-depth-max
DEFAULT_SIZE = (192, 640)  # (H, W) of the released "only depth" and "full" models
SIZE_MULTIPLE = 32  # five stride-2 stages with exact skip sizes


class SGDepthNet(nn.Module):
  """SGDepth's depth path: shared encoder + decoder, one sigmoid disparity per scale.

  Attributes:
    num_layers: ResNet depth of the shared encoder (18 released; 34, 50 supported).
    num_scales: `--model-depth-resolutions`, disparity heads for scales 0 .. num_scales - 1 (4
      in the released models).
  """
  num_layers: int = 18
  num_scales: int = 4

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array, ...]:
    """images: (B, H, W, 3) RGB in [0, 1], H and W multiples of 32 -> `num_scales` disparity maps
    (B, H / 2**s, W / 2**s, 1) in (0, 1), s = 0 .. num_scales - 1.

    train: use the batch's BN statistics (PyTorch train mode); the running estimates are updated
    only when `batch_stats` is passed as mutable.
    """
    from pitta_jax.models.sgdepth.spec import SPEC  # the spec builds this module
    SPEC.check_size(images.shape[1], images.shape[2])
    if not 1 <= self.num_scales <= 4:
      raise ValueError(f"num_scales must be 1..4 (upstream --model-depth-resolutions), "
                       f"got {self.num_scales}")
    features = ResnetEncoder(self.num_layers, 1, input_mean=IMAGENET_MEAN, input_std=IMAGENET_STD,
                             name="encoder")(images, train)
    return DepthDecoder(scales=tuple(range(self.num_scales)), name="decoder")(features)
