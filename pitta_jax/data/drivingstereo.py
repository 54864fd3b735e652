"""DrivingStereo weather subsets (left images + projected LiDAR depth), the paper's Table 1.

Layout of the weather archives as downloaded (see docs/datasets.md):

  <root>/<weather>/left-image-{half,full}-size/<stem>.{jpg,png}
  <root>/<weather>/depth-map-{half,full}-size/<stem>.png
  (some archives nest one level more: <root>/<weather>/<weather>/left-image-..., and an image or
  depth directory holding no image but a single subdirectory is entered, e.g.
  left-image-full-size/left-image-full-size/ from unzipping into a directory of the zip's name)

with `<stem> = <seq>_<YYYY-MM-DD-HH-MM-SS-mmm>`, the same stem for image and map. Half-size
images are `.jpg`, full-size images and all maps `.png` (either suffix is accepted for images;
the documented one wins when both exist). Depth: uint16 PNG, metres = value / 256, 0 = invalid.
Frames are sorted by stem (chronological within a sequence: the order is temporal); weather
"all" concatenates cloudy, foggy, rainy, sunny in that order (the paper's "All", adaptation
continuing across them). Frame names are `<weather>/<stem>`.

The stems' timestamps say how far apart the frames are: a weather whose frames are more than
`SPARSE_FRAMES_S` apart (median) is noted as a subsample of the drive (`frame_spacing_note`).

Size: `size=None` takes the size whose `left-image-<size>-size/` exists in every requested
weather: half when both do, else the only one (said in `FrameSequence.notes`).

Calibration (optional; frames then carry K): the per-sequence files of DrivingStereo's
calibration download, `half-image-calib/<seq>.txt` and `full-image-calib/<seq>.txt`, KITTI-style
text whose `P_rect_101` is the rectified left camera's projection (K = its left 3x3) and
`S_rect_101` its image size. Looked up in `calib_dir` (the `<seq>.txt` directory or its parent)
or else under `<root>`, `<root>/calib`, `<root>/calib_train`, `<root>/calib_test` and the
weather directory; the calibration of the size in use is preferred, the other one is scaled
to the image (full = 2 x half). A file without `S_rect_101` is for the size its folder names
(`half-image-calib/`, `full-image-calib/`, also when that folder is `calib_dir` itself).

Panoptic segmentations (optional) are COCO panoptic PNG + JSON with the image's stem, found in
`panoptic_dir` (`<stem>.png` or `<weather>/<stem>.png`; per-image JSONs or one COCO annotation
file inside or beside the directory, see `panoptic_io`), or with `panoptic_json` a COCO
annotation file, or else in `<root>/<weather>/panoptic/` when that directory exists (what the
synthetic exporter writes). Once a panoptic source applies, every frame must have its map.
"""

from __future__ import annotations

import datetime
import functools
from pathlib import Path

import numpy as np

from pitta_jax.data.calib import rectified_calib
from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import PathLike, list_images, read_depth_png, require_dir, require_file
from pitta_jax.data.panoptic_io import PanopticSource, panoptic_source
from pitta_jax.data.sequence import FrameFiles, FrameSequence, require_frames

WEATHERS = ("cloudy", "foggy", "rainy", "sunny")  # the order of the paper's "All"
SIZES = ("half", "full")
NOMINAL_SIZE = {"half": (400, 881), "full": (800, 1762)}  # (H, W) of each release size
CALIB_BASES = ("", "calib", "calib_train", "calib_test")  # under root, where calib folders lie
LEFT_CAMERA = "101"  # DrivingStereo's name of the left camera in the calibration files
INTRINSICS_REMEDY = ("DrivingStereo's calibration files <seq>.txt (half-image-calib/ or "
                     "full-image-calib/ of the calibration download) in --root or --root/calib/, "
                     "or --option calib_dir=DIR")


def _candidates(root: Path, weather: str) -> tuple[Path, Path]:
  return root / weather, root / weather / weather


def weather_dir(root: PathLike, weather: str, size: str = "half") -> Path:
  """The directory holding `left-image-<size>-size/` for `weather` (flat or nested layout)."""
  root = require_dir(root, "DrivingStereo root")
  image_dir = f"left-image-{size}-size"
  for candidate in _candidates(root, weather):
    if (candidate / image_dir).is_dir():
      return candidate
  raise DataError(root / weather, f"no {image_dir}/ directory here or in {weather}/{weather}/ "
                                  f"(is this a DrivingStereo weather subset?)")


def sizes_present(root: PathLike, weather: str) -> tuple[str, ...]:
  """The sizes whose `left-image-<size>-size/` exists for `weather`."""
  root = require_dir(root, "DrivingStereo root")
  return tuple(s for s in SIZES if any((c / f"left-image-{s}-size").is_dir()
                                       for c in _candidates(root, weather)))


