"""KITTI raw frames listed by a MonoDepth2 split file, with Eigen or improved ground truth.

Split file (MonoDepth2 `splits/<split>/test_files.txt`): one frame per line,
`<folder> <frame> <side>`, e.g. `2011_09_26/2011_09_26_drive_0002_sync 0000000069 l`; side
`l`/`2` = left colour camera (`image_02`), `r`/`3` = right (`image_03`). Images:
`<data>/<folder>/image_0{2,3}/data/{frame:010d}.{jpg,png}` (MonoDepth2 converts the PNGs to JPEG;
both are accepted, `ext` forces one).

Ground truth: `improved_gt` if given, else `gt_depths`, else the Velodyne scans:
- `gt_depths`: MonoDepth2's `gt_depths.npz` (written by `export_gt_depth.py`), key `data`, one
  float32 (H, W) map per split line, in the split's order. The maps differ in size, so the
  array was saved as an *object* array, i.e. a pickle. Unpickling runs code named in the file,
  so we never call `np.load(allow_pickle=True)`: `load_gt_depths` reads the pickle with an
  allow-list unpickler that can only rebuild NumPy arrays and dtypes and rejects anything else.
  The whole object array is unpickled at once (about 1.3 GB for the 697 Eigen test maps) on the
  first frame that needs it, then shared by all frames. Default: `gt_depths.npz` beside the
  split file, when it exists.
- `improved_gt`: the KITTI depth-completion annotations (Uhrig et al.),
  `<improved_gt>/[train/|val/]<drive>/proj_depth/groundtruth/image_0{2,3}/{frame:010d}.png`,
  uint16 / 256. They cover 652 of the 697 Eigen test frames: use MonoDepth2's
  `eigen_benchmark` split with them.
- the drives' Velodyne scans, `<data>/<folder>/velodyne_points/data/{frame:010d}.bin`, when
  neither is given and there is no `gt_depths.npz` beside the split file: each map is computed
  as `export_gt_depth.py` computes it (`pitta_jax.data.velodyne`), with the date folder's
  `calib_velo_to_cam.txt` and `calib_cam_to_cam.txt`.

`Frame.depth` is the ground-truth map at its own size (375x1242 or so); the metrics module
scores it (1e-3 < gt < 80). A split file in a folder named `eigen` (MonoDepth2's
`splits/eigen/test_files.txt`) is evaluated inside the Garg crop, as MonoDepth2's
`evaluate_depth.py --eval_split eigen` does (`FrameSequence.evaluation`); one under
`eigen_benchmark/` (the improved ground truth) on every pixel with ground truth > 0, without
the crop, as `--eval_split eigen_benchmark`; other splits on 1e-3 < gt < 80 without the crop. Frame names are
`<folder>/image_0{2,3}/{frame:010d}`; panoptic maps (optional) are looked up under the image's
relative path without suffix, `<folder>/image_0{2,3}/data/{frame:010d}`, in `panoptic_dir`.
Frames carry K from `<date>/calib_cam_to_cam.txt` when it exists; a split is temporal when its
lines are runs of consecutive frames (`split_is_temporal`).

`open_raw_sequences` reads whole raw drives without a split (CoMoDa's source replay set).
"""

from __future__ import annotations

import functools
import os
import pickle
import zipfile
import zlib
from pathlib import Path

import numpy as np

from weights_convert.pth import CheckpointError, ForbiddenGlobalError, unpickle_arrays

from pitta_jax.data.calib import KITTI_CAM_TO_CAM, Calib, rectified_calib
from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import (PathLike, list_images, read_depth_png, require_dir,
                                     require_file)
from pitta_jax.data.panoptic_io import panoptic_source
from pitta_jax.data.sequence import FrameFiles, FrameSequence, require_frames
from pitta_jax.data.velodyne import project_scan, velodyne_path, velodyne_projection

SIDE_TO_CAMERA = {"l": 2, "r": 3, "2": 2, "3": 3}
INTRINSICS_REMEDY = (f"KITTI raw's <date>/{KITTI_CAM_TO_CAM} (the date's calibration "
                     f"download) in --root")

