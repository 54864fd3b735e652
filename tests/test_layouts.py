"""Readers on the layouts the official downloads produce, with the minimum of options.

KITTI raw drives as downloaded (`open_raw_sequences`), DrivingStereo weather subsets with only
one image size, calibration files and a COCO annotation file inside the panoptic directory,
folders with a calib.json, Waymo opened at one sequence directory; and what each reader says
about temporal order and intrinsics. References: the values the fixtures write (images
uint8 / 255), and camera matrices scaled by hand (pixel-centre convention: f' = s f,
c' = s (c + 0.5) - 0.5).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pitta_jax.data import drivingstereo, folder, kitti, panoptic_io, readers, waymo
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Segment
from pitta_jax.data.panoptic_io import segments_info, write_panoptic_png
from pitta_jax.sources import open_reader
from test_readers import STEMS, _depth_u16, _rgb, _write_rgb, _write_u16, make_waymo

FOGGY = sorted(STEMS["foggy"] + ["2018-10-25-07-37-26_2018-10-25-07-37-40-100"])
FOGGY_SEQ = "2018-10-25-07-37-26"


def _scaled(K: np.ndarray, s: float) -> np.ndarray:
  """Hand reference: K of the image resized by s in both axes, pixel centres kept."""
  out = np.array(K, np.float64)
  out[:2, :2] *= s
  out[:2, 2] = s * (out[:2, 2] + 0.5) - 0.5
  return out


def _p_rect(fx: float, fy: float, cx: float, cy: float) -> str:
  return f"{fx:e} 0 {cx:e} 0 0 {fy:e} {cy:e} 0 0 0 1 0"


# ---------------------------------------------------------------------------------------------
# KITTI raw drives (the CoMoDa replay set)

KITTI_CALIB = ("calib_time: 09-Jan-2012 13:57:47\n"
               "S_rect_02: 1.600000e+01 1.200000e+01\n"          # twice the fixture images
               f"P_rect_02: {_p_rect(20.0, 21.0, 7.5, 5.5)}\n"
               f"P_rect_03: {_p_rect(20.0, 21.0, 7.5, 5.5)}\n")


def make_raw(root: Path) -> dict[str, list[np.ndarray]]:
  """Two dates as downloaded; returns {drive folder: images in index order}."""
  drives = {"2011_09_26/2011_09_26_drive_0001_sync": (3, "png"),
            "2011_09_26/2011_09_26_drive_0002_sync": (1, "png"),   # 1 frame: no pair
            "2011_09_28/2011_09_28_drive_0005_sync": (2, "jpg")}
  written = {}
  for k, (folder_name, (n, ext)) in enumerate(drives.items()):
    images = [_rgb(300 + 10 * k + i) for i in range(n)]
    for i in reversed(range(n)):  # written out of order
      _write_rgb(root / folder_name / "image_02" / "data" / f"{i:010d}.{ext}", images[i])
    _write_rgb(root / folder_name / "image_03" / "data" / f"{0:010d}.{ext}", _rgb(0))
    written[folder_name] = images
  (root / "2011_09_26" / "calib_cam_to_cam.txt").write_text(KITTI_CALIB)  # 09_28 has none
  return written


def test_open_raw_sequences(tmp_path):
  written = make_raw(tmp_path)
  seqs = kitti.open_raw_sequences(tmp_path)
  assert [s.names for s in seqs] == [
      tuple(f"2011_09_26/2011_09_26_drive_0001_sync/image_02/{i:010d}" for i in range(3)),
      tuple(f"2011_09_28/2011_09_28_drive_0005_sync/image_02/{i:010d}" for i in range(2))]
  assert all(s.temporal for s in seqs)
  frames = list(seqs[0])
  for frame, rgb in zip(frames, written["2011_09_26/2011_09_26_drive_0001_sync"]):
    np.testing.assert_array_equal(frame.image, rgb.astype(np.float32) / np.float32(255))
    assert frame.depth is None
    # K of the 16x12 rectified image (S_rect_02), halved to the 8x6 image
    np.testing.assert_allclose(frame.intrinsics, [[10, 0, 3.5], [0, 10.5, 2.5], [0, 0, 1]])
  assert seqs[1][0].intrinsics is None and seqs[1][1].image.shape == (6, 8, 3)  # jpg, no calib
  # the root may be one date folder
  one = kitti.open_raw_sequences(tmp_path / "2011_09_26")
  assert [len(s) for s in one] == [3]


def test_open_raw_sequences_split_at_missing_frames(tmp_path):
  """Frames 0-2, 5-6 and 9 of a drive: two sequences of consecutive frames (frames 2 and 5 are
  no pair), the lone frame 9 left out, and a note naming where the numbers jump."""
  drive = "2011_09_26/2011_09_26_drive_0001_sync"
  for i in (0, 1, 2, 5, 6, 9):
    _write_rgb(tmp_path / drive / "image_02" / "data" / f"{i:010d}.png", _rgb(i))
  seqs = kitti.open_raw_sequences(tmp_path)
  assert [s.names for s in seqs] == [
      tuple(f"{drive}/image_02/{i:010d}" for i in (0, 1, 2)),
      tuple(f"{drive}/image_02/{i:010d}" for i in (5, 6))]
  assert all(s.temporal for s in seqs)
  assert seqs[0].notes == seqs[1].notes == (
      f"{drive}: frame numbers jump after 0000000002, 0000000006; read as 2 sequence(s) of "
      f"consecutive frames, without 1 frame(s) that have no neighbour (0000000009)",)
  np.testing.assert_array_equal(seqs[1][0].image, _rgb(5).astype(np.float32) / np.float32(255))


@pytest.mark.parametrize("case, pattern", [
    ("missing", r"nowhere: KITTI raw root \(--replay-root\) not found"),
    ("no_pairs", r"raw: no KITTI raw drive with at least 2 frames \(looked for <date>/"),
])
def test_open_raw_sequences_errors(tmp_path, case, pattern):
  root = tmp_path / "nowhere"
  if case == "no_pairs":
    root = tmp_path / "raw"
    _write_rgb(root / "2011_09_26" / "2011_09_26_drive_0002_sync" / "image_02" / "data"
               / "0000000000.png", _rgb(0))
  with pytest.raises(DataError, match=pattern) as info:
    kitti.open_raw_sequences(root)
  assert "\n" not in str(info.value)


@pytest.mark.parametrize("entries, temporal", [
    ([("a", 5, 2), ("a", 6, 2), ("a", 7, 2), ("b", 0, 2), ("b", 1, 2)], True),
    ([("a", 69, 2), ("a", 54, 2), ("b", 3, 2)], False),               # Eigen-like
    ([("a", 5, 2), ("a", 6, 2), ("b", 0, 2)], False),                  # a run of one frame
    ([("a", 5, 2), ("a", 6, 2), ("b", 0, 2), ("b", 1, 2), ("a", 7, 2), ("a", 8, 2)], False),
    ([("a", 5, 2), ("a", 6, 3)], False),                               # the other camera
])
def test_kitti_split_temporal(entries, temporal):
  assert kitti.split_is_temporal(entries) is temporal


# ---------------------------------------------------------------------------------------------
# DrivingStereo as downloaded


def make_foggy(root: Path, size: str = "full", nested_images: bool = False) -> list[np.ndarray]:
  """`foggy/left-image-<size>-size/` + `foggy/depth-map-<size>-size/` only; images by stem."""
  images = []
  image_dir = root / "foggy" / f"left-image-{size}-size"
  if nested_images:
    image_dir = image_dir / f"left-image-{size}-size"
  for k, stem in enumerate(FOGGY):
    rgb = _rgb(400 + k, 8, 16)
    _write_rgb(image_dir / f"{stem}{'.png' if size == 'full' else '.jpg'}", rgb)
    _write_u16(root / "foggy" / f"depth-map-{size}-size" / f"{stem}.png", _depth_u16(k, 8, 16))
    images.append(rgb)
  return images


def _coco_annotation(path: Path, png_dir: Path) -> list[tuple[Segment, ...]]:
  """A panoptic PNG per foggy stem and one COCO annotation file at `path` for all of them."""
  annotations, expected = [], []
  for k, stem in enumerate(FOGGY):
    ids = np.zeros((8, 16), np.int32)
    ids[2:5, 3 + k:7 + k] = 5 + k
    ids[6:, :] = 1
    segments = (Segment(5 + k, 3, True), Segment(1, 149, False))
    write_panoptic_png(png_dir / f"{stem}.png", ids)
    annotations.append({"file_name": f"{stem}.png", "image_id": k,
                        "segments_info": segments_info(ids, segments)})
    expected.append((Segment(1, 149, False), Segment(5 + k, 3, True)))
  path.write_text(json.dumps({"annotations": annotations, "categories": [
      {"id": 3, "name": "car", "isthing": 1}, {"id": 149, "name": "road", "isthing": 0}]}))
  return expected


@pytest.mark.parametrize("where", ["inside", "beside"])
def test_drivingstereo_issue_layout_with_two_flags(tmp_path, where):
  # The issue's layout: full size only, COCO panoptic PNGs with one panoptic.json (inside the
  # PNG folder, or beside it as DIR.json): `--option weather=foggy --segmentation png:DIR`.
  images = make_foggy(tmp_path)
  pan = tmp_path / "pan"
  ann = pan / "panoptic.json" if where == "inside" else tmp_path / "pan.json"
  pan.mkdir()
  expected = _coco_annotation(ann, pan)
  frames = open_reader("drivingstereo", str(tmp_path), ["weather=foggy"], f"png:{pan}")
  assert frames.names == tuple(f"foggy/{s}" for s in FOGGY)
  assert frames.temporal and frames.notes == (
      "DrivingStereo size=full: the only left-image-*-size/ directory (foggy)",
      f"panoptic segments from the COCO annotation file {ann}")
  for k, frame in enumerate(frames):
    np.testing.assert_array_equal(frame.image, images[k].astype(np.float32) / np.float32(255))
    assert tuple(sorted(frame.segments, key=lambda s: s.id)) == expected[k]
    assert frame.panoptic[3, 4 + k] == 5 + k and frame.intrinsics is None
  assert "calib" in frames.remedies["intrinsics"]


def test_drivingstereo_sizes_and_lone_subdirectory(tmp_path):
  images = make_foggy(tmp_path, "full", nested_images=True)  # left-image-full-size/ twice
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="foggy")
  np.testing.assert_array_equal(frames[0].image, images[0].astype(np.float32) / np.float32(255))
  make_foggy(tmp_path, "half")
  both = drivingstereo.open_drivingstereo(tmp_path, weather="foggy")
  assert both.files[0].image.suffix == ".jpg"  # half when both exist, said in a note
  assert both.notes == ("DrivingStereo size=half: both left-image-half-size/ and "
                        "left-image-full-size/ are here; the half-size images and ground truth "
                        "are read and scored (--option size=full for the full size)",)
  # the default weather=all with only foggy downloaded: the message names what is there
  with pytest.raises(DataError, match=r"weather cloudy, rainy, sunny not found here \(with the "
                                      r"default weather=all .*\); found foggy: --option "
                                      r"weather=foggy"):
    drivingstereo.open_drivingstereo(tmp_path, weather="all")
  with pytest.raises(DataError, match=r"foggy: this is one weather's directory .*: pass its "
                                      r"parent as --root and --option weather=foggy"):
    drivingstereo.open_drivingstereo(tmp_path / "foggy", weather="foggy")
  (tmp_path / "cloudy").mkdir()  # no weather at all: the subset's own message
  with pytest.raises(DataError, match=r"cloudy: no left-image-half-size/ or left-image-full-size/ "
                                      r"directory here or in cloudy/cloudy/"):
    drivingstereo.open_drivingstereo(tmp_path / "cloudy", weather="cloudy")
  other = tmp_path / "other"
  make_foggy(other, "full")
  (other / "sunny" / "sunny" / "left-image-half-size").mkdir(parents=True)
  with pytest.raises(DataError, match=r"other: no image size common to the weathers \(foggy: "
                                      r"full, sunny: half\); pass --option size=half\|full"):
    drivingstereo.choose_size(other, ("foggy", "sunny"))


def test_drivingstereo_notes_frames_seconds_apart():
  """The stems' timestamps: 0.680 s and 0.815 s gaps (median 0.7475, by hand) are noted; 10 Hz
  frames and stems without timestamps are not."""
  seq = "2018-10-25-07-37-26"
  sparse = [f"{seq}_2018-10-25-07-45-25-505", f"{seq}_2018-10-25-07-45-26-185",
            f"{seq}_2018-10-25-07-45-27-000"]
  assert drivingstereo.frame_spacing_note("foggy", sparse) == (
      "DrivingStereo foggy: consecutive frames are 0.75 s apart (median; largest 0.8 s), a "
      "subsample of the drive rather than video-rate frames: methods that pair consecutive "
      "frames (CoMoDa, Ada-Depth) see that interval's motion")
  video = [f"{seq}_2018-10-25-07-45-25-{ms:03d}" for ms in (0, 100, 200, 300)]
  assert drivingstereo.frame_spacing_note("foggy", video) is None
  assert drivingstereo.frame_spacing_note("foggy", ["a_1", "a_2"]) is None


def _ds_calib(path: Path, fx: float, cx: float, fy: float, cy: float, w: int, h: int) -> None:
  """A DrivingStereo calibration file (KITTI-style keys of cameras 101 and 103)."""
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text(f"S_101: {2 * w:e} {2 * h:e}\nK_101: {fx} 0 {cx} 0 {fy} {cy} 0 0 1\n"
                  f"D_101: 0 0 0 0 0\nS_rect_101: {w:e} {h:e}\n"
                  f"P_rect_101: {_p_rect(fx, fy, cx, cy)}\n"
                  f"S_rect_103: {w:e} {h:e}\nP_rect_103: {_p_rect(fx, fy, cx + 1, cy)}\n"
                  f"T_103: -5.4e-01 0 0\n")


def test_drivingstereo_calibration(tmp_path):
  make_foggy(tmp_path, "half")  # 16x8 images under the "half" name
  K_half = np.array([[30.0, 0, 7.5], [0, 31.0, 3.5], [0, 0, 1]])
  _ds_calib(tmp_path / "calib" / "full-image-calib" / f"{FOGGY_SEQ}.txt", 60, 15.5, 62, 7.5, 32, 16)
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="foggy")
  # only the full-size calibration (32x16): scaled by 1/2 to the 16x8 image
  np.testing.assert_allclose(frames[0].intrinsics, _scaled([[60, 0, 15.5], [0, 62, 7.5],
                                                            [0, 0, 1]], 0.5))
  np.testing.assert_allclose(frames[0].intrinsics, K_half)
  # the calibration of the size in use wins
  _ds_calib(tmp_path / "calib" / "half-image-calib" / f"{FOGGY_SEQ}.txt", 29, 7, 30, 3, 16, 8)
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="foggy")
  np.testing.assert_array_equal(frames[1].intrinsics, [[29, 0, 7], [0, 30, 3], [0, 0, 1]])
  # an explicit calib_dir: the directory of <seq>.txt
  _ds_calib(tmp_path / "mine" / f"{FOGGY_SEQ}.txt", 28, 7, 28, 3, 16, 8)
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="foggy", calib_dir=tmp_path / "mine")
  assert frames[0].intrinsics[0, 0] == 28
  (tmp_path / "mine" / f"{FOGGY_SEQ}.txt").unlink()
  with pytest.raises(DataError, match=rf"mine/{FOGGY_SEQ}\.txt: calibration file not found"):
    drivingstereo.open_drivingstereo(tmp_path, weather="foggy", calib_dir=tmp_path / "mine")
  _ds_calib(tmp_path / "calib" / "half-image-calib" / f"{FOGGY_SEQ}.txt", 29, 7, 30, 3, 16, 16)
  with pytest.raises(DataError, match=r"image is 16x8 but the calibration .* is for 16x16"):
    drivingstereo.open_drivingstereo(tmp_path, weather="foggy")[0]


# ---------------------------------------------------------------------------------------------
# Panoptic annotation files, folder, Waymo, order


def test_annotation_file_detection(tmp_path):
  ids = np.array([[0, 4]], np.int32)
  write_panoptic_png(tmp_path / "a.png", ids)
  (tmp_path / "a.json").write_text(json.dumps({"segments_info": [{"id": 4, "category_id": 1}]}))
  (tmp_path / "notes.json").write_text(json.dumps({"author": "me"}))  # not an annotation file
  source = panoptic_io.PanopticSource(tmp_path)
  assert source.annotation_file is None and source.ref("a").load()[1] == (Segment(4, 1, True),)
  write_panoptic_png(tmp_path / "b.png", ids)
  ann = {"annotations": [{"file_name": "b.png", "segments_info": [{"id": 4, "category_id": 3}]}]}
  (tmp_path / "all.json").write_text(json.dumps(ann))
  source = panoptic_io.PanopticSource(tmp_path)
  assert source.annotation_file == tmp_path / "all.json"
  assert source.ref("b").load()[1] == (Segment(4, 3, True),)
  assert source.ref("a").load()[1] == (Segment(4, 1, True),)  # its own JSON still serves
  (tmp_path / "more.json").write_text(json.dumps(ann))
  with pytest.raises(DataError, match=r"several COCO annotation files \(all\.json, more\.json\); "
                                      r"pass one with --option panoptic_json=FILE"):
    panoptic_io.PanopticSource(tmp_path)


def test_folder_temporal_and_calib(tmp_path):
  for k in range(3):
    _write_rgb(tmp_path / f"{k:06d}.png", _rgb(k))
  frames = folder.open_folder(tmp_path)
  assert not frames.temporal and frames[0].intrinsics is None
  assert "--option temporal=true" in frames.remedies["previous_frame"]
  (tmp_path / "calib.json").write_text(json.dumps(
      {"K": [[8.0, 0, 7.5], [0, 8.0, 5.5], [0, 0, 1]], "width": 16, "height": 12}))
  frames = readers.open_dataset("folder", tmp_path, temporal=True)
  assert frames.temporal and frames.names == ("000000", "000001", "000002")
  np.testing.assert_allclose(frames[2].intrinsics, _scaled([[8, 0, 7.5], [0, 8, 5.5], [0, 0, 1]],
                                                           0.5))
  other = tmp_path / "cam.json"
  other.write_text(json.dumps({"K": np.eye(3).tolist(), "width": 8, "height": 6}))
  np.testing.assert_array_equal(folder.open_folder(tmp_path, calib=other)[0].intrinsics, np.eye(3))
  assert not frames[::2].temporal and frames[1:].temporal and (frames + frames[:1]).temporal


def test_folder_temporal_orders_unpadded_numbers_as_numbers(tmp_path):
  """frame_1, frame_2, frame_10, frame_11 (a video exported without zero padding): in capture
  order with temporal=true, with a note; without it the plain sort stays (no order promised)."""
  for k in (1, 2, 10, 11):
    _write_rgb(tmp_path / f"frame_{k}.png", _rgb(k))
  frames = folder.open_folder(tmp_path, temporal=True)
  assert frames.names == ("frame_1", "frame_2", "frame_10", "frame_11")
  np.testing.assert_array_equal(frames[1].image, _rgb(2).astype(np.float32) / np.float32(255))
  assert frames.notes == ("temporal=true: the stems' numbers ordered as numbers (frame_1, "
                          "frame_2, frame_10, ...), not as text",)
  assert folder.open_folder(tmp_path).names == ("frame_1", "frame_10", "frame_11", "frame_2")


def test_waymo_sequence_directory_as_root(tmp_path):
  expected = make_waymo(tmp_path, "segment-a", n=2)
  frames = waymo.open_waymo(tmp_path / "segment-a")
  assert frames.names == ("segment-a/000000", "segment-a/000001") and frames.temporal
  np.testing.assert_array_equal(frames[1].depth, expected[1])
  np.testing.assert_array_equal(frames[0].intrinsics, [[5, 0, 4], [0, 5, 3], [0, 0, 1]])


def test_required_reader_option_named(tmp_path):
  with pytest.raises(DataError, match=r"^dataset 'kitti' needs --option split_file=\.\.\.$"):
    readers.open_dataset("kitti", tmp_path)


def test_synthetic_export_reads_back_with_one_option(tmp_path):
  # the exporter's DrivingStereo layout (full size, panoptic/, full-image-calib/): weather only
  from pitta_jax.data.synthetic import SyntheticConfig, export_drivingstereo, generate_sequence
  frames = generate_sequence(SyntheticConfig(height=16, width=24, num_frames=2, domain="fog"))
  export_drivingstereo(frames, tmp_path, "foggy")
  back = readers.open_dataset("drivingstereo", tmp_path, weather="foggy")
  assert back.temporal and len(back) == 2 and back.notes[0].startswith("DrivingStereo size=full")
  for original, read in zip(frames, back):
    np.testing.assert_allclose(read.intrinsics, original.intrinsics, rtol=1e-9)
    np.testing.assert_array_equal(read.panoptic, original.panoptic)
    np.testing.assert_allclose(read.image, original.image, atol=0.5 / 255 + 1e-6)


def test_drivingstereo_calibration_without_s_rect_is_for_its_folders_size(tmp_path):
  """Full-size images (1762x800) and only the half-size calibration, which has no S_rect_101:
  its P_rect is for the release's half size (881x400, from the folder's name), so K doubles on
  the images (pixel centres kept), instead of being taken as the full size's."""
  image_dir = tmp_path / "foggy" / "left-image-full-size"
  for stem in FOGGY:
    _write_rgb(image_dir / f"{stem}.png", np.full((800, 1762, 3), 90, np.uint8))
  path = tmp_path / "calib" / "half-image-calib" / f"{FOGGY_SEQ}.txt"
  path.parent.mkdir(parents=True)
  path.write_text(f"P_rect_101: {_p_rect(1000.0, 1000.0, 440.0, 200.0)}\n")
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="foggy", depth=False)
  np.testing.assert_allclose(frames[0].intrinsics,
                             _scaled([[1000, 0, 440], [0, 1000, 200], [0, 0, 1]], 2.0))


