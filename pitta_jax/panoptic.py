"""Mask2Former panoptic post-processing on the host (NumPy), outside any gradient.

Implements detectron2 Mask2Former's `MaskFormer.panoptic_inference` (upstream
`mask2former/maskformer_model.py`) for one image:

1. per query: softmax over the K + 1 class logits; score, label = max and argmax over all
   K + 1 (the last being "no object"); keep the queries with label != K and score >
   `object_mask_threshold` (0.8);
2. per pixel: the kept query maximising score * sigmoid(mask logit) (first on ties);
3. per kept query k, in query order: mask_area = pixels assigned to k, original_area = pixels
   with sigmoid >= 0.5, segment = assigned & sigmoid >= 0.5; dropped if any of these is empty
   or mask_area / original_area < `overlap_threshold` (0.8); a stuff query whose class already
   has a segment paints its pixels with that segment's id (one segment per stuff class);
   otherwise a new id (1, 2, ...). Unpainted pixels are 0 (void).

This is upstream's (the paper's) rule, not transformers' `post_process_panoptic_segmentation`,
which differs: it has no sigmoid >= 0.5 test of the owner's own mask (its `mask_threshold`
applies to score x probability), its own area and score thresholds (0.8 and 0.5 by default)
and resizes first, leaving void only where a query fails its area test; on the same logits the
two give different maps (e.g. 4 segments with void pixels here, 12 there).

Segments carry detectron2's contiguous class ids (0..132 for COCO panoptic, things 0..79 first);
`to_frame_segments` maps them to COCO category ids (`pitta_jax.data.coco`) as
`pitta_jax.data.frame.Segment`s, the format of `Frame.segments`.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from pitta_jax.data import coco
from pitta_jax.data.frame import Segment as FrameSegment


class Segment(NamedTuple):
  """One panoptic segment: id in the id map, contiguous class id, thing (True) or stuff."""
  id: int
  category_id: int
  isthing: bool


def default_is_thing(num_classes: int) -> np.ndarray:
  """(K,) bool thing flags of COCO panoptic's contiguous ids (0..79 things); K must be 133."""
  if num_classes != coco.NUM_CLASSES:
    raise ValueError(f"{num_classes} classes is not COCO panoptic ({coco.NUM_CLASSES}); "
                     f"pass is_thing explicitly")
  return coco.is_thing_table()


def _softmax(x: np.ndarray) -> np.ndarray:
  x = x.astype(np.float64)
  e = np.exp(x - x.max(-1, keepdims=True))
  return e / e.sum(-1, keepdims=True)


def panoptic_inference(mask_cls: np.ndarray, mask_pred: np.ndarray,
                       is_thing: np.ndarray | None = None,
                       object_mask_threshold: float = 0.8, overlap_threshold: float = 0.8
                       ) -> tuple[np.ndarray, list[Segment]]:
  """detectron2 Mask2Former panoptic inference (see the module docstring).

  Args:
    mask_cls: (Q, K + 1) class logits, the last column "no object".
    mask_pred: (Q, H, W) mask logits at the output resolution.
    is_thing: (K,) bool per contiguous class id; default `default_is_thing(K)`.
    object_mask_threshold: minimum class probability of a kept query.
    overlap_threshold: minimum visible / predicted area of a kept query's mask.

  Returns:
    id_map (H, W) int32 (0 = void) and the segments in id order.
  """
  mask_cls = np.asarray(mask_cls, np.float32)
  mask_pred = np.asarray(mask_pred, np.float32)
  num_classes = mask_cls.shape[-1] - 1
  if is_thing is None:
    is_thing = default_is_thing(num_classes)
  is_thing = np.asarray(is_thing, bool)
  if is_thing.shape != (num_classes,):
    raise ValueError(f"is_thing has shape {is_thing.shape}, expected ({num_classes},)")
  probs = _softmax(mask_cls).astype(np.float32)
  scores, labels = probs.max(-1), probs.argmax(-1)
  keep = (labels != num_classes) & (scores > object_mask_threshold)
  h, w = mask_pred.shape[-2:]
  id_map = np.zeros((h, w), np.int32)
  segments: list[Segment] = []
  if not keep.any():
    return id_map, segments
  cur_scores, cur_classes = scores[keep], labels[keep]
  with np.errstate(over="ignore"):  # exp overflow -> sigmoid 0, as torch
    cur_masks = 1.0 / (1.0 + np.exp(-mask_pred[keep]))  # (K', H, W) sigmoid
  cur_mask_ids = np.argmax(cur_scores[:, None, None] * cur_masks, axis=0)  # first max on ties
  stuff_ids: dict[int, int] = {}
  for k, cls in enumerate(cur_classes.tolist()):
    thing = bool(is_thing[cls])
    assigned = cur_mask_ids == k
    predicted = cur_masks[k] >= 0.5
    mask_area, original_area = int(assigned.sum()), int(predicted.sum())
    mask = assigned & predicted
    if mask_area == 0 or original_area == 0 or not mask.any():
      continue
    if mask_area / original_area < overlap_threshold:
      continue
    if not thing and cls in stuff_ids:  # merge stuff of one class into one segment
      id_map[mask] = stuff_ids[cls]
      continue
    new_id = len(segments) + 1
    if not thing:
      stuff_ids[cls] = new_id
    id_map[mask] = new_id
    segments.append(Segment(new_id, int(cls), thing))
  return id_map, segments


def to_frame_segments(segments: Sequence[Segment], contiguous_to_id: Sequence[int] | None = None
                      ) -> tuple[FrameSegment, ...]:
  """Contiguous class ids -> COCO category ids (default table: `coco.contiguous_to_id_table`)."""
  table = coco.contiguous_to_id_table() if contiguous_to_id is None else contiguous_to_id
  return tuple(FrameSegment(s.id, int(table[s.category_id]), s.isthing) for s in segments)