def _open_npy_member(path: Path, archive: zipfile.ZipFile, key: str):
  member = f"{key}.npy"
  if member not in archive.namelist():
    raise DataError(path, f"no array '{key}' in the .npz (has: "
                          f"{', '.join(n.removesuffix('.npy') for n in archive.namelist())})")
  stream = archive.open(member)
  version = np.lib.format.read_magic(stream)
  if version == (1, 0):
    shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
  elif version == (2, 0):
    shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream)
  else:
    raise DataError(path, f"unsupported .npy format version {version} for '{key}'")
  return stream, shape, fortran, dtype


def gt_depths_count(path: PathLike, key: str = "data") -> int:
  """Number of maps in a `gt_depths.npz` (from the array header, nothing unpickled)."""
  path = require_file(path, "gt_depths file")
  try:
    with zipfile.ZipFile(path) as archive:
      stream, shape, _, _ = _open_npy_member(path, archive, key)
      stream.close()
  # zlib.error: damaged deflate data (export_gt_depth.py writes it with np.savez_compressed)
  except (zipfile.BadZipFile, zlib.error, ValueError, OSError) as e:
    raise DataError(path, f"not a readable .npz file ({e})") from None
  if not shape:
    raise DataError(path, f"'{key}' is a scalar, expected one depth map per split line")
  return shape[0]


def read_cam_to_cam(path: Path, camera: int) -> np.ndarray:
  """K (3, 3) of camera 2 or 3 from KITTI raw's `calib_cam_to_cam.txt`: the left 3x3 of its
  rectified projection `P_rect_0{camera}` (the matrix of the rectified `image_0{camera}`)."""
  return rectified_calib(path, f"0{camera}").K


class _Calibrations:
  """Calib (K, S_rect size) per (date folder, camera), read once from
  `<data>/<date>/calib_cam_to_cam.txt` when the file exists (None otherwise: the frames then
  carry no intrinsics)."""

  def __init__(self):
    self._cache: dict[tuple[Path, int], Calib | None] = {}

  def path(self, data: Path, folder: str) -> Path:
    return data / folder.split("/")[0] / KITTI_CAM_TO_CAM

  def get(self, data: Path, folder: str, camera: int) -> Calib | None:
    path = self.path(data, folder)
    if (path, camera) not in self._cache:
      self._cache[(path, camera)] = (rectified_calib(path, f"0{camera}") if path.is_file()
                                     else None)
    return self._cache[(path, camera)]

  def frame_fields(self, data: Path, folder: str, camera: int) -> dict:
    """The FrameFiles intrinsics fields of a frame of `folder` seen by `camera`."""
    calib = self.get(data, folder, camera)
    if calib is None:
      return {}
    return {"intrinsics": calib.K, "intrinsics_size": calib.size,
            "intrinsics_source": self.path(data, folder)}


def load_gt_depths(path: PathLike, key: str = "data") -> np.ndarray:
  """Loads MonoDepth2's `gt_depths.npz` without executing code from the file.

  Returns:
    (N,) object array of (H_i, W_i) float maps, or an (N, H, W) float array when all maps share
    a size and the file was saved as a plain array.
  """
  path = require_file(path, "gt_depths file")
  try:
    with zipfile.ZipFile(path) as archive:
      stream, shape, fortran, dtype = _open_npy_member(path, archive, key)
      with stream:
        if dtype.hasobject:
          array = unpickle_arrays(stream, f"{path}:{key}")
        else:
          count = int(np.prod(shape))
          flat = np.frombuffer(stream.read(count * dtype.itemsize), dtype, count)
          array = flat.reshape(shape[::-1]).T if fortran else flat.reshape(shape)
  except ForbiddenGlobalError as e:
    raise DataError(path, f"unsafe or corrupt pickle in '{key}' (refusing to load global "
                          f"{e.global_name})") from None
  except (pickle.UnpicklingError, CheckpointError) as e:
    raise DataError(path, f"unsafe or corrupt pickle in '{key}' ({e})") from None
  except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, TypeError,
          AttributeError, IndexError, KeyError) as e:
    raise DataError(path, f"not a readable .npz file ({type(e).__name__}: {e})") from None
  if not isinstance(array, np.ndarray) or array.ndim < 1:
    raise DataError(path, f"'{key}' is not an array of depth maps")
  return array