def choose_size(root: PathLike, weathers: tuple[str, ...]) -> tuple[str, str | None]:
  """(size, note): half when every weather has both, else the one size all of them have."""
  root = require_dir(root, "DrivingStereo root")
  present = {w: sizes_present(root, w) for w in weathers}
  missing = [w for w, sizes in present.items() if not sizes]
  if missing and len(missing) < len(weathers):  # weather=all, some weathers not here
    have = [w for w in weathers if w not in missing]
    raise DataError(root, f"weather {', '.join(missing)} not found here (with the default "
                          f"weather=all every one of {', '.join(weathers)} is read); found "
                          f"{', '.join(have)}: --option weather={have[0]}")
  for w in missing:
    if any((root / f"left-image-{size}-size").is_dir() for size in SIZES):
      raise DataError(root, f"this is one weather's directory (it holds left-image-*-size/): "
                            f"pass its parent as --root and --option weather={root.name}")
    raise DataError(root / w, f"no left-image-half-size/ or left-image-full-size/ directory "
                              f"here or in {w}/{w}/ (is this a DrivingStereo weather subset?)")
  common = [s for s in SIZES if all(s in sizes for sizes in present.values())]
  if not common:
    found = ", ".join(f"{w}: {'/'.join(sizes)}" for w, sizes in present.items())
    raise DataError(root, f"no image size common to the weathers ({found}); pass --option "
                          f"size=half|full and complete that size")
  if len(common) == 2:
    return "half", ("DrivingStereo size=half: both left-image-half-size/ and "
                    "left-image-full-size/ are here; the half-size images and ground truth are "
                    "read and scored (--option size=full for the full size)")
  return common[0], (f"DrivingStereo size={common[0]}: the only left-image-*-size/ directory "
                     f"({', '.join(weathers)})")


def _enter_lone_subdir(directory: Path) -> Path:
  """`directory`, or the single subdirectory it holds when it has no file (unzipped twice)."""
  while True:
    entries = [p for p in directory.iterdir() if not p.name.startswith(".")]
    subdirs = [p for p in entries if p.is_dir()]
    if len(subdirs) != 1 or any(p.is_file() for p in entries):
      return directory
    directory = subdirs[0]


class _Calibrations:
  """The left camera's Calib per (sequence, size), from the first `<seq>.txt` found."""

  def __init__(self, root: Path, calib_dir: Path | None):
    self.root, self.calib_dir = root, calib_dir
    self._cache: dict[tuple[str, str, Path], dict] = {}

  def _dirs(self, wdir: Path, size: str) -> list[tuple[Path, str | None]]:
    """(directory, the size its files are for, if known) in search order."""
    kinds = (size,) + tuple(s for s in SIZES if s != size)  # the size in use first
    if self.calib_dir is not None:
      # a `<size>-image-calib/` given itself is for that size, as when found under it: its
      # files' P_rect_101 may come without S_rect_101 (K would be taken as the image's own)
      own = next((s for s in SIZES if self.calib_dir.name == f"{s}-image-calib"), None)
      dirs: list[tuple[Path, str | None]] = [(self.calib_dir, own)]
      bases = [self.calib_dir]
    else:
      dirs = []
      bases = [self.root / b for b in CALIB_BASES] + [wdir]
    for kind in kinds:
      for base in bases:
        dirs += [(base / f"{kind}-image-calib", kind),
                 (base / f"{kind}-image-calib" / f"{kind}-image-calib", kind)]
    return dirs

  def fields(self, seq: str, size: str, wdir: Path) -> dict:
    """The FrameFiles intrinsics fields of sequence `seq` ({} without a calibration file)."""
    key = (seq, size, wdir)
    if key not in self._cache:
      self._cache[key] = {}
      for directory, kind in self._dirs(wdir, size):
        path = directory / f"{seq}.txt"
        if path.is_file():
          calib = rectified_calib(path, LEFT_CAMERA)
          self._cache[key] = {
              "intrinsics": calib.K, "intrinsics_source": path,
              "intrinsics_size": calib.size or (NOMINAL_SIZE[kind] if kind else None)}
          break
      else:
        if self.calib_dir is not None:
          raise DataError(self.calib_dir / f"{seq}.txt", "calibration file not found (nor in "
                                                         "half-image-calib/ or full-image-calib/)")
    return self._cache[key]


# frames further apart than this (median, seconds) are noted as a subsample of the drive: the
# KITTI raw drives that MonoDepth2-style self-supervision was built on run at 10 Hz (0.1 s)
SPARSE_FRAMES_S = 0.2


