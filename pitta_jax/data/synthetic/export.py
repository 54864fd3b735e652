"""Writes synthetic frames in the DrivingStereo on-disk layout (plus COCO panoptic).

Layout under `root` (one folder per weather, as the DrivingStereo weather subsets)::

  <root>/<weather>/left-image-full-size/<stem>.png   8-bit RGB image
  <root>/<weather>/depth-map-full-size/<stem>.png    uint16: round(metres * 256), 0 = invalid
  <root>/<weather>/panoptic/<stem>.png               COCO panoptic RGB, id = R + 256 G + 256^2 B
  <root>/<weather>/panoptic/<stem>.json              {"file_name", "segments_info": [{"id",
                                                       "category_id", "iscrowd": 0, "bbox":
                                                       [x, y, w, h], "area", "isthing"}]}
  <root>/<weather>/full-image-calib/<seq>.txt        the camera, as DrivingStereo's calibration
                                                     files: S_rect_101 (W H), P_rect_101 = [K|0]

`stem` = `<seq>_<YYYY-MM-DD-HH-MM-SS-mmm>` as in DrivingStereo (e.g.
`2018-10-25-07-37-26_2018-10-25-07-37-26-100`): `seq` is the start time of the sequence and
the second part the frame's timestamp, frames `1 / fps` apart.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from pitta_jax.data.frame import Frame

DEFAULT_START = datetime.datetime(2018, 10, 25, 7, 37, 26)


def stem(start: datetime.datetime, index: int, fps: float = 10.0) -> str:
  """DrivingStereo-style file stem of frame `index` of the sequence started at `start`."""
  ts = start + datetime.timedelta(seconds=index / fps)
  return (f"{start:%Y-%m-%d-%H-%M-%S}_{ts:%Y-%m-%d-%H-%M-%S}-"
          f"{ts.microsecond // 1000:03d}")


def encode_panoptic(ids: np.ndarray) -> np.ndarray:
  """(H, W) int ids -> (H, W, 3) uint8 RGB with id = R + 256 G + 256^2 B."""
  ids = np.asarray(ids, np.int64)
  if ids.min(initial=0) < 0 or ids.max(initial=0) >= 256 ** 3:
    raise ValueError("panoptic ids must be in [0, 256^3)")
  return np.stack([ids % 256, ids // 256 % 256, ids // 65536], -1).astype(np.uint8)


def segments_info(frame: Frame) -> list[dict]:
  """COCO panoptic `segments_info` of a frame: bbox [x, y, w, h] and area from the id map."""
  out = []
  for seg in frame.segments:
    ys, xs = np.nonzero(frame.panoptic == seg.id)
    if len(ys) == 0:
      continue
    x0, y0 = int(xs.min()), int(ys.min())
    out.append({"id": int(seg.id), "category_id": int(seg.category_id), "iscrowd": 0,
                "bbox": [x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1],
                "area": int(len(ys)), "isthing": int(seg.isthing)})
  return out


def _write(path: Path, array: np.ndarray) -> None:
  path.parent.mkdir(parents=True, exist_ok=True)
  if not cv2.imwrite(str(path), array):
    raise OSError(f"{path}: could not write")


def export_drivingstereo(frames: Iterable[Frame], root: str | Path, weather_name: str,
                         start: datetime.datetime = DEFAULT_START,
                         fps: float = 10.0) -> list[str]:
  """Writes `frames` (in order) under `<root>/<weather_name>/` (see the module docstring).

  Returns the stems written. Depths above 65535 / 256 m are clipped; 0 stays invalid.
  """
  base = Path(root) / weather_name
  stems = []
  for i, fr in enumerate(frames):
    name = stem(start, i, fps)
    rgb = (np.clip(fr.image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    _write(base / "left-image-full-size" / f"{name}.png", rgb[..., ::-1])   # cv2 wants BGR
    if fr.depth is not None:
      depth = np.clip(np.round(np.asarray(fr.depth, np.float64) * 256.0), 0, 65535)
      _write(base / "depth-map-full-size" / f"{name}.png", depth.astype(np.uint16))
    if fr.panoptic is not None:
      _write(base / "panoptic" / f"{name}.png", encode_panoptic(fr.panoptic)[..., ::-1])
      info = {"file_name": f"{name}.png", "segments_info": segments_info(fr)}
      (base / "panoptic" / f"{name}.json").write_text(json.dumps(info))
    if i == 0 and fr.intrinsics is not None:
      write_calib(base / "full-image-calib" / f"{name.split('_')[0]}.txt", fr.intrinsics,
                  fr.image.shape[:2])
    stems.append(name)
  return stems


def write_calib(path: Path, K: np.ndarray, size: tuple[int, int]) -> None:
  """A DrivingStereo-style calibration file of the left camera: `S_rect_101: W H` and
  `P_rect_101: K | 0` (row-major 3x4), what `data.calib.rectified_calib` reads."""
  P = np.concatenate([np.asarray(K, np.float64), np.zeros((3, 1))], axis=1)
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text(f"S_rect_101: {size[1]:.6e} {size[0]:.6e}\n"
                  f"P_rect_101: {' '.join(f'{v:.9e}' for v in P.ravel())}\n")