class _GtDepths:
  """Loads a gt_depths.npz on first use and serves map i; shared by all frames of a split."""

  def __init__(self, path: Path):
    self.path = path
    self._maps: np.ndarray | None = None

  def __call__(self, index: int) -> np.ndarray:
    if self._maps is None:
      self._maps = load_gt_depths(self.path)
    depth = np.asarray(self._maps[index])
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
      raise DataError(self.path, f"map {index} is {depth.dtype} {depth.shape}, expected (H, W)")
    return depth.astype(np.float32)


def read_split(path: PathLike) -> list[tuple[str, int, int]]:
  """Parses a MonoDepth2 split file into (folder, frame index, camera 2 or 3) per line."""
  path = require_file(path, "split file")
  try:
    text = path.read_text(encoding="utf-8-sig")  # (a byte-order mark is not the folder's)
  except UnicodeDecodeError:
    raise DataError(path, "not a text split file (not UTF-8)") from None
  entries = []
  for number, line in enumerate(text.splitlines(), start=1):
    fields = line.split()
    if not fields:
      continue
    if (len(fields) != 3 or fields[2] not in SIDE_TO_CAMERA or not fields[1].isascii()
        or not fields[1].isdigit()):
      raise DataError(path, f"line {number} is {line.strip()!r}, expected '<folder> <frame> "
                            f"<side l|r|2|3>'")
    if fields[0].isdigit():  # MonoDepth2's odometry splits: '<sequence> <frame> <side>'
      raise DataError(path, f"line {number} is {line.strip()!r}: a KITTI odometry split "
                            f"(sequences/NN/), which is not read; use a raw-data split "
                            f"('<date>/<drive>_sync <frame> <side>', e.g. splits/eigen)")
    entries.append((fields[0], int(fields[1]), SIDE_TO_CAMERA[fields[2]]))
  return entries


def _find_image(data: Path, folder: str, frame: int, camera: int, ext: str | None) -> Path:
  base = data / folder / f"image_0{camera}" / "data" / f"{frame:010d}"
  # ext as given, then lowercase: `ext` is checked case-insensitively, KITTI's files are lowercase
  suffixes = (".jpg", ".png") if ext is None else tuple(
      dict.fromkeys("." + e for e in (ext.lstrip("."), ext.lstrip(".").lower())))
  for suffix in suffixes:
    if base.with_suffix(suffix).is_file():
      return base.with_suffix(suffix)
  raise DataError(base.with_suffix(suffixes[0]), "image not found"
                  + (" (nor .png)" if ext is None else ""))


def _find_improved_gt(root: Path, folder: str, frame: int, camera: int) -> Path:
  tail = Path("proj_depth", "groundtruth", f"image_0{camera}", f"{frame:010d}.png")
  drive = Path(folder).name
  candidates = [root / drive / tail, root / "train" / drive / tail, root / "val" / drive / tail,
                root / folder / tail]
  for candidate in candidates:
    if candidate.is_file():
      return candidate
  raise DataError(candidates[0], "improved ground truth not found (also looked under train/, "
                                 "val/ and the raw folder); it covers 652 of the 697 Eigen test "
                                 "frames, use the eigen_benchmark split")


