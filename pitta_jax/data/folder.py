"""A plain folder of images, with optional depth and panoptic folders matched by file stem.

  <root>/<stem>.{png,jpg,jpeg}          colour images, sorted by stem (PNG wins over JPEG)
  <root>/calib.json                     optional camera: {"K": 3x3, "width", "height"}
  <depth_dir>/<stem>.png                uint16, metres = value / depth_scale (256), 0 = invalid
             or <stem>.npy              float (H, W) metres, 0 = invalid
  <panoptic_dir>/<stem>.png + .json     COCO panoptic (or one annotation file, panoptic_json, or
                                        found inside/beside the directory)

When a depth or panoptic source is given, every image must have its file there. Frame names
are the stems.

A folder says nothing about its order, so it is *not* temporal unless the user says
`temporal=True` (the stems sort in capture order, e.g. `000000.png, 000001.png, ...` from a
video): methods that use the previous frame refuse it otherwise. With `temporal=True`, numbers
in the stems are compared as numbers (`frame_2` before `frame_10`, which a plain sort puts
after `frame_1`), with a note when that order differs from the plain one. The camera matrix comes from
`calib` (a `calib.json` file; default `<root>/calib.json` when it exists), scaled to each image
when its size differs from the file's width x height.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from pitta_jax.data.calib import read_calib_json
from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import (DEPTH_PNG_SCALE, PathLike, depth_loader, list_images,
                                     require_dir)
from pitta_jax.data.panoptic_io import panoptic_source
from pitta_jax.data.sequence import FrameFiles, FrameSequence, require_frames

CALIB_NAME = "calib.json"
REMEDIES = {
    "intrinsics": f"a {CALIB_NAME} ({{\"K\": 3x3, \"width\": W, \"height\": H}}) in --root or "
                  f"--option calib=FILE",
    "previous_frame": "--option temporal=true when the images are consecutive video frames in "
                      "file-name order",
}


def open_folder(root: PathLike, depth_dir: PathLike | None = None,
                panoptic_dir: PathLike | None = None, panoptic_json: PathLike | None = None,
                depth_scale: float = DEPTH_PNG_SCALE, temporal: bool = False,
                calib: PathLike | None = None) -> FrameSequence:
  """Opens a folder of images.

  Args:
    root: the image directory (not searched recursively).
    depth_dir: directory of depth maps named by image stem, or None.
    panoptic_dir: directory of COCO panoptic PNGs (+ per-image JSONs or one annotation file)
      named by stem, or None.
    panoptic_json: a COCO panoptic annotation file for those PNGs, or None.
    depth_scale: divisor from uint16 PNG value to metres.
    temporal: the images are consecutive frames in stem order (see the module docstring).
    calib: a calib.json giving every image's K; None = `<root>/calib.json` if present.

  Returns:
    the frames sorted by stem (numbers as numbers when temporal), loaded on access.
  """
  if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
    raise DataError(None, f"--option depth_scale={depth_scale!r}: must be a positive number "
                          f"(uint16 PNG value / depth_scale = metres)")
  images = list_images(root)
  require_frames(images, root, "*.{png,jpg,jpeg}")
  calib_path = Path(calib) if calib is not None else Path(root) / CALIB_NAME
  camera = read_calib_json(calib_path) if calib is not None or calib_path.is_file() else None
  depth_root = None if depth_dir is None else require_dir(depth_dir, "depth directory")
  panoptic = panoptic_source(panoptic_dir, panoptic_json)
  order = sorted(images)
  notes = list(panoptic.notes) if panoptic else []
  if temporal and sorted(order, key=natural_key) != order:
    order = sorted(order, key=natural_key)
    notes.append(f"temporal=true: the stems' numbers ordered as numbers ({order[0]}, "
                 f"{', '.join(order[1:3])}{', ...' if len(order) > 3 else ''}), not as text")
  files = []
  for stem in order:
    depth_file, depth = ("", None) if depth_root is None else depth_loader(
        depth_root, stem, png_scale=depth_scale,
        missing=f"depth map for image {images[stem].name} not found (nor .npy)")
    intrinsics = {} if camera is None else {
        "intrinsics": camera.K, "intrinsics_size": camera.size, "intrinsics_source": calib_path}
    files.append(FrameFiles(name=stem, image=images[stem], depth=depth,
                            depth_file=str(depth_file),
                            panoptic=None if panoptic is None else panoptic.ref(stem),
                            **intrinsics))
  return FrameSequence(files, temporal=temporal, remedies=REMEDIES, notes=notes)


def natural_key(stem: str) -> tuple:
  """Sort key comparing the digit runs of `stem` as numbers (`frame_2` < `frame_10`), the
  other characters as text; ties (`frame_02`, `frame_2`) fall back to the plain text."""
  parts = re.split(r"(\d+)", stem)
  return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts), stem
