"""Depth Anything V2 (ViT-S/14 by default): Flax modules and the project's `SPEC`.

`build(config)` takes the `config` dict `weights_convert.depth_anything_v2` writes into
model.json: the architecture fields of `DepthAnythingV2` (`ARCH_FIELDS`), plus "height"/"width"
(518, the size the released weights were trained at: 518x518 crops, `img_size=518`) and
"encoder" ("vits", "vitb", "vitl" or "custom"), which `build` does not need. "max_depth" > 0
makes it upstream's metric model (architecture `depth_anything_v2_metric`, `METRIC_SPEC`).

Input sizes: multiples of 14. Upstream's `infer_image` resizes the shorter side to 518 (keeping
the aspect ratio, sides rounded to multiples of 14, bicubic) and resizes the prediction back;
`predict` and every run (`run.input_size`: the first frame's aspect ratio) feed it the same
way (`SPEC.keep_aspect`, `SPEC.image_resize`), e.g. KITTI's 375x1242 frames at 518x1722.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from pitta_jax.models.depth_anything_v2.dinov2 import (
    HF_POS_OFFSET, OFFICIAL_POS_OFFSET, PATCH_SIZE, POS_GRID, VIT_VARIANTS, DinoVisionTransformer)
from pitta_jax.models.depth_anything_v2.dpt import DepthAnythingV2, DPTHead, check_input_size
from pitta_jax.models.spec import ModelSpec

# model.json fields that are attributes of `DepthAnythingV2`
ARCH_FIELDS = tuple(f.name for f in dataclasses.fields(DepthAnythingV2)
                    if f.name not in ("parent", "name"))
_TUPLE_FIELDS = ("layer_idx", "out_channels")
# model.json entries that describe the weights rather than the module
_META_FIELDS = ("height", "width", "encoder", "architecture", "has_pose", "source")


def build(config: Mapping[str, Any]) -> DepthAnythingV2:
  """model.json config (or the whole model.json) -> `DepthAnythingV2`; JSON lists become tuples
  (hashable attributes); a missing field takes the module's (ViT-S, relative) default."""
  unknown = sorted(set(config) - set(ARCH_FIELDS) - set(_META_FIELDS))
  if unknown:
    raise ValueError(f"unknown Depth Anything V2 config fields {unknown}; known: {ARCH_FIELDS}")
  kwargs = {k: (tuple(config[k]) if k in _TUPLE_FIELDS else config[k])
            for k in ARCH_FIELDS if k in config}
  return DepthAnythingV2(**kwargs)


def _build_checked(metric: bool):
  """`build` for the relative (max_depth 0) or the metric (max_depth > 0) architecture name:
  a model.json whose max_depth contradicts its architecture is refused."""
  def build_one(config: Mapping[str, Any]) -> DepthAnythingV2:
    max_depth = config.get("max_depth", 0)
    if (max_depth > 0) != metric:
      raise ValueError(f"Depth Anything V2 max_depth {max_depth}: the "
                       f"{'metric' if metric else 'relative'} architecture needs "
                       f"{'max_depth > 0' if metric else 'max_depth 0 (or none)'}")
    return build(config)
  return build_one


SPEC = ModelSpec(
    name="depth_anything_v2",
    build=_build_checked(metric=False),
    output="relative_inverse_depth",
    size_multiple=PATCH_SIZE,
    default_size=(POS_GRID * PATCH_SIZE, POS_GRID * PATCH_SIZE),
    alignment="scale_shift",
    encoder="encoder",
    description="Depth Anything V2 (DINOv2 ViT-S/14 + DPT head): relative inverse depth, "
                "inputs multiples of 14 (trained at 518x518)",
    keep_aspect=True,  # upstream's infer_image keeps the image's aspect ratio
    image_resize="cubic",  # and resizes with cv2.INTER_CUBIC (util/transform.py's Resize)
    exif_orientation=True,  # run.py reads with cv2.imread, which applies EXIF orientation
)

# upstream's metric models (metric_depth/): the same network with a sigmoid x max_depth head
METRIC_SPEC = dataclasses.replace(
    SPEC, name="depth_anything_v2_metric", build=_build_checked(metric=True),
    output="metric_depth", alignment="none",
    description="Depth Anything V2 metric (DINOv2 ViT + DPT head, sigmoid x max_depth): depth "
                "in metres, inputs multiples of 14 (trained at 518x518)")

__all__ = ["DepthAnythingV2", "DinoVisionTransformer", "DPTHead", "SPEC", "METRIC_SPEC",
           "build", "check_input_size", "ARCH_FIELDS", "VIT_VARIANTS", "OFFICIAL_POS_OFFSET",
           "HF_POS_OFFSET"]
