"""Camera calibration files the readers share: KITTI-style text and our JSON.

- KITTI-style text (KITTI raw `calib_cam_to_cam.txt`, DrivingStereo's per-sequence
  `<seq>.txt` of `half-image-calib/` and `full-image-calib/`): one `key: numbers` entry per line,
  e.g. `P_rect_02: fu 0 cu tx 0 fv cv ty 0 0 1 tz` (the rectified 3x4 projection, row-major) and
  `S_rect_02: width height` (the rectified image size). Non-numeric entries (`calib_time: ...`)
  are skipped. The camera matrix K of a rectified image is the left 3x3 of its `P_rect_*`.
- JSON (`calib.json`): `{"K": [[fu, 0, cu], [0, fv, cv], [0, 0, 1]] (or 9 numbers), "width": W,
  "height": H}`, what our Waymo recipe writes and what a folder of images may carry.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import PathLike, require_file

# KITTI raw's calibration files, one pair per date folder (the date's calibration download)
KITTI_CAM_TO_CAM = "calib_cam_to_cam.txt"
KITTI_VELO_TO_CAM = "calib_velo_to_cam.txt"


@dataclasses.dataclass(frozen=True)
class Calib:
  """One camera: K (3, 3) float64 pinhole intrinsics of images of `width` x `height` pixels
  (None when the file does not say; the image's own size then applies)."""
  K: np.ndarray
  width: int | None = None
  height: int | None = None

  @property
  def size(self) -> tuple[int, int] | None:
    """(H, W) of the images K belongs to, or None."""
    return None if self.width is None or self.height is None else (self.height, self.width)


def check_intrinsics(K: np.ndarray, path: PathLike, what: str = "K") -> np.ndarray:
  """K (3, 3) if it is a pinhole camera matrix: finite, focal lengths fx, fy > 0, no skew
  requirement, bottom row (0, 0, 1); DataError naming the file otherwise (methods that warp
  with K invert it)."""
  if not np.all(np.isfinite(K)):
    raise DataError(path, f"{what} has non-finite values: {K.tolist()}")
  if not (K[0, 0] > 0 and K[1, 1] > 0):
    raise DataError(path, f"{what} must have positive focal lengths fx = K[0][0], fy = K[1][1], "
                          f"got {K[0, 0]:g}, {K[1, 1]:g}")
  if not np.array_equal(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
    raise DataError(path, f"{what} must be a pinhole camera matrix [[fx, s, cx], [0, fy, cy], "
                          f"[0, 0, 1]], got {K.tolist()}")
  return K


def read_calib_txt(path: PathLike) -> dict[str, np.ndarray]:
  """Every numeric `key: v1 v2 ...` entry of a KITTI-style calibration file (float64 arrays)."""
  path = require_file(path, "calibration file")
  entries = {}
  for line in path.read_text(errors="replace").splitlines():
    key, sep, values = line.partition(":")
    if not sep:
      continue
    try:
      entries[key.strip()] = np.array([float(v) for v in values.split()], np.float64)
    except ValueError:
      continue  # e.g. calib_time: 09-Jan-2012 13:57:47
  return entries


def rectified_calib(path: PathLike, camera: str) -> Calib:
  """K from `P_rect_<camera>` (12 numbers) and the size from `S_rect_<camera>` when present.

  camera: "02"/"03" for KITTI raw's colour cameras, "101"/"103" for DrivingStereo's left/right.
  """
  entries = read_calib_txt(path)
  p = entries.get(f"P_rect_{camera}")
  if p is None or p.size != 12:
    raise DataError(path, f"no valid P_rect_{camera} (12 numbers) in the calibration file")
  size = entries.get(f"S_rect_{camera}")
  width = height = None
  if size is not None:
    if (size.size != 2 or not np.all(np.isfinite(size)) or not np.all(size > 0)
        or not np.all(size == np.round(size))):
      raise DataError(path, f"S_rect_{camera} must be 2 positive integers (width height), got "
                            f"{size.tolist()}")
    width, height = int(size[0]), int(size[1])
  K = check_intrinsics(p.reshape(3, 4)[:, :3].copy(), path, f"P_rect_{camera}'s left 3x3")
  return Calib(K=K, width=width, height=height)


def read_calib_json(path: PathLike) -> Calib:
  """Reads a `calib.json` (`K` as 3x3 or 9 numbers, `width`, `height`)."""
  path = require_file(path, "calibration file")
  try:
    data = json.loads(Path(path).read_text())
    K = np.asarray(data["K"], np.float64).reshape(3, 3)
    width, height = data["width"], data["height"]
  except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
    raise DataError(path, f"expected JSON with K (3x3), width and height ({type(e).__name__}: "
                          f"{e})") from None
  if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
    raise DataError(path, f"width and height must be positive integers, got {width!r}, {height!r}")
  return Calib(K=check_intrinsics(K, path), width=width, height=height)
