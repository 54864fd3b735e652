"""MonoViT (Zhao et al., 3DV 2022): MPViT-small encoder + HR-Depth-style decoder (NHWC), `SPEC`."""

from __future__ import annotations

from typing import Any, Mapping

from pitta_jax.models.monovit.network import SIZE_MULTIPLE, MonoViT, check_input_size
from pitta_jax.models.spec import ModelSpec


def build(config: Mapping[str, Any]) -> MonoViT:
  """model.json config -> module. Every MonoViT release is MPViT-small + the HR decoder; the
  config's height/width (the training size) do not change the module."""
  del config
  return MonoViT()


SPEC = ModelSpec(
    name="monovit",
    build=build,
    output="sigmoid_disparity",
    size_multiple=SIZE_MULTIPLE,
    default_size=(192, 640),
    alignment="median",
    depth_range=(0.1, 100.0),
    encoder="encoder",
    description="MonoViT (3DV 2022): MPViT-small + HR-Depth decoder, self-supervised on KITTI",
)

__all__ = ["MonoViT", "SPEC", "build", "check_input_size"]
