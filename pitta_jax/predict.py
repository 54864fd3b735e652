"""Depth prediction with a converted (or trained) depth network: `pitta-jax predict`.

Each image is read, resized to the network's input size (`resize_image`, as the readers do),
run in eval mode (running BN statistics), and written as `<stem>_disp.npy` (the network's
scale-0 output, a sigmoid disparity scaled as MonoDepth2's `disp_to_depth` scales it:
`ModelSpec.saved_disparity`), `<stem>_depth.npy` (its depth, e.g. the inverse of that), and
`<stem>_disp.png` (magma, MonoDepth2's convention) at the image's own size, as each upstream
writes them: MonoDepth2's `test_simple.py` saves the arrays at the network's resolution and
colours the disparity resized to the image (bilinear, align_corners=False); Depth Anything
V2's `infer_image` returns its output resized to the image (bilinear, align_corners=True), so a
network that keeps the aspect ratio (`ModelSpec.keep_aspect`) writes every output at the
image's size. This is also how a user checks a conversion by eye.
"""

from __future__ import annotations

import dataclasses
import glob
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from pitta_jax import viz
from pitta_jax.checkpoint import load_weights
from pitta_jax.outputs import WatchedDirectory, atomic_write_files, npy_bytes
from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import (IMAGE_SUFFIXES, exif_upright, image_bytes, list_images,
                                     read_image)
from pitta_jax.data.resize import resize_image
from pitta_jax.models.interpolate import resize_bilinear


DISP_PNG, DISP_NPY = "_disp.png", "_disp.npy"  # predict's outputs per image (+ _depth.npy)


def expand_images(spec: str, unique_stems: bool = True) -> list[Path]:
  """A file, a directory (its images), a glob pattern (`**`: any depth), or a `.txt` list of
  image paths, one per line (Depth Anything V2's `run.py --img-path list.txt`; relative paths
  from the working directory, as there) -> image paths (sorted, except a list's order).

  unique_stems: refuse two images with one file stem (their outputs, named by stem, would
  overwrite each other); False where nothing is written per image (source statistics).
  """
  path = Path(spec)
  if path.is_dir():  # every image, `a.png` and `a.jpg` too (the stem check below refuses them)
    paths = sorted(list_images(path, IMAGE_SUFFIXES, all_suffixes=True).values())
  elif path.is_file() and path.suffix.lower() == ".txt":
    paths = read_image_list(path)
  elif path.is_file():
    paths = [path]
  else:
    paths = sorted(Path(p) for p in glob.glob(spec, recursive=True)  # `**`: any depth
                   if Path(p).suffix.lower() in IMAGE_SUFFIXES)
  if not paths:
    raise DataError(spec, f"no image found (a file, a directory or a glob of {IMAGE_SUFFIXES})")
  if unique_stems:
    check_unique_stems(paths)
  return paths


def read_image_list(path: Path) -> list[Path]:
  """The image paths of a text file, one per line (blank lines skipped); DataError naming the
  list and the line of the first that is not an image file."""
  try:
    lines = path.read_text().splitlines()
  except (OSError, UnicodeDecodeError) as e:
    raise DataError(path, f"cannot read the image list ({e})") from None
  paths = []
  for number, line in enumerate(lines, start=1):
    if not line.strip():
      continue
    image = Path(line.strip())
    if not image.exists():  # (as Depth Anything V2's run.py reads them: from the working dir)
      raise DataError(path, f"line {number}: {line.strip()!r} not found (a relative path is "
                            f"taken from the working directory {Path.cwd()})")
    if not image.is_file() or image.suffix.lower() not in IMAGE_SUFFIXES:
      raise DataError(path, f"line {number}: {line.strip()!r} is not an image file "
                            f"({', '.join(IMAGE_SUFFIXES)})")
    paths.append(image)
  return paths


