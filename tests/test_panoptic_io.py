"""COCO panoptic PNG + JSON reading/writing (reference: panopticapi's id = R + 256 G + 256^2 B)."""

from __future__ import annotations

import json
import re

import cv2
import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings

from pitta_jax.data import panoptic_io
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Segment


@settings(max_examples=30, deadline=None)
@given(hnp.arrays(np.int64, (3, 4), elements={"min_value": 0, "max_value": 256**3 - 1}))
def test_id_rgb_round_trip(ids):
  rgb = panoptic_io.id_to_rgb(ids)
  assert rgb.dtype == np.uint8 and rgb.shape == (3, 4, 3)
  np.testing.assert_array_equal(panoptic_io.rgb_to_id(rgb), ids)


def test_id_to_rgb_hand_value():
  # 1 + 2 * 256 + 3 * 65536 = 197121 -> R, G, B = 1, 2, 3.
  np.testing.assert_array_equal(panoptic_io.id_to_rgb(np.array([[197121]])), [[[1, 2, 3]]])
  with pytest.raises(ValueError):
    panoptic_io.id_to_rgb(np.array([256**3]))


def test_png_round_trip_and_channel_order(tmp_path):
  ids = np.array([[0, 1, 256, 65536], [197121, 256**3 - 1, 7, 7]], np.int32)
  path = tmp_path / "a.png"
  panoptic_io.write_panoptic_png(path, ids)
  # On disk (OpenCV reads B, G, R): pixel 197121 must be R=1, G=2, B=3.
  np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[1, 0], [3, 2, 1])
  back = panoptic_io.read_panoptic_png(path)
  assert back.dtype == np.int32
  np.testing.assert_array_equal(back, ids)


def test_png_written_by_hand_rgba_accepted(tmp_path):
  bgra = np.zeros((2, 2, 4), np.uint8)
  bgra[..., 3] = 255
  bgra[0, 0, :3] = [0, 1, 5]  # B=0, G=1, R=5 -> id 5 + 256 = 261
  cv2.imwrite(str(tmp_path / "a.png"), bgra)
  np.testing.assert_array_equal(panoptic_io.read_panoptic_png(tmp_path / "a.png"),
                                [[261, 0], [0, 0]])


def test_write_panoptic_json_and_read_back(tmp_path):
  ids = np.zeros((4, 6), np.int32)
  ids[1:3, 2:5] = 5  # a car: bbox x=2, y=1, w=3, h=2, area 6
  ids[3, 0] = 9  # road (stuff)
  segments = (Segment(5, 3, True), Segment(9, 149, False), Segment(11, 1, True))  # 11 absent
  json_path = panoptic_io.write_panoptic(tmp_path / "f.png", ids, segments)
  info = json.loads(json_path.read_text())["segments_info"]
  assert info[0] == {"id": 5, "category_id": 3, "iscrowd": 0, "bbox": [2, 1, 3, 2], "area": 6,
                     "isthing": True}
  assert info[1]["bbox"] == [0, 3, 1, 1] and info[1]["area"] == 1
  assert info[2]["area"] == 0
  ref = panoptic_io.PanopticSource(tmp_path).ref("f")
  back_ids, back_segments = ref.load()
  np.testing.assert_array_equal(back_ids, ids)
  assert back_segments == segments[:2]  # the absent segment 11 is dropped


def test_an_interrupted_write_leaves_neither_file(tmp_path, monkeypatch):
  """A Ctrl-C while a map's files are made leaves neither the PNG nor its JSON (the JSON was
  written first and stayed alone, and `segment` then refused to rerun over it); no temporary
  file stays either. The same write then goes through."""
  ids = np.full((2, 3), 5, np.int32)

  def interrupted(*args, **kwargs):
    raise KeyboardInterrupt
  monkeypatch.setattr(panoptic_io, "id_to_rgb", interrupted)  # encoding the PNG
  with pytest.raises(KeyboardInterrupt):
    panoptic_io.write_panoptic(tmp_path / "f.png", ids, (Segment(5, 3, True),))
  assert list(tmp_path.iterdir()) == []
  monkeypatch.undo()
  panoptic_io.write_panoptic(tmp_path / "f.png", ids, (Segment(5, 3, True),))
  assert sorted(p.name for p in tmp_path.iterdir()) == ["f.json", "f.png"]