def test_raw_drives_are_read_in_date_order(tmp_path):
  """Five date folders made out of order: the drives (CoMoDa's replay order) follow the dates,
  not the directory listing."""
  dates = ["2011_09_29", "2011_10_03", "2011_09_26", "2011_09_30", "2011_09_28"]
  for date in dates:
    for i in range(2):
      _write_rgb(tmp_path / date / f"{date}_drive_0001_sync" / "image_02" / "data"
                 / f"{i:010d}.png", _rgb(i))
  seqs = kitti.open_raw_sequences(tmp_path)
  assert [s.names[0].split("/")[0] for s in seqs] == sorted(dates)


def test_intrinsics_of_a_resize_that_changes_the_aspect_ratio():
  # Hand values: (H, W) 50x100 -> 50x200: row 0 of K scales by 2 with cx = 2 (50 + 0.5) - 0.5
  # = 100.5; row 1 is unchanged.
  from pitta_jax.data.resize import scale_intrinsics
  K = np.array([[100.0, 0, 50], [0, 100, 25], [0, 0, 1]])
  np.testing.assert_array_equal(scale_intrinsics(K, (50, 100), (50, 200)),
                                [[200, 0, 100.5], [0, 100, 25], [0, 0, 1]])
  np.testing.assert_array_equal(scale_intrinsics(K, (50, 100), (100, 100)),
                                [[100, 0, 50], [0, 200, 50.5], [0, 0, 1]])


def test_drivingstereo_calib_dir_named_for_a_size_is_for_that_size(tmp_path):
  """`--option calib_dir=.../full-image-calib` (the `<seq>.txt` directory itself, as the docs
  allow) with half-size images (881x400) and a calibration without S_rect_101: its P_rect is
  for the full size (1762x800, the folder's name), as when the same folder is found under
  --root, so K halves on the images (pixel centres kept); it was taken as the half size's."""
  image_dir = tmp_path / "foggy" / "left-image-half-size"
  for stem in FOGGY:
    _write_rgb(image_dir / f"{stem}.jpg", np.full((400, 881, 3), 90, np.uint8))
  calib_dir = tmp_path / "download" / "full-image-calib"
  calib_dir.mkdir(parents=True)
  (calib_dir / f"{FOGGY_SEQ}.txt").write_text(
      f"P_rect_101: {_p_rect(2000.0, 2000.0, 880.0, 400.0)}\n")
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="foggy", depth=False,
                                            calib_dir=calib_dir)
  np.testing.assert_allclose(frames[0].intrinsics,
                             _scaled([[2000, 0, 880], [0, 2000, 400], [0, 0, 1]], 0.5))
