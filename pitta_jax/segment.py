"""Panoptic maps from the frozen Mask2Former: frames on the fly, or COCO panoptic files on disk.

PITTA's instance masks come from a frozen Mask2Former (Swin-T, COCO panoptic; paper Sec. 3.1).
Two ways to use it:

- `segmented_frames(frames, DIR)`: a lazy sequence whose frames carry `panoptic` + `segments`
  computed when a frame is read (`--segmentation mask2former:DIR`);
- `segment_images(DIR, images, OUT)` (`pitta-jax segment`): writes `<stem>.png` (COCO panoptic
  RGB, id = R + 256 G + 256^2 B) + `<stem>.json` (`{"segments_info": [...]}`) per image, the
  layout the readers' `panoptic_dir` option (`--segmentation png:OUT`) reads, so that a
  sequence is segmented once and adapted many times.

Input size: by default each image enters the network at its own size, zero-padded up to a
multiple of 32 (detectron2's size divisibility), i.e. a 192x640 frame is a 192x640 input and
a 375x1242 KITTI frame a 384x1248 one; we do not upscale the shortest edge to 800 as
detectron2's test-time `ResizeShortestEdge` does (about 4x the pixels and the time on
PITTA-sized frames). `input_size=(H, W)` resizes every image to H x W first;
`input_size=DETECTRON2_RESIZE` resizes each image as detectron2's test time does (shortest edge
800, longest at most 1333, aspect kept): upstream's own maps. Either way the id map comes back
at the image's own size (the masks are resized back, `mask2former.mask_logits_to_image`), as
`Frame.panoptic` requires.

The network is jitted and compiled once per input shape (`mask2former.network` caches on the
module and the shape; a sequence's frames share one). Its outputs leave JAX as NumPy id maps
before they reach the adaptation step, so the segmenter is outside any gradient.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, overload

import numpy as np
from tqdm import tqdm

from pitta_jax.data import coco
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame, Segment
from pitta_jax.data.image_io import read_image
from pitta_jax.data.panoptic_io import is_segments_json, write_panoptic
from pitta_jax.data.sequence import FrameSequence
from pitta_jax.outputs import WatchedDirectory
from pitta_jax.models.mask2former import (CONFIG_JSON, InferenceConfig, load_mask2former,
                                         resized_shape, segment)
from pitta_jax.predict import (Outputs, check_images, check_outputs_free, check_unique_stems,
                               expand_images, without_own_outputs)


PathLike = str | os.PathLike[str]
DETECTRON2_RESIZE = "detectron2"  # input_size: ResizeShortestEdge(800, max 1333) per image
CONVERT_HINT = ("make one with `pitta-jax convert mask2former --from {detectron2,hf} CKPT "
                "--out DIR`")


class Segmenter:
  """A loaded, frozen Mask2Former: `segmenter(image) -> (id map, segments)`.

  Args:
    weights_dir: a directory written by `pitta-jax convert mask2former` (config.json + params).
    input_size: (H, W) network input before padding; None = each image's own size;
      DETECTRON2_RESIZE = detectron2's test-time resize of each image (module docstring).
  """

  def __init__(self, weights_dir: PathLike, input_size: tuple[int, int] | None = None):
    if not os.fspath(weights_dir):
      raise DataError(None, f"Mask2Former needs a weights directory ({CONVERT_HINT})")
    root = Path(weights_dir)
    if not root.is_dir():
      problem = "not found" if not root.exists() else "is not a directory"
      raise DataError(root, f"Mask2Former weights directory {problem} ({CONVERT_HINT})")
    if not (root / CONFIG_JSON).is_file():
      raise DataError(root / CONFIG_JSON, f"not found: not a Mask2Former weights directory "
                                          f"({CONVERT_HINT})")
    if input_size is not None and input_size != DETECTRON2_RESIZE:
      input_size = tuple(int(s) for s in input_size)
      if len(input_size) != 2 or min(input_size) < 1:
        raise ValueError(f"input_size must be (height, width) > 0, got {input_size}")
    self.weights_dir = root
    self.input_size = input_size
    self.module, self.variables = load_mask2former(root)
    n = self.module.config.num_classes
    if n != coco.NUM_CLASSES:  # before any image: the segments' classes must be COCO's
      raise DataError(root / CONFIG_JSON, f"a Mask2Former with {n} classes; the segmenter "
                                          f"writes COCO panoptic categories (the dynamic "
                                          f"classes are COCO ids): convert a COCO panoptic "
                                          f"model ({coco.NUM_CLASSES} classes)")

  def inference_config(self, height: int, width: int) -> InferenceConfig:
    """The `InferenceConfig` for an (height, width) image."""
    if self.input_size == DETECTRON2_RESIZE:
      return InferenceConfig()  # input_size None: ResizeShortestEdge(min_size, max_size)
    return InferenceConfig(input_size=self.input_size or (height, width))

  def __call__(self, image: np.ndarray) -> tuple[np.ndarray, tuple[Segment, ...]]:
    """image (H, W, 3) float32 RGB in [0, 1] -> id map (H, W) int32 (0 = void), segments
    with COCO category ids."""
    image = np.asarray(image, np.float32)
    ids, segments = segment(self.module, self.variables, image,
                            self.inference_config(*image.shape[:2]))
    return np.asarray(ids, np.int32), tuple(segments)

  def segment_frame(self, frame: Frame) -> Frame:
    """`frame` with `panoptic` and `segments` replaced by the segmenter's."""
    ids, segments = self(frame.image)
    return dataclasses.replace(frame, panoptic=ids, segments=segments)


