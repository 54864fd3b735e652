"""The `ModelSpec` of SGDepth's depth network."""

from __future__ import annotations

from pitta_jax.models.sgdepth.network import DEFAULT_SIZE, DEPTH_RANGE, SIZE_MULTIPLE, SGDepthNet
from pitta_jax.models.spec import ModelSpec, field_builder

CONFIG_FIELDS = ("num_layers", "num_scales")  # what `build` reads from model.json's config


build = field_builder(SGDepthNet, CONFIG_FIELDS)  # model.json config -> `SGDepthNet`


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
