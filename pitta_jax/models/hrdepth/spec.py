"""The `ModelSpec` of HR-Depth."""

from __future__ import annotations

from typing import Any, Mapping

from pitta_jax.models.hrdepth.network import DEFAULT_SIZE, DEPTH_RANGE, SIZE_MULTIPLE, HRDepthNet
from pitta_jax.models.spec import ModelSpec

CONFIG_FIELDS = ("num_layers",)  # what `build` reads from model.json's config


def build(config: Mapping[str, Any]) -> HRDepthNet:
  """model.json config (as `weights_convert.hrdepth` writes it) -> `HRDepthNet`; absent fields
  keep the module's defaults."""
  return HRDepthNet(**{k: config[k] for k in CONFIG_FIELDS if k in config})


SPEC = ModelSpec(
    name="hrdepth",
    build=build,
    output="sigmoid_disparity",
    size_multiple=SIZE_MULTIPLE,
    default_size=DEFAULT_SIZE,
    alignment="median",
    depth_range=DEPTH_RANGE,
    encoder="encoder",
    description="HR-Depth (AAAI 2021): MonoDepth2 ResNet-18 encoder + nested decoder with "
                "fSE attention",
)
