"""The in-memory frame format every reader and the synthetic benchmark produce.

A reader yields `Frame`s at the file's native resolution; resizing to the network input
happens later (MonoDepth2 protocol: the image is resized, the ground truth stays full size).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Segment:
  """One panoptic segment, as in COCO panoptic `segments_info`.

  id: the segment id in the id map (> 0; 0 is void).
  category_id: COCO category id (1 = person, 3 = car, ...; see `pitta_jax.data.coco`).
  isthing: True for countable objects (instances), False for stuff.
  """
  id: int
  category_id: int
  isthing: bool = True


@dataclasses.dataclass(frozen=True)
class Frame:
  """One monocular frame.

  image:    (H, W, 3) float32 RGB in [0, 1].
  depth:    (Hd, Wd) float32 metres, 0 = invalid; None when the dataset has no ground truth.
            May be larger or smaller than the image (evaluation resizes the prediction to it).
  panoptic: (H, W) int32 segment id map (0 = void), or None.
  segments: the segments present in `panoptic`.
  name:     a stable identifier (file stem, or "<seq>/<index>").
  intrinsics: (3, 3) float64 camera matrix K of `image` in pixels, or None when the dataset
            gives none (methods that reproject, e.g. CoMoDa, need it).
  starts_recording: True when the frame is the first of a recording that follows another one
            in the same stream (a new drive or sequence): methods that use the previous frame
            (Ada-Depth, CoMoDa) treat it as a first frame. Readers set it
            (`FrameSequence`); a stream's very first frame has no previous frame either way.
  image_file: the file the image was read from ("" for a frame built in memory), named in
            errors about the frame's data.
  depth_file: where `depth` was read from ("" for a frame built in memory): a file, or an
            archive's entry such as `gt_depths.npz[12]`, named in errors about the ground truth.
  """
  image: np.ndarray
  depth: np.ndarray | None = None
  panoptic: np.ndarray | None = None
  segments: tuple[Segment, ...] = ()
  name: str = ""
  intrinsics: np.ndarray | None = None
  starts_recording: bool = False
  image_file: str = ""
  depth_file: str = ""


ASPECT_TOLERANCE = 0.01  # relative difference of W / H a prediction can be resized across


def aspect_mismatch(image_hw: tuple[int, ...], depth_hw: tuple[int, ...]) -> str | None:
  """Why a prediction for an image of `image_hw` (H, W, ...) cannot be resized onto ground
  truth of `depth_hw`: their aspect ratios differ by more than 1%; None when they agree."""
  (h, w), (gh, gw) = image_hw[:2], depth_hw[:2]
  if abs(gw / gh - w / h) <= ASPECT_TOLERANCE * (w / h):
    return None
  return (f"ground truth is {gw}x{gh} but the image is {w}x{h} (W x H): another aspect ratio, "
          f"so the prediction cannot be resized onto it")
