"""A plain folder of images, with optional depth and panoptic folders matched by file stem.

  <root>/<stem>.{png,jpg,jpeg}          colour images, sorted by stem (PNG wins over JPEG)
  <depth_dir>/<stem>.png                uint16, metres = value / depth_scale (256), 0 = invalid
             or <stem>.npy              float (H, W) metres, 0 = invalid
  <panoptic_dir>/<stem>.png + .json     COCO panoptic (or one annotation file, panoptic_json)

When a depth or panoptic source is given, every image must have its file there. Frame names
are the stems.
"""

from __future__ import annotations

import math

from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import (DEPTH_PNG_SCALE, PathLike, depth_loader, list_images,
                                     require_dir)
from pitta_jax.data.panoptic_io import panoptic_source
from pitta_jax.data.sequence import FrameFiles, FrameSequence, require_frames


def open_folder(root: PathLike, depth_dir: PathLike | None = None,
                panoptic_dir: PathLike | None = None, panoptic_json: PathLike | None = None,
                depth_scale: float = DEPTH_PNG_SCALE) -> FrameSequence:
  """Opens a folder of images.

  Args:
    root: the image directory (not searched recursively).
    depth_dir: directory of depth maps named by image stem, or None.
    panoptic_dir: directory of COCO panoptic PNGs (+ per-image JSONs) named by stem, or None.
    panoptic_json: a COCO panoptic annotation file for those PNGs, or None.
    depth_scale: divisor from uint16 PNG value to metres.

  Returns:
    the frames sorted by stem, loaded on access.
  """
  if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
    raise DataError(None, f"--option depth_scale={depth_scale!r}: must be a positive number "
                          f"(uint16 PNG value / depth_scale = metres)")
  images = list_images(root)
  require_frames(images, root, "*.{png,jpg,jpeg}")
  depth_root = None if depth_dir is None else require_dir(depth_dir, "depth directory")
  panoptic = panoptic_source(panoptic_dir, panoptic_json)
  files = []
  for stem in sorted(images):
    depth = None if depth_root is None else depth_loader(
        depth_root, stem, png_scale=depth_scale,
        missing=f"depth map for image {images[stem].name} not found (nor .npy)")
    files.append(FrameFiles(name=stem, image=images[stem], depth=depth,
                            panoptic=None if panoptic is None else panoptic.ref(stem)))
  return FrameSequence(files)
