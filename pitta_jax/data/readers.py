"""The dataset registry: `open_dataset(name, root, **options)` -> lazily loaded frames.

  drivingstereo  `drivingstereo.open_drivingstereo`  weather subsets: left images + depth maps
  kitti          `kitti.open_kitti`                  KITTI raw + MonoDepth2 split + gt_depths.npz, improved GT or Velodyne scans
  waymo          `waymo.open_waymo`                  our FRONT-camera layout (see waymo.py)
  folder         `folder.open_folder`                images (+ depth, + panoptic) by stem

Every reader returns a `FrameSequence` (len(), indexing, slicing, iteration) whose frames are
read when accessed, at native resolution (`resize.resize_frame` brings them to the network size).
"""

from __future__ import annotations

import inspect
from typing import Any, Callable

from pitta_jax.data.drivingstereo import open_drivingstereo
from pitta_jax.data.errors import DataError
from pitta_jax.data.folder import open_folder
from pitta_jax.data.image_io import PathLike
from pitta_jax.data.kitti import open_kitti
from pitta_jax.data.sequence import FrameSequence
from pitta_jax.data.waymo import open_waymo

READERS: dict[str, Callable[..., FrameSequence]] = {
    "drivingstereo": open_drivingstereo,
    "kitti": open_kitti,
    "waymo": open_waymo,
    "folder": open_folder,
}


def reader_options(name: str) -> tuple[str, ...]:
  """The keyword options of dataset `name` (everything after `root`)."""
  return tuple(p for p in inspect.signature(READERS[name]).parameters if p != "root")


def open_dataset(name: str, root: PathLike, **options: Any) -> FrameSequence:
  """Opens dataset `name` at `root`; DataError for an unknown name or option."""
  if name not in READERS:
    raise DataError(None, f"unknown dataset {name!r}; choose from {', '.join(READERS)}")
  unknown = sorted(set(options) - set(reader_options(name)))
  if unknown:
    raise DataError(None, f"dataset {name!r} has no option {', '.join(unknown)} (options: "
                          f"{', '.join(reader_options(name))})")
  required = [p.name for p in inspect.signature(READERS[name]).parameters.values()
              if p.name != "root" and p.default is inspect.Parameter.empty
              and p.name not in options]
  if required:
    raise DataError(None, f"dataset {name!r} needs " + " ".join(f"--option {r}=..."
                                                               for r in required))
  return READERS[name](root, **options)
