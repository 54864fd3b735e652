"""MonoViT (Zhao et al., 3DV 2022): MPViT-small encoder + HR-Depth-style decoder (NHWC), `SPEC`."""

from __future__ import annotations

from typing import Any, Mapping

from pitta_jax.models.depth_decoder import MAX_DEPTH, MIN_DEPTH
from pitta_jax.models.monovit.network import SIZE_MULTIPLE, MonoViT, check_input_size
from pitta_jax.models.spec import ModelSpec

ARCH_FIELDS = ("num_path", "num_layers", "embed_dims", "mlp_ratios", "num_heads")


def build(config: Mapping[str, Any]) -> MonoViT:
  """model.json config -> module: the MPViT layout fields the converter recorded (per-stage
  lists; absent ones keep MonoViT's MPViT-small defaults). height/width do not change it."""
  return MonoViT(**{k: tuple(config[k]) for k in ARCH_FIELDS if k in config})


SPEC = ModelSpec(
    name="monovit",
    build=build,
    output="sigmoid_disparity",
    size_multiple=SIZE_MULTIPLE,
    default_size=(192, 640),
    alignment="median",
    depth_range=(MIN_DEPTH, MAX_DEPTH),  # MonoDepth2's disp_to_depth(0.1, 100), as upstream
    encoder="encoder",
    description="MonoViT (3DV 2022): MPViT-small + HR-Depth decoder, self-supervised on KITTI",
)

__all__ = ["ARCH_FIELDS", "MonoViT", "SPEC", "build", "check_input_size"]