def test_isthing_defaults_from_coco_table(tmp_path):
  path = tmp_path / "s.json"
  path.write_text(json.dumps({"segments_info": [
      {"id": 1, "category_id": 3, "iscrowd": 0, "bbox": [0, 0, 1, 1], "area": 1},
      {"id": 2, "category_id": 149, "iscrowd": 0, "bbox": [0, 0, 1, 1], "area": 1},
      {"id": 3, "category_id": 3, "isthing": 0}]}))
  assert panoptic_io.read_segments_json(path) == (
      Segment(1, 3, True), Segment(2, 149, False), Segment(3, 3, False))


@pytest.mark.parametrize("category_id", [0, 91, 201])
def test_a_category_id_that_is_not_cocos_is_refused_with_isthing_given(tmp_path, category_id):
  """Detectron2's raw `segments_info` (contiguous classes: 0 = person) with `isthing`: read as
  COCO ids, its person (0) was never dynamic and no error was raised; panopticapi refuses ids
  outside its categories. 91 and 201 are not COCO panoptic ids either."""
  path = tmp_path / "s.json"
  path.write_text(json.dumps({"segments_info": [
      {"id": 1, "category_id": 3, "isthing": True},
      {"id": 2, "category_id": category_id, "isthing": True}]}))
  with pytest.raises(DataError, match=rf"s\.json: segments_info\[1\]: category_id {category_id} "
                                      rf"is not a COCO panoptic category id \(Detectron2"):
    panoptic_io.read_segments_json(path)


def test_annotation_file(tmp_path):
  ids = np.array([[0, 4], [8, 8]], np.int32)
  png_dir = tmp_path / "panoptic_val"
  panoptic_io.write_panoptic_png(png_dir / "000139.png", ids)
  ann = tmp_path / "panoptic_val.json"
  ann.write_text(json.dumps({
      "annotations": [{"file_name": "000139.png", "image_id": 139, "segments_info": [
          {"id": 4, "category_id": 1, "iscrowd": 0, "bbox": [1, 0, 1, 1], "area": 1},
          {"id": 8, "category_id": 500, "iscrowd": 0, "bbox": [0, 1, 2, 1], "area": 2}]}],
      "categories": [{"id": 1, "name": "person", "isthing": 1},
                     {"id": 500, "name": "custom", "isthing": 0}]}))
  source = panoptic_io.PanopticSource(annotation_file=ann)  # PNG dir = JSON path minus .json
  assert source.has("000139") and not source.has("000140")
  back_ids, segments = source.ref("000139").load()
  np.testing.assert_array_equal(back_ids, ids)
  assert segments == (Segment(4, 1, True), Segment(8, 500, False))
  panoptic_io.write_panoptic_png(png_dir / "000140.png", ids)  # a PNG without annotation
  with pytest.raises(DataError, match="panoptic_val.json: no annotation with file_name '000140"):
    source.ref("000140")


def test_annotation_file_of_another_taxonomy_is_mapped_to_coco_by_name(tmp_path):
  """A panoptic annotation file as cityscapesScripts' createPanopticImgs.py writes it: Cityscapes
  label ids (road 7, sidewalk 8, person 24, rider 25, car 26), which COCO's table reads as
  train, truck, zebra, giraffe and nothing. Read by name, the dynamic instances are the person,
  the rider and the cars (hand-listed), not the road and the sidewalk."""
  from pitta_jax.masks import dynamic_ids_from_segments
  ids = np.array([[7, 8, 24001], [25001, 26001, 26002]], np.int32)
  png_dir = tmp_path / "cityscapes_panoptic_val"
  panoptic_io.write_panoptic_png(png_dir / "frankfurt_000000_000294_gtFine_panoptic.png", ids)
  segments_info = [{"id": int(i), "category_id": int(i) // 1000 or int(i), "iscrowd": 0,
                    "bbox": [0, 0, 1, 1], "area": 1} for i in ids.ravel()]
  categories = [{"id": 7, "name": "road", "supercategory": "flat", "isthing": 0},
                {"id": 8, "name": "sidewalk", "supercategory": "flat", "isthing": 0},
                {"id": 24, "name": "person", "supercategory": "human", "isthing": 1},
                {"id": 25, "name": "rider", "supercategory": "human", "isthing": 1},
                {"id": 26, "name": "car", "supercategory": "vehicle", "isthing": 1}]
  ann = tmp_path / "cityscapes_panoptic_val.json"
  ann.write_text(json.dumps({"annotations": [{
      "image_id": "frankfurt_000000_000294",
      "file_name": "frankfurt_000000_000294_gtFine_panoptic.png",
      "segments_info": segments_info}], "categories": categories}))
  source = panoptic_io.PanopticSource(annotation_file=ann)
  assert len(source.notes) == 1 and "category ids are not COCO's" in source.notes[0]
  assert "26 'car' -> 3" in source.notes[0] and "8 'sidewalk'" in source.notes[0]
  _, segments = source.ref("frankfurt_000000_000294_gtFine_panoptic").load()
  assert {s.id: s.category_id for s in segments} == {
      7: 149, 8: 0, 24001: 1, 25001: 1, 26001: 3, 26002: 3}  # road, none, person x2, car x2
  assert sorted(dynamic_ids_from_segments(segments, 8)[:4].tolist()) == [24001, 25001, 26001,
                                                                         26002]
  # the frame's image stem is not the annotation's file name: the message shows one
  with pytest.raises(DataError, match=r"frankfurt_000000_000294_leftImg8bit\.png: panoptic PNG "
                     r"not found \(the file_names in cityscapes_panoptic_val\.json are like "
                     r"'frankfurt_000000_000294_gtFine_panoptic\.png'\)"):
    source.ref("frankfurt_000000_000294_leftImg8bit")


