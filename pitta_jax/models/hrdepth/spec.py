"""The `ModelSpec` of HR-Depth."""

from __future__ import annotations

from pitta_jax.models.hrdepth.network import DEFAULT_SIZE, DEPTH_RANGE, SIZE_MULTIPLE, HRDepthNet
from pitta_jax.models.spec import ModelSpec, field_builder

CONFIG_FIELDS = ("num_layers",)  # what `build` reads from model.json's config


build = field_builder(HRDepthNet, CONFIG_FIELDS)  # model.json config -> `HRDepthNet`


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