def check_unique_stems(paths: Sequence[Path]) -> None:
  """DataError naming the second of two images with one file stem: outputs named by stem
  (OUT/<stem>.png) would overwrite each other."""
  stems: dict[str, Path] = {}
  for p in paths:
    if p.stem in stems:
      raise DataError(p, f"has the same file stem as {stems[p.stem]}; their outputs (named by "
                         f"stem) would overwrite each other: rename one, or give a glob of one "
                         f"suffix or one folder")
    stems[p.stem] = p


def check_images(paths: Sequence[Path], quiet: bool = False,
                 check: Callable[[np.ndarray], None] | None = None) -> None:
  """Reads every image once before anything is written (DataError naming the first unreadable
  one): a bad image found halfway would leave half of the outputs behind. `check(image)`, when
  given, vets each (H, W, 3) image too; its ValueError becomes a DataError naming the file."""
  for path in tqdm(paths, desc="checking images", unit="img", disable=quiet or len(paths) < 50):
    image = read_image(path, gray=True)
    if check is not None:
      try:
        check(image)
      except ValueError as e:
        raise DataError(path, str(e)) from None


@dataclasses.dataclass(frozen=True)
class Outputs:
  """The files a command writes per image `<stem>`: `<stem><suffix>` for each of `suffixes`.
  `looks_own(path)` says whether an existing file of the first suffix holds what the command
  writes there (default: it exists); a group is an earlier output of the command when every
  file is there and the first looks its own."""
  suffixes: tuple[str, ...]
  looks_own: Callable[[Path], bool] = Path.is_file

  def group(self, out_dir: Path, stem: str) -> list[Path]:
    return [out_dir / f"{stem}{s}" for s in self.suffixes]

  def is_earlier_output(self, path: Path) -> bool:
    """Whether `path`, named `<stem>` + one of the suffixes, belongs to a complete group."""
    for suffix in self.suffixes:
      if path.name.endswith(suffix):
        group = self.group(path.parent, path.name[:-len(suffix)])
        return all(p.is_file() for p in group) and self.looks_own(group[0])
    return False


PREDICT_OUTPUTS = Outputs((DISP_NPY, "_depth.npy", DISP_PNG))


def without_own_outputs(paths: Sequence[Path], out_dir: Path, outputs: Outputs) -> list[Path]:
  """`paths` less the files a previous run of the command wrote into `out_dir` (complete groups
  of `outputs`), so that a rerun with --out in the image directory does not take them as
  input; a user's own image of such a name stays an input."""
  out = out_dir.resolve()
  return [p for p in paths
          if not (p.resolve().parent == out and outputs.is_earlier_output(p))]


def check_outputs_free(out_dir: Path, stems: Sequence[str], outputs: Outputs) -> None:
  """DataError naming the first file the command is about to write that exists without being
  part of one of its earlier outputs (a complete group): a user's file (e.g. a ground-truth
  `<stem>_depth.npy` beside the images, or a labelme `<stem>.json`) would be replaced."""
  for stem in stems:
    group = outputs.group(out_dir, stem)
    present = [p for p in group if p.exists()]
    if present and not outputs.is_earlier_output(present[0]):
      others = ", ".join(p.name for p in group if p != present[0])
      raise DataError(present[0], f"exists and is not an earlier output of this command (which "
                                  f"writes {others} beside it; remove it if a killed run left "
                                  f"it); it is not overwritten: choose "
                                  f"another --out")


def resize_map(x: np.ndarray, size: tuple[int, int], align_corners: bool) -> np.ndarray:
  """(h, w) -> `size` (H, W) by PyTorch's bilinear `interpolate` (`models.interpolate`)."""
  return np.asarray(resize_bilinear(jnp.asarray(x)[..., None], size, align_corners))[..., 0]


def make_predictor(network):
  """Jitted (variables, images (B, H, W, 3)) -> (the network's own full-resolution output
  (B, H, W), its depth (B, H, W)), eval mode."""
  def predict(v, x):
    out = network.outputs(v, x, False)[0][..., 0]
    return out, network.spec.to_depth(out)
  return jax.jit(predict)


