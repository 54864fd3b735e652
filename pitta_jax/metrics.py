"""Depth evaluation metrics, MonoDepth2 protocol (host-side NumPy).

The 7 Eigen et al. metrics as MonoDepth2's `compute_errors` computes them, for one frame:

  abs_rel  = mean(|gt - pred| / gt)          sq_rel   = mean((gt - pred)**2 / gt)
  rmse     = sqrt(mean((gt - pred)**2))      rmse_log = sqrt(mean((log gt - log pred)**2))
  a1, a2, a3 = mean(max(gt/pred, pred/gt) < 1.25, 1.25**2, 1.25**3)

Protocol (MonoDepth2 `evaluate_depth.py`): the predicted disparity is resized to the ground
truth's size with `cv2.resize(..., interpolation=cv2.INTER_LINEAR)` and inverted; the valid pixels are
`min_depth < gt < max_depth` (and the Garg crop when asked); per-image median scaling
`pred *= median(gt_valid) / median(pred_valid)` (monocular models); then pred is clamped to
[min_depth, max_depth]. Frames are averaged with `mean_metrics`. The valid-pixel range is
MonoDepth2's rule for its Eigen split; on its other splits it scores every pixel with gt > 0
(`valid_gt="positive"`), the 80 m then capping the prediction only. Ours applies the range
everywhere unless told (DrivingStereo and Waymo included, whose protocol the paper leaves to
an appendix we do not have); far ground truth beyond `max_depth` is then not scored.

`depth_metrics` takes a depth (or, with `pred_is_disparity`, a disparity) and by default
interpolates in disparity as MonoDepth2 does (`resize="disparity"`: a depth is inverted, resized
and inverted back); `resize="depth"` interpolates the depth itself, which mixes the two
surfaces at a depth edge differently (on KITTI-like sparse ground truth abs_rel grows by a few
thousandths). Metrics are computed in float64; which pixels are valid is decided in the
ground truth's own float type, as upstream compares its float32 maps.
"""

from __future__ import annotations

from typing import Iterable, Mapping

import cv2
import numpy as np

MIN_DEPTH, MAX_DEPTH = 1e-3, 80.0  # valid ground truth and cap, MonoDepth2's evaluation
# MonoDepth2's `evaluate_depth.py`: a stereo-trained model's depth is metric up to the KITTI
# baseline it was trained with (0.1 units = 54 cm), so it is multiplied by 5.4, not median-scaled
STEREO_SCALE_FACTOR = 5.4
RESIZE_DOMAINS = ("disparity", "depth")  # what `depth_metrics` interpolates onto the gt's size
# which ground-truth pixels are scored: "range" min_depth < gt < max_depth (MonoDepth2's eigen
# split), "positive" finite gt > 0 (its eigen_benchmark split, improved ground truth beyond 80 m
# kept)
VALID_GT = ("range", "positive")


class NoValidPixels(ValueError):
  """A frame whose ground truth has no pixel in the valid depth range (it cannot be scored)."""


METRIC_NAMES = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")

# Garg/Eigen crop fractions of MonoDepth2 (rows top, bottom; cols left, right).
GARG_CROP = (0.40810811, 0.99189189, 0.03594771, 0.96405229)


def garg_crop_mask(height: int, width: int) -> np.ndarray:
  """MonoDepth2's Garg crop as a bool mask (bounds truncated with int32, as MonoDepth2 does).

  Returns:
    (height, width) bool, True in rows [0.40810811 H, 0.99189189 H), cols [0.03594771 W,
    0.96405229 W).
  """
  crop = np.array([GARG_CROP[0] * height, GARG_CROP[1] * height,
                   GARG_CROP[2] * width, GARG_CROP[3] * width]).astype(np.int32)
  mask = np.zeros((height, width), bool)
  mask[crop[0]:crop[1], crop[2]:crop[3]] = True
  return mask


