"""Depth prediction with a converted (or trained) depth network: `pitta-jax predict`.

Each image is read, resized to the network's input size (`resize_image`, as the readers do),
run in eval mode (running BN statistics), and written as `<stem>_disp.npy` (the network's own
scale-0 output, e.g. MonoDepth2's sigmoid disparity), `<stem>_depth.npy` (its depth, e.g.
`disp_to_depth(disp, 0.1, 100)`), and `<stem>_disp.png` (magma, MonoDepth2's convention) at the
image's own size, as each upstream writes them: MonoDepth2's `test_simple.py` saves the arrays
at the network's resolution and colours the disparity resized to the image (bilinear,
align_corners=False); Depth Anything V2's `infer_image` returns its output resized to the image
(bilinear, align_corners=True), so a network that keeps the aspect ratio (`ModelSpec.keep_aspect`)
writes every output at the image's size. This is also how a user checks a conversion by eye.
"""

from __future__ import annotations

import glob
from pathlib import Path
from typing import Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from pitta_jax import viz
from pitta_jax.checkpoint import load_weights
from pitta_jax.outputs import save_npy
from pitta_jax.data.errors import DataError
from pitta_jax.data.image_io import IMAGE_SUFFIXES, list_images, read_image, write_image
from pitta_jax.data.resize import resize_image
from pitta_jax.models.interpolate import resize_bilinear


DISP_PNG, DISP_NPY = "_disp.png", "_disp.npy"  # predict's outputs per image (+ _depth.npy)


def expand_images(spec: str, unique_stems: bool = True) -> list[Path]:
  """A file, a directory (its images), or a glob pattern -> sorted image paths.

  unique_stems: refuse two images with one file stem (their outputs, named by stem, would
  overwrite each other); False where nothing is written per image (source statistics).
  """
  path = Path(spec)
  if path.is_dir():  # every image, `a.png` and `a.jpg` too (the stem check below refuses them)
    paths = sorted(list_images(path, IMAGE_SUFFIXES, all_suffixes=True).values())
  elif path.is_file():
    paths = [path]
  else:
    paths = sorted(Path(p) for p in glob.glob(spec) if Path(p).suffix.lower() in IMAGE_SUFFIXES)
  if not paths:
    raise DataError(spec, f"no image found (a file, a directory or a glob of {IMAGE_SUFFIXES})")
  if unique_stems:
    check_unique_stems(paths)
  return paths


def check_unique_stems(paths: Sequence[Path]) -> None:
  """DataError naming the second of two images with one file stem: outputs named by stem
  (OUT/<stem>.png) would overwrite each other."""
  stems: dict[str, Path] = {}
  for p in paths:
    if p.stem in stems:
      raise DataError(p, f"has the same file stem as {stems[p.stem]}; their outputs would "
                         f"overwrite each other (one directory at a time)")
    stems[p.stem] = p


def check_images(paths: Sequence[Path], quiet: bool = False) -> None:
  """Reads every image once before anything is written (DataError naming the first unreadable
  one): a bad image found halfway would leave half of the outputs behind."""
  for path in tqdm(paths, desc="checking images", unit="img", disable=quiet or len(paths) < 50):
    read_image(path)


def is_own_output(path: Path, companion_suffix: str, suffix: str) -> bool:
  """Whether `path` (named ...`suffix`) was written by this command: the file it always writes
  beside it (`companion_suffix` in place of `suffix`) is there too."""
  return path.name.endswith(suffix) and (
      path.with_name(path.name[:-len(suffix)] + companion_suffix).is_file())


def without_own_outputs(paths: Sequence[Path], out_dir: Path, suffix: str,
                        companion_suffix: str) -> list[Path]:
  """`paths` less the files a previous run of the command wrote into `out_dir` (names ending in
  `suffix`, with their companion file beside them), so that a rerun with --out in the image
  directory does not take them as input; a user's own image of such a name stays an input."""
  out = out_dir.resolve()
  return [p for p in paths
          if not (p.resolve().parent == out and is_own_output(p, companion_suffix, suffix))]


def check_outputs_free(targets: Sequence[Path], suffix: str, companion_suffix: str) -> None:
  """DataError naming the first of `targets` (the files the command is about to write) that
  exists without being one of its earlier outputs: a user's file would be replaced."""
  for target in targets:
    if target.exists() and not is_own_output(target, companion_suffix, suffix):
      raise DataError(target, f"exists and is not an earlier output of this command (no "
                              f"{target.name[:-len(suffix)] + companion_suffix} beside it); it "
                              "is not overwritten: choose another --out")


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
                   quiet: bool = False, size: tuple[int, int] | None = None) -> list[Path]:
  """Writes disparity/depth .npy and a colour PNG per image; returns the PNG paths.

  images: paths, or a spec for `expand_images` (expanded after the weights load, so a bad
  weights directory is reported first).
  size: (H, W) network input size (default: the size the weights were trained at, or for a
    network that keeps the aspect ratio, e.g. Depth Anything V2, `ModelSpec.inference_size`
    of each image).
  """
  weights = load_weights(weights_dir)
  if size is not None:
    weights.spec.check_size(*size)  # ValueError naming the network's rule
  trained = (weights.height, weights.width)
  out = Path(out_dir)
  images = expand_images(images) if isinstance(images, str) else list(images)
  images = without_own_outputs(images, out, DISP_PNG, DISP_NPY)
  if not images:
    raise DataError(out, "no image to predict besides this command's own outputs")
  check_outputs_free([out / f"{p.stem}{DISP_PNG}" for p in images], DISP_PNG, DISP_NPY)
  check_images(images, quiet)
  predict = make_predictor(weights.network())
  out.mkdir(parents=True, exist_ok=True)
  written = []
  for path in tqdm(images, desc="predict", unit="img", disable=quiet):
    image = read_image(path)
    h, w = size or weights.spec.inference_size(image.shape[:2], trained)
    size_in = image.shape[:2]
    image = resize_image(image, h, w, weights.spec.image_resize)
    disp, depth = (np.asarray(a)[0] for a in predict(weights.depth, jnp.asarray(image[None])))
    if weights.spec.keep_aspect:  # infer_image: the output at the image's size, then its depth
      disp = resize_map(disp, size_in, align_corners=True)
      depth = np.asarray(weights.spec.to_depth(disp))
    if not np.all(np.isfinite(disp)):
      raise ValueError(f"{path}: the network produced non-finite outputs on this image")
    save_npy(out / f"{path.stem}{DISP_NPY}", disp.astype(np.float32))  # first: it marks the
    save_npy(out / f"{path.stem}_depth.npy", depth.astype(np.float32))  # PNG as an output
    png = out / f"{path.stem}{DISP_PNG}"
    # near = bright: the disparity as it is, or the inverse of a metric network's depth; at the
    # image's size (test_simple.py colours the disparity resized to it)
    shown = 1.0 / depth if weights.spec.output == "metric_depth" else disp
    write_image(png, viz.colorize(resize_map(shown, size_in, align_corners=False)))
    written.append(png)
  return written