def _check_benchmark_gt(data: Path, split_file: Path, first: tuple[str, int, int]) -> None:
  """That the eigen_benchmark split's ground truth without gt_depths.npz is there: KITTI's
  improved ground truth inside the raw drives, `<data>/<folder>/proj_depth/groundtruth/
  image_0X/`, where MonoDepth2's `export_gt_depth.py --split eigen_benchmark` reads it (never
  the Velodyne scans: the benchmark's numbers are on the improved maps); DataError naming the
  split file when the first line's map is not there."""
  folder, frame, camera = first
  try:
    _find_improved_gt(data, folder, frame, camera)  # (also train/, val/ as unpacked there)
  except DataError:
    tail = Path("proj_depth", "groundtruth", f"image_0{camera}", f"{frame:010d}.png")
    raise DataError(split_file, f"the eigen_benchmark split is scored on KITTI's improved ground "
                                f"truth, not found at {data / folder / tail} nor as "
                                f"gt_depths.npz beside the split: pass improved_gt=DIR or "
                                f"gt_depths=FILE, or depth=False") from None


def open_kitti(root: PathLike, split_file: PathLike, gt_depths: PathLike | None = None,
               improved_gt: PathLike | None = None, depth: bool = True, ext: str | None = None,
               panoptic_dir: PathLike | None = None, panoptic_json: PathLike | None = None
               ) -> FrameSequence:
  """Opens the KITTI frames of a MonoDepth2 split.

  Args:
    root: the KITTI raw data directory (holding `2011_09_26/...`).
    split_file: MonoDepth2 split file, e.g. `splits/eigen/test_files.txt`.
    gt_depths: MonoDepth2 `gt_depths.npz`; default: `gt_depths.npz` beside the split file.
    improved_gt: root of the KITTI depth-completion ground truth (instead of `gt_depths`).
    depth: load ground truth at all (False: images only).
    ext: image suffix "jpg" or "png"; None = whichever exists (jpg first).
    panoptic_dir: COCO panoptic PNGs (+ JSONs) mirroring the image tree (see module docstring).
    panoptic_json: a COCO panoptic annotation file for those PNGs.

  Returns:
    the frames in split order, loaded on access; depth = ground truth at its own size.
  """
  data = require_dir(root, "KITTI data directory")
  split_file = Path(split_file)
  if ext is not None and ext.lstrip(".").lower() not in ("jpg", "png"):
    raise DataError(None, f"--option ext={ext}: the KITTI images' suffix is jpg or png")
  entries = read_split(split_file)
  require_frames(entries, split_file, "lines '<folder> <frame> <side>'")
  if gt_depths is not None and improved_gt is not None:
    raise DataError(split_file, "give either gt_depths or improved_gt, not both")
  gt = velodyne = None
  evaluation = split_evaluation(split_file)
  if (depth and gt_depths is None and improved_gt is None
      and evaluation.get("valid_gt") == "positive"  # the eigen_benchmark split
      and not (split_file.parent / "gt_depths.npz").is_file()):
    _check_benchmark_gt(data, split_file, entries[0])
    improved_gt = data
  if depth and improved_gt is None:
    gt_path = Path(gt_depths) if gt_depths is not None else split_file.parent / "gt_depths.npz"
    if gt_depths is not None or gt_path.is_file():
      count = gt_depths_count(gt_path)
      if count != len(entries):
        raise DataError(gt_path, f"holds {count} depth maps but {split_file.name} lists "
                                 f"{len(entries)} frames")
      gt = _GtDepths(gt_path)
    elif velodyne_path(data, entries[0][0], entries[0][1]).is_file():
      velodyne = _velodyne_loaders(data, entries)
    else:
      raise DataError(gt_path, "ground truth not found; export it with MonoDepth2's "
                               "export_gt_depth.py, pass gt_depths/improved_gt, keep the drives' "
                               "velodyne_points/ in the data directory, or depth=False")
  improved_root = None if improved_gt is None else require_dir(improved_gt, "improved GT root")
  panoptic = panoptic_source(panoptic_dir, panoptic_json)
  calibs = _Calibrations()
  files = []
  for index, (folder, frame, camera) in enumerate(entries):
    image = _find_image(data, folder, frame, camera, ext)
    depth_loader, depth_file = None, ""
    if depth and improved_root is not None:
      depth_file = _find_improved_gt(improved_root, folder, frame, camera)
      depth_loader = functools.partial(read_depth_png, depth_file)
    elif gt is not None:
      depth_loader, depth_file = functools.partial(gt, index), f"{gt.path}[{index}]"
    elif velodyne is not None:
      depth_loader, depth_file = velodyne[index], velodyne_path(data, folder, frame)
    key = f"{folder}/image_0{camera}/data/{frame:010d}"
    files.append(FrameFiles(name=f"{folder}/image_0{camera}/{frame:010d}", image=image,
                            depth=depth_loader, depth_file=str(depth_file),
                            panoptic=None if panoptic is None else panoptic.ref(key),
                            recording=f"{folder}/image_0{camera}",
                            **calibs.frame_fields(data, folder, camera)))
  right = sum(camera == 3 for _, _, camera in entries)
  source = "gt_depths.npz holds" if gt is not None else "the Velodyne ground truth is"
  notes = [f"{split_file.name}: {right} line(s) take the right camera's image (image_03), but "
           f"{source} the left camera's ground truth for every line (MonoDepth2's "
           f"export_gt_depth.py); use improved_gt for both cameras"
           ] if right and (gt is not None or velodyne is not None) else []
  if velodyne is not None:
    notes.append(f"{split_file.name}: ground truth projected from the Velodyne scans "
                 f"(velodyne_points/), as MonoDepth2's export_gt_depth.py writes gt_depths.npz")
  notes += list(panoptic.notes) if panoptic is not None else []
  return FrameSequence(files, temporal=split_is_temporal(entries), notes=notes, remedies={
      "intrinsics": INTRINSICS_REMEDY,
      "previous_frame": "a split file whose lines are consecutive frames of each drive (the "
                        "Eigen test split is not)"},
      evaluation=evaluation)


