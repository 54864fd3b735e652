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
  """model.json config {"model", "height", "width", ["dilation_size"]} (what
  `weights_convert.litemono` writes) -> the Flax module; "model" defaults to the base model.

  Upstream ties the DilatedConv rates to the training size (640x192 or 1024x320);
  "dilation_size" [H, W] names the table for weights trained at another size (`train-source`
  trains at 320x96 with the 640x192 rates); by default it is the weights' height and width.
  """
  h, w = config.get("dilation_size", (config["height"], config["width"]))
  return LiteMono(model=str(config.get("model", DEFAULT_MODEL)), height=int(h), width=int(w))


def source_config(height: int, width: int) -> dict[str, Any]:
  """model.json fields of a Lite-Mono trained from scratch at (height, width)."""
  return {"height": height, "width": width, "dilation_size": list(DEFAULT_SIZE)}


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
    source_config=source_config,
)


__all__ = ["LiteMono", "LiteMonoDecoder", "LiteMonoEncoder", "SPEC", "VARIANTS", "build",
           "check_input_size", "dilations_for", "DEFAULT_MODEL", "DEFAULT_SIZE"]