def compute_errors(gt: np.ndarray, pred: np.ndarray) -> dict[str, float]:
  """The 7 metrics on matched valid pixels (MonoDepth2's `compute_errors`).

  Args:
    gt: (P,) positive ground-truth depths.
    pred: (P,) positive predicted depths.

  Returns:
    dict with `METRIC_NAMES` keys, Python floats.
  """
  gt = np.asarray(gt, np.float64)
  pred = np.asarray(pred, np.float64)
  thresh = np.maximum(gt / pred, pred / gt)
  out = {
      "abs_rel": np.mean(np.abs(gt - pred) / gt),
      "sq_rel": np.mean((gt - pred) ** 2 / gt),
      "rmse": np.sqrt(np.mean((gt - pred) ** 2)),
      "rmse_log": np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2)),
      "a1": np.mean(thresh < 1.25),
      "a2": np.mean(thresh < 1.25 ** 2),
      "a3": np.mean(thresh < 1.25 ** 3),
  }
  return {k: float(out[k]) for k in METRIC_NAMES}


def depth_metrics(pred: np.ndarray, gt: np.ndarray, *, min_depth: float = MIN_DEPTH,
                  max_depth: float = MAX_DEPTH, median_scaling: bool = True, garg_crop: bool = False,
                  clamp: bool = True, pred_is_disparity: bool = False,
                  alignment: str | None = None, resize: str = "disparity",
                  valid_gt: str = "range") -> dict[str, float]:
  """The 7 depth metrics of one frame, MonoDepth2 protocol.

  Args:
    pred: (h, w) predicted depth (or disparity with `pred_is_disparity`), any size; resized to
      gt's size with cv2 INTER_LINEAR when the sizes differ, as `resize` says.
    gt: (H, W) ground-truth depth in metres; pixels outside (min_depth, max_depth) are ignored.
    min_depth, max_depth: valid range of gt, and the clamp range of pred.
    median_scaling: multiply pred by median(gt) / median(pred) over the valid pixels (monocular).
    garg_crop: also restrict to the Garg crop (KITTI Eigen split).
    clamp: clamp pred to [min_depth, max_depth] after scaling.
    pred_is_disparity: pred is a disparity (depth = 1 / disparity).
    resize: the map interpolated when the sizes differ: "disparity" (MonoDepth2's order: resize
      the disparity, then depth = 1 / disparity) or "depth".
    valid_gt: the scored pixels, "range" (min_depth < gt < max_depth) or "positive" (gt > 0,
      MonoDepth2's eigen_benchmark protocol); pred is clamped to [min_depth, max_depth] either
      way.
    alignment: overrides `median_scaling` when given: "median" (MonoDepth2's per-image median
      scaling), "scale_shift" (per-image least squares of scale s and shift t in inverse depth,
      s / pred + t ~ 1 / gt on the valid pixels, then inverted with the inverse depth floored at
      1 / max_depth: the protocol of affine-invariant relative depth networks such as Depth
      Anything V2), "stereo" (times `STEREO_SCALE_FACTOR`, MonoDepth2's protocol for models
      trained with stereo pairs), or "none".

  Returns:
    dict with `METRIC_NAMES` keys, Python floats.

  Raises:
    ValueError: pred or gt not 2-D, NaN in pred, no valid pixel, or (without clamping) a
      non-positive or non-finite prediction on a valid pixel.
  """
  pred = np.asarray(pred)
  gt = np.asarray(gt)
  if pred.ndim != 2:
    raise ValueError(f"pred must be a 2-D (H, W) map, got shape {pred.shape}")
  if gt.ndim != 2:
    raise ValueError(f"gt must be a 2-D (H, W) map, got shape {gt.shape}")
  if np.isnan(pred).any():
    raise ValueError("pred contains NaN")
  if resize not in RESIZE_DOMAINS:
    raise ValueError(f"resize must be one of {', '.join(RESIZE_DOMAINS)}, got {resize!r}")
  if valid_gt not in VALID_GT:
    raise ValueError(f"valid_gt must be one of {', '.join(VALID_GT)}, got {valid_gt!r}")
  gt_h, gt_w = gt.shape
  pred = pred.astype(np.float32)
  if pred.shape != gt.shape:
    if pred_is_disparity != (resize == "disparity"):  # into the domain to interpolate in
      with np.errstate(divide="ignore"):
        pred = np.float32(1.0) / pred
      pred_is_disparity = not pred_is_disparity
    pred = cv2.resize(pred, (gt_w, gt_h), interpolation=cv2.INTER_LINEAR)
  if pred_is_disparity:
    with np.errstate(divide="ignore"):
      pred = 1.0 / pred
  # The valid pixels are found in the ground truth's own float type, as evaluate_depth.py's
  # `gt_depth > MIN_DEPTH` on its float32 maps compares (float32(1e-3) is not above 1e-3 there,
  # and is above it in float64); the metrics are then computed in float64.
  native = gt if np.issubdtype(gt.dtype, np.floating) else gt.astype(np.float64)
  lo, hi = native.dtype.type(min_depth), native.dtype.type(max_depth)
  with np.errstate(invalid="ignore"):  # (H, W); NaN gt is invalid
    # an infinite depth is no measurement ("range" excludes it by its upper bound)
    valid = ((native > 0) & np.isfinite(native) if valid_gt == "positive"
             else (native > lo) & (native < hi))
  gt = gt.astype(np.float64)
  pred = pred.astype(np.float64)
  if garg_crop:
    valid &= garg_crop_mask(gt_h, gt_w)
  if not valid.any():
    raise NoValidPixels("no valid ground-truth pixel " + ("(> 0)" if valid_gt == "positive"
                                                          else f"in ({min_depth}, {max_depth})")
                        + (" inside the Garg crop" if garg_crop else ""))
  gt_v, pred_v = gt[valid], pred[valid]  # (P,)
  if alignment is None:
    alignment = "median" if median_scaling else "none"
  if alignment == "median":
    median = np.median(pred_v)
    if not 0 < median < np.inf:  # (a ratio of inf, 0 or NaN, whatever the clamping)
      raise ValueError(f"the prediction's median on the valid pixels is {median}: median "
                       f"scaling needs a positive finite one; check the prediction")
    pred_v = pred_v * (np.median(gt_v) / median)
  elif alignment == "scale_shift":
    pred_v = 1.0 / np.maximum(scale_shift_inverse(1.0 / pred_v, 1.0 / gt_v), 1.0 / max_depth)
  elif alignment == "stereo":
    pred_v = pred_v * STEREO_SCALE_FACTOR
  elif alignment != "none":
    raise ValueError(f"alignment must be median, scale_shift, stereo or none, got {alignment!r}")
  if clamp:
    pred_v = np.clip(pred_v, min_depth, max_depth)
  if not (np.isfinite(pred_v).all() and (pred_v > 0).all()):
    raise ValueError("pred must be positive and finite on the valid pixels (after scaling); "
                     "use clamp=True or check the prediction")
  return compute_errors(gt_v, pred_v)


