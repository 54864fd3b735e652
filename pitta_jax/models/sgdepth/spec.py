"""The `ModelSpec` of SGDepth's depth network."""

from __future__ import annotations

from typing import Any, Mapping

from pitta_jax.models.sgdepth.network import DEFAULT_SIZE, DEPTH_RANGE, SIZE_MULTIPLE, SGDepthNet
from pitta_jax.models.spec import ModelSpec

CONFIG_FIELDS = ("num_layers", "num_scales")  # what `build` reads from model.json's config


def build(config: Mapping[str, Any]) -> SGDepthNet:
  """model.json config (as `weights_convert.sgdepth` writes it) -> `SGDepthNet`; absent fields
  keep the module's defaults."""
  return SGDepthNet(**{k: config[k] for k in CONFIG_FIELDS if k in config})


SPEC = ModelSpec(
    name="sgdepth",
    build=build,
    output="sigmoid_disparity",
    size_multiple=SIZE_MULTIPLE,
    default_size=DEFAULT_SIZE,
    alignment="median",
    depth_range=DEPTH_RANGE,
    encoder="encoder",
    description="SGDepth (ECCV 2020): semantically guided MonoDepth2-style ResNet depth network, "
                "ImageNet-normalised input",
)
