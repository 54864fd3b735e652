"""HR-Depth's depth network (shawLyu/HR-Depth `evaluate_depth.py`): MonoDepth2's ResNet encoder
(its `(x - 0.45) / 0.225` input normalisation included) + `HRDepthDecoder`, NHWC.

Upstream evaluates the ResNet-18 model ("HR-Depth"; the MobileNetV3 "Lite-HR-Depth" is not
implemented here); ResNet-34 has the same channels and also works with the decoder (ResNet-50's
wider maps do not fit upstream's decoder channel formulas).
"""

from __future__ import annotations

import jax
import flax.linen as nn

from pitta_jax.models.hrdepth.decoder import HRDepthDecoder
from pitta_jax.models.resnet import ResnetEncoder, encoder_channels

NUM_LAYERS = (18, 34)  # ResNets whose channels the decoder's formulas fit
DEPTH_RANGE = (0.1, 100.0)  # evaluate_depth.py's disp_to_depth(disp, 0.1, 100.0)
DEFAULT_SIZE = (192, 640)  # (H, W) of HR_Depth_CS_K_MS_640x192 (also 1024x320, 1280x384)
SIZE_MULTIPLE = 32  # five stride-2 stages with exact skip sizes


class HRDepthNet(nn.Module):
  """HR-Depth: `encoder` (ResNet) + `decoder` (HRDepthDecoder).

  Attributes:
    num_layers: ResNet depth of the encoder, 18 (released) or 34.
  """
  num_layers: int = 18

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array, ...]:
    """images: (B, H, W, 3) RGB in [0, 1], H and W multiples of 32 -> 4 disparity maps
    (B, H / 2**s, W / 2**s, 1) in (0, 1), s = 0..3.

    train: use the batch's BN statistics (PyTorch train mode); the running estimates are updated
    only when `batch_stats` is passed as mutable.
    """
    from pitta_jax.models.hrdepth.spec import SPEC  # the spec builds this module
    SPEC.check_size(images.shape[1], images.shape[2])
    if self.num_layers not in NUM_LAYERS:
      raise ValueError(f"HR-Depth's decoder fits ResNet-{'/'.join(map(str, NUM_LAYERS))} "
                       f"encoders, got num_layers={self.num_layers}")
    features = ResnetEncoder(self.num_layers, 1, name="encoder")(images, train)
    return HRDepthDecoder(encoder_channels(self.num_layers), name="decoder")(features)
