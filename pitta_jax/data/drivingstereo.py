"""DrivingStereo weather subsets (left images + projected LiDAR depth), the paper's Table 1.

Layout of the weather archives (see docs/datasets.md):

  <root>/<weather>/left-image-{half,full}-size/<stem>.{jpg,png}
  <root>/<weather>/depth-map-{half,full}-size/<stem>.png
  (some archives nest one level more: <root>/<weather>/<weather>/left-image-...)

with `<stem> = <seq>_<YYYY-MM-DD-HH-MM-SS-mmm>`, the same stem for image and map. Half-size
images are `.jpg`, full-size images and all maps `.png` (either suffix is accepted for images;
the documented one wins when both exist). Depth: uint16 PNG, metres = value / 256, 0 = invalid.
Frames are sorted by stem (chronological within a sequence); weather "all" concatenates
cloudy, foggy, rainy, sunny in that order (the paper's "All", adaptation continuing across
them). Frame names are `<weather>/<stem>`.

Panoptic segmentations (optional) are COCO panoptic PNG + JSON with the image's stem, found in
`panoptic_dir` (`<stem>.png` or `<weather>/<stem>.png`), or with `panoptic_json` a COCO
annotation file, or else in `<root>/<weather>/panoptic/` when that directory exists (what the
synthetic exporter writes). Once a panoptic source applies, every frame must have its map.
"""

from __future__ import annotations

import functools
from pathlib import Path

from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import PathLike, list_images, read_depth_png, require_dir, require_file
from pitta_jax.data.panoptic_io import PanopticSource, panoptic_source
from pitta_jax.data.sequence import FrameFiles, FrameSequence, require_frames

WEATHERS = ("cloudy", "foggy", "rainy", "sunny")  # the order of the paper's "All"
SIZES = ("half", "full")


def weather_dir(root: PathLike, weather: str, size: str = "half") -> Path:
  """The directory holding `left-image-<size>-size/` for `weather` (flat or nested layout)."""
  root = require_dir(root, "DrivingStereo root")
  flat, nested = root / weather, root / weather / weather
  image_dir = f"left-image-{size}-size"
  for candidate in (flat, nested):
    if (candidate / image_dir).is_dir():
      return candidate
  raise DataError(flat, f"no {image_dir}/ directory here or in {weather}/{weather}/ "
                        f"(is this a DrivingStereo weather subset?)")


def _weather_files(root: PathLike, weather: str, size: str, depth: bool,
                   panoptic: PanopticSource | None) -> list[FrameFiles]:
  wdir = weather_dir(root, weather, size)
  image_dir = wdir / f"left-image-{size}-size"
  suffixes = (".jpg", ".png", ".jpeg") if size == "half" else (".png", ".jpg", ".jpeg")
  images = list_images(image_dir, suffixes)
  require_frames(images, image_dir, "<seq>_<timestamp>" + "{" + ",".join(suffixes) + "}")
  depth_dir = require_dir(wdir / f"depth-map-{size}-size", "depth directory") if depth else None
  if panoptic is None and (wdir / "panoptic").is_dir():
    panoptic = PanopticSource(wdir / "panoptic")
  files = []
  for stem in sorted(images):
    depth_loader = None
    if depth_dir is not None:
      depth_png = require_file(depth_dir / f"{stem}.png", "depth map")
      depth_loader = functools.partial(read_depth_png, depth_png)
    panoptic_ref = None
    if panoptic is not None:
      nested_key = f"{weather}/{stem}"
      panoptic_ref = panoptic.ref(nested_key if panoptic.has(nested_key) else stem)
    files.append(FrameFiles(name=f"{weather}/{stem}", image=images[stem], depth=depth_loader,
                            panoptic=panoptic_ref))
  return files


def open_drivingstereo(root: PathLike, weather: str = "all", size: str = "half",
                       depth: bool = True, panoptic_dir: PathLike | None = None,
                       panoptic_json: PathLike | None = None) -> FrameSequence:
  """Opens DrivingStereo weather subsets.

  Args:
    root: the directory holding `cloudy/`, `foggy/`, `rainy/`, `sunny/`.
    weather: one of `WEATHERS`, or "all" (cloudy, foggy, rainy, sunny concatenated).
    size: "half" (about 881x400) or "full" (1762x800) images and maps.
    depth: read the ground-truth depth maps (every image must have one).
    panoptic_dir: directory of COCO panoptic PNGs (+ per-image JSONs) named by stem.
    panoptic_json: a COCO panoptic annotation file for those PNGs.

  Returns:
    the frames, loaded on access; image (H, W, 3), depth (H, W) metres.
  """
  weather = weather.lower()
  if weather != "all" and weather not in WEATHERS:
    raise DataError(root, f"unknown DrivingStereo weather {weather!r}; choose from "
                          f"{', '.join(WEATHERS)} or all")
  if size not in SIZES:
    raise DataError(root, f"unknown DrivingStereo size {size!r}; choose half or full")
  panoptic = panoptic_source(panoptic_dir, panoptic_json)
  weathers = WEATHERS if weather == "all" else (weather,)
  files = []
  for w in weathers:
    files += _weather_files(root, w, size, depth, panoptic)
  return FrameSequence(files)
