"""Host side of the engine: `Frame`s -> stacked, padded `StepInput` chunks (NumPy).

Images and panoptic maps are resized to the network's input size (`resize_frame`: image area /
linear, ids nearest, the ground-truth depth untouched). Segments become fixed-size padded
arrays; the last chunk is padded with copies of its last frame marked `valid=False`, so one
compiled scan serves the whole sequence.
"""

from __future__ import annotations

from typing import Collection, Iterable, Iterator

import numpy as np

from pitta_jax.adapt.engine import StepInput
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame
from pitta_jax.data.resize import IMAGE_RESIZE, resize_frame
from pitta_jax.masks import DEFAULT_DYNAMIC_COCO_IDS

# how far outside [0, 1] a frame's values may stray (float rounding of a reader's or a
# renderer's output) before the image is taken for another scale (0..255, mean/std-normalised)
IMAGE_RANGE_SLACK = 1e-3


def step_input(frame: Frame, height: int, width: int, max_segments: int,
               image_resize: str = IMAGE_RESIZE[0],
               keep_first: Collection[int] = DEFAULT_DYNAMIC_COCO_IDS) -> StepInput:
  """One frame at the network's size (its image resized by `image_resize`, the network's
  `ModelSpec.image_resize`). A frame without panoptic map has no instances (N = 0).

  A frame with more than `max_segments` segments keeps those of the classes `keep_first` (the
  method's dynamic set O, what L_d masks) first, then the other things, then stuff, each in the
  frame's order: COCO's things include static objects (traffic lights, benches), which must not
  crowd the cars and people out."""
  if frame.image.ndim != 3 or frame.image.shape[-1] != 3:
    raise DataError(frame.name or "frame", f"image must be (H, W, 3), got {frame.image.shape}")
  # An 8-bit image taken as it is reached the network as floats of 0..255 (or, resized, clipped
  # to white): `Frame.image` is RGB in [0, 1], as `registry.checked_images` asks of a batch.
  if not np.issubdtype(frame.image.dtype, np.floating):
    raise DataError(frame.name or "frame", f"image must be floating RGB in [0, 1], got "
                                           f"{frame.image.dtype} (divide 8-bit images by 255)")
  if not np.all(np.isfinite(frame.image)):
    raise DataError(frame.name or "frame", "image holds NaN or infinite values")
  lo, hi = ((float(np.min(frame.image)), float(np.max(frame.image))) if frame.image.size
            else (0.0, 0.0))
  if lo < -IMAGE_RANGE_SLACK or hi > 1.0 + IMAGE_RANGE_SLACK:
    # 0..255 floats (a cast without the division) or a mean/std-normalised image: the networks
    # normalise [0, 1] RGB themselves, and took either without a word
    raise DataError(frame.name or "frame", f"image values must be RGB in [0, 1], got "
                                           f"{lo:g}..{hi:g} (divide 8-bit values by 255; the "
                                           f"networks normalise it themselves)")
  if frame.panoptic is not None:
    ids = np.asarray(frame.panoptic)
    if not np.issubdtype(ids.dtype, np.integer):
      # a float id map cast to int32 read segment 3.7 as 3 (`masks.segment_id_array` refuses it)
      raise DataError(frame.name or "frame", f"panoptic must be an integer map of segment ids, "
                                             f"got {ids.dtype}")
    if ids.shape != frame.image.shape[:2]:
      # resized on its own to the network's size, a map of another size (a transposed one, a
      # segmenter's own resolution) would label other pixels; the file readers refuse it too
      raise DataError(frame.name or "frame", f"panoptic map is {ids.shape} but the image is "
                                             f"{frame.image.shape[:2]} (H, W)")
  frame = resize_frame(frame, height, width, image_resize)
  if frame.panoptic is None:
    panoptic = np.zeros((height, width), np.int32)
    segments = ()
  else:
    panoptic = np.asarray(frame.panoptic, np.int32)
    segments = frame.segments
  if len(segments) > max_segments:  # keep the dynamic classes, then the things, first
    keep = frozenset(int(c) for c in keep_first)
    segments = tuple(sorted(segments, key=lambda s: (int(s.category_id) not in keep,
                                                     not s.isthing)))[:max_segments]
  ids = np.zeros((max_segments,), np.int32)
  classes = np.zeros((max_segments,), np.int32)
  valid = np.zeros((max_segments,), bool)
  for k, seg in enumerate(segments):
    ids[k], classes[k], valid[k] = seg.id, seg.category_id, True
  has_k = frame.intrinsics is not None
  K = np.asarray(frame.intrinsics, np.float32) if has_k else np.zeros((3, 3), np.float32)
  return StepInput(np.asarray(frame.image, np.float32), panoptic, ids, classes, valid,
                   np.array(True), K, np.array(has_k), np.array(bool(frame.starts_recording)))


def stack(inputs: list[StepInput], size: int) -> StepInput:
  """Stacks frames on a leading axis, padding to `size` with invalid copies of the last one."""
  if not inputs:
    raise ValueError("no frame to stack")
  pad = [inputs[-1]._replace(valid=np.array(False))] * (size - len(inputs))
  return StepInput(*(np.stack(field) for field in zip(*(inputs + pad))))


def chunks(frames: Iterable[Frame], height: int, width: int, chunk_size: int,
           max_segments: int, image_resize: str = IMAGE_RESIZE[0],
           keep_first: Collection[int] = DEFAULT_DYNAMIC_COCO_IDS
           ) -> Iterator[tuple[StepInput, list[Frame]]]:
  """Yields (stacked chunk, the original frames of it) — frames keep their full-size depth for
  evaluation. Memory holds one chunk at a time. image_resize, keep_first: `step_input`'s."""
  batch: list[Frame] = []

  def stacked() -> StepInput:
    return stack([step_input(f, height, width, max_segments, image_resize, keep_first)
                  for f in batch], chunk_size)

  for frame in frames:
    batch.append(frame)
    if len(batch) == chunk_size:
      yield stacked(), batch
      batch = []
  if batch:
    yield stacked(), batch
