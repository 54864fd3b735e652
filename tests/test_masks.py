"""Instance table, index map and masks (eqs. 3-4): against literal NumPy loops and hand values."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pitta_jax import masks
from reference_numpy import instance_masks_loop, instance_table_loop, used_ids

S_MAX = 8
SHAPE = (5, 7)


@pytest.fixture(scope="module")
def jitted():
  return {
      "table": jax.jit(masks.instance_table, static_argnums=4),
      "index": jax.jit(masks.instance_index_map),
      "masks": jax.jit(masks.instance_masks, static_argnums=3),
      "from_index": jax.jit(masks.masks_from_index, static_argnums=(1, 2)),
      "compact": jax.jit(masks.table_from_dynamic_ids),
  }


def test_default_dynamic_set():
  # Hand value: COCO ids of person, bicycle, car, motorcycle, bus, train, truck (paper Sec. 3.1).
  assert masks.DEFAULT_DYNAMIC_COCO_IDS == (1, 2, 3, 4, 6, 7, 8)


def test_instance_table_hand(jitted):
  # Hand value: segments 10 (car 3), 11 (road 100), 12 (person 1), 13 (invalid car),
  # 14 (bus 6), 0 (padding); dynamic first in order: 10, 12, 14.
  ids = np.array([10, 11, 12, 13, 14, 0, 0, 0], np.int32)
  cls = np.array([3, 100, 1, 3, 6, 0, 0, 0], np.int32)
  valid = np.array([1, 1, 1, 0, 1, 0, 0, 0], bool)
  dyn = np.array(masks.DEFAULT_DYNAMIC_COCO_IDS + (-1,), np.int32)
  inst_ids, inst_valid = jitted["table"](ids, cls, valid, dyn, 4)
  np.testing.assert_array_equal(inst_ids, [10, 12, 14, 0])
  np.testing.assert_array_equal(inst_valid, [True, True, True, False])
  inst_ids, inst_valid = jitted["table"](ids, cls, valid, dyn, 2)  # truncated to n_max
  np.testing.assert_array_equal(inst_ids, [10, 12])
  np.testing.assert_array_equal(inst_valid, [True, True])


def test_instance_table_larger_than_the_segment_list(jitted):
  # Hand value: 4 segment slots, one dynamic (10, a car), table of 6 rows: one instance, the
  # five rows after it empty (the padding rows past the segment list are no instances).
  inst_ids, inst_valid = jitted["table"](np.array([10, 11, 0, 0], np.int32),
                                         np.array([3, 100, 0, 0], np.int32),
                                         np.array([1, 1, 0, 0], bool),
                                         np.array([3], np.int32), 6)
  np.testing.assert_array_equal(inst_ids, [10, 0, 0, 0, 0, 0])
  np.testing.assert_array_equal(inst_valid, [True] + [False] * 5)


@settings(max_examples=30, deadline=None)
@given(ids=hnp.arrays(np.int32, S_MAX, elements=st.integers(0, 40), unique=True),
       cls=hnp.arrays(np.int32, S_MAX, elements=st.integers(1, 10)),
       valid=hnp.arrays(bool, S_MAX),
       n_max=st.sampled_from([3, 12]))
def test_instance_table_matches_loop(jitted, ids, cls, valid, n_max):
  # Reference: loop over the segments keeping the dynamic ones in order (instance_table_loop).
  dyn = np.array([1, 3, 8, -1], np.int32)
  got_ids, got_valid = jitted["table"](ids, cls, valid, dyn, n_max)
  want_ids, want_valid = instance_table_loop(ids, cls, valid, dyn, n_max)
  np.testing.assert_array_equal(got_ids, want_ids)
  np.testing.assert_array_equal(got_valid, want_valid)


def test_table_from_dynamic_ids_compacts(jitted):
  # Hand value: [0, 5, -1, 7] -> instances 5 (j=1) and 7 (j=2), then padding.
  ids, valid = jitted["compact"](np.array([0, 5, -1, 7], np.int32))
  np.testing.assert_array_equal(ids, [5, 7, 0, 0])
  np.testing.assert_array_equal(valid, [True, True, False, False])


def index_map_loop(panoptic, inst_ids, inst_valid):
  """Reference: per pixel, the 1-based row of the table holding its id (0 if none)."""
  out = np.zeros(panoptic.shape, np.int32)
  for x in range(panoptic.shape[0]):
    for y in range(panoptic.shape[1]):
      for j, (sid, ok) in enumerate(zip(inst_ids, inst_valid), start=1):
        if ok and sid > 0 and panoptic[x, y] == sid:
          out[x, y] = j
          break
  return out


def test_index_map_hand(jitted):
  # Hand value: table [7, 3, (invalid 5)]: id 7 -> 1, id 3 -> 2, ids 5, 0, 9 -> 0.
  pan = np.array([[7, 3, 5], [0, 9, 7]], np.int32)
  got = jitted["index"](pan, np.array([7, 3, 5], np.int32), np.array([True, True, False]))
  np.testing.assert_array_equal(got, [[1, 2, 0], [0, 0, 1]])


def test_index_map_takes_the_first_of_repeated_table_ids(jitted):
  # Hand value: the table holds id 5 twice; every pixel of segment 5 is instance 1, the first
  # matching row (as the docstring says), not 2.
  got = jitted["index"](np.array([[5, 5], [5, 0]], np.int32), np.array([5, 5], np.int32),
                        np.array([True, True]))
  np.testing.assert_array_equal(got, [[1, 1], [1, 0]])


@settings(max_examples=30, deadline=None)
@given(pan=hnp.arrays(np.int32, SHAPE, elements=st.integers(0, 9)),
       dyn=hnp.arrays(np.int32, 6, elements=st.integers(-1, 12), unique=True))
def test_index_map_and_masks_match_loops(jitted, pan, dyn):
  # Reference: index_map_loop and instance_masks_loop (eq. 3) in every g_j mode; the masks
  # built from the panoptic map and from the index map agree.
  inst_ids, inst_valid = jitted["compact"](dyn)
  index = np.asarray(jitted["index"](pan, inst_ids, inst_valid))
  np.testing.assert_array_equal(index, index_map_loop(pan, np.asarray(inst_ids),
                                                      np.asarray(inst_valid)))
  n = len(used_ids(dyn))
  for mode in masks.MASK_MODES:
    got = np.asarray(jitted["masks"](pan, inst_ids, inst_valid, mode))  # (N_max, H, W)
    want = instance_masks_loop(pan, dyn, mode)
    assert got.shape == (dyn.shape[0],) + SHAPE
    for j in range(dyn.shape[0]):
      np.testing.assert_array_equal(got[j], want[j] if j < n else 0.0)
    np.testing.assert_array_equal(
        np.asarray(jitted["from_index"](index, dyn.shape[0], mode, inst_ids)), got)


def test_instance_id_mode_hand(jitted):
  # Hand value: eq. 3 literally, g_j = j: the second instance's mask holds 2.
  pan = np.array([[4, 4, 6]], np.int32)
  m = np.asarray(jitted["masks"](pan, np.array([4, 6], np.int32), np.array([True, True]),
                                 "instance_id"))
  np.testing.assert_array_equal(m, [[[1, 1, 0]], [[0, 0, 2]]])


def test_pixel_gain_is_sum_of_masks():
  # Reference: sum_j M_j from masks_from_index.
  index = jnp.array([[0, 1, 2], [2, 0, 3]], jnp.int32)
  ids = jnp.array([7, 12, 30], jnp.int32)  # segment ids of rows 1..3 ("segment_id": g = id)
  for mode in masks.MASK_MODES:
    np.testing.assert_array_equal(masks.pixel_gain(index, mode, ids),
                                  masks.masks_from_index(index, 3, mode, ids).sum(0))
  np.testing.assert_array_equal(masks.pixel_gain(index, "segment_id", ids), [[0, 7, 12], [12, 0, 30]])


def test_pixel_gain_of_a_negative_index_is_zero_as_the_sum_of_masks():
  # Reference: sum_j M_j (masks_from_index: no row matches -1); a -1 read the last row's id in
  # "segment_id" mode and gave -1 in "instance_id" mode.
  index = jnp.array([[-1, 0, 1], [2, -3, 0]], jnp.int32)
  ids = jnp.array([5, 9], jnp.int32)
  for mode in masks.MASK_MODES:
    np.testing.assert_array_equal(masks.pixel_gain(index, mode, ids),
                                  masks.masks_from_index(index, 2, mode, ids).sum(0), err_msg=mode)
  np.testing.assert_array_equal(masks.pixel_gain(index, "segment_id", ids), [[0, 0, 5], [9, 0, 0]])


def test_bad_mode():
  with pytest.raises(ValueError, match="mode"):
    masks.instance_gains(3, "weird")


def test_dynamic_ids_from_segments():
  # Hand value: Segment-like records; cars/persons kept in order, sky (category 119) dropped.
  @dataclasses.dataclass
  class Seg:
    id: int
    category_id: int
  segs = [Seg(5, 3), Seg(6, 119), Seg(9, 1), Seg(2, 8)]
  np.testing.assert_array_equal(masks.dynamic_ids_from_segments(segs, 4), [5, 9, 2, 0])
  np.testing.assert_array_equal(masks.dynamic_ids_from_segments(segs, 2), [5, 9])


def test_float_segment_ids_are_refused():
  # A float id map would be truncated (segment 3.7 read as 3): refused by name, also under jit.
  pan = np.array([[3.7, 0.0], [3.0, 1.0]], np.float32)
  ids, valid = masks.table_from_dynamic_ids(np.array([3, 0], np.int32))
  with pytest.raises(TypeError, match="panoptic must be an integer array"):
    masks.instance_index_map(pan, ids, valid)
  with pytest.raises(TypeError, match="dynamic_ids must be an integer array"):
    jax.jit(masks.table_from_dynamic_ids)(np.array([3.0, 0.0]))
  with pytest.raises(TypeError, match="segment_ids must be an integer array"):
    masks.instance_table(np.array([1.5]), np.array([3]), np.array([True]), np.array([3]), 2)
  # class ids too: a class 3.7 was read as car (3)
  with pytest.raises(TypeError, match="segment_classes must be an integer array of class ids"):
    masks.instance_table(np.array([1, 2]), np.array([3.7, 5.0]), np.array([True, True]),
                         np.array([3]), 2)
  with pytest.raises(TypeError, match="dynamic_classes must be an integer array of class ids"):
    masks.instance_table(np.array([1]), np.array([3]), np.array([True]), np.array([3.2]), 2)
  # Every integer width is accepted and gives the int32 map.
  for dtype in (np.uint8, np.int16, np.int64):
    got = masks.instance_index_map(pan.astype(dtype), ids, valid)
    np.testing.assert_array_equal(got, [[1, 0], [1, 0]])


def test_ids_beyond_int32_are_refused_not_wrapped():
  """A uint32 id of 2**31 + 3 or an int64 id of 2**40 + 5 was cast to int32 (or to 32 bits by
  JAX without x64) and wrapped silently onto another id: 2**40 + 5 became segment 5, so the
  table's instance 5 took the pixels of a segment it is not. Refused by name; ids in range of
  any width are accepted."""
  ids, valid = masks.table_from_dynamic_ids(np.array([5, 0], np.int32))
  big = np.array([[2**40 + 5, 0], [5, 1]], np.int64)
  with pytest.raises(ValueError, match=r"panoptic holds segment ids outside int32 \(1099511627781\)"):
    masks.instance_index_map(big, ids, valid)
  with pytest.raises(ValueError, match=r"dynamic_ids holds segment ids outside int32"):
    masks.table_from_dynamic_ids(np.array([2**31 + 3, 0], np.uint32))
  with pytest.raises(ValueError, match=r"panoptic holds segment ids outside int32 \(-4294967291\)"):
    masks.instance_index_map(np.array([[-2**32 + 5]], np.int64), ids, valid)
  ok = np.array([[2**31 - 1, 0], [5, 1]], np.uint32)
  np.testing.assert_array_equal(masks.instance_index_map(ok, ids, valid), [[0, 0], [1, 0]])


def test_every_path_refuses_float_ids_and_indices():
  """Float ids or instance indices are refused on every path, not truncated on some (the
  literal L_d read a panoptic 5.7 as segment 5 where the fast one refused it; a float index map
  was cast everywhere)."""
  from pitta_jax import losses
  depth = jnp.ones((4, 5))
  pan = np.zeros((4, 5), np.float32)
  pan[1:3, 1:3] = 5.7
  for impl in ("fast", "literal"):
    with pytest.raises(TypeError, match="panoptic must be an integer array"):
      losses.depth_refining_loss(depth, pan, np.array([5], np.int32), impl=impl)
    with pytest.raises(TypeError, match="index_map must be an integer array of instance indices"):
      losses.depth_refining_loss_from_index(depth, (pan > 0) * 1.0, 1, impl=impl, n_max=2)
  with pytest.raises(TypeError, match="panoptic must be an integer array"):
    masks.instance_masks(pan, np.array([5]), np.array([True]))
  for call in (lambda m: masks.pixel_gain(m), lambda m: masks.masks_from_index(m, 2)):
    with pytest.raises(TypeError, match="index_map must be an integer array"):
      call((pan > 0) + 0.7)


def test_table_sizes_and_ids_are_checked_by_name():
  """A traced n_max says to make it static (it failed inside JAX with four different errors);
  a segment-id table shorter than the index map's instances is refused (JAX's clamped gather
  gave instance 2 the id of instance 1); a 1-D panoptic is refused (it became one row)."""
  index = np.zeros((4, 5), np.int32)
  index[0, 0], index[2, 3] = 1, 2
  for call in (lambda n: masks.masks_from_index(index, n), masks.instance_gains,
               lambda n: masks.instance_table(np.array([5]), np.array([3]), np.array([True]),
                                              np.array([3]), n)):
    with pytest.raises(ValueError, match=r"n_max must be a Python int, not a traced value"):
      jax.jit(call)(2)
  with pytest.raises(ValueError, match="index_map holds instance 2, beyond the 1 rows of inst_ids"):
    masks.pixel_gain(index, "segment_id", np.array([5]))
  np.testing.assert_array_equal(masks.pixel_gain(index, "segment_id", np.array([5, 9])),
                                np.where(index == 1, 5.0, np.where(index == 2, 9.0, 0.0)))
  with pytest.raises(ValueError, match=r"inst_ids must be the table's \(N_max,\) segment ids "
                                       r"with N_max = 3"):
    masks.instance_gains(3, "segment_id", np.array([5, 9]))
  with pytest.raises(ValueError, match=r"panoptic must be an \(H, W\) map"):
    masks.instance_index_map(np.array([5, 0, 5]), np.array([5]), np.array([True]))


def test_masks_of_a_map_that_is_not_2d_are_refused():
  """instance_masks and masks_from_index take one (H, W) map (as instance_index_map, which
  refuses others). A batch of B maps with N_max = B rows broadcast into (1, B, H, W): row j's
  mask taken from frame j only, with no error; other B failed in a broadcasting error."""
  pan = np.array([[[1, 2], [2, 0]], [[1, 1], [2, 2]]], np.int32)  # (B=2, H, W)
  with pytest.raises(ValueError, match=r"panoptic must be an \(H, W\) map"):
    masks.instance_masks(pan, np.array([1, 2]), np.array([True, True]))
  with pytest.raises(ValueError, match=r"index_map must be an \(H, W\) map"):
    masks.masks_from_index(pan, 2)


def test_index_map_of_an_empty_instance_table_is_all_zero():
  """An instance table of 0 rows (table_rows, instance_table and instance_masks take n_max = 0)
  holds no instance: every pixel is 0. It failed in an empty reduction ("zero-size array to
  reduction operation min")."""
  pan = np.array([[1, 2], [2, 0]], np.int32)
  ids, valid = masks.instance_table(np.array([1, 2]), np.array([3, 3]), np.array([True, True]),
                                    np.array([3]), 0)
  index = masks.instance_index_map(pan, ids, valid)
  assert index.shape == (2, 2) and index.dtype == jnp.int32
  np.testing.assert_array_equal(np.asarray(index), 0)
  assert masks.instance_masks(pan, ids, valid).shape == (0, 2, 2)


def test_a_repeated_dynamic_id_is_refused():
  """dynamic_ids [5, 5] made two instances of one segment (documented as not allowed): the
  fast L_d counted its pixels once and the literal one twice, so the two disagreed without a
  word. Refused by name on a concrete table; under jit (values unknown) as before."""
  with pytest.raises(ValueError, match=r"dynamic_ids repeats segment id\(s\) \[5\]"):
    masks.table_from_dynamic_ids(np.array([5, 0, 5, 9], np.int32))
  ids, valid = masks.table_from_dynamic_ids(np.array([5, 0, -1, 9], np.int32))
  assert ids.tolist() == [5, 9, 0, 0] and valid.tolist() == [True, True, False, False]
  ids, _ = jax.jit(masks.table_from_dynamic_ids)(np.array([5, 5], np.int32))
  assert ids.tolist() == [5, 5]
