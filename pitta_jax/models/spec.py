"""What the rest of the project knows about a depth network: its `ModelSpec`.

Each network lives in its own folder under `pitta_jax/models/` with its Flax modules and a
`SPEC`; `pitta_jax.models.registry` lists them. The engine, `predict`, the selectors, the
checkpoint loader and the CLI see a network only through its spec:

* `build(config)` -> the Flax module, from the `config` dict stored in the weights directory's
  `model.json` (what the converter or `train-source` wrote).
* The module's call: `module.apply(variables, images, train=use_batch_stats)` with images
  (B, H, W, 3) RGB in [0, 1] (the module normalises them itself, as its upstream does) returns a
  tuple of output maps (B, H_s, W_s, 1), the full-resolution one first.
* `output`: what those maps are, and so how they become depth (`to_depth`):
  "sigmoid_disparity" (the MonoDepth2 family: depth = 1 / (1/max + (1/min - 1/max) disp)) or
  "relative_inverse_depth" (affine-invariant, e.g. Depth Anything V2: the engine's depth is
  1 / max(out, eps), meaningful only up to scale and shift) or "metric_depth" (depth in metres,
  e.g. Depth Anything V2's metric models: the engine's depth is max(out, eps)).
* Input rules: H and W multiples of `size_multiple`; `default_size` is the size the released
  weights were trained at; `keep_aspect`: frames keep their aspect ratio (`inference_size`);
  `image_resize`: how an image is brought to that size (`data.resize.resize_image`);
  `exif_orientation`: `predict` turns a JPEG upright by its EXIF orientation first.
* `alignment`: the evaluation protocol the network's outputs need ("median" scaling for
  monocular self-supervised networks, "scale_shift" least squares for relative depth).
* `encoder`: the top-level module name of the encoder, the part the paper adapts (eq. 11); the
  selectors find its normalisation and convolution layers in forward order from the module
  itself (`pitta_jax.trainable`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax.models.depth_decoder import (MAX_DEPTH, MIN_DEPTH, disp_to_depth,
                                            scaled_disparity)

OUTPUTS = ("sigmoid_disparity", "relative_inverse_depth", "metric_depth")
ALIGNMENTS = ("median", "scale_shift", "none")
RELATIVE_EPS = 1e-6  # floor of a relative inverse depth before inverting it
MAX_SIDE = 16384  # the largest input side taken: beyond any camera here (an 8K frame is 7680 wide)


@dataclasses.dataclass(frozen=True)
class ModelSpec:
  """One depth network as the project sees it (see the module docstring)."""
  name: str                                  # registry key and model.json "architecture"
  build: Callable[[Mapping[str, Any]], Any]  # model.json "config" -> flax.linen.Module
  output: str                                # one of OUTPUTS
  size_multiple: int                         # input H and W must be multiples of this
  default_size: tuple[int, int]              # (H, W) of the released weights
  alignment: str = "median"                  # default evaluation alignment, one of ALIGNMENTS
  depth_range: tuple[float, float] = (MIN_DEPTH, MAX_DEPTH)  # disp_to_depth range, sigmoid outputs
  encoder: str = "encoder"                   # top-level module name of the encoder
  description: str = ""                      # one line for --help and model listings
  build_pose: Callable[[Mapping[str, Any]], Any] | None = None  # its pose network, if any
  # model.json fields of the network trained from scratch at (H, W) (`train-source`);
  # None = {"height": H, "width": W}
  source_config: Callable[[int, int], dict[str, Any]] | None = None
  # `predict` on an image: False = resized to the trained (H, W) (MonoDepth2's test_simple.py);
  # True = its aspect ratio kept, each side at least the trained one (`inference_size`)
  keep_aspect: bool = False
  # how images are resized to the input size, one of data.resize.IMAGE_RESIZE: "area"
  # (MonoDepth2's antialiased shrink) or "cubic" (Depth Anything V2's cv2.INTER_CUBIC)
  image_resize: str = "area"
  # `predict` on a JPEG with an EXIF orientation: False = the pixels as stored (MonoDepth2's
  # test_simple.py reads with PIL, which does not turn them); True = turned upright as
  # cv2.imread does (Depth Anything V2's run.py)
  exif_orientation: bool = False

  def __post_init__(self):
    if self.output not in OUTPUTS:
      raise ValueError(f"{self.name}: output {self.output!r} is not one of {OUTPUTS}")
    if self.alignment not in ALIGNMENTS:
      raise ValueError(f"{self.name}: alignment {self.alignment!r} is not one of {ALIGNMENTS}")
    from pitta_jax.data.resize import IMAGE_RESIZE
    if self.image_resize not in IMAGE_RESIZE:
      raise ValueError(f"{self.name}: image_resize {self.image_resize!r} is not one of "
                       f"{IMAGE_RESIZE}")

  def check_size(self, height: int, width: int) -> None:
    """Raises ValueError naming the rule when (height, width) is not a valid input size."""
    m = self.size_multiple
    if height <= 0 or width <= 0 or height % m or width % m:
      raise ValueError(f"input size {width}x{height} (WxH) is not supported by {self.name}: "
                       f"width and height must be positive multiples of {m} "
                       f"(default {self.default_size[1]}x{self.default_size[0]})")
    if max(height, width) > MAX_SIDE:  # a size no image here has (an edited model.json?)
      raise ValueError(f"input size {width}x{height} (WxH) is more than {MAX_SIDE} pixels on "
                       f"a side")

  def inference_size(self, image_size: tuple[int, int], trained: tuple[int, int]
                     ) -> tuple[int, int]:
    """The (H, W) an image of `image_size` (H, W) is resized to for a prediction or a run
    (`run.run_sequence` takes its first frame's): `trained`, or
    with `keep_aspect` Depth Anything V2's `infer_image` rule (its `Resize` with
    keep_aspect_ratio, resize_method "lower_bound", ensure_multiple_of 14): one scale for both
    sides, the larger of trained / image per side, each side then rounded to a multiple of
    `size_multiple` (np.round), rounded up where that falls below the trained side."""
    if not self.keep_aspect:
      return tuple(trained)
    scale = max(t / s for t, s in zip(trained, image_size))
    m = self.size_multiple

    def fit(x: float, least: int) -> int:
      y = int(np.round(x / m) * m)
      return y if y >= least else int(math.ceil(x / m) * m)

    return fit(scale * image_size[0], trained[0]), fit(scale * image_size[1], trained[1])

  def to_depth(self, out: jax.Array) -> jax.Array:
    """The network's scale-0 output -> the depth the losses see (same shape)."""
    if self.output == "sigmoid_disparity":
      return disp_to_depth(out, *self.depth_range)
    if self.output == "metric_depth":
      return jnp.maximum(out, RELATIVE_EPS)
    return 1.0 / jnp.maximum(out, RELATIVE_EPS)

  def saved_disparity(self, out: jax.Array) -> jax.Array:
    """The network's scale-0 output as `predict` saves it in `_disp.npy`: a sigmoid disparity
    scaled to [1 / max_depth, 1 / min_depth], as MonoDepth2's `test_simple.py` saves it (the
    inverse of `to_depth`'s depth); other outputs as they are."""
    if self.output == "sigmoid_disparity":
      return scaled_disparity(out, *self.depth_range)
    return out


def field_builder(module_cls: type, fields: tuple[str, ...]) -> Callable[[Mapping[str, Any]], Any]:
  """A `ModelSpec.build` that passes the model.json `fields` it finds to `module_cls` (absent
  ones keep the module's defaults; other model.json entries are not the module's)."""
  def build(config: Mapping[str, Any]):
    return module_cls(**{k: config[k] for k in fields if k in config})
  return build
