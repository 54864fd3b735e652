"""Reading and writing the image and depth files every reader shares (OpenCV, host side).

Conventions (see docs/datasets.md):
- Images are read with OpenCV (BGR on disk order) and returned RGB, float32 in [0, 1]
  (8-bit / 255, 16-bit / 65535). Grayscale images are rejected (the network needs colour and
  a grayscale file in a colour dataset is a sign of a wrong directory); RGBA/BGRA images lose
  their alpha channel without error (PNG exporters often add an opaque alpha).
- Depth PNGs are single-channel uint16, metres = value / 256, 0 = invalid (KITTI, DrivingStereo,
  our Waymo layout). Anything else is rejected rather than guessed.
- Every problem is a `DataError` naming the file.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from pitta_jax.data.errors import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_PNG_SCALE = 256.0  # KITTI / DrivingStereo: metres = uint16 value / 256

PathLike = str | os.PathLike[str]


def require_file(path: PathLike, what: str = "file") -> Path:
  """`path` as a Path; DataError when it is not an existing regular file."""
  path = Path(path)
  if not path.is_file():
    raise DataError(path, f"{what} not found" if not path.exists() else f"{what} is not a file")
  return path


def require_dir(path: PathLike, what: str = "directory") -> Path:
  """`path` as a Path; DataError when it is not an existing directory."""
  path = Path(path)
  if not path.is_dir():
    problem = "not found" if not path.exists() else "is not a directory"
    raise DataError(path, f"{what} {problem}")
  return path


def decode_file(path: Path, what: str) -> np.ndarray:
  """Decodes an image file with OpenCV from its bytes (any file name works, including names that
  are not valid UTF-8, which `cv2.imread` cannot take); IMREAD_UNCHANGED keeps the bit depth and
  the channel count, so that both can be checked."""
  try:
    data = np.fromfile(path, np.uint8)
  except OSError as e:
    raise DataError(path, f"cannot read {what} ({e.strerror or e})") from None
  if _png_cut_short(data[:8].tobytes(), data[-12:].tobytes(), data.tobytes):
    raise DataError(path, _cut_short(what))  # (libpng would print its own line first)
  _check_png_size(path, data[:24].tobytes(), what)
  try:
    array = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
  except cv2.error as e:
    if "Insufficient memory" in str(e):
      raise  # the commands' out-of-memory line
    # e.g. a JPEG whose header declares more pixels than OpenCV decodes (a PNG's is checked above)
    failed = str(getattr(e, "err", "") or e).strip()
    reason = ("more pixels than OpenCV decodes" if "MAX_IMAGE_PIXELS" in failed
              else f"OpenCV: {failed}")
    raise DataError(path, f"cannot decode {what} ({reason})") from None
  if array is None:
    raise DataError(path, _undecodable(what))
  return array


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# the most pixels OpenCV's imdecode takes (its CV_IO_MAX_IMAGE_PIXELS default); a larger image
# stops it with an assertion
MAX_DECODED_PIXELS = 1 << 30


def opencv_pixel_limit(value: str) -> int:
  """The most pixels OpenCV decodes with OPENCV_IO_MAX_IMAGE_PIXELS = `value`, read as OpenCV
  reads a size setting: decimal digits and an optional suffix KB / Kb / kb (x 1024) or MB / Mb /
  mb (x 1024^2). Any other text (which stops OpenCV itself where it reads the setting, at
  import): `MAX_DECODED_PIXELS`, its default."""
  scale = {"": 1, "KB": 1 << 10, "Kb": 1 << 10, "kb": 1 << 10,
           "MB": 1 << 20, "Mb": 1 << 20, "mb": 1 << 20}
  digits = len(value) - len(value.lstrip("0123456789"))
  if digits == 0 or value[digits:] not in scale:
    return MAX_DECODED_PIXELS
  return int(value[:digits]) * scale[value[digits:]]


def _check_png_size(path: Path, head: bytes, what: str) -> None:
  """DataError when `head` (a file's first 24 bytes) is a PNG's whose header declares more
  pixels than OpenCV decodes (`MAX_DECODED_PIXELS`, or the OPENCV_IO_MAX_IMAGE_PIXELS it reads)."""
  if head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR" or len(head) < 24:
    return
  width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
  limit = opencv_pixel_limit(os.environ.get("OPENCV_IO_MAX_IMAGE_PIXELS", ""))
  if width * height > limit:
    raise DataError(path, f"{what} of {width}x{height} pixels: more than OpenCV decodes "
                          f"({limit} pixels)")


def _cut_short(what: str) -> str:
  return f"cannot decode {what} (a PNG file cut short: no IEND chunk)"


def _undecodable(what: str) -> str:
  return f"cannot decode {what} (not a PNG/JPEG file, or truncated)"


def _png_cut_short(head: bytes, tail: bytes, whole: Callable[[], bytes]) -> bool:
  """Whether a file starting with `head` (8 bytes) and ending with `tail` (its last 12) is a
  PNG without its IEND chunk; `whole()` gives all its bytes, read only when IEND is not at the
  end (a PNG may carry data after it)."""
  return head[:8] == PNG_SIGNATURE and tail.find(b"IEND") < 0 and whole().rfind(b"IEND") < 0


def check_image_file(path: PathLike, what: str = "image") -> Path:
  """`path`, checked without decoding for the damage `decode_file` would report when the file
  is read: missing, not a file, empty, a PNG cut short (no IEND chunk) or one of more pixels
  than OpenCV decodes. Reads 36 bytes of a sound file, so that a long sequence can be checked
  before any work. DataError (the message `decode_file` gives) otherwise; damage only a decoder
  sees still shows when it is read."""
  path = require_file(path, what)
  try:
    with open(path, "rb") as f:
      head = f.read(24)
      size = f.seek(0, os.SEEK_END)
      f.seek(max(size - 12, 0))
      tail = f.read(12)
  except OSError as e:
    raise DataError(path, f"cannot read {what} ({e.strerror or e})") from None
  if size == 0:
    raise DataError(path, _undecodable(what))
  if _png_cut_short(head, tail, path.read_bytes):
    raise DataError(path, _cut_short(what))
  _check_png_size(path, head, what)
  return path


def encode_bytes(path: PathLike, array: np.ndarray, what: str = "file") -> bytes:
  """The bytes of `array` encoded as the file `path` (by its suffix) holds it; DataError for a
  suffix OpenCV cannot write. For files written in a group (`outputs.atomic_write_files`)."""
  path = Path(path)
  ok, data = cv2.imencode(path.suffix, array) if path.suffix else (False, None)
  if not ok:
    raise DataError(path, f"cannot encode {what} (unknown suffix {path.suffix!r})")
  return data.tobytes()


def encode_file(path: PathLike, array: np.ndarray, what: str = "file") -> None:
  """Encodes `array` by the path's suffix and writes it atomically (temp file + rename), from
  bytes (any file name works)."""
  data = encode_bytes(path, array, what)
  path = Path(path)
  try:
    path.parent.mkdir(parents=True, exist_ok=True)
    from pitta_jax.outputs import atomic_write_bytes
    atomic_write_bytes(path, data)
  except OSError as e:
    raise DataError(path, f"cannot write {what} ({e.strerror or e})") from None


def _imread(path: PathLike, what: str) -> np.ndarray:
  return decode_file(require_file(path, what), what)


PNG_GRAY_ALPHA = 4  # IHDR colour type of a grayscale + alpha PNG


def _png_gray_alpha(path: PathLike) -> bool:
  """Whether `path` is a grayscale + alpha PNG, which OpenCV decodes as 4 equal-looking BGRA
  channels: its IHDR colour type (byte 25 of the file)."""
  with open(path, "rb") as f:
    head = f.read(26)
  return len(head) == 26 and head[:8] == PNG_SIGNATURE and head[25] == PNG_GRAY_ALPHA


# The EXIF orientation entry's tag (0x0112) and type (SHORT, 3) as a TIFF directory stores them,
# little- and big-endian: a file without either holds no orientation for a decoder to apply.
EXIF_ORIENTATION_ENTRIES = (b"\x12\x01\x03\x00", b"\x01\x12\x00\x03")


def exif_upright(path: PathLike, image: np.ndarray) -> np.ndarray:
  """`image` (as decoded from `path`, (H, W, C)) turned upright by the file's EXIF orientation,
  as `cv2.imread` does by default (a JPEG from a phone or camera stores it; other files and a
  JPEG without one come back unchanged). OpenCV applies the orientation while decoding to
  8-bit colour; the turn found there (none, a rotation, a flip) is applied to `image`. A file
  without an orientation entry (`EXIF_ORIENTATION_ENTRIES`) is not decoded again."""
  data = np.fromfile(path, np.uint8)
  raw = data.tobytes()
  if not any(entry in raw for entry in EXIF_ORIENTATION_ENTRIES):
    return image  # no orientation tag anywhere in the file: nothing for OpenCV to apply
  stored = cv2.imdecode(data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
  upright = cv2.imdecode(data, cv2.IMREAD_COLOR)
  if stored is None or upright is None or (stored.shape == upright.shape
                                           and np.array_equal(stored, upright)):
    return image
  for k in range(4):  # the 8 EXIF orientations: rotations by k * 90 degrees, with a flip or not
    for flipped in (False, True):
      candidate = np.rot90(np.fliplr(stored) if flipped else stored, -k)
      if candidate.shape == upright.shape and np.array_equal(candidate, upright):
        turned = np.rot90(np.fliplr(image) if flipped else image, -k)
        return np.ascontiguousarray(turned)
  return image


def read_image(path: PathLike, gray: bool = False) -> np.ndarray:
  """Reads a colour image.

  Args:
    path: a PNG or JPEG file, 8 or 16 bit, 3 or 4 channels.
    gray: also take a grayscale image (with or without alpha), its channel repeated as R, G
      and B (what PIL's `convert("RGB")` in MonoDepth2's test_simple.py and cv2.imread in
      Depth Anything V2's run.py make of an 8-bit one; a 16-bit one is scaled by 1/65535 as
      any 16-bit image, where PIL's conversion clips it at 255); else it is an error, for a
      dataset's frames a sign of a wrong directory (KITTI's image_00/01 are the grayscale
      cameras).

  Returns:
    (H, W, 3) float32 RGB in [0, 1] (alpha, if any, dropped).
  """
  array = _imread(path, "image")
  if array.ndim == 2 or array.shape[2] == 1:
    if not gray:
      raise DataError(path, f"grayscale image of shape {array.shape}, expected 3 colour channels")
    array = np.repeat(array.reshape(array.shape[0], array.shape[1], 1), 3, axis=2)
  elif not gray and _png_gray_alpha(path):
    raise DataError(path, "grayscale image with alpha, expected 3 colour channels")
  if array.shape[2] not in (3, 4):
    raise DataError(path, f"image has {array.shape[2]} channels, expected 3 (or 4 with alpha)")
  if array.dtype == np.uint8:
    scale = 255.0
  elif array.dtype == np.uint16:
    scale = 65535.0
  else:
    raise DataError(path, f"image of dtype {array.dtype}, expected 8 or 16 bit")
  rgb = cv2.cvtColor(array[..., :3], cv2.COLOR_BGR2RGB)  # (H, W, 3)
  return (rgb.astype(np.float32) / np.float32(scale)).astype(np.float32)


def write_image(path: PathLike, image: np.ndarray) -> None:
  """Writes (H, W, 3) RGB, float in [0, 1] (rounded to 8 bit) or uint8, as PNG/JPEG by suffix."""
  _imwrite(path, _bgr8(image))


def image_bytes(path: PathLike, image: np.ndarray) -> bytes:
  """The bytes `write_image(path, image)` writes (for a group of files written at once,
  `outputs.atomic_write_files`)."""
  return encode_bytes(path, _bgr8(image), "image")


def _bgr8(image: np.ndarray) -> np.ndarray:
  """(H, W, 3) RGB, float in [0, 1] (rounded to 8 bit) or uint8 -> uint8 BGR (OpenCV's)."""
  image = np.asarray(image)
  if image.dtype != np.uint8:
    image = np.clip(np.rint(np.asarray(image, np.float64) * 255.0), 0, 255).astype(np.uint8)
  return cv2.cvtColor(image, cv2.COLOR_RGB2BGR)


def _imwrite(path: PathLike, array: np.ndarray) -> None:
  encode_file(path, array)


def read_depth_png(path: PathLike, scale: float = DEPTH_PNG_SCALE) -> np.ndarray:
  """Reads a uint16 depth PNG.

  Args:
    path: single-channel 16-bit PNG.
    scale: divisor from stored value to metres (256 for KITTI/DrivingStereo depth).

  Returns:
    (H, W) float32 metres, 0 = invalid.
  """
  array = _imread(path, "depth map")
  if array.dtype != np.uint16 or array.ndim != 2:
    channels = 1 if array.ndim == 2 else array.shape[2]
    hint = " (an 8-bit visualisation instead of the map?)" if array.dtype == np.uint8 else ""
    raise DataError(path, f"depth PNG must be single-channel uint16, got {array.dtype} with "
                          f"{channels} channel(s){hint}")
  return array.astype(np.float32) / np.float32(scale)


def write_depth_png(path: PathLike, depth: np.ndarray, scale: float = DEPTH_PNG_SCALE) -> None:
  """Writes (H, W) metres as uint16 PNG `round(depth * scale)`, clipped to 1..65535 where > 0.

  Invalid pixels (depth <= 0 or not finite) are stored as 0. Values beyond 65535 / scale
  (256 m at scale 256) saturate.
  """
  depth = np.asarray(depth, np.float64)
  valid = np.isfinite(depth) & (depth > 0)
  stored = np.where(valid, np.clip(np.rint(np.where(valid, depth, 0.0) * scale), 1, 65535), 0)
  _imwrite(path, stored.astype(np.uint16))


def load_npy(path: PathLike, what: str) -> np.ndarray:
  """np.load without pickle (a .npy cannot run code); DataError naming the file otherwise."""
  try:
    array = np.load(path, allow_pickle=False)
  except (ValueError, OSError, EOFError) as e:  # EOFError: an empty file
    raise DataError(path, f"cannot read .npy {what} ({e or type(e).__name__})") from None
  if not isinstance(array, np.ndarray):  # np.load opens a zip (.npz) whatever its name
    array.close()
    raise DataError(path, f"cannot read .npy {what} (an .npz archive, not one array)")
  return array


def read_depth_npy(path: PathLike) -> np.ndarray:
  """Reads a dense (H, W) depth `.npy` (metres, 0 = invalid) without pickle; float32."""
  path = require_file(path, "depth map")
  array = load_npy(path, "depth map")
  if array.ndim != 2 or not np.issubdtype(array.dtype, np.floating):
    raise DataError(path, f"depth .npy must be a float (H, W) array, got {array.dtype} "
                          f"{array.shape}")
  return array.astype(np.float32)


def depth_loader(depth_dir: Path, stem: str, *, png_scale: float = DEPTH_PNG_SCALE,
                 read_npy: Callable[[Path], np.ndarray] = read_depth_npy,
                 missing: str = "depth map not found (nor .npy)"
                 ) -> tuple[Path, Callable[[], np.ndarray]]:
  """The file and lazy loader of `<depth_dir>/<stem>.png` (uint16 / png_scale), else
  `<stem>.npy` (read by `read_npy`); DataError(`<stem>.png`, missing) when neither exists."""
  png, npy = depth_dir / f"{stem}.png", depth_dir / f"{stem}.npy"
  if png.is_file():
    return png, functools.partial(read_depth_png, png, png_scale)
  if npy.is_file():
    return npy, functools.partial(read_npy, npy)
  raise DataError(png, missing)


def list_images(directory: PathLike, suffixes: tuple[str, ...] = IMAGE_SUFFIXES,
                all_suffixes: bool = False) -> dict[str, Path]:
  """Image files of `directory` (not recursive) by stem, suffix case-insensitive.

  Hidden files (`.name`, e.g. macOS `._*` resource forks in zip archives) are skipped; a
  directory with an image's name is a DataError.

  Args:
    directory: the directory to list; DataError when missing.
    suffixes: accepted suffixes (lower case, with the dot), in order of preference: when a stem
      exists with two suffixes (`a.png` and `a.jpg`) the earlier one wins.
    all_suffixes: keep every file instead, keyed by file name (a stem with two suffixes is two
      images).
  """
  directory = require_dir(directory, "image directory")
  found: dict[str, Path] = {}
  for path in sorted(directory.iterdir()):
    suffix = path.suffix.lower()
    if suffix not in suffixes or path.name.startswith("."):
      continue
    if path.is_symlink() and not path.exists():
      raise DataError(path, "is a dangling symbolic link (its target is missing)")
    if not path.is_file():  # a frame silently missing from a sequence would shift the rest
      raise DataError(path, "has an image's name but is not a file")
    if all_suffixes:
      found[path.name] = path
      continue
    other = found.get(path.stem)
    if other is None or (suffixes.index(suffix) < suffixes.index(other.suffix.lower())
                         and not _is_panoptic_png(path)) or _is_panoptic_png(other):
      found[path.stem] = path
  return found


def _is_panoptic_png(path: Path) -> bool:
  """A PNG with a per-image panoptic JSON of its stem beside it: a panoptic id map (what
  `pitta-jax segment` writes beside the images it segments), not the stem's colour image."""
  from pitta_jax.data.panoptic_io import is_segments_json
  return path.suffix.lower() == ".png" and is_segments_json(path.with_suffix(".json"))