def _velodyne_loaders(data: Path, entries: list[tuple[str, int, int]]) -> list:
  """One loader per split line of its ground truth from the Velodyne scan
  (`velodyne.velodyne_depth` with camera 2 and the forward distance, what `export_gt_depth.py`
  writes for every line); DataError naming the first missing scan or bad calibration file
  before any frame is read. Each date's calibration is read once, here."""
  projections = {}
  loaders = []
  for folder, frame, _ in entries:
    date = data / folder.split("/")[0]
    if date not in projections:
      projections[date] = velodyne_projection(date, 2)
    scan = velodyne_path(data, folder, frame)
    if not scan.is_file():
      raise DataError(scan, "Velodyne scan not found (the split's other frames have theirs; "
                            "pass gt_depths or depth=False)")
    loaders.append(functools.partial(project_scan, *projections[date], scan, True))
  return loaders


def split_evaluation(split_file: Path) -> dict[str, object]:
  """The evaluation protocol of a MonoDepth2 split (`run.EvalConfig` values), as MonoDepth2's
  `evaluate_depth.py` applies it: the Garg crop for `--eval_split eigen` (`splits/eigen/...`),
  every ground-truth pixel > 0 (no 80 m cap) for `eigen_benchmark`, neither for other splits.
  The folder is the one the path names (made absolute, symbolic links not followed: a
  `splits/eigen/test_files.txt` linked to a file elsewhere is still the Eigen split), else the
  one it leads to (a link `my_split/test_files.txt`, or a linked folder, to a file of
  `splits/eigen/` is the Eigen split too)."""
  protocols = {"eigen": {"garg_crop": True}, "eigen_benchmark": {"valid_gt": "positive"}}
  for folder in (Path(os.path.abspath(split_file)).parent, Path(split_file).resolve().parent):
    if folder.name in protocols:
      return protocols[folder.name]
  return {}


def split_is_temporal(entries: list[tuple[str, int, int]]) -> bool:
  """True when the split lists runs of consecutive frames: each line continues the previous
  one (same drive and camera, frame + 1) or starts a drive/camera not seen before, and every
  run has at least 2 frames."""
  seen: set[tuple[str, int]] = set()
  run = 0
  for k, (folder, frame, camera) in enumerate(entries):
    if k and (folder, camera) == entries[k - 1][::2] and frame == entries[k - 1][1] + 1:
      run += 1
      continue
    if (folder, camera) in seen or (k and run < 2):
      return False
    seen.add((folder, camera))
    run = 1
  return run >= 2


