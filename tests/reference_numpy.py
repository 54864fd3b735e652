"""Literal NumPy references, written straight from the paper's equations with loops over pixels.

No vectorised tricks here: these are what the JAX implementations are tested against.
"""

from __future__ import annotations

import numpy as np


def median_filter_loop(x: np.ndarray, s: int) -> np.ndarray:
  """Eq. 7: median over rows max(i-r,0)..min(i+r,H-1), cols max(j-r,0)..min(j+r,W-1)."""
  x = np.asarray(x, np.float32)
  h, w = x.shape
  r = s // 2
  out = np.empty((h, w), np.float32)
  for i in range(h):
    for j in range(w):
      window = x[max(i - r, 0):min(i + r, h - 1) + 1, max(j - r, 0):min(j + r, w - 1) + 1]
      out[i, j] = np.median(window)
  return out


def laplacian_edge_loop(x: np.ndarray, weight=None) -> np.ndarray:
  """Eq. 6 (eq. 5 on I_bar): W(x,y) |X(x+1,y) + X(x-1,y) + X(x,y+1) + X(x,y-1) - 4 X(x,y)|,
  indices clamped to the image."""
  x = np.asarray(x, np.float32)
  h, w = x.shape
  weight = np.ones((h, w), np.float32) if weight is None else np.broadcast_to(
      np.asarray(weight, np.float32), (h, w))
  out = np.empty((h, w), np.float32)
  for i in range(h):
    for j in range(w):
      lap = (x[min(i + 1, h - 1), j] + x[max(i - 1, 0), j] + x[i, min(j + 1, w - 1)]
             + x[i, max(j - 1, 0)] - 4 * x[i, j])
      out[i, j] = weight[i, j] * abs(lap)
  return out


def channel_mean_loop(image: np.ndarray) -> np.ndarray:
  """I_bar(x, y) = 1/C sum_z I(x, y, z)."""
  image = np.asarray(image, np.float32)
  h, w, c = image.shape
  out = np.empty((h, w), np.float32)
  for i in range(h):
    for j in range(w):
      total = np.float32(0)
      for z in range(c):
        total += image[i, j, z]
      out[i, j] = total / c
  return out


def edge_guided_loss_loop(image, depth, u=None, v=None) -> float:
  """Eq. 9: sum over pixels of |dI - dD| (eqs. 5-6)."""
  d_i = laplacian_edge_loop(channel_mean_loop(image), u)
  d_d = laplacian_edge_loop(depth, v)
  total = 0.0
  for i in range(d_i.shape[0]):
    for j in range(d_i.shape[1]):
      total += abs(float(d_i[i, j]) - float(d_d[i, j]))
  return total


def instance_table_loop(segment_ids, segment_classes, segment_valid, dynamic_classes, n_max):
  """Eq. 3's set N: the valid segments (id > 0) whose class is dynamic, in order, first n_max."""
  ids = []
  for sid, cls, ok in zip(segment_ids, segment_classes, segment_valid):
    if ok and sid > 0 and int(cls) in [int(c) for c in dynamic_classes]:
      ids.append(int(sid))
  ids = ids[:n_max]
  inst_ids = np.zeros((n_max,), np.int32)
  inst_valid = np.zeros((n_max,), bool)
  inst_ids[:len(ids)] = ids
  inst_valid[:len(ids)] = True
  return inst_ids, inst_valid


def used_ids(dynamic_ids) -> list[int]:
  """The used entries (> 0) of a padded dynamic id list, in order: instance j = entry j - 1."""
  return [int(i) for i in np.asarray(dynamic_ids).reshape(-1) if i > 0]