class MappedFrames(Sequence[Frame]):
  """`transform` applied on access to the frames of any sequence (for non-FrameSequence input,
  e.g. a list of frames); slicing stays lazy."""

  def __init__(self, frames: Sequence[Frame], transform: Callable[[Frame], Frame]):
    self.frames = frames
    self.transform = transform

  def __len__(self) -> int:
    return len(self.frames)

  @overload
  def __getitem__(self, index: int) -> Frame: ...

  @overload
  def __getitem__(self, index: slice) -> MappedFrames: ...

  def __getitem__(self, index: int | slice) -> Frame | MappedFrames:
    if isinstance(index, slice):
      return MappedFrames(self.frames[index], self.transform)
    return self.transform(self.frames[index])

  def __iter__(self) -> Iterator[Frame]:
    for frame in self.frames:
      yield self.transform(frame)

  def __repr__(self) -> str:
    return f"MappedFrames(len={len(self)})"


def segmented_frames(frames: Sequence[Frame], weights_dir: PathLike | Segmenter,
                     input_size: tuple[int, int] | None = None
                     ) -> FrameSequence | MappedFrames:
  """The frames with Mask2Former's panoptic maps, computed lazily when a frame is read.

  The weights are loaded now (a bad directory is reported when the sequence is opened, not at
  its first frame); a frame's own panoptic map, if any, is replaced.

  Args:
    frames: a `FrameSequence` (stays one, via `.map`) or any sequence of frames.
    weights_dir: a Mask2Former weights directory, or a loaded `Segmenter` (then `input_size`
      must be None).
    input_size: (H, W) to resize images to; None = their own size, padded to a multiple of 32.

  Returns:
    a sequence of the same length whose frames carry `panoptic` (H, W) int32 and `segments`.
  """
  if isinstance(weights_dir, Segmenter):
    if input_size is not None:
      raise ValueError("pass input_size to the Segmenter, not with one")
    segmenter = weights_dir
  else:
    segmenter = Segmenter(weights_dir, input_size)
  if isinstance(frames, FrameSequence):
    return frames.map(segmenter.segment_frame)
  return MappedFrames(frames, segmenter.segment_frame)


# per image: the segments JSON (written first) and the id PNG
SEGMENT_OUTPUTS = Outputs((".json", ".png"), looks_own=is_segments_json)


def segment_images(weights_dir: PathLike, images: str | Iterable[PathLike], out_dir: PathLike,
                   input_size: tuple[int, int] | None = None, quiet: bool = False,
                   check_out: Callable[[], Any] | None = None) -> list[Path]:
  """Segments images into COCO panoptic files: OUT/<stem>.png + OUT/<stem>.json.

  Args:
    weights_dir: a Mask2Former weights directory.
    images: paths, or a file / directory / glob for `predict.expand_images` (expanded after the
      weights load, so a bad weights directory is reported first).
    out_dir: output directory (created); earlier outputs of the same stems (a PNG with its
      JSON) are overwritten, any other file of those names is refused (DataError).
    input_size: (H, W) network input; None = each image's own size (padded to a multiple of 32);
      DETECTRON2_RESIZE = detectron2's test-time resize (shortest edge 800, max 1333).
    quiet: no progress bar.
    check_out: called before each image's files are written (as `predict.predict_images`').

  Returns:
    the written PNG paths, in input order. The maps have each image's own size.
  """
  segmenter = Segmenter(weights_dir, input_size)
  out = Path(out_dir)
  paths = (expand_images(images, unique_stems=False) if isinstance(images, str)
           else [Path(p) for p in images])
  paths = without_own_outputs(paths, out, SEGMENT_OUTPUTS)  # a rerun into the image directory
  if not paths:
    raise DataError(out, "no image to segment besides this command's own outputs")
  check_unique_stems(paths)  # a list given by the caller too
  for path in paths:
    if (out / f"{path.stem}.png").resolve() == path.resolve():
      raise DataError(path, f"--out {out} would overwrite this input with its panoptic map "
                            "(outputs are OUT/<stem>.png): choose another --out")
  check_outputs_free(out, [p.stem for p in paths], SEGMENT_OUTPUTS)
  # (an image too thin for the detectron2 resize is refused here, before any is segmented)
  check_images(paths, quiet, lambda image: resized_shape(
      *image.shape[:2], segmenter.inference_config(*image.shape[:2])))
  out.mkdir(parents=True, exist_ok=True)
  written = []
  with WatchedDirectory(out) as watch:
    for path in tqdm(paths, desc="segment", unit="img", disable=quiet):
      ids, segments = segmenter(read_image(path, gray=True))
      png = out / f"{path.stem}.png"
      (check_out or watch.check)()
      write_panoptic(png, ids, segments)
      written.append(png)
  return written