def scale_shift_inverse(pred_inv: np.ndarray, gt_inv: np.ndarray) -> np.ndarray:
  """s * pred_inv + t with (s, t) = argmin sum (s pred_inv + t - gt_inv)^2 (closed form), (P,)."""
  a = np.stack([pred_inv, np.ones_like(pred_inv)], axis=1)  # (P, 2)
  (s, t), *_ = np.linalg.lstsq(a, gt_inv, rcond=None)
  return s * pred_inv + t


def mean_metrics(per_frame: Iterable[Mapping[str, float]]) -> dict[str, float]:
  """Average of per-frame metrics (MonoDepth2 averages the frames' metrics, not the pixels).

  Args:
    per_frame: dicts with at least the `METRIC_NAMES` keys.

  Returns:
    dict with `METRIC_NAMES` keys.

  Raises:
    ValueError: no frame, or a frame missing a metric.
  """
  rows = list(per_frame)
  if not rows:
    raise ValueError("mean_metrics needs at least one frame")
  for i, row in enumerate(rows):
    missing = [k for k in METRIC_NAMES if k not in row]
    if missing:
      raise ValueError(f"frame {i} lacks the metrics {missing}")
  return {k: float(np.mean([float(row[k]) for row in rows])) for k in METRIC_NAMES}