def instance_masks_loop(panoptic, dynamic_ids, mode="binary") -> list[np.ndarray]:
  """Eq. 3: M_j(x, y) = g_j on segment j, else 0; g_j = 1 (binary), the segment id i
  (segment_id: eq. 3 as written, g_i = i on R_i) or j (instance_id)."""
  panoptic = np.asarray(panoptic)
  h, w = panoptic.shape
  masks = []
  for j, sid in enumerate(used_ids(dynamic_ids), start=1):
    g = {"binary": 1.0, "segment_id": float(sid), "instance_id": float(j)}[mode]
    m = np.zeros((h, w), np.float32)
    for x in range(h):
      for y in range(w):
        if panoptic[x, y] == sid:
          m[x, y] = g
    masks.append(m)
  return masks


def depth_refining_loss_loop(depth, panoptic, dynamic_ids, s, mode="binary") -> float:
  """Eq. 8: 1/N sum_j sum_{x,y} |D~_j - D~'_j|, D~_j = D * M_j (eq. 4), D~'_j by eq. 7."""
  depth = np.asarray(depth, np.float32)
  masks = instance_masks_loop(panoptic, dynamic_ids, mode)
  n = len(masks)
  if n == 0:
    return 0.0
  total = 0.0
  for m in masks:
    masked = (depth * m).astype(np.float32)
    pseudo = median_filter_loop(masked, s)
    for x in range(depth.shape[0]):
      for y in range(depth.shape[1]):
        total += abs(float(masked[x, y]) - float(pseudo[x, y]))
  return total / n


def depth_refining_grad_loop(depth, panoptic, dynamic_ids, s, mode="binary") -> np.ndarray:
  """d L_d / d D with the pseudo labels held constant:
  1/N sum_j M_j(x, y) sign(D~_j(x, y) - D~'_j(x, y)), with sign(0) = 0 where a pixel equals its
  own pseudo label (the derivative of |u| at 0 that PyTorch's abs and NumPy's sign use)."""
  depth = np.asarray(depth, np.float32)
  masks = instance_masks_loop(panoptic, dynamic_ids, mode)
  grad = np.zeros(depth.shape, np.float64)
  if not masks:
    return grad
  for m in masks:
    masked = (depth * m).astype(np.float32)
    pseudo = median_filter_loop(masked, s)
    for x in range(depth.shape[0]):
      for y in range(depth.shape[1]):
        diff = float(masked[x, y]) - float(pseudo[x, y])
        grad[x, y] += m[x, y] * float(np.sign(diff))
  return grad / len(masks)


def depth_metrics_literal(pred, gt, min_depth=1e-3, max_depth=80.0, median_scaling=True,
                          clamp=True):
  """MonoDepth2's protocol and `compute_errors`, one pixel at a time (same-size pred and gt)."""
  gt_v, pred_v = [], []
  for x in range(gt.shape[0]):
    for y in range(gt.shape[1]):
      if min_depth < gt[x, y] < max_depth:
        gt_v.append(float(gt[x, y]))
        pred_v.append(float(pred[x, y]))
  if median_scaling:
    ratio = float(np.median(gt_v)) / float(np.median(pred_v))
    pred_v = [p * ratio for p in pred_v]
  if clamp:
    pred_v = [min(max(p, min_depth), max_depth) for p in pred_v]
  n = len(gt_v)
  sums = dict(abs_rel=0.0, sq_rel=0.0, rmse=0.0, rmse_log=0.0, a1=0.0, a2=0.0, a3=0.0)
  for g, p in zip(gt_v, pred_v):
    sums["abs_rel"] += abs(g - p) / g
    sums["sq_rel"] += (g - p) ** 2 / g
    sums["rmse"] += (g - p) ** 2
    sums["rmse_log"] += (np.log(g) - np.log(p)) ** 2
    t = max(g / p, p / g)
    sums["a1"] += t < 1.25
    sums["a2"] += t < 1.25 ** 2
    sums["a3"] += t < 1.25 ** 3
  out = {k: v / n for k, v in sums.items()}
  out["rmse"] = np.sqrt(out["rmse"])
  out["rmse_log"] = np.sqrt(out["rmse_log"])
  return out
