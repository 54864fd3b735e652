"""Bringing a frame to the network's input size, MonoDepth2's intrinsic-free protocol.

MonoDepth2 feeds the whole image resized to 640x192 (no crop, aspect ratio not kept) and
evaluates the prediction resized back to the ground truth's size; the ground truth itself is
never resized. Its KITTI data loader and `test_simple.py` resize with PIL's LANCZOS
(`ANTIALIAS`), whose kernel widens with the scale factor and so antialiases when shrinking.
OpenCV's `INTER_LANCZOS4` has a fixed 8x8 support and aliases at the 2-3x reductions we need
(KITTI 1242 -> 640, DrivingStereo 1762 -> 640, Waymo 1920 -> 640), so we use `cv2.INTER_AREA`
(the exact box-filter average for shrinking) when neither side grows and `cv2.INTER_LINEAR`
otherwise. Values therefore differ from PIL's Lanczos by a few grey levels near edges.

Panoptic id maps are resized by nearest neighbour with pixel-centre alignment (source pixel
floor((i + 0.5) * in / out), the rule of `cv2.INTER_NEAREST_EXACT` and PIL's NEAREST; plain
`cv2.INTER_NEAREST` samples floor(i * in / out), shifted by half a pixel), so ids are never
blended. Segments that no pixel keeps after resizing are dropped from `Frame.segments`, so that
the instance count N of eq. (8) counts visible instances only.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from pitta_jax.data.frame import Frame

# how a network's images are resized (`ModelSpec.image_resize`): "area" as above (MonoDepth2's
# family); "cubic": cv2.INTER_CUBIC on the [0, 1] image, not clipped, as Depth Anything V2's
# `infer_image` (its util/transform.py `Resize`, applied to image / 255)
IMAGE_RESIZE = ("area", "cubic")


def resize_image(image: np.ndarray, height: int, width: int, method: str = IMAGE_RESIZE[0]
                 ) -> np.ndarray:
  """(H, W, 3) float32 [0, 1] -> (height, width, 3) float32: "area" INTER_AREA when shrinking
  (INTER_LINEAR otherwise), clipped to [0, 1]; "cubic" INTER_CUBIC, unclipped (`IMAGE_RESIZE`)."""
  if method not in IMAGE_RESIZE:
    raise ValueError(f"image resize must be one of {IMAGE_RESIZE}, got {method!r}")
  h, w = image.shape[:2]
  if (h, w) == (height, width):
    return image.astype(np.float32)
  if method == "cubic":
    return cv2.resize(image.astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
  interpolation = cv2.INTER_AREA if height <= h and width <= w else cv2.INTER_LINEAR
  out = cv2.resize(image.astype(np.float32), (width, height), interpolation=interpolation)
  return np.clip(out, 0.0, 1.0)


def nearest_indices(size_in: int, size_out: int) -> np.ndarray:
  """(size_out,) int source index of each output pixel, pixel-centre aligned."""
  return np.minimum(((np.arange(size_out) + 0.5) * size_in / size_out).astype(np.int64),
                    size_in - 1)


def resize_ids(ids: np.ndarray, height: int, width: int) -> np.ndarray:
  """(H, W) integer map -> (height, width), nearest neighbour, same dtype."""
  rows = nearest_indices(ids.shape[0], height)
  cols = nearest_indices(ids.shape[1], width)
  return ids[rows[:, None], cols[None, :]]


def resize_frame(frame: Frame, height: int, width: int,
                 image_resize: str = IMAGE_RESIZE[0]) -> Frame:
  """The frame with image and panoptic map at (height, width), the network's input size (its
  `ModelSpec`'s); depth (ground truth) untouched.
  image_resize: the image's interpolation (`resize_image`)."""
  image = resize_image(frame.image, height, width, image_resize)
  panoptic, segments = frame.panoptic, frame.segments
  if panoptic is not None:
    panoptic = resize_ids(panoptic, height, width)
    present = set(np.unique(panoptic).tolist())
    segments = tuple(s for s in segments if s.id in present)
  intrinsics = frame.intrinsics
  if intrinsics is not None:
    intrinsics = scale_intrinsics(intrinsics, frame.image.shape[:2], (height, width))
  return dataclasses.replace(frame, image=image, panoptic=panoptic, segments=segments,
                             intrinsics=intrinsics)


def scale_intrinsics(K: np.ndarray, size_in: tuple[int, int], size_out: tuple[int, int]
                     ) -> np.ndarray:
  """K of an image resized from size_in to size_out (H, W), pixel-centre convention: row 0 of K
  scales by W'/W, row 1 by H'/H (the principal point moves with the pixel grid)."""
  K = np.array(K, np.float64)
  sy, sx = size_out[0] / size_in[0], size_out[1] / size_in[1]
  K[0, :] *= sx
  K[1, :] *= sy
  K[0, 2] += 0.5 * sx - 0.5
  K[1, 2] += 0.5 * sy - 0.5
  return K