RAW_IMAGE_DIR = ("image_02", "data")  # the left colour camera (MonoDepth2's side "l")


def _drive_dirs(root: Path) -> list[Path]:
  """`<date>/<date>_drive_<nnnn>_sync` directories under `root` (or in `root` itself when it is
  a date folder), sorted."""
  root = root.resolve()  # `.` has no name to match its drives by
  dates = [root] if any(root.glob("*_drive_*_sync")) else sorted(
      d for d in root.iterdir() if d.is_dir() and not d.name.startswith("."))
  return [drive for date in dates for drive in sorted(date.glob(f"{date.name}_drive_*_sync"))
          if drive.is_dir()]


def consecutive_runs(stems: list[str]) -> list[list[str]]:
  """Sorted numeric stems cut where the number does not go up by exactly 1: runs of consecutive
  frames (a drive with missing frames must not pair the frames around the gap)."""
  runs: list[list[str]] = []
  for stem in stems:
    if runs and int(stem) == int(runs[-1][-1]) + 1:
      runs[-1].append(stem)
    else:
      runs.append([stem])
  return runs


def open_raw_sequences(root: PathLike) -> list[FrameSequence]:
  """KITTI raw drives as downloaded: one temporal sequence per drive, no ground truth.

  Layout: `<root>/<date>/<date>_drive_<nnnn>_sync/image_02/data/<10 digits>.{png,jpg}` (the
  left colour camera, frames in index order) and `<root>/<date>/calib_cam_to_cam.txt` (K from
  P_rect_02, scaled to the image size by S_rect_02; no calibration file = no intrinsics).
  `root` may also be one date folder. A drive whose frame numbers have gaps is read as one
  sequence per run of consecutive numbers (with a note): frames around a gap are not
  neighbours (upstream's loaders find a frame's neighbours by number). Runs and drives with
  fewer than 2 frames are left out (they give no frame pair). Frame names are
  `<date>/<drive>/image_02/<frame>`.

  Returns:
    the drives' sequences, sorted by date and drive; DataError naming `root` when none has 2
    frames.
  """
  root = require_dir(root, "KITTI raw root (--replay-root)")
  calibs = _Calibrations()
  sequences = []
  for drive in _drive_dirs(root):
    image_dir = drive.joinpath(*RAW_IMAGE_DIR)
    if not image_dir.is_dir():
      continue
    images = list_images(image_dir, (".jpg", ".png"))
    stems = sorted(s for s in images if len(s) == 10 and s.isdigit())
    folder = f"{drive.parent.name}/{drive.name}"
    runs = consecutive_runs(stems)
    kept = [run for run in runs if len(run) >= 2]
    alone = [run[0] for run in runs if len(run) < 2]
    notes = [f"{folder}: frame numbers jump after {', '.join(run[-1] for run in runs[:-1])}; "
             f"read as {len(kept)} sequence(s) of consecutive frames"
             + (f", without {len(alone)} frame(s) that have no neighbour ({alone[0]}"
                f"{', ...' if len(alone) > 1 else ''})" if alone else "")
             ] if len(runs) > 1 else []
    fields = calibs.frame_fields(drive.parent.parent, folder, 2)
    for run in kept:
      files = [FrameFiles(name=f"{folder}/{RAW_IMAGE_DIR[0]}/{stem}", image=images[stem],
                          recording=f"{folder}/{run[0]}", **fields) for stem in run]
      sequences.append(FrameSequence(files, temporal=True, notes=notes,
                                     remedies={"intrinsics": INTRINSICS_REMEDY}))
  if not sequences:
    raise DataError(root, "no KITTI raw drive with at least 2 frames (looked for <date>/"
                          "<date>_drive_<nnnn>_sync/image_02/data/<10 digits>.png|jpg)")
  return sequences