@pytest.mark.parametrize("case, pattern", [
    ("unlisted", r"a\.png: segment ids 2 appear in the PNG but not in segments_info"),
    ("gray", r"a\.png: panoptic PNG must be 8-bit RGB"),
    ("no_json", r"a\.json: panoptic JSON not found"),
    ("bad_json", r"a\.json: invalid JSON"),
    ("duplicate", r"a\.json: segment id 1 listed twice"),
    ("unknown_category", r"a\.json: .*category_id 999 is not a COCO panoptic category"),
    ("annotation_file_as_per_image", r"a\.json: no 'segments_info' key"),
])
def test_errors_name_the_file(tmp_path, case, pattern):
  ids = np.array([[1, 2]], np.int32)
  panoptic_io.write_panoptic(tmp_path / "a.png", ids, [Segment(1, 3), Segment(2, 1)])
  json_path = tmp_path / "a.json"
  if case == "unlisted":
    json_path.write_text(json.dumps({"segments_info": [{"id": 1, "category_id": 3}]}))
  elif case == "gray":
    cv2.imwrite(str(tmp_path / "a.png"), np.ones((1, 2), np.uint8))
  elif case == "no_json":
    json_path.unlink()
  elif case == "bad_json":
    json_path.write_text("{not json")
  elif case == "duplicate":
    json_path.write_text(json.dumps({"segments_info": [{"id": 1, "category_id": 3}] * 2}))
  elif case == "unknown_category":
    json_path.write_text(json.dumps({"segments_info": [{"id": 1, "category_id": 999}]}))
  elif case == "annotation_file_as_per_image":
    json_path.write_text(json.dumps({"annotations": []}))
  with pytest.raises(DataError, match=pattern) as info:
    panoptic_io.PanopticSource(tmp_path).ref("a").load()
  assert "\n" not in str(info.value)


@pytest.mark.parametrize("annotation, pattern", [
    ({"file_name": 139, "segments_info": []},
     r"annotations\[0\] has file_name 139, expected the PNG's name"),
    ({"file_name": None, "segments_info": []},
     r"annotations\[0\] has file_name None, expected the PNG's name"),
])
def test_an_annotation_file_with_a_file_name_that_is_not_text_names_the_file(
    tmp_path, annotation, pattern):
  """A COCO annotation file whose file_name is a number (or null), or whose category id is a
  list, is a one-line DataError naming the file (it was a TypeError of pathlib or of a dict,
  which the commands print without the file)."""
  path = tmp_path / "panoptic.json"
  path.write_text(json.dumps({"annotations": [annotation]}))
  with pytest.raises(DataError, match=f"^{re.escape(str(path))}: {pattern}"):
    panoptic_io.read_annotation_file(path)
  path.write_text(json.dumps({"annotations": [], "categories": [
      {"id": [24], "name": "person", "isthing": 1}]}))
  assert panoptic_io.read_annotation_file(path)[0] == {}
