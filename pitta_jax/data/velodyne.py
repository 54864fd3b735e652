"""KITTI raw ground truth from the Velodyne scans, as MonoDepth2's `export_gt_depth.py` makes it.

MonoDepth2 evaluates the Eigen split on `gt_depths.npz`, which its `export_gt_depth.py` writes by
projecting each frame's scan (`<folder>/velodyne_points/data/{frame:010d}.bin`, float32 x, y, z,
reflectance per point) into the image (`kitti_utils.generate_depth_map(calib_dir, velo, cam=2,
vel_depth=True)`). `velodyne_depth` computes the same map, so a KITTI raw tree with its scans
needs no exported file:

- calibration of the date folder: `calib_velo_to_cam.txt` (R, T: Velodyne -> camera 0) and
  `calib_cam_to_cam.txt` (R_rect_00, P_rect_0{cam}; the map's size is camera 2's `S_rect_02`,
  for either camera, as upstream);
- points with x >= 0 (in front of the sensor) are projected with P_rect_0{cam} R_rect_00
  [R | T]; the reflectance column is replaced by 1 (homogeneous coordinates);
- `vel_depth`: the depth written is the point's Velodyne x (forward distance), not the camera's
  z; `export_gt_depth.py` asks for this;
- pixel = round(u) - 1, round(v) - 1 (NumPy's round, halves to even; "minus 1 to get the exact
  same value as KITTI's matlab code"), kept inside the image;
- several points on one pixel: the nearest depth. Upstream finds such pixels with the linear
  index row * (W - 1) + col - 1, which also gives the last pixel of a row and the first of the
  next one the same index; such a pair counts as one pixel and the smaller depth of the two is
  written at the first point's position. We keep this, so that the maps equal the exported ones;
- negative depths become 0; float32, as the export saves them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pitta_jax.data.calib import (KITTI_CAM_TO_CAM, KITTI_VELO_TO_CAM, read_calib_txt,
                                  rectified_calib)
from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import PathLike, require_file


def velodyne_path(data: Path, folder: str, frame: int) -> Path:
  """Where KITTI raw keeps the scan of `frame` of the drive `folder` (`<date>/<drive>`)."""
  return data / folder / "velodyne_points" / "data" / f"{frame:010d}.bin"


def read_velodyne_points(path: PathLike) -> np.ndarray:
  """(N, 4) float32 homogeneous points (x, y, z, 1) of a KITTI `.bin` scan (its fourth column,
  the reflectance, replaced by 1)."""
  path = require_file(path, "Velodyne scan")
  raw = np.fromfile(path, dtype="<f4")
  if path.stat().st_size % 16:  # (bytes: a scan cut 13 bytes short still holds whole floats)
    raise DataError(path, f"{path.stat().st_size} bytes is not a KITTI scan of float32 (x, y, "
                          f"z, reflectance) points (16 bytes each)")
  points = raw.reshape(-1, 4).copy()
  points[:, 3] = 1.0
  return points


def _entry(entries: dict[str, np.ndarray], path: Path, key: str, size: int) -> np.ndarray:
  value = entries.get(key)
  if value is None or value.size != size:
    raise DataError(path, f"no valid {key} ({size} numbers) in the calibration file")
  return value


def velodyne_projection(calib_dir: PathLike, camera: int) -> tuple[np.ndarray, tuple[int, int]]:
  """(P (3, 4) float64 from Velodyne points to camera `camera`'s rectified image, the map's
  (H, W) from S_rect_02) for KITTI raw's date folder `calib_dir`."""
  calib_dir = Path(calib_dir)
  velo_path, cam_path = calib_dir / KITTI_VELO_TO_CAM, calib_dir / KITTI_CAM_TO_CAM
  velo = read_calib_txt(velo_path)
  cam = read_calib_txt(cam_path)
  velo_to_cam = np.eye(4)
  velo_to_cam[:3, :3] = _entry(velo, velo_path, "R", 9).reshape(3, 3)
  velo_to_cam[:3, 3] = _entry(velo, velo_path, "T", 3)
  rect = np.eye(4)
  rect[:3, :3] = _entry(cam, cam_path, "R_rect_00", 9).reshape(3, 3)
  P_rect = _entry(cam, cam_path, f"P_rect_0{camera}", 12).reshape(3, 4)
  size = rectified_calib(cam_path, "02").size  # S_rect_02, checked there
  if size is None:
    raise DataError(cam_path, "no S_rect_02 (width height): the ground truth's size")
  return P_rect @ rect @ velo_to_cam, size


def velodyne_depth(calib_dir: PathLike, scan: PathLike, camera: int = 2,
                   vel_depth: bool = True) -> np.ndarray:
  """(H, W) float32 ground-truth depth of one scan, 0 where no point falls (module docstring).

  calib_dir: the date folder holding calib_velo_to_cam.txt and calib_cam_to_cam.txt; scan: the
  frame's `.bin`; camera: 2 or 3 (`export_gt_depth.py` always uses 2); vel_depth: depth = the
  Velodyne x (True, the export's) or the camera's z (False).
  """
  return project_scan(*velodyne_projection(calib_dir, camera), scan, vel_depth)


def project_scan(P: np.ndarray, size: tuple[int, int], scan: PathLike,
                 vel_depth: bool = True) -> np.ndarray:
  """`velodyne_depth` with the date's projection P (3, 4) and map size (H, W) already read
  (`velodyne_projection`): what a split's frames of one date share."""
  h, w = size
  points = read_velodyne_points(scan)
  points = points[points[:, 0] >= 0]
  image = (P @ points.T).T                                              # (N, 3) float64
  with np.errstate(divide="ignore", invalid="ignore"):  # z = 0: off the image, as upstream
    image[:, :2] = image[:, :2] / image[:, 2:3]
  if vel_depth:
    image[:, 2] = points[:, 0]
  cols, rows = np.round(image[:, 0]) - 1, np.round(image[:, 1]) - 1
  inside = (cols >= 0) & (rows >= 0) & (cols < w) & (rows < h)
  cols, rows, depth_values = cols[inside].astype(int), rows[inside].astype(int), image[inside, 2]
  depth = np.zeros((h, w))
  depth[rows, cols] = depth_values
  index = rows * (w - 1) + cols - 1            # upstream's sub2ind: not one-to-one (docstring)
  _, first, group, counts = np.unique(index, return_index=True, return_inverse=True,
                                      return_counts=True)
  nearest = np.full(first.size, np.inf)
  np.minimum.at(nearest, group, depth_values)
  shared = counts > 1
  depth[rows[first[shared]], cols[first[shared]]] = nearest[shared]
  depth[depth < 0] = 0
  return depth.astype(np.float32)


__all__ = ["velodyne_path", "read_velodyne_points", "velodyne_projection", "velodyne_depth",
           "project_scan"]
