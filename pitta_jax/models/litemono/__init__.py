"""Lite-Mono (Zhang et al., CVPR 2023) in Flax: `LiteMono` (encoder + decoder) and its `SPEC`,
what the engine, the CLI and the selectors know about it."""

from __future__ import annotations

from typing import Any, Mapping

from pitta_jax.models.depth_decoder import MAX_DEPTH, MIN_DEPTH
from pitta_jax.models.litemono.depth_net import (SIZE_MULTIPLE, LiteMono, LiteMonoDecoder,
                                                 check_input_size)
from pitta_jax.models.litemono.encoder import VARIANTS, LiteMonoEncoder, dilations_for
from pitta_jax.models.spec import ModelSpec

NAME = "litemono"
DEFAULT_MODEL = "lite-mono"  # the base model (3.1M parameters)
DEFAULT_SIZE = (192, 640)    # (H, W) of the released KITTI 640x192 weights


def build(config: Mapping[str, Any]) -> LiteMono:
  """model.json config {"model", "height", "width", ...} (what `weights_convert.litemono`
  writes) -> the Flax module; "model" defaults to the base model."""
  return LiteMono(model=str(config.get("model", DEFAULT_MODEL)), height=int(config["height"]),
                  width=int(config["width"]))


SPEC = ModelSpec(
    name=NAME,
    build=build,
    output="sigmoid_disparity",  # sigmoid(dispconv) -> disp_to_depth(0.1, 100), as upstream
    size_multiple=SIZE_MULTIPLE,
    default_size=DEFAULT_SIZE,
    alignment="median",          # self-supervised monocular: scale-ambiguous
    depth_range=(MIN_DEPTH, MAX_DEPTH),
    encoder="encoder",
    description="Lite-Mono (CNN + XCA transformer, 3 disparity scales; BN in the stem and "
                "dilated blocks, LayerNorm in the LGFI blocks)",
)


__all__ = ["LiteMono", "LiteMonoDecoder", "LiteMonoEncoder", "SPEC", "VARIANTS", "build",
           "check_input_size", "dilations_for", "DEFAULT_MODEL", "DEFAULT_SIZE"]
