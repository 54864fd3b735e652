"""Mask2Former panoptic post-processing (`pitta_jax.panoptic`) on hand-built predictions.

Reference: detectron2 Mask2Former's `MaskFormer.panoptic_inference` (upstream
`mask2former/maskformer_model.py`), worked by hand for each case below. Three classes plus
"no object": class 0 is a thing, classes 1 and 2 are stuff. Mask logits are +-10 (sigmoid
0.99995 / 0.00005) unless a case needs otherwise; class logits are built for a chosen
probability.
"""

from __future__ import annotations

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from pitta_jax import panoptic
from pitta_jax.data import coco
from pitta_jax.data.frame import Segment as FrameSegment
from pitta_jax.panoptic import Segment, panoptic_inference

K = 3
IS_THING = np.array([True, False, False])
HW = (4, 6)


def cls_logits(label: int, prob: float) -> np.ndarray:
  """(K + 1,) logits whose softmax gives `prob` to `label` and equal shares to the rest."""
  logits = np.zeros(K + 1, np.float32)
  logits[label] = np.log(prob * K / (1 - prob))
  return logits


def mask(rows=slice(None), cols=slice(None), inside: float = 10.0) -> np.ndarray:
  m = np.full(HW, -10.0, np.float32)
  m[rows, cols] = inside
  return m


def run(queries, **kw):
  """queries: list of (class logits, mask logits)."""
  mask_cls = np.stack([q[0] for q in queries])
  mask_pred = np.stack([q[1] for q in queries])
  return panoptic_inference(mask_cls, mask_pred, is_thing=IS_THING, **kw)


def test_cls_logits_helper():
  p = np.exp(cls_logits(2, 0.9))
  assert abs(p[2] / p.sum() - 0.9) < 1e-6


def test_two_things_of_one_class_are_two_segments():
  id_map, segs = run([(cls_logits(0, 0.99), mask(cols=slice(0, 3))),
                      (cls_logits(0, 0.99), mask(cols=slice(3, 6)))])
  expected = np.zeros(HW, np.int32)
  expected[:, :3], expected[:, 3:] = 1, 2
  np.testing.assert_array_equal(id_map, expected)
  assert segs == [Segment(1, 0, True), Segment(2, 0, True)]
  assert id_map.dtype == np.int32


def test_stuff_of_one_class_is_merged():
  id_map, segs = run([(cls_logits(1, 0.99), mask(cols=slice(0, 3))),
                      (cls_logits(1, 0.95), mask(cols=slice(3, 6)))])
  np.testing.assert_array_equal(id_map, np.ones(HW, np.int32))
  assert segs == [Segment(1, 1, False)]


def test_stuff_merged_across_a_thing_keeps_the_first_id():
  id_map, segs = run([(cls_logits(1, 0.99), mask(cols=slice(0, 2))),
                      (cls_logits(0, 0.99), mask(cols=slice(2, 4))),
                      (cls_logits(1, 0.99), mask(cols=slice(4, 6)))])
  np.testing.assert_array_equal(id_map[0], [1, 1, 2, 2, 1, 1])
  assert segs == [Segment(1, 1, False), Segment(2, 0, True)]


def test_no_object_and_low_scores_are_dropped():
  no_object = np.zeros(K + 1, np.float32)
  no_object[K] = 10.0  # argmax is "no object", probability 0.99986
  queries = [(no_object, mask()),
             (cls_logits(2, 0.75), mask(rows=slice(2, 4))),  # 0.75 < 0.8
             (cls_logits(0, 0.9), mask(rows=slice(0, 2), cols=slice(0, 2)))]
  id_map, segs = run(queries)
  expected = np.zeros(HW, np.int32)
  expected[:2, :2] = 1
  np.testing.assert_array_equal(id_map, expected)
  assert segs == [Segment(1, 0, True)]
  # with a lower object threshold the 0.75 stuff query is kept (query order = id order)
  id_map, segs = run(queries, object_mask_threshold=0.7)
  assert segs == [Segment(1, 2, False), Segment(2, 0, True)]
  assert (id_map[2:] == 1).all()


def test_nothing_kept_gives_void():
  id_map, segs = run([(cls_logits(0, 0.5), mask())])
  assert segs == [] and id_map.shape == HW and not id_map.any()


def test_overlap_threshold_drops_a_mostly_hidden_query():
  # q0 (0.99) covers cols 0-3, q1 (0.95) covers cols 2-5; q0 wins cols 2-3 by its higher score,
  # so q1 keeps 2 of its 4 columns: 0.5 < 0.8 -> dropped, cols 4-5 stay void.
  queries = [(cls_logits(0, 0.99), mask(cols=slice(0, 4))),
             (cls_logits(0, 0.95), mask(cols=slice(2, 6)))]
  id_map, segs = run(queries)
  np.testing.assert_array_equal(id_map[0], [1, 1, 1, 1, 0, 0])
  assert segs == [Segment(1, 0, True)]
  id_map, segs = run(queries, overlap_threshold=0.5)  # 0.5 is not < 0.5: kept
  np.testing.assert_array_equal(id_map[0], [1, 1, 1, 1, 2, 2])
  assert segs == [Segment(1, 0, True), Segment(2, 0, True)]