def predict_images(weights_dir: str | Path, images: str | Iterable[Path], out_dir: str | Path,
                   quiet: bool = False, size: tuple[int, int] | None = None,
                   check_out: Callable[[], Any] | None = None) -> list[Path]:
  """Writes disparity/depth .npy and a colour PNG per image; returns the PNG paths.

  images: paths, or a spec for `expand_images` (expanded after the weights load, so a bad
  weights directory is reported first).
  size: (H, W) network input size (default: the size the weights were trained at, or for a
    network that keeps the aspect ratio, e.g. Depth Anything V2, `ModelSpec.inference_size`
    of each image).
  check_out: called before each image's files are written; it raises to stop where `out_dir`
    was removed or replaced meanwhile (the command passes its locked --out's `OutputDir.check`;
    None: `out_dir` as it is once made, `outputs.WatchedDirectory`).
  """
  weights = load_weights(weights_dir)
  if size is not None:
    try:
      weights.spec.check_size(*size)  # ValueError naming the network's rule
    except ValueError as e:
      raise ValueError(f"--height/--width: {e}; these weights were trained at "
                       f"{weights.width}x{weights.height}") from None
  trained = (weights.height, weights.width)
  out = Path(out_dir)
  images = expand_images(images) if isinstance(images, str) else list(images)
  images = without_own_outputs(images, out, PREDICT_OUTPUTS)
  if not images:
    raise DataError(out, "no image to predict besides this command's own outputs")
  check_outputs_free(out, [p.stem for p in images], PREDICT_OUTPUTS)
  check_images(images, quiet)
  predict = make_predictor(weights.network())
  out.mkdir(parents=True, exist_ok=True)
  with WatchedDirectory(out) as watch:
    return _predict_each(weights, predict, images, out, size, trained, quiet,
                         check_out or watch.check)


def _predict_each(weights, predict, images: list[Path], out: Path,
                  size: tuple[int, int] | None, trained: tuple[int, int], quiet: bool,
                  check_out: Callable[[], Any]) -> list[Path]:
  """`predict_images`' loop over the checked images."""
  written = []
  for path in tqdm(images, desc="predict", unit="img", disable=quiet):
    image = read_image(path, gray=True)
    if weights.spec.exif_orientation:  # Depth Anything V2's run.py: cv2.imread turns it upright
      image = exif_upright(path, image)
    h, w = size or weights.spec.inference_size(image.shape[:2], trained)
    size_in = image.shape[:2]
    image = resize_image(image, h, w, weights.spec.image_resize)
    disp, depth = (np.asarray(a)[0] for a in predict(weights.depth, jnp.asarray(image[None])))
    if weights.spec.keep_aspect:  # infer_image: the output at the image's size, then its depth
      disp = resize_map(disp, size_in, align_corners=True)
      depth = np.asarray(weights.spec.to_depth(disp))
    if not np.all(np.isfinite(disp)):
      raise ValueError(f"{path}: the network produced non-finite outputs on this image")
    # near = bright: the disparity as it is, or the inverse of a metric network's depth; at the
    # image's size (test_simple.py colours the disparity resized to it)
    shown = 1.0 / depth if weights.spec.output == "metric_depth" else disp
    # the image's three files at once (all written, then renamed): an interrupted run leaves
    # an image with all of them or none, so its rerun takes them as its own
    check_out()
    atomic_write_files(out, {
        f"{path.stem}{DISP_NPY}": npy_bytes(
            np.asarray(weights.spec.saved_disparity(disp)).astype(np.float32)),
        f"{path.stem}_depth.npy": npy_bytes(depth.astype(np.float32)),
        f"{path.stem}{DISP_PNG}": image_bytes(
            DISP_PNG, viz.colorize(resize_map(shown, size_in, align_corners=False)))})
    written.append(out / f"{path.stem}{DISP_PNG}")
  return written