def frame_spacing_note(weather: str, stems: list[str]) -> str | None:
  """A note on how far apart in time a weather's frames are, from the timestamps in their stems
  (`<seq>_<YYYY-MM-DD-HH-MM-SS-mmm>`), when the median gap within a recording exceeds
  `SPARSE_FRAMES_S`: the methods that pair consecutive frames (CoMoDa's and Ada-Depth's warps)
  then see the motion of that interval. None when the stems carry no such timestamps."""
  epoch = datetime.datetime(1970, 1, 1)  # naive: differences without time zones
  times: dict[str, list[float]] = {}
  for stem in stems:
    seq, _, stamp = stem.partition("_")
    try:
      t = datetime.datetime.strptime(stamp, "%Y-%m-%d-%H-%M-%S-%f")
    except ValueError:
      return None
    times.setdefault(seq, []).append((t - epoch).total_seconds())
  gaps = np.concatenate([np.diff(np.sort(ts)) for ts in times.values()])  # within recordings
  if not gaps.size or float(np.median(gaps)) <= SPARSE_FRAMES_S:
    return None
  return (f"DrivingStereo {weather}: consecutive frames are {float(np.median(gaps)):.2f} s apart "
          f"(median; largest {float(gaps.max()):.1f} s), a subsample of the drive rather than "
          f"video-rate frames: methods that pair consecutive frames (CoMoDa, Ada-Depth) see "
          f"that interval's motion")


def _weather_files(root: Path, weather: str, size: str, depth: bool,
                   panoptic: PanopticSource | None, calibs: _Calibrations) -> list[FrameFiles]:
  wdir = weather_dir(root, weather, size)
  image_dir = _enter_lone_subdir(wdir / f"left-image-{size}-size")
  suffixes = (".jpg", ".png", ".jpeg") if size == "half" else (".png", ".jpg", ".jpeg")
  images = list_images(image_dir, suffixes)
  require_frames(images, image_dir, "<seq>_<timestamp>" + "{" + ",".join(suffixes) + "}")
  depth_dir = None
  if depth:
    depth_dir = _enter_lone_subdir(require_dir(
        wdir / f"depth-map-{size}-size", "depth directory (--option depth=false to run without "
                                         "ground truth)"))
  if panoptic is None and (wdir / "panoptic").is_dir():
    panoptic = PanopticSource(wdir / "panoptic")
  files = []
  for stem in sorted(images):
    depth_loader, depth_png = None, ""
    if depth_dir is not None:
      depth_png = require_file(depth_dir / f"{stem}.png", "depth map")
      depth_loader = functools.partial(read_depth_png, depth_png)
    panoptic_ref = None
    if panoptic is not None:
      nested_key = f"{weather}/{stem}"
      panoptic_ref = panoptic.ref(nested_key if panoptic.has(nested_key) else stem)
    seq = stem.split("_")[0]  # the recording: <seq>_<timestamp>
    files.append(FrameFiles(name=f"{weather}/{stem}", image=images[stem], depth=depth_loader,
                            depth_file=str(depth_png),
                            panoptic=panoptic_ref, recording=f"{weather}/{seq}",
                            **calibs.fields(seq, size, wdir)))
  return files


def open_drivingstereo(root: PathLike, weather: str = "all", size: str | None = None,
                       depth: bool = True, panoptic_dir: PathLike | None = None,
                       panoptic_json: PathLike | None = None, calib_dir: PathLike | None = None
                       ) -> FrameSequence:
  """Opens DrivingStereo weather subsets.

  Args:
    root: the directory holding `cloudy/`, `foggy/`, `rainy/`, `sunny/`.
    weather: one of `WEATHERS`, or "all" (cloudy, foggy, rainy, sunny concatenated).
    size: "half" (about 881x400) or "full" (1762x800) images and maps; None = the size present
      (half when both are).
    depth: read the ground-truth depth maps (every image must have one).
    panoptic_dir: directory of COCO panoptic PNGs (+ per-image JSONs or one annotation file)
      named by stem.
    panoptic_json: a COCO panoptic annotation file for those PNGs.
    calib_dir: directory of the calibration files `<seq>.txt` (or of `half-image-calib/` and
      `full-image-calib/`); None = searched under root (module docstring).

  Returns:
    the frames (temporal order), loaded on access; image (H, W, 3), depth (H, W) metres, K
    when a calibration file was found.
  """
  weather = weather.lower()
  if weather != "all" and weather not in WEATHERS:
    raise DataError(root, f"unknown DrivingStereo weather {weather!r}; choose from "
                          f"{', '.join(WEATHERS)} or all")
  if size is not None and size not in SIZES:
    raise DataError(root, f"unknown DrivingStereo size {size!r}; choose half or full")
  root = require_dir(root, "DrivingStereo root")
  weathers = WEATHERS if weather == "all" else (weather,)
  notes = []
  if size is None:
    size, note = choose_size(root, weathers)
    notes += [note] if note else []
  calibs = _Calibrations(root, None if calib_dir is None else require_dir(
      calib_dir, "calibration directory (--option calib_dir)"))
  panoptic = panoptic_source(panoptic_dir, panoptic_json)
  files = []
  for w in weathers:
    part = _weather_files(root, w, size, depth, panoptic, calibs)
    note = frame_spacing_note(w, [f.name.split("/", 1)[1] for f in part])
    notes += [note] if note else []
    files += part
  return FrameSequence(files, temporal=True, remedies={"intrinsics": INTRINSICS_REMEDY},
                       notes=notes + list(panoptic.notes if panoptic else ()))