def test_pixels_below_half_are_void_even_when_assigned():
  m = mask()
  m[0, :] = -1.0  # sigmoid 0.27: still the argmax (only query), but not in the segment
  id_map, segs = run([(cls_logits(0, 0.99), m)])
  np.testing.assert_array_equal(id_map[0], 0)
  np.testing.assert_array_equal(id_map[1:], 1)
  assert segs == [Segment(1, 0, True)]


def test_ties_go_to_the_first_query():
  q = (cls_logits(0, 0.9), mask(rows=slice(0, 2)))
  id_map, segs = run([q, q])  # identical: q1 is never the argmax, mask_area 0 -> dropped
  assert segs == [Segment(1, 0, True)]
  assert set(np.unique(id_map)) == {0, 1}


def test_default_is_thing_is_coco_panoptic():
  t = panoptic.default_is_thing(133)
  assert t[:80].all() and not t[80:].any()
  with pytest.raises(ValueError, match="is_thing"):
    panoptic_inference(np.zeros((2, 5)), np.zeros((2, 3, 3)))
  with pytest.raises(ValueError, match="134 classes is not COCO panoptic"):  # more classes too
    panoptic_inference(np.zeros((2, 135)), np.zeros((2, 3, 3)))


def test_to_frame_segments_maps_contiguous_to_coco_ids():
  segs = [Segment(1, 2, True), Segment(2, 80, False), Segment(3, 0, True)]
  out = panoptic.to_frame_segments(segs)
  assert out == (FrameSegment(1, 3, True), FrameSegment(2, 92, False), FrameSegment(3, 1, True))
  assert coco.contiguous_to_id(80) == 92
  assert panoptic.to_frame_segments(segs[:1], [7, 8, 9]) == (FrameSegment(1, 9, True),)


@settings(max_examples=40, deadline=None)
@given(mask_cls=hnp.arrays(np.float32, (6, K + 1), elements=st.floats(-4, 8, width=32)),
       mask_pred=hnp.arrays(np.float32, (6, 5, 7), elements=st.floats(-6, 6, width=32)),
       threshold=st.sampled_from([0.0, 0.3, 0.8]))
def test_invariants(mask_cls, mask_pred, threshold):
  """Ids 1..n in order; the map holds exactly those ids (and 0); one segment per stuff class;
  every painted pixel has sigmoid >= 0.5 for some kept query of the segment's class."""
  id_map, segs = panoptic_inference(mask_cls, mask_pred, is_thing=IS_THING,
                                    object_mask_threshold=threshold)
  assert [s.id for s in segs] == list(range(1, len(segs) + 1))
  assert set(np.unique(id_map)) - {0} == {s.id for s in segs}
  stuff = [s.category_id for s in segs if not s.isthing]
  assert len(stuff) == len(set(stuff))
  for s in segs:
    assert s.isthing == IS_THING[s.category_id]
    probs = np.exp(mask_cls - mask_cls.max(-1, keepdims=True))
    probs /= probs.sum(-1, keepdims=True)
    same = (probs.argmax(-1) == s.category_id) & (probs.max(-1) > threshold)
    with np.errstate(over="ignore"):
      covered = (1 / (1 + np.exp(-mask_pred[same])) >= 0.5).any(0)  # float32, as implemented
    assert covered[id_map == s.id].all()


def test_a_query_whose_argmax_is_no_object_is_dropped_at_any_threshold():
  # Logits (1.0, -10, -10, 1.2): "no object" is the argmax (p 0.55), class 0 has p 0.45. At an
  # object threshold of 0.3 the query still goes, as detectron2 drops it by its label over the
  # K + 1 columns before the score test (a score over the K classes alone would keep it).
  logits = np.array([1.0, -10.0, -10.0, 1.2], np.float32)
  id_map, segs = run([(logits, mask())], object_mask_threshold=0.3)
  assert segs == [] and not id_map.any()


def test_object_threshold_is_strict():
  """detectron2 keeps `scores.gt(object_mask_threshold)`: a query whose probability equals the
  threshold is dropped. Logits (log 9, 0, 0, 0) give class 0 the probability 9 / 12 = 0.75,
  exactly 0.75 once rounded to float32; at threshold 0.75 it goes, at 0.74 it stays."""
  logits = np.array([np.log(9.0), 0.0, 0.0, 0.0], np.float32)
  p = np.exp(logits.astype(np.float64))
  assert np.float32(p[0] / p.sum()) == np.float32(0.75)
  id_map, segs = run([(logits, mask())], object_mask_threshold=0.75)
  assert segs == [] and not id_map.any()
  id_map, segs = run([(logits, mask())], object_mask_threshold=0.74)
  assert segs == [Segment(1, 0, True)] and (id_map == 1).all()


