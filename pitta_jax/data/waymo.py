"""Waymo Open Dataset FRONT camera with projected LiDAR depth, in pitta-jax's neutral layout.

No standard depth layout exists for Waymo, so we define one:

  <root>/<seq>/image/{frame:06d}.{png,jpg}
  <root>/<seq>/depth/{frame:06d}.png    uint16, metres = value / 256, 0 = no LiDAR return
                  or {frame:06d}.npy    float32 (H, W) metres (0 = none), or
                                        float32 (N, 3) sparse points [u, v, z]
  <root>/<seq>/calib.json               {"K": [[fu, 0, cu], [0, fv, cv], [0, 0, 1]],
                                         "width": 1920, "height": 1280}
  <root>/<seq>/panoptic/{frame:06d}.{png,json}   optional COCO panoptic maps

Sparse points are rasterised at the image size: pixel (row, col) = (floor(v + 0.5),
floor(u + 0.5)) (OpenCV convention, pixel centres at integer coordinates), points with z > 0
inside the image only, and where several points fall on one pixel the *nearest* (minimum z)
wins, since it is the surface the camera sees. calib.json is optional; when present its
width/height must match every image (they set the raster size), and `read_calib` returns K.
Frames are sorted by file name; names are `<seq>/<frame>`; sequences default to every
directory of `root` with an `image/` subdirectory, in sorted order.

Recipe: producing this layout from the official release (v1.x tfrecords, `waymo_open_dataset`)
----------------------------------------------------------------------------------------------
For each segment `<seq>` (the tfrecord's name) and each frame k = 0, 1, ... in it:

1. `frame = dataset_pb2.Frame(); frame.ParseFromString(record)`.
2. Image: the `frame.images` entry with `name == CameraName.FRONT`; its `.image` is JPEG
   bytes, write them unchanged to `<seq>/image/{k:06d}.jpg` (1920x1280).
3. Calibration: the `frame.context.camera_calibrations` entry with `name == FRONT`:
   `intrinsic = [f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3]`, `extrinsic.transform` = 4x4
   row-major camera -> vehicle, `width`, `height`. Write `calib.json` once per sequence with
   `K = [[f_u, 0, c_u], [0, f_v, c_v], [0, 0, 1]]`, `width`, `height`.
4. LiDAR points in the vehicle frame and where each lands in the cameras:
   `range_images, camera_projections, _, top_pose =
   frame_utils.parse_range_image_and_camera_projection(frame)`, then
   `points, cp_points = frame_utils.convert_range_image_to_point_cloud(frame, range_images,
   camera_projections, top_pose)` (first returns, ri_index=0); concatenate the five LiDARs:
   P (N, 3) metres, vehicle frame, and cp (N, 6).
5. Pixel positions from the dataset's own camera projection (it applies the lens distortion
   k1..k3, p1, p2 and the rolling shutter, which a pinhole projection of P with K ignores):
   keep the points with `cp[:, 0] == CameraName.FRONT`, their
   (u, v) = `cp[:, 1], cp[:, 2]`; a point that projects into the FRONT camera only as its
   second projection has `cp[:, 3] == FRONT` and (u, v) = `cp[:, 4], cp[:, 5]`.
6. Depth Z of each kept point: camera frame `[x, y, z, 1]^T = inverse(extrinsic) @ [P, 1]^T`
   (Waymo's camera axes: x forward, y left, z up), Z = x; keep Z > 0 and 0 <= u < width,
   0 <= v < height.
7. Save `np.stack([u, v, Z], axis=1).astype(np.float32)` to `<seq>/depth/{k:06d}.npy`
   (or rasterise as above and save `round(256 Z)` as uint16 `<seq>/depth/{k:06d}.png`).

Evaluation caps Waymo depth at 75 or 80 m (metrics option).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Sequence

import numpy as np

from pitta_jax.data.calib import Calib, read_calib_json
from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import (PathLike, depth_loader, list_images, load_npy, read_image,
                                     require_dir)
from pitta_jax.data.panoptic_io import PanopticSource, panoptic_source
from pitta_jax.data.sequence import FrameFiles, FrameSequence, require_frames


read_calib = read_calib_json  # <seq>/calib.json: K, width, height (`data.calib.Calib`)
INTRINSICS_REMEDY = "<seq>/calib.json (K, width, height; see the recipe in data/waymo.py)"


def rasterise_points(points: np.ndarray, height: int, width: int) -> np.ndarray:
  """Sparse LiDAR points -> depth map, nearest point per pixel.

  Args:
    points: (N, 3) [u, v, z]: column, row (pixel centres at integers) and depth in metres.
    height, width: the image size.

  Returns:
    (height, width) float32 metres, 0 where no point with z > 0 falls.
  """
  points = np.asarray(points, np.float64)
  u, v, z = points[:, 0], points[:, 1], points[:, 2]
  keep = np.isfinite(u) & np.isfinite(v) & np.isfinite(z) & (z > 0)
  col = np.floor(np.where(keep, u, -1.0) + 0.5)
  row = np.floor(np.where(keep, v, -1.0) + 0.5)
  keep &= (col >= 0) & (col < width) & (row >= 0) & (row < height)
  depth = np.full((height, width), np.inf)
  np.minimum.at(depth, (row[keep].astype(np.int64), col[keep].astype(np.int64)), z[keep])
  return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


def read_waymo_depth_npy(path: Path, image: Path, calib: Calib | None) -> np.ndarray:
  """A dense (H, W) float or sparse (N, 3) `.npy` depth file -> (H, W) float32 metres.

  The raster size is calib's (height, width), or the image's when there is no calib.json.
  """
  array = load_npy(path, "depth")
  if array.ndim != 2 or not np.issubdtype(array.dtype, np.number):
    raise DataError(path, f"depth .npy must be (H, W) or (N, 3) numbers, got {array.dtype} "
                          f"{array.shape}")
  if calib is not None:
    size = (calib.height, calib.width)
  else:
    size = read_image(image).shape[:2]
  if array.shape == size:
    if not np.issubdtype(array.dtype, np.floating):  # e.g. a PNG's uint16 metres x 256
      raise DataError(path, f"a dense depth .npy must hold float metres, got {array.dtype}")
    return array.astype(np.float32)
  if array.shape[1] == 3:
    return rasterise_points(array, *size)
  raise DataError(path, f"depth .npy of shape {array.shape} is neither the image size "
                        f"{size} nor sparse (N, 3) points")


def _sequence_files(root: Path, seq: str, depth: bool, panoptic: PanopticSource | None
                    ) -> list[FrameFiles]:
  seq_dir = require_dir(root / seq, "Waymo sequence directory")
  image_dir = seq_dir / "image"
  images = list_images(image_dir, (".png", ".jpg", ".jpeg"))
  require_frames(images, image_dir, "{frame:06d}.{png,jpg}")
  calib = read_calib(seq_dir / "calib.json") if (seq_dir / "calib.json").exists() else None
  depth_dir = require_dir(seq_dir / "depth", "depth directory") if depth else None
  if panoptic is None and (seq_dir / "panoptic").is_dir():
    panoptic, prefix = PanopticSource(seq_dir / "panoptic"), ""
  else:
    prefix = f"{seq}/"
  files = []
  for stem in sorted(images):
    depth_file, depth = ("", None) if depth_dir is None else depth_loader(
        depth_dir, stem,
        read_npy=functools.partial(read_waymo_depth_npy, image=images[stem], calib=calib))
    files.append(FrameFiles(
        name=f"{seq}/{stem}", image=images[stem], depth=depth, depth_file=str(depth_file),
        panoptic=None if panoptic is None else panoptic.ref(prefix + stem),
        size=None if calib is None else (calib.height, calib.width),
        size_source=None if calib is None else seq_dir / "calib.json",
        intrinsics=None if calib is None else calib.K,
        intrinsics_source=None if calib is None else seq_dir / "calib.json", recording=seq))
  return files


def list_sequences(root: PathLike) -> list[str]:
  """Sorted names of the directories of `root` that have an `image/` subdirectory."""
  root = require_dir(root, "Waymo root")
  return sorted(p.name for p in root.iterdir() if (p / "image").is_dir())


def open_waymo(root: PathLike, sequences: Sequence[str] | str | None = None, depth: bool = True,
               panoptic_dir: PathLike | None = None, panoptic_json: PathLike | None = None
               ) -> FrameSequence:
  """Opens Waymo FRONT-camera sequences in the layout of the module docstring.

  Args:
    root: the directory of sequence directories (or one sequence directory).
    sequences: names of the sequences to read, in this order (a comma-separated string is
      accepted); None = all, sorted.
    depth: read the depth maps (every image must have one).
    panoptic_dir: COCO panoptic PNGs (+ JSONs) as `<panoptic_dir>/<seq>/<frame>.png`
      (default: each sequence's `panoptic/` directory when it exists).
    panoptic_json: a COCO panoptic annotation file for those PNGs (file_name `<seq>/<frame>.png`).

  Returns:
    the frames, sequence after sequence (temporal order), loaded on access; K from calib.json.
  """
  root = require_dir(root, "Waymo root")
  if sequences is None and (root / "image").is_dir():  # the root is one sequence directory
    root, sequences = root.absolute().parent, [root.absolute().name]
  if sequences is None:
    sequences = list_sequences(root)
    require_frames(sequences, root, "<seq>/image/ directories")
  elif isinstance(sequences, str):
    sequences = [s.strip() for s in sequences.split(",") if s.strip()]
  repeated = sorted({s for s in sequences if list(sequences).count(s) > 1})
  if repeated:  # its frames would be run and scored twice, the repeat paired with the first
    raise DataError(root, f"sequences: {', '.join(repeated)} given more than once")
  panoptic = panoptic_source(panoptic_dir, panoptic_json)
  files = []
  for seq in sequences:
    files += _sequence_files(root, seq, depth, panoptic)
  return FrameSequence(files, temporal=True, remedies={"intrinsics": INTRINSICS_REMEDY},
                       notes=panoptic.notes if panoptic else ())
