"""MonoDepth2 (Godard et al. 2019): ResNet encoder + U-Net depth decoder, and its pose network.

The modules live beside this file's parent (`models/resnet.py`, `models/depth_decoder.py`,
`models/pose.py`) because SGDepth and HR-Depth reuse them; this folder is MonoDepth2's registry
entry. model.json fields: `num_layers` (18, 34, 50), `height`, `width` (the training size,
640x192 for `mono_640x192`), `use_stereo`.
"""

from __future__ import annotations

from typing import Any, Mapping

from pitta_jax.models.depth_decoder import DepthNet
from pitta_jax.models.pose import PoseNet
from pitta_jax.models.resnet import RESNET_SPECS
from pitta_jax.models.spec import ModelSpec

DEFAULT_SIZE = (192, 640)  # (H, W) of the released mono_640x192 weights


def _num_layers(config: Mapping[str, Any], key: str = "num_layers") -> int:
  """config[key], a ResNet depth (an int: the text "18" or 18.0 is refused); the pose
  network's `pose_num_layers` defaults to the depth network's `num_layers`."""
  n = config.get(key, _num_layers(config) if key != "num_layers" else 18)
  if not isinstance(n, int) or isinstance(n, bool) or n not in RESNET_SPECS:
    raise ValueError(f"{key} must be one of {sorted(RESNET_SPECS)}, got {n!r}")
  return n


SPEC = ModelSpec(
    name="monodepth2",
    build=lambda config: DepthNet(_num_layers(config)),
    build_pose=lambda config: PoseNet(_num_layers(config, "pose_num_layers")),
    output="sigmoid_disparity",
    size_multiple=32,
    default_size=DEFAULT_SIZE,
    alignment="median",
    encoder="encoder",
    description="MonoDepth2 (ResNet-18/34/50 encoder, sigmoid disparity at 4 scales)",
)

__all__ = ["SPEC", "DepthNet", "PoseNet", "DEFAULT_SIZE"]