def test_a_pixel_at_exactly_one_half_belongs_to_the_segment():
  """detectron2 counts `cur_masks[k] >= 0.5` in the original area and the segment: a mask
  logit of exactly 0 (sigmoid 1 / (1 + e^0) = 0.5) is painted, not void."""
  m = mask()
  m[0, :] = 0.0
  id_map, segs = run([(cls_logits(0, 0.99), m)])
  assert segs == [Segment(1, 0, True)]
  np.testing.assert_array_equal(id_map, np.ones(HW, np.int32))


def test_ties_between_classes_go_to_the_first_query():
  """Two queries with equal scores and equal masks but different classes: every pixel goes to
  the first (torch's argmax takes the first maximum), so the segment is the first query's
  thing, and the second (stuff) query owns nothing and is dropped; in the other order, the
  stuff class wins."""
  thing = (cls_logits(0, 0.9), mask(rows=slice(0, 2)))
  stuff = (cls_logits(1, 0.9), mask(rows=slice(0, 2)))
  p = np.exp(np.stack([thing[0], stuff[0]]).astype(np.float64))
  p /= p.sum(-1, keepdims=True)
  assert np.float32(p[0, 0]) == np.float32(p[1, 1])  # equal scores (the classes permuted)
  expected = np.zeros(HW, np.int32)
  expected[:2] = 1
  id_map, segs = run([thing, stuff])
  assert segs == [Segment(1, 0, True)]
  np.testing.assert_array_equal(id_map, expected)
  id_map, segs = run([stuff, thing])
  assert segs == [Segment(1, 1, False)]
  np.testing.assert_array_equal(id_map, expected)


def test_pixels_go_to_the_highest_score_times_mask_probability():
  """Each pixel goes to the kept query maximising class score x sigmoid(mask logit), not the
  mask probability alone. Both masks have logit 2 (sigmoid 0.881) on their columns: q0 (class
  0, p 0.85) on columns 0-3, q1 (class 1, p 0.99) on 2-5. Columns 2-3 go to q1 (0.872 >
  0.749), so q0 keeps 8 of its 16 pixels (0.5 < 0.8, dropped) and q1 all 16 of its: one
  segment on columns 2-5, columns 0-1 void (assigned to the dropped q0)."""
  id_map, segs = run([(cls_logits(0, 0.85), mask(cols=slice(0, 4), inside=2.0)),
                      (cls_logits(1, 0.99), mask(cols=slice(2, 6), inside=2.0))])
  assert segs == [Segment(1, 1, False)]
  np.testing.assert_array_equal(id_map[0], [0, 0, 1, 1, 1, 1])
  np.testing.assert_array_equal(id_map, np.broadcast_to(id_map[0], HW))


def test_a_query_whose_assigned_pixels_are_all_below_half_makes_no_segment():
  """detectron2 also requires the segment (assigned & sigmoid >= 0.5) to be non-empty. q1
  (p 0.95) predicts columns 0-2 (logit 10) but q0 (p 0.99, same columns) wins them; q1 wins
  columns 3-5 with logit -1 (0.95 x 0.27 > 0.99 x 0.00005) where its sigmoid is below 0.5:
  mask area 12 / original area 12 passes the overlap test, yet its segment is empty, so it is
  dropped (no id without pixels) and columns 3-5 stay void."""
  q1_mask = mask(cols=slice(0, 3))
  q1_mask[:, 3:] = -1.0
  id_map, segs = run([(cls_logits(0, 0.99), mask(cols=slice(0, 3))),
                      (cls_logits(0, 0.95), q1_mask)])
  assert segs == [Segment(1, 0, True)]
  np.testing.assert_array_equal(id_map[0], [1, 1, 1, 0, 0, 0])
  np.testing.assert_array_equal(id_map, np.broadcast_to(id_map[0], HW))


def test_merged_stuff_paints_only_pixels_at_or_above_half():
  """A stuff query merged into its class's segment paints assigned & sigmoid >= 0.5, as a new
  segment does. q1 (class 1 like q0, p 0.95) predicts columns 2-4 (logit 10) and wins column 5
  with logit -1 (sigmoid 0.27; q0 there: 0.99 x 0.00005): area 16 / 12 passes, its pixels join
  segment 1 except column 5, which stays void."""
  q1_mask = mask(cols=slice(2, 5))
  q1_mask[:, 5] = -1.0
  id_map, segs = run([(cls_logits(1, 0.99), mask(cols=slice(0, 2))),
                      (cls_logits(1, 0.95), q1_mask)])
  assert segs == [Segment(1, 1, False)]
  np.testing.assert_array_equal(id_map[0], [1, 1, 1, 1, 1, 0])
  np.testing.assert_array_equal(id_map, np.broadcast_to(id_map[0], HW))


def test_huge_class_logits_do_not_overflow():
  """The softmax is taken stably (as torch's): logits (1000, 0, 0, 0) give class 0 the
  probability 1 (exp(1000) overflows float64, exp(0 - 1000) does not), so the query is kept."""
  logits = np.array([1000.0, 0.0, 0.0, 0.0], np.float32)
  id_map, segs = run([(logits, mask())])
  assert segs == [Segment(1, 0, True)] and (id_map == 1).all()
