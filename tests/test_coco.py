"""COCO panoptic category table: facts from detectron2's `COCO_CATEGORIES` (builtin_meta.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pitta_jax.data import coco


def test_table_shape():
  assert len(coco.CATEGORIES) == coco.NUM_CLASSES == 133
  assert coco.NUM_THINGS == 80
  # detectron2 order: the 80 things first, then the 53 stuff classes.
  assert [c.isthing for c in coco.CATEGORIES] == [True] * 80 + [False] * 53
  assert [c.contiguous for c in coco.CATEGORIES] == list(range(133))
  assert len({c.id for c in coco.CATEGORIES}) == 133
  assert len({c.name for c in coco.CATEGORIES}) == 133
  # Within each group, ascending COCO ids (panopticapi's order); ids span 1..200.
  ids = [c.id for c in coco.CATEGORIES]
  assert ids[:80] == sorted(ids[:80]) and ids[80:] == sorted(ids[80:])
  assert (ids[0], ids[79], ids[80], ids[132]) == (1, 90, 92, 200)


def test_coco_has_ten_missing_thing_ids():
  # COCO's 80 thing ids are 1..90 minus these ten (hand-checked against the COCO category list).
  missing = sorted(set(range(1, 91)) - {c.id for c in coco.CATEGORIES if c.isthing})
  assert missing == [12, 26, 29, 30, 45, 66, 68, 69, 71, 83]


@pytest.mark.parametrize("name, coco_id, contiguous", [
    ("person", 1, 0), ("bicycle", 2, 1), ("car", 3, 2), ("motorcycle", 4, 3), ("bus", 6, 5),
    ("train", 7, 6), ("truck", 8, 7), ("traffic light", 10, 9), ("road", 149, 100),
    ("sand", 154, 102), ("sea", 155, 103),
    ("sky-other-merged", 187, 119), ("rug-merged", 200, 132)])
def test_known_categories(name, coco_id, contiguous):
  assert coco.name_to_id(name) == coco_id
  assert coco.id_to_contiguous(coco_id) == contiguous
  assert coco.contiguous_to_id(contiguous) == coco_id
  assert coco.by_id(coco_id).name == name


def test_dynamic_set():
  assert coco.DYNAMIC_NAMES == ("person", "bicycle", "car", "motorcycle", "bus", "train", "truck")
  assert coco.ids_of(coco.DYNAMIC_NAMES) == (1, 2, 3, 4, 6, 7, 8)
  assert all(coco.is_thing(i) for i in coco.ids_of(coco.DYNAMIC_NAMES))
  with pytest.raises(KeyError, match="rider"):
    coco.name_to_id("rider")  # COCO has no rider class


def test_round_trips_and_tables():
  for k in range(coco.NUM_CLASSES):
    assert coco.id_to_contiguous(coco.contiguous_to_id(k)) == k
  table = coco.contiguous_to_id_table()
  assert table.dtype == np.int32 and table.shape == (133,)
  np.testing.assert_array_equal(table, [coco.contiguous_to_id(k) for k in range(133)])
  np.testing.assert_array_equal(coco.is_thing_table(), np.arange(133) < 80)


def test_unknown_lookups_raise():
  with pytest.raises(KeyError):
    coco.by_id(12)  # a COCO id with no category
  with pytest.raises(KeyError):
    coco.contiguous_to_id(133)
  with pytest.raises(KeyError):
    coco.contiguous_to_id(-1)  # not the last category, as Python's negative indexing would give
  with pytest.raises(KeyError, match="traffic light"):
    coco.by_name("traffic")  # suggests the close match
