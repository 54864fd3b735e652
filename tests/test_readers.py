"""Dataset readers on tiny fixtures written in each dataset's real layout.

References: the values written with cv2/NumPy by the fixtures themselves (images uint8 / 255,
depth uint16 / 256), the layouts of docs/datasets.md, and for Waymo's sparse depth a
literal per-point loop (nearest point per pixel).
"""

from __future__ import annotations

import dataclasses
import io
import json
import re
import os
import pickle
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from pitta_jax.data import drivingstereo, kitti, readers, resize, waymo
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame, Segment
from pitta_jax.data.image_io import read_image, write_depth_png
from pitta_jax.data.panoptic_io import write_panoptic
from pitta_jax.data.sequence import FrameFiles, FrameSequence

H, W = 6, 8


def _rgb(seed: int, h: int = H, w: int = W) -> np.ndarray:
  return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _depth_u16(seed: int, h: int = H, w: int = W) -> np.ndarray:
  d = np.random.default_rng(seed + 1000).integers(0, 65536, (h, w), dtype=np.uint16)
  d[0, 0] = 0  # an invalid pixel
  return d


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
  path.parent.mkdir(parents=True, exist_ok=True)
  assert cv2.imwrite(str(path), rgb[..., ::-1])  # RGB -> OpenCV's BGR


def _write_u16(path: Path, array: np.ndarray) -> None:
  path.parent.mkdir(parents=True, exist_ok=True)
  assert cv2.imwrite(str(path), array)


# ---------------------------------------------------------------------------------------------
# DrivingStereo

# Stems `<seq>_<YYYY-MM-DD-HH-MM-SS-mmm>`, listed here out of order.
STEMS = {
    "cloudy": ["2018-10-31-06-55-01_2018-10-31-06-55-12-202",
               "2018-10-31-06-55-01_2018-10-31-06-55-11-102"],
    "foggy": ["2018-10-25-07-37-26_2018-10-25-07-37-40-000"],
    "rainy": ["2018-08-17-09-45-58_2018-08-17-09-46-10-500",
              "2018-08-17-09-45-58_2018-08-17-09-46-09-100"],
    "sunny": ["2018-10-19-09-30-39_2018-10-19-09-31-01-001"],
}


def make_drivingstereo(root: Path, size: str = "full", nested: tuple[str, ...] = ()
                       ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
  """Writes the four weathers; returns {stem: (rgb uint8, depth uint16)}."""
  suffix = ".jpg" if size == "half" else ".png"
  written = {}
  for k, (weather, stems) in enumerate(STEMS.items()):
    wdir = root / weather / weather if weather in nested else root / weather
    for j, stem in enumerate(stems):
      rgb, depth = _rgb(10 * k + j), _depth_u16(10 * k + j)
      _write_rgb(wdir / f"left-image-{size}-size" / f"{stem}{suffix}", rgb)
      _write_u16(wdir / f"depth-map-{size}-size" / f"{stem}.png", depth)
      written[stem] = (rgb, depth)
  return written


def test_drivingstereo_values_round_trip(tmp_path):
  written = make_drivingstereo(tmp_path, size="full")
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="rainy", size="full")
  assert len(frames) == 2
  for frame in frames:
    rgb, depth = written[frame.name.split("/")[1]]
    assert frame.image.dtype == np.float32 and frame.image.shape == (H, W, 3)
    np.testing.assert_array_equal(frame.image, rgb.astype(np.float32) / np.float32(255))
    assert frame.depth.dtype == np.float32
    np.testing.assert_array_equal(frame.depth, depth.astype(np.float32) / 256)
    assert frame.depth[0, 0] == 0 and frame.panoptic is None
    stem = frame.name.split("/")[1]  # named in errors about the ground truth
    assert frame.depth_file == str(tmp_path / "rainy" / "depth-map-full-size" / f"{stem}.png")


def test_drivingstereo_all_order_and_nested_layout(tmp_path):
  make_drivingstereo(tmp_path, size="half", nested=("foggy", "sunny"))
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="All")
  expected = [f"{w}/{s}" for w in ("cloudy", "foggy", "rainy", "sunny") for s in sorted(STEMS[w])]
  assert frames.names == tuple(expected)
  assert [f.name for f in frames] == expected
  assert frames[1].image.shape == (H, W, 3)  # half-size .jpg read


def test_drivingstereo_jpeg_is_rgb(tmp_path):
  make_drivingstereo(tmp_path, size="half")
  stem = STEMS["foggy"][0]
  red = np.zeros((16, 16, 3), np.uint8)
  red[..., 0] = 250
  _write_rgb(tmp_path / "foggy" / "left-image-half-size" / f"{stem}.jpg", red)
  image = drivingstereo.open_drivingstereo(tmp_path, weather="foggy")[0].image
  assert image[..., 0].min() > 0.9 and image[..., 2].max() < 0.1  # red stays in channel 0


def test_drivingstereo_panoptic(tmp_path):
  make_drivingstereo(tmp_path)
  ids = np.zeros((H, W), np.int32)
  ids[2:4, 3:6] = 7
  for stem in STEMS["foggy"]:  # the synthetic exporter's layout
    write_panoptic(tmp_path / "foggy" / "panoptic" / f"{stem}.png", ids, [Segment(7, 3, True)])
  frame = drivingstereo.open_drivingstereo(tmp_path, weather="foggy", size="full")[0]
  np.testing.assert_array_equal(frame.panoptic, ids)
  assert frame.segments == (Segment(7, 3, True),)
  # An explicit panoptic_dir must cover every frame.
  other = tmp_path / "m2f"
  write_panoptic(other / f"{STEMS['cloudy'][0]}.png", ids, [Segment(7, 1, True)])
  with pytest.raises(DataError, match=f"{STEMS['cloudy'][1]}.png: panoptic PNG not found"):
    drivingstereo.open_drivingstereo(tmp_path, weather="cloudy", size="full", panoptic_dir=other)


def test_drivingstereo_is_lazy(tmp_path):
  make_drivingstereo(tmp_path)
  frames = drivingstereo.open_drivingstereo(tmp_path, weather="cloudy", size="full")
  # Corrupt a file after opening: only accessing that frame fails.
  bad = tmp_path / "cloudy" / "left-image-full-size" / f"{sorted(STEMS['cloudy'])[1]}.png"
  bad.write_bytes(b"not a png")
  assert frames[0].image.shape == (H, W, 3)
  assert isinstance(frames[1:], FrameSequence) and len(frames[1:]) == 1
  with pytest.raises(DataError, match="cannot decode image"):
    frames[1]


def _ds_error_case(root: Path, case: str) -> dict:
  make_drivingstereo(root)
  foggy = root / "foggy"
  stem = STEMS["foggy"][0]
  options = {"weather": "foggy", "size": "full"}
  if case == "missing_weather":
    os.rename(foggy, root / "foggy_old")
  elif case == "missing_depth":
    (foggy / "depth-map-full-size" / f"{stem}.png").unlink()
  elif case == "depth_not_uint16":
    _write_u16(foggy / "depth-map-full-size" / f"{stem}.png", np.ones((H, W), np.uint8))
  elif case == "grayscale":
    _write_u16(foggy / "left-image-full-size" / f"{stem}.png", np.ones((H, W), np.uint8))
  elif case == "panoptic_size":
    write_panoptic(foggy / "panoptic" / f"{stem}.png", np.ones((H + 1, W), np.int32),
                   [Segment(1, 3)])
  elif case == "empty":
    (foggy / "left-image-full-size" / f"{stem}.png").unlink()
  elif case == "weather":
    options["weather"] = "snowy"
  return options


@pytest.mark.parametrize("case, pattern", [
    ("missing_weather", r"foggy: no left-image-full-size/ directory"),
    ("missing_depth", r"depth-map-full-size/2018-10-25-07-37-26_2018-10-25-07-37-40-000\.png: "
                      r"depth map not found"),
    ("depth_not_uint16", r"2018-10-25-07-37-26_2018-10-25-07-37-40-000\.png: depth PNG must be "
                         r"single-channel uint16, got uint8"),
    ("grayscale", r"left-image-full-size/2018-10-25-07-37-26_2018-10-25-07-37-40-000\.png: "
                  r"grayscale image"),
    ("panoptic_size", r"panoptic/2018-10-25-07-37-26_2018-10-25-07-37-40-000\.png: panoptic map "
                      r"is 8x7 but its image .* is 8x6"),
    ("empty", r"left-image-full-size: no frames found \(looked for <seq>_<timestamp>"),
    ("weather", r"unknown DrivingStereo weather 'snowy'"),
])
def test_drivingstereo_errors(tmp_path, case, pattern):
  options = _ds_error_case(tmp_path, case)
  with pytest.raises(DataError, match=pattern) as info:
    frames = drivingstereo.open_drivingstereo(tmp_path, **options)
    frames[0]
  assert "\n" not in str(info.value)


def test_rgba_drops_alpha(tmp_path):
  bgra = np.concatenate([_rgb(1)[..., ::-1], np.full((H, W, 1), 7, np.uint8)], axis=-1)
  cv2.imwrite(str(tmp_path / "a.png"), bgra)
  np.testing.assert_array_equal(read_image(tmp_path / "a.png"),
                                _rgb(1).astype(np.float32) / np.float32(255))


# ---------------------------------------------------------------------------------------------
# KITTI

KITTI_LINES = [("2011_09_26/2011_09_26_drive_0002_sync", 69, "l"),
               ("2011_09_26/2011_09_26_drive_0002_sync", 5, "r"),
               ("2011_09_28/2011_09_28_drive_0001_sync", 3, "2")]


def make_kitti(root: Path, ext: str = "png") -> tuple[Path, list[np.ndarray], list[np.ndarray]]:
  """Writes raw images and a split file; returns (split path, RGB images, GT maps)."""
  images, maps = [], []
  lines = []
  for k, (folder, frame, side) in enumerate(KITTI_LINES):
    camera = {"l": 2, "r": 3, "2": 2, "3": 3}[side]
    rgb = _rgb(100 + k)
    _write_rgb(root / "data" / folder / f"image_0{camera}" / "data" / f"{frame:010d}.{ext}", rgb)
    images.append(rgb)
    maps.append(np.random.default_rng(k).uniform(0, 80, (H + k, W + 2 * k)).astype(np.float32))
    lines.append(f"{folder} {frame:010d} {side}")
  split = root / "splits" / "eigen" / "test_files.txt"
  split.parent.mkdir(parents=True)
  split.write_text("\n".join(lines) + "\n")
  return split, images, maps


def _save_object_npz(path: Path, maps: list[np.ndarray]) -> None:
  data = np.empty(len(maps), object)  # what MonoDepth2's export_gt_depth.py wrote (sizes differ)
  data[:] = maps
  np.savez_compressed(path, data=data)


def test_kitti_eigen_gt(tmp_path):
  split, images, maps = make_kitti(tmp_path)
  _save_object_npz(split.parent / "gt_depths.npz", maps)
  frames = kitti.open_kitti(tmp_path / "data", split)  # gt_depths.npz found beside the split
  assert len(frames) == 3
  # splits/eigen/: scored inside the Garg crop (MonoDepth2's --eval_split eigen), kept by slicing
  assert frames.evaluation == frames[1:].evaluation == {"garg_crop": True}
  # a split file linked from elsewhere is the split its path names; a relative path too
  store = tmp_path / "store" / "eigen_test_files.txt"
  store.parent.mkdir()
  store.write_text(split.read_text())
  linked = tmp_path / "linked" / "eigen" / "test_files.txt"
  linked.parent.mkdir(parents=True)
  linked.symlink_to(store)
  assert kitti.split_evaluation(linked) == {"garg_crop": True}
  assert kitti.split_evaluation(store) == {}
  # and a link from elsewhere to the split's file, or to its folder, is that split (it was
  # scored on the whole frame once the link's own folder was taken)
  (tmp_path / "mine").mkdir()
  (tmp_path / "mine" / "my_split.txt").symlink_to(split)
  (tmp_path / "kitti_eigen").symlink_to(split.parent, target_is_directory=True)
  for path in (tmp_path / "mine" / "my_split.txt", tmp_path / "kitti_eigen" / split.name):
    assert kitti.split_evaluation(path) == {"garg_crop": True}, path
  monkey = pytest.MonkeyPatch()
  monkey.chdir(split.parent)
  try:
    assert kitti.split_evaluation(Path("test_files.txt")) == {"garg_crop": True}
  finally:
    monkey.undo()
  # the `r` line's image is camera 3's, MonoDepth2's exported ground truth camera 2's
  assert frames.notes == ("test_files.txt: 1 line(s) take the right camera's image (image_03), "
                          "but gt_depths.npz holds the left camera's ground truth for every line "
                          "(MonoDepth2's export_gt_depth.py); use improved_gt for both cameras",)
  assert frames.names == ("2011_09_26/2011_09_26_drive_0002_sync/image_02/0000000069",
                          "2011_09_26/2011_09_26_drive_0002_sync/image_03/0000000005",
                          "2011_09_28/2011_09_28_drive_0001_sync/image_02/0000000003")
  for index, (frame, rgb, gt) in enumerate(zip(frames, images, maps)):
    np.testing.assert_array_equal(frame.image, rgb.astype(np.float32) / np.float32(255))
    assert frame.depth.dtype == np.float32
    np.testing.assert_array_equal(frame.depth, gt)
    assert frame.depth_file == f"{split.parent / 'gt_depths.npz'}[{index}]"


def test_a_run_scores_the_eigen_split_as_published_without_being_told(tmp_path):
  """run_sequence without an EvalConfig takes the sequence's own protocol, as the commands do:
  the Eigen split inside the Garg crop (MonoDepth2's evaluate_depth.py --eval_split eigen);
  the library call scored the whole frame. An EvalConfig given is what scores."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import Weights
  from pitta_jax.models.random_init import random_monodepth2_variables
  from pitta_jax.models.registry import get_spec
  from pitta_jax.run import EvalConfig, frame_metrics, run_sequence
  split, _, maps = make_kitti(tmp_path)
  maps = [m[:H, :W] for m in maps]  # the images' size (a run checks the aspect ratio)
  _save_object_npz(split.parent / "gt_depths.npz", maps)
  frames = kitti.open_kitti(tmp_path / "data", split)
  weights = Weights(get_spec("monodepth2"), {"num_layers": 18, "height": 64, "width": 96},
                    random_monodepth2_variables(0), None)
  cfg = AdaptConfig(method="none", bn_stats="running")
  res = run_sequence(weights, frames, cfg, quiet=True, keep=range(3))
  whole = run_sequence(weights, frames, cfg, eval_cfg=EvalConfig(), quiet=True)
  for k, gt in enumerate(maps):
    depth = res.kept_depths[k]
    cropped = frame_metrics(depth, gt, EvalConfig(garg_crop=True), "median")["abs_rel"]
    full = frame_metrics(depth, gt, EvalConfig(), "median")["abs_rel"]
    assert res.per_frame[k]["abs_rel"] == cropped != full
    assert whole.per_frame[k]["abs_rel"] == full


def test_kitti_plain_npz_and_jpg(tmp_path):
  split, _, maps = make_kitti(tmp_path, ext="jpg")
  same = np.stack([m[:H, :W] for m in maps])  # equal sizes: saved as a plain float array
  np.savez(tmp_path / "gt.npz", data=same)
  frames = kitti.open_kitti(tmp_path / "data", split, gt_depths=tmp_path / "gt.npz")
  np.testing.assert_array_equal(frames[2].depth, same[2])
  assert frames[0].image.shape == (H, W, 3)


@pytest.mark.parametrize("protocol", [2, 3])
def test_kitti_gt_written_by_numpy1(tmp_path, protocol):
  # NumPy 1.x (MonoDepth2's era) np.save pickled with protocol 3 (GLOBAL opcodes) and named the
  # reconstructor numpy.core.multiarray; protocol 2 adds _codecs.encode for bytes.
  maps = [np.full((2, 3), 1.5, np.float32), np.arange(6, dtype=np.float32).reshape(3, 2)]
  data = np.empty(2, object)
  data[:] = maps
  payload = pickle.dumps(data, protocol=protocol).replace(b"numpy._core.multiarray\n",
                                                   b"numpy.core.multiarray\n")
  assert b"numpy.core.multiarray\n_reconstruct" in payload
  buffer = io.BytesIO()
  np.lib.format.write_array_header_1_0(buffer, {"descr": "|O", "fortran_order": False,
                                                "shape": (2,)})
  with zipfile.ZipFile(tmp_path / "gt.npz", "w") as archive:
    archive.writestr("data.npy", buffer.getvalue() + payload)
  loaded = kitti.load_gt_depths(tmp_path / "gt.npz")
  for got, want in zip(loaded, maps):
    np.testing.assert_array_equal(got, want)


def _evil_npz(path: Path) -> None:
  class Evil:
    def __reduce__(self):
      return (os.getcwd, ())
  buffer = io.BytesIO()
  np.lib.format.write_array_header_1_0(buffer, {"descr": "|O", "fortran_order": False,
                                                "shape": (3,)})
  pickle.dump(Evil(), buffer, protocol=3)
  with zipfile.ZipFile(path, "w") as archive:
    archive.writestr("data.npy", buffer.getvalue())


@pytest.mark.parametrize("case, pattern", [
    ("evil", r"gt\.npz: unsafe or corrupt pickle in 'data' \(refusing to load global "
             r"(posix|nt)\.getcwd\)"),
    ("count", r"gt\.npz: holds 2 depth maps but test_files\.txt lists 3 frames"),
    ("key", r"gt\.npz: no array 'data' in the \.npz \(has: depth\)"),
    ("split_line", r"test_files\.txt: line 2 is 'oops', expected"),
    ("missing_image", r"image_03/data/0000000005\.png: image not found"),
    ("missing_gt", r"eigen/gt_depths\.npz: ground truth not found"),
])
def test_kitti_errors(tmp_path, case, pattern):
  split, _, maps = make_kitti(tmp_path)
  gt = tmp_path / "gt.npz"
  _save_object_npz(gt, maps)
  options = {"gt_depths": gt}
  if case == "evil":
    _evil_npz(gt)
  elif case == "count":
    _save_object_npz(gt, maps[:2])
  elif case == "key":
    np.savez(gt, depth=np.zeros(3))
  elif case == "split_line":
    lines = split.read_text().splitlines()
    split.write_text("\n".join([lines[0], "oops"] + lines[1:]))
  elif case == "missing_image":
    next((tmp_path / "data").rglob("0000000005.png")).unlink()
    options["ext"] = "png"
  elif case == "missing_gt":
    options = {}
  with pytest.raises(DataError, match=pattern):
    frames = kitti.open_kitti(tmp_path / "data", split, **options)
    frames[0]


def test_kitti_improved_gt(tmp_path):
  split, _, _ = make_kitti(tmp_path)
  written = []
  for k, (folder, frame, side) in enumerate(KITTI_LINES):
    camera = {"l": 2, "r": 3, "2": 2}[side]
    depth = _depth_u16(k)
    sub = "train" if k != 1 else "val"
    drive = folder.split("/")[1]
    _write_u16(tmp_path / "improved" / sub / drive / "proj_depth" / "groundtruth"
               / f"image_0{camera}" / f"{frame:010d}.png", depth)
    written.append(depth)
  bench = tmp_path / "splits" / "eigen_benchmark" / "test_files.txt"  # no crop for this split
  bench.parent.mkdir(parents=True)
  bench.write_text(split.read_text())
  assert kitti.open_kitti(tmp_path / "data", bench, improved_gt=tmp_path / "improved"
                          ).evaluation == {"valid_gt": "positive"}  # its gt beyond 80 m counts
  frames = kitti.open_kitti(tmp_path / "data", split, improved_gt=tmp_path / "improved")
  assert frames.notes == ()  # the improved ground truth has both cameras
  for frame, depth in zip(frames, written):
    np.testing.assert_array_equal(frame.depth, depth.astype(np.float32) / 256)
  assert frames[1].depth_file == str(tmp_path / "improved" / "val" / KITTI_LINES[1][0].split("/")[1]
                                     / "proj_depth" / "groundtruth" / "image_03"
                                     / f"{KITTI_LINES[1][1]:010d}.png")


def test_kitti_eigen_benchmark_without_gt_depths_reads_the_improved_gt_in_the_drives(tmp_path):
  """The eigen_benchmark split without its gt_depths.npz: the ground truth is KITTI's improved
  maps where MonoDepth2's export_gt_depth.py --split eigen_benchmark reads them,
  <data>/<folder>/proj_depth/groundtruth/image_0X/, not the Velodyne scans (which were
  projected and scored as if they were the benchmark's); without those maps, one line naming
  the split file."""
  from pitta_jax.data.velodyne import velodyne_path
  split, _, _ = make_kitti(tmp_path)
  bench = tmp_path / "splits" / "eigen_benchmark" / "test_files.txt"
  bench.parent.mkdir(parents=True)
  bench.write_text(split.read_text())
  data, written = tmp_path / "data", []
  for k, (folder, frame, side) in enumerate(KITTI_LINES):
    camera = {"l": 2, "r": 3, "2": 2}[side]
    _velodyne_calibration(data / folder.split("/")[0])
    _write_velodyne(velodyne_path(data, folder, frame))
    written.append(_depth_u16(k))
    _write_u16(data / folder / "proj_depth" / "groundtruth" / f"image_0{camera}"
               / f"{frame:010d}.png", written[-1])
  frames = kitti.open_kitti(data, bench)
  assert frames.notes == () and frames.evaluation == {"valid_gt": "positive"}
  for frame, depth in zip(frames, written):
    np.testing.assert_array_equal(frame.depth, depth.astype(np.float32) / 256)
  assert "proj_depth" in frames[0].depth_file
  first = KITTI_LINES[0]
  (data / first[0] / "proj_depth" / "groundtruth" / "image_02" / f"{first[1]:010d}.png").unlink()
  with pytest.raises(DataError, match=f"^{re.escape(str(bench))}: the eigen_benchmark split is "
                                      f"scored on KITTI's improved ground truth"):
    kitti.open_kitti(data, bench)
  assert len(kitti.open_kitti(data, split)) == 3  # the Eigen split: the scans, as upstream
  # the improved ground truth's download unpacked into the raw root (train/, val/) is found too
  moved = data / "train" / first[0].split("/")[1] / "proj_depth" / "groundtruth" / "image_02"
  moved.mkdir(parents=True)
  _write_u16(moved / f"{first[1]:010d}.png", written[0])
  np.testing.assert_array_equal(kitti.open_kitti(data, bench)[0].depth,
                                written[0].astype(np.float32) / 256)


# KITTI ground truth from the Velodyne scans (MonoDepth2's kitti_utils.generate_depth_map, as
# export_gt_depth.py calls it). Hand-made calibration: Velodyne (x forward, y left, z up) ->
# camera (-y, -z, x + 0.5); P_rect_02 = [[2, 0, 4, 0], [0, 2, 2, 0], [0, 0, 1, 0]], so a point
# lands at u = 2 (-y) / (x + 0.5) + 4, v = 2 (-z) / (x + 0.5) + 2, pixel (round(v) - 1,
# round(u) - 1) of a 6 x 8 map (S_rect_02 = 8 6, the fixture images' size); P_rect_03 has
# cx = 3 and S_rect_03 another size.
VELO_CALIB = ("calib_time: 15-Mar-2012 11:37:16\n"
              "R: 0 -1 0 0 0 -1 1 0 0\nT: 0 0 0.5\n"
              "delta_f: 0 0\ndelta_c: 0 0\n")
VELO_CAM_CALIB = ("calib_time: 09-Jan-2012 13:57:47\n"
                  "R_rect_00: 1 0 0 0 1 0 0 0 1\n"
                  "S_rect_02: 8 6\nP_rect_02: 2 0 4 0 0 2 2 0 0 0 1 0\n"
                  "S_rect_03: 16 12\nP_rect_03: 2 0 3 0 0 2 2 0 0 0 1 0\n")
VELO_POINTS = [(3.5, 0.0, 0.0),     # u 4, v 2: pixel (1, 3) at 3.5 m ...
               (1.5, 0.0, 0.0),     # ... and at 1.5 m: the nearest is kept
               (-1.0, 0.0, 0.0),    # behind the sensor (x < 0): dropped (else (1, 3) at -1 -> 0)
               (1.5, -10.0, 0.0),   # u 14: outside the image
               (5.5, -12.0, 3.0),   # u 8, v 1: pixel (0, 7) at 5.5 m ...
               (2.5, 4.5, 0.0),     # ... u 1, v 2: pixel (1, 0) at 2.5 m, the same linear index
               (1.5, 1.5, -2.0)]    # u 2.5 (rounds to even: 2), v 4: pixel (3, 1)


def _write_velodyne(path: Path, points=VELO_POINTS) -> None:
  path.parent.mkdir(parents=True, exist_ok=True)
  scan = np.array([(x, y, z, 0.25) for x, y, z in points], "<f4")  # reflectance 0.25, not 1
  scan.tofile(path)


def _velodyne_calibration(date: Path) -> None:
  date.mkdir(parents=True, exist_ok=True)
  (date / "calib_velo_to_cam.txt").write_text(VELO_CALIB)
  (date / "calib_cam_to_cam.txt").write_text(VELO_CAM_CALIB)


def test_velodyne_depth_hand_computed(tmp_path):
  """The map of `VELO_POINTS` worked out by hand from the projection above, with upstream's
  conventions: depth = the Velodyne x (vel_depth), round(.) - 1, nearest point per pixel, and
  the index quirk: pixels (0, 7) and (1, 0) share row * (W - 1) + col - 1 = 6, so the smaller
  depth of the two (2.5) is written at the first point's pixel (0, 7) too."""
  from pitta_jax.data.velodyne import velodyne_depth
  _velodyne_calibration(tmp_path / "date")
  _write_velodyne(tmp_path / "scan.bin")
  want = np.zeros((6, 8), np.float32)
  want[1, 3], want[0, 7], want[1, 0], want[3, 1] = 1.5, 2.5, 2.5, 1.5
  got = velodyne_depth(tmp_path / "date", tmp_path / "scan.bin")
  assert got.dtype == np.float32
  np.testing.assert_array_equal(got, want)
  # camera 3 (cx 3: one column left), the camera's z (x + 0.5) as depth; the size stays S_rect_02
  want3 = np.zeros((6, 8), np.float32)
  want3[1, 2], want3[0, 6], want3[3, 1] = 2.0, 6.0, 2.0   # (1, 0) -> column -1: outside
  got3 = velodyne_depth(tmp_path / "date", tmp_path / "scan.bin", camera=3, vel_depth=False)
  np.testing.assert_array_equal(got3, want3)


def test_kitti_ground_truth_from_velodyne(tmp_path):
  """No gt_depths.npz: each line's map is projected from its drive's scan, camera 2's for the
  right-camera line too (export_gt_depth.py); a missing scan is named before any frame loads."""
  split, _, _ = make_kitti(tmp_path)
  for k, (folder, frame, _) in enumerate(KITTI_LINES):
    _velodyne_calibration(tmp_path / "data" / folder.split("/")[0])
    _write_velodyne(tmp_path / "data" / folder / "velodyne_points" / "data" / f"{frame:010d}.bin",
                    VELO_POINTS[:1 + k])   # (1, 3) at 3.5 m; from the second line on also 1.5 m
  frames = kitti.open_kitti(tmp_path / "data", split)
  assert frames.notes[-1] == ("test_files.txt: ground truth projected from the Velodyne scans "
                              "(velodyne_points/), as MonoDepth2's export_gt_depth.py writes "
                              "gt_depths.npz")
  assert "the Velodyne ground truth is the left camera's" in frames.notes[0]
  for k, want in enumerate([3.5, 1.5, 1.5]):
    expected = np.zeros((6, 8), np.float32)
    expected[1, 3] = want
    np.testing.assert_array_equal(frames[k].depth, expected)
    folder, frame, _ = KITTI_LINES[k]
    assert frames[k].depth_file == str(tmp_path / "data" / folder / "velodyne_points" / "data"
                                       / f"{frame:010d}.bin")
  (tmp_path / "data" / KITTI_LINES[2][0] / "velodyne_points" / "data" / "0000000003.bin").unlink()
  with pytest.raises(DataError, match=r"velodyne_points/data/0000000003\.bin: Velodyne scan not "
                                      r"found"):
    kitti.open_kitti(tmp_path / "data", split)
  (tmp_path / "data" / "2011_09_26" / "calib_velo_to_cam.txt").write_text("R: 1 0 0\n")
  with pytest.raises(DataError, match=r"calib_velo_to_cam\.txt: no valid R \(9 numbers\)"):
    kitti.open_kitti(tmp_path / "data", split)


# ---------------------------------------------------------------------------------------------
# Waymo


def _rasterise_loop(points: np.ndarray, height: int, width: int) -> np.ndarray:
  """Reference: one point at a time, keep the nearest (minimum z) per pixel."""
  depth = np.zeros((height, width), np.float64)
  for u, v, z in points.astype(np.float64):
    if not (np.isfinite(u) and np.isfinite(v) and np.isfinite(z)) or z <= 0:
      continue
    col, row = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
    if 0 <= row < height and 0 <= col < width and (depth[row, col] == 0 or z < depth[row, col]):
      depth[row, col] = z
  return depth.astype(np.float32)


def test_rasterise_matches_loop():
  rng = np.random.default_rng(0)
  points = np.stack([rng.uniform(-2, W + 1, 400), rng.uniform(-2, H + 1, 400),
                     rng.uniform(-5, 80, 400)], axis=1).astype(np.float32)
  points[:5, 2] = np.nan
  points[5:10] = [3.2, 2.7, 9.0]  # many points on one pixel: the minimum wins
  points[7, 2] = 4.5
  raster = waymo.rasterise_points(points, H, W)
  np.testing.assert_array_equal(raster, _rasterise_loop(points, H, W))
  assert 0 < raster[3, 3] <= 4.5  # the pixel (row 3, col 3) of the stacked points
  assert (raster > 0).sum() > 10


def make_waymo(root: Path, seq: str, n: int = 3, calib: bool = True) -> list[np.ndarray]:
  """Frames 0: depth PNG, 1: dense .npy, 2: sparse .npy; returns the expected depth maps."""
  expected = []
  for k in range(n):
    _write_rgb(root / seq / "image" / f"{k:06d}.png", _rgb(200 + k))
    depth_dir = root / seq / "depth"
    depth_dir.mkdir(parents=True, exist_ok=True)
    if k % 3 == 0:
      d = _depth_u16(k)
      _write_u16(depth_dir / f"{k:06d}.png", d)
      expected.append(d.astype(np.float32) / 256)
    elif k % 3 == 1:
      d = np.random.default_rng(k).uniform(0, 75, (H, W)).astype(np.float32)
      np.save(depth_dir / f"{k:06d}.npy", d)
      expected.append(d)
    else:
      rng = np.random.default_rng(k)
      points = np.stack([rng.uniform(0, W, 50), rng.uniform(0, H, 50), rng.uniform(1, 75, 50)],
                        axis=1).astype(np.float32)
      np.save(depth_dir / f"{k:06d}.npy", points)
      expected.append(_rasterise_loop(points, H, W))
  if calib:
    (root / seq / "calib.json").write_text(json.dumps(
        {"K": [[5.0, 0, 4.0], [0, 5.0, 3.0], [0, 0, 1]], "width": W, "height": H}))
  return expected


def test_waymo_layout(tmp_path):
  expected_b = make_waymo(tmp_path, "segment-b", n=3)
  expected_a = make_waymo(tmp_path, "segment-a", n=2, calib=False)
  (tmp_path / "notes").mkdir()  # not a sequence (no image/)
  frames = waymo.open_waymo(tmp_path)
  assert frames.names == ("segment-a/000000", "segment-a/000001", "segment-b/000000",
                          "segment-b/000001", "segment-b/000002")
  for frame, depth in zip(frames, expected_a + expected_b):
    np.testing.assert_array_equal(frame.depth, depth)
    seq, stem = frame.name.split("/")
    assert frame.depth_file in (str(tmp_path / seq / "depth" / f"{stem}{suffix}")
                                for suffix in (".png", ".npy"))
  np.testing.assert_array_equal(frames[2].image, _rgb(200).astype(np.float32) / np.float32(255))
  # segment-b's first frame follows segment-a's last in the stream: a new recording
  assert [f.starts_recording for f in frames] == [True, False, True, False, False]
  only_b = waymo.open_waymo(tmp_path, sequences="segment-b")
  assert len(only_b) == 3
  calib = waymo.read_calib(tmp_path / "segment-b" / "calib.json")
  assert (calib.width, calib.height) == (W, H) and calib.K[0, 2] == 4.0


@pytest.mark.parametrize("case, pattern", [
    ("calib_size", r"segment-a/image/000000\.png: image is 8x6 but .*calib\.json says 9x6"),
    ("missing_depth", r"segment-a/depth/000001\.png: depth map not found \(nor \.npy\)"),
    ("bad_calib", r"calib\.json: expected JSON with K \(3x3\), width and height"),
    ("no_sequences", r"no frames found \(looked for <seq>/image/ directories\)"),
    ("empty_npy", r"segment-a/depth/000001\.npy: cannot read \.npy depth \(No data left"),
])
def test_waymo_errors(tmp_path, case, pattern):
  make_waymo(tmp_path, "segment-a", n=2)
  calib = tmp_path / "segment-a" / "calib.json"
  root = tmp_path
  if case == "calib_size":
    calib.write_text(json.dumps({"K": np.eye(3).tolist(), "width": W + 1, "height": H}))
  elif case == "missing_depth":
    (tmp_path / "segment-a" / "depth" / "000001.npy").unlink()
  elif case == "bad_calib":
    calib.write_text(json.dumps({"K": [1, 2], "width": W, "height": H}))
  elif case == "no_sequences":
    root = tmp_path / "segment-a" / "depth"
  elif case == "empty_npy":  # a zero-byte file (an interrupted export)
    (tmp_path / "segment-a" / "depth" / "000001.npy").write_bytes(b"")
  with pytest.raises(DataError, match=pattern):
    frames = waymo.open_waymo(root)
    frames[0], frames[1]


# ---------------------------------------------------------------------------------------------
# Folder, registry, resizing


def test_folder_with_depth_and_panoptic(tmp_path):
  for k, stem in enumerate(["b", "a"]):
    _write_rgb(tmp_path / "img" / f"{stem}.png", _rgb(k))
    write_depth_png(tmp_path / "depth" / f"{stem}.png", np.full((H, W), 1.5 + k))
    ids = np.full((H, W), 3, np.int32)
    write_panoptic(tmp_path / "pan" / f"{stem}.png", ids, [Segment(3, 8, True)])
  frames = readers.open_dataset("folder", tmp_path / "img", depth_dir=tmp_path / "depth",
                                panoptic_dir=tmp_path / "pan")
  assert frames.names == ("a", "b")
  np.testing.assert_array_equal(frames[0].image, _rgb(1).astype(np.float32) / np.float32(255))
  np.testing.assert_array_equal(frames[0].depth, np.full((H, W), 2.5, np.float32))
  assert frames[1].segments == (Segment(3, 8, True),)
  write_depth_png(tmp_path / "depth" / "a.png", np.full((H, H), 1.5))  # another aspect ratio
  from pitta_jax.run import check_aspect  # what a run checks of each frame, naming its files
  with pytest.raises(DataError, match=rf"depth/a\.png: ground truth is {H}x{H} but the image is "
                                      rf"{W}x{H} \(W x H\): another aspect ratio, so the "
                                      rf"prediction cannot be resized onto it \(image "
                                      rf"\S*img/a\.png\)"):
    check_aspect(readers.open_dataset("folder", tmp_path / "img", depth_dir=tmp_path / "depth")[0])
  (tmp_path / "depth" / "a.png").unlink()
  with pytest.raises(DataError, match=r"depth/a\.png: depth map for image a\.png not found"):
    readers.open_dataset("folder", tmp_path / "img", depth_dir=tmp_path / "depth")
  (tmp_path / "empty").mkdir()
  with pytest.raises(DataError, match=r"empty: no frames found \(looked for \*\.\{png,jpg,jpeg\}"):
    readers.open_dataset("folder", tmp_path / "empty")
  with pytest.raises(DataError, match=r"nowhere: image directory not found"):
    readers.open_dataset("folder", tmp_path / "nowhere")


def test_registry():
  assert set(readers.READERS) == {"drivingstereo", "kitti", "waymo", "folder"}
  with pytest.raises(DataError, match="unknown dataset 'nyu'"):
    readers.open_dataset("nyu", "/x")
  with pytest.raises(DataError, match="dataset 'kitti' has no option weather"):
    readers.open_dataset("kitti", "/x", weather="foggy")


def test_resize_frame():
  rng = np.random.default_rng(0)
  image = rng.uniform(0, 1, (12, 16, 3)).astype(np.float32)
  ids = rng.integers(0, 4, (12, 16)).astype(np.int32)
  ids[0, 0] = 9  # a one-pixel segment that the 4x reduction does not sample
  depth = rng.uniform(0, 80, (24, 32)).astype(np.float32)
  segments = tuple(Segment(i, 3, True) for i in (1, 2, 3, 9))
  frame = Frame(image=image, depth=depth, panoptic=ids, segments=segments, name="x")
  small = resize.resize_frame(frame, height=6, width=8)
  # INTER_AREA at an integer factor = the mean of each 2x2 block (hand-derived reference).
  blocks = image.reshape(6, 2, 8, 2, 3).mean(axis=(1, 3))
  np.testing.assert_allclose(small.image, blocks, atol=1e-6)
  assert small.image.dtype == np.float32
  assert small.depth is depth  # ground truth stays full size
  np.testing.assert_array_equal(small.panoptic, ids[1::2, 1::2])  # centre of 2x2 -> index 2i+1
  tiny = resize.resize_frame(frame, height=3, width=4)
  reference = cv2.resize(ids.astype(np.uint16), (4, 3), interpolation=cv2.INTER_NEAREST_EXACT)
  np.testing.assert_array_equal(tiny.panoptic, reference)
  assert 9 not in tiny.panoptic and [s.id for s in tiny.segments] == sorted(
      set(np.unique(tiny.panoptic).tolist()) - {0})
  big = resize.resize_frame(frame, 192, 640)  # MonoDepth2's size, upsampling here
  assert big.image.shape == (192, 640, 3) and big.panoptic.shape == (192, 640)
  assert 0 <= big.image.min() and big.image.max() <= 1


def test_data_error_is_one_line_and_picklable(tmp_path):
  error = DataError(tmp_path / "a.png", "two\nlines")
  assert str(error) == f"{tmp_path / 'a.png'}: two lines"
  again = pickle.loads(pickle.dumps(error))
  assert str(again) == str(error) and again.path == error.path


def test_hidden_files_skipped(tmp_path):
  _write_rgb(tmp_path / "a.png", _rgb(0))
  (tmp_path / "._a.png").write_bytes(b"macOS resource fork")
  assert readers.open_dataset("folder", tmp_path).names == ("a",)


def test_kitti_intrinsics_from_calib_cam_to_cam(tmp_path):
  # Hand value: K = the left 3x3 of P_rect_02 of the date folder's calib_cam_to_cam.txt.
  from pitta_jax.data.kitti import read_cam_to_cam
  p = tmp_path / "calib_cam_to_cam.txt"
  p.write_text("calib_time: 09-Jan-2012\nP_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 "
               "4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 2.163791e-01 0.000000e+00 "
               "0.000000e+00 1.000000e+00 2.745884e-03\n")
  np.testing.assert_allclose(read_cam_to_cam(p, 2), [[721.5377, 0, 609.5593],
                                                     [0, 721.5377, 172.854], [0, 0, 1]])
  with pytest.raises(DataError, match="P_rect_03"):
    read_cam_to_cam(p, 3)


@pytest.mark.parametrize("values, message", [
    ("nan 0 609 0 0 721 172 0 0 0 1 0", "non-finite"),
    ("inf 0 609 0 0 721 172 0 0 0 1 0", "non-finite"),
    ("0 0 0 0 0 0 0 0 0 0 0 0", "positive focal lengths"),
    ("-721 0 609 0 0 721 172 0 0 0 1 0", "positive focal lengths"),
    ("721 0 609 0 0 721 172 0 5 5 5 0", "pinhole camera matrix")])
def test_camera_matrices_that_are_not_pinhole_are_refused(tmp_path, values, message):
  """K is inverted by the methods that warp (CoMoDa, Ada-Depth): a calibration whose K is not
  finite, has a focal length <= 0 or another bottom row than (0, 0, 1) is refused, naming the
  file, in both formats."""
  from pitta_jax.data.calib import read_calib_json
  from pitta_jax.data.kitti import read_cam_to_cam
  p = tmp_path / "calib_cam_to_cam.txt"
  p.write_text(f"P_rect_02: {values}\n")
  with pytest.raises(DataError, match=f"^{re.escape(str(p))}: .*{message}"):
    read_cam_to_cam(p, 2)
  K = np.array([float(v) for v in values.split()]).reshape(3, 4)[:, :3]
  j = tmp_path / "calib.json"
  j.write_text(json.dumps({"K": K.tolist(), "width": 8, "height": 6}))
  with pytest.raises(DataError, match=f"^{re.escape(str(j))}: .*{message}"):
    read_calib_json(j)


@pytest.mark.parametrize("size", ["inf 96", "320 nan", "-inf 96", "320.5 96", "320"])
def test_a_rectified_size_that_is_not_two_positive_integers_names_the_file(tmp_path, size):
  """S_rect_02 inf (a float that int() cannot take) is refused like any other bad size."""
  from pitta_jax.data.kitti import read_cam_to_cam
  p = tmp_path / "calib_cam_to_cam.txt"
  p.write_text(f"S_rect_02: {size}\nP_rect_02: 721.5 0 160 0 0 721.5 48 0 0 0 1 0\n")
  with pytest.raises(DataError, match=f"^{re.escape(str(p))}: S_rect_02 must be 2 positive "):
    read_cam_to_cam(p, 2)


def test_images_of_more_pixels_than_opencv_decodes_name_the_file(tmp_path):
  """A PNG whose header declares 60000x60000 pixels is refused from its header, before any
  decoding (the check of a sequence before work, and the read itself); a JPEG's header is
  OpenCV's to read, and its refusal becomes the same kind of one-line error."""
  import struct
  import zlib
  from pitta_jax.data.image_io import check_image_file, decode_file

  def chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
  png = tmp_path / "big.png"
  png.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000,
                                                                      8, 2, 0, 0, 0))
                  + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + chunk(b"IEND", b""))
  for check in (check_image_file, lambda p: decode_file(p, "image")):
    with pytest.raises(DataError, match=f"^{re.escape(str(png))}: image of 60000x60000 pixels"):
      check(png)
  ok, data = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
  jpeg = bytearray(data.tobytes())
  sof = jpeg.find(b"\xff\xc0")   # baseline frame header: height and width at +5 and +7
  jpeg[sof + 5:sof + 9] = struct.pack(">HH", 60000, 60000)
  (tmp_path / "big.jpg").write_bytes(bytes(jpeg))
  with pytest.raises(DataError, match="big.jpg: cannot decode image .more pixels than OpenCV"):
    decode_file(tmp_path / "big.jpg", "image")


def test_the_header_check_reads_opencv_io_max_image_pixels_as_opencv_does(tmp_path):
  """OPENCV_IO_MAX_IMAGE_PIXELS in OpenCV's size syntax (digits, then KB or MB: x 1024, x 1024^2)
  is the limit the PNG header check applies, the one OpenCV decodes under (a fresh process:
  OpenCV reads the setting once, when it loads). "1MB" was read as the default limit: a PNG of
  1100x1000 pixels passed the check and its decode then failed."""
  import subprocess
  import sys
  big, small = tmp_path / "big.png", tmp_path / "small.png"
  cv2.imwrite(str(big), np.zeros((1000, 1100), np.uint8))      # 1.1e6 > 2^20 pixels
  cv2.imwrite(str(small), np.zeros((1000, 1048), np.uint8))    # 1048000 <= 2^20
  code = """if True:
    import sys, cv2
    from pitta_jax.data.errors import DataError
    from pitta_jax.data.image_io import check_image_file
    for path in sys.argv[1:]:
      try:  # (None, or an error, by how OpenCV was told to report failures)
        opencv = cv2.imread(path, cv2.IMREAD_UNCHANGED) is not None
      except cv2.error:
        opencv = False
      try:
        check_image_file(path)
        ours = True
      except DataError as e:
        ours = str(e)
      print(opencv, ours)
  """
  for value, limit in [("1MB", 1 << 20), ("1mb", 1 << 20), ("1024Kb", 1 << 20),
                       ("1048576", 1 << 20)]:
    run = subprocess.run([sys.executable, "-c", code, str(big), str(small)], text=True,
                         capture_output=True, env={**os.environ,
                                                   "OPENCV_IO_MAX_IMAGE_PIXELS": value})
    assert run.returncode == 0, run.stderr
    (cv_big, ours_big), (cv_small, ours_small) = (line.split(" ", 1)
                                                  for line in run.stdout.splitlines())
    assert (cv_big, cv_small, ours_small) == ("False", "True", "True"), (value, run.stdout)
    assert ours_big.endswith(f"image of 1100x1000 pixels: more than OpenCV decodes ({limit} "
                             f"pixels)"), (value, ours_big)


def test_waymo_sequences_are_named_once_and_dense_npy_depth_is_float_metres(tmp_path):
  """sequences=s1,s1 (read twice, the repeat paired with the first as its previous frame and
  scored twice) is refused; names around commas are stripped; a dense depth .npy of integers
  (a PNG's metres x 256, read as 15352 m) is refused as the folder reader refuses it."""
  make_waymo(tmp_path, "s1")
  make_waymo(tmp_path, "s2")
  with pytest.raises(DataError, match=f"^{re.escape(str(tmp_path))}: sequences: s1 given more "
                                      f"than once"):
    waymo.open_waymo(tmp_path, sequences="s1,s2, s1")
  assert waymo.open_waymo(tmp_path, sequences="s1, s2").names[3] == "s2/000000"
  npy = tmp_path / "s1" / "depth" / "000001.npy"
  np.save(npy, (np.load(npy) * 256).astype(np.uint16))
  with pytest.raises(DataError, match=f"^{re.escape(str(npy))}: a dense depth .npy must hold "
                                      f"float metres, got uint16"):
    waymo.open_waymo(tmp_path, sequences="s1")[1]


def test_kitti_ext_in_capitals_finds_the_lowercase_files(tmp_path):
  """--option ext=JPG is accepted (the check ignores case) and finds KITTI's lowercase .jpg
  files; it had looked for .JPG only and reported every image as not found."""
  split, _, _ = make_kitti(tmp_path, ext="jpg")
  for ext in ("JPG", ".Jpg", "jpg"):
    frames = kitti.open_kitti(tmp_path / "data", split, depth=False, ext=ext)
    assert frames[0].image.shape == (H, W, 3)


def test_a_dense_depth_npy_that_is_an_npz_archive_is_named(tmp_path):
  """A dense depth map saved with np.savez under a .npy name (np.load opens any zip as an
  archive) is a one-line error naming the file, not an AttributeError on the archive."""
  make_waymo(tmp_path, "s1")
  npy = tmp_path / "s1" / "depth" / "000001.npy"
  with open(npy, "wb") as f:
    np.savez(f, depth=np.ones((2, 3), np.float32))
  with pytest.raises(DataError, match=f"^{re.escape(str(npy))}: cannot read .npy depth "
                                      f"\\(an .npz archive"):
    waymo.open_waymo(tmp_path, sequences="s1")[1]


def test_a_velodyne_scan_cut_short_by_whole_floats_is_refused(tmp_path):
  """A scan whose size is not a multiple of 16 bytes (one point) is refused, also when it is a
  multiple of 4 (cut 12 bytes short by an interrupted copy: it had read 19999 points)."""
  from pitta_jax.data.velodyne import read_velodyne_points
  scan = tmp_path / "0000000000.bin"
  np.arange(40, dtype="<f4").tofile(scan)   # 10 points
  assert read_velodyne_points(scan).shape == (10, 4)
  for cut in (1, 4, 12, 13):
    scan.write_bytes(np.arange(40, dtype="<f4").tobytes()[:-cut])
    with pytest.raises(DataError, match="is not a KITTI scan of float32"):
      read_velodyne_points(scan)


def test_kitti_split_lines_and_ext_option_are_checked_by_their_own_words(tmp_path):
  """A split file with a byte-order mark reads as without it; a frame number of non-ASCII
  digits is a bad line of the split file (not int()'s words); --option ext other than jpg or
  png is named (not pathlib's 'Invalid suffix')."""
  split, _, _ = make_kitti(tmp_path)
  split.write_bytes(b"\xef\xbb\xbf" + split.read_bytes())
  assert kitti.read_split(split)[0][0] == KITTI_LINES[0][0]
  split.write_text(f"{KITTI_LINES[0][0]} \u00b2 l\n", encoding="utf-8")
  with pytest.raises(DataError, match=f"^{re.escape(str(split))}: line 1 is"):
    kitti.read_split(split)
  for ext in ("", "a/b", "tif"):
    with pytest.raises(DataError, match=f"^--option ext={re.escape(ext)}: the KITTI images' "
                                        f"suffix is jpg or png"):
      kitti.open_kitti(tmp_path / "data", split, depth=False, ext=ext)


def test_segments_written_beside_jpeg_images_are_not_taken_for_the_images(tmp_path):
  """`pitta-jax segment --images D --out D` on JPEG images writes each stem's id PNG and its
  segments JSON into D; reading D as a folder (and Waymo's image/ directory) with those maps
  takes the JPEGs as the images and the PNGs as their panoptic maps. The PNG had won as the
  stem's image: the network adapted on RGB-encoded ids. A PNG beside another JSON (a labelme
  annotation) is still an image, preferred to a JPEG of its stem as before."""
  from pitta_jax.data import folder
  from pitta_jax.data.frame import Segment
  from pitta_jax.data.panoptic_io import write_panoptic
  ids = np.zeros((H, W), np.int32)
  ids[1:3, 2:5] = 7
  for k in range(2):
    cv2.imwrite(str(tmp_path / f"x{k}.jpg"), _rgb(k)[..., ::-1])
    write_panoptic(tmp_path / f"x{k}.png", ids, [Segment(7, 3, True)])
  frames = folder.open_folder(tmp_path, panoptic_dir=tmp_path)
  assert [f.image.suffix for f in frames.files] == [".jpg", ".jpg"]
  frame = frames[0]
  assert frame.image_file == str(tmp_path / "x0.jpg")
  np.testing.assert_array_equal(frame.panoptic, ids)
  assert frame.image.shape == (H, W, 3)
  _write_rgb(tmp_path / "y.png", _rgb(5))  # a user's PNG with a labelme JSON and a JPEG
  (tmp_path / "y.json").write_text(json.dumps({"version": "5.0", "shapes": []}))
  cv2.imwrite(str(tmp_path / "y.jpg"), _rgb(6)[..., ::-1])
  assert folder.open_folder(tmp_path).files[2].image == tmp_path / "y.png"
  seq = tmp_path / "w" / "s1"
  for k in range(2):
    (seq / "image").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(seq / "image" / f"{k:06d}.jpg"), _rgb(k)[..., ::-1])
    write_panoptic(seq / "image" / f"{k:06d}.png", ids, [Segment(7, 3, True)])
  got = waymo.open_waymo(tmp_path / "w", depth=False)
  assert [f.image.suffix for f in got.files] == [".jpg", ".jpg"]


def test_calib_json_sizes_must_be_integers_not_booleans(tmp_path):
  from pitta_jax.data.calib import read_calib_json
  j = tmp_path / "calib.json"
  j.write_text(json.dumps({"K": np.eye(3).tolist(), "width": True, "height": 6}))
  with pytest.raises(DataError, match="width and height must be positive integers"):
    read_calib_json(j)


def test_panoptic_maps_from_two_flags_or_an_empty_path_option_are_refused(tmp_path, capsys):
  """--option panoptic_dir=A with --segmentation png:B (B had silently won) or mask2former:DIR
  (whose maps replace the frames' own) is refused naming both flags, before the weights load;
  png:DIR with --option panoptic_json (the annotation file of those PNGs) is not. An empty path
  option (--option panoptic_dir=, read as the working directory) is refused naming it."""
  from pitta_jax.cli import main
  from pitta_jax.sources import check_dataset_args
  make_waymo(tmp_path / "waymo", "segment-a", n=2)
  weights = tmp_path / "w"  # a model.json only: loading the weights would fail
  weights.mkdir()
  (weights / "model.json").write_text(json.dumps({"architecture": "monodepth2", "num_layers": 18,
                                                  "height": 64, "width": 96}))
  base = ["adapt", "--dataset", "waymo", "--root", str(tmp_path / "waymo"), "--weights",
          str(weights), "--out", str(tmp_path / "o")]
  for extra, want in [
      (["--option", "panoptic_dir=A", "--segmentation", "png:B"],
       "error: --option panoptic_dir and --segmentation png:B both say where the panoptic maps "
       "come from: give one\n"),
      (["--option", "panoptic_json=a.json", "--segmentation", "mask2former:M"],
       "error: --option panoptic_json and --segmentation mask2former:M both say where the "
       "panoptic maps come from: give one\n"),
      (["--option", "panoptic_dir="], "error: --option panoptic_dir= names no file or "
                                      "directory\n")]:
    assert main(base + extra) == 2
    assert capsys.readouterr().err == want
  assert check_dataset_args("waymo", str(tmp_path), ["panoptic_json=a.json"], "png:B") == {
      "panoptic_json": "a.json"}
  assert check_dataset_args("waymo", str(tmp_path), ["sequences="], "gt") == {"sequences": ""}


def test_an_option_selecting_no_frame_fails_before_the_weights_load(tmp_path, capsys):
  from pitta_jax.cli import main
  make_waymo(tmp_path / "waymo", "segment-a", n=2)
  weights = tmp_path / "w"  # a model.json only: loading the weights would fail
  weights.mkdir()
  (weights / "model.json").write_text(json.dumps({"architecture": "monodepth2", "num_layers": 18,
                                                  "height": 64, "width": 96}))
  rc = main(["adapt", "--dataset", "waymo", "--root", str(tmp_path / "waymo"), "--option",
             "sequences=", "--weights", str(weights), "--out", str(tmp_path / "o")])
  err = capsys.readouterr().err
  assert rc == 2 and "no frames to adapt on" in err and err.count("\n") == 1, err


def _png_chunk(kind: bytes, data: bytes) -> bytes:
  import struct
  import zlib
  return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def test_gray_alpha_png_is_refused_like_grayscale(tmp_path):
  """A grayscale + alpha PNG (colour type 4), written byte by byte from the PNG spec: OpenCV
  decodes it as 4 BGRA channels, yet it holds no colour."""
  import struct
  import zlib
  h, w = 4, 6
  rows = b"".join(b"\x00" + bytes([90, 255] * w) for _ in range(h))  # filter 0, (gray, alpha)
  png = (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 4, 0, 0, 0))
         + _png_chunk(b"IDAT", zlib.compress(rows)) + _png_chunk(b"IEND", b""))
  (tmp_path / "la.png").write_bytes(png)
  assert cv2.imread(str(tmp_path / "la.png"), cv2.IMREAD_UNCHANGED).shape == (h, w, 4)
  with pytest.raises(DataError, match=r"la\.png: grayscale image"):
    read_image(tmp_path / "la.png")
  # taken where a user's images are read (predict, segment): the gray value in R, G and B
  np.testing.assert_array_equal(read_image(tmp_path / "la.png", gray=True),
                                np.full((h, w, 3), np.float32(90) / np.float32(255)))


def test_recording_starts_survive_slices_joins_and_maps(tmp_path):
  """Frames start a recording where FrameFiles.recording changes; a slice keeps its frames'
  marks (a resumed run slices at frame k and must see what an uninterrupted run saw), a join
  starts one at the joint, a transform keeps them."""
  images = []
  for k in range(5):
    _write_rgb(tmp_path / f"{k}.png", _rgb(k))
    images.append(tmp_path / f"{k}.png")
  files = [FrameFiles(name=str(k), image=images[k], recording=rec)
           for k, rec in enumerate("aabbb")]
  seq = FrameSequence(files, temporal=True)
  marks = lambda s: [f.starts_recording for f in s]
  assert marks(seq) == [True, False, True, False, False]
  assert marks(seq[1:]) == [False, True, False, False] and marks(seq[3:]) == [False, False]
  assert marks(seq[3:] + seq[:2]) == [False, False, True, False]
  assert marks(seq.map(lambda f: dataclasses.replace(f, name=f.name + "!"))) == marks(seq)
  with pytest.raises(ValueError, match="starts has 2 values for 5 frames"):
    FrameSequence(files, starts=[True, False])


def test_a_join_of_sequences_with_other_transforms_keeps_each_and_reads_nothing(tmp_path,
                                                                               monkeypatch):
  """Two readers' sequences (each its own resize) joined: each frame gets its own sequence's
  transform, nothing is read until a frame is indexed, and the second part starts a recording;
  a join and a slice of joins still do (the tables join a case's parts so)."""
  for k in range(4):
    _write_rgb(tmp_path / f"{k}.png", _rgb(k))
  files = [FrameFiles(name=str(k), image=tmp_path / f"{k}.png", recording="r") for k in range(4)]
  tag = lambda t: (lambda f: dataclasses.replace(f, name=f.name + t))
  a = FrameSequence(files[:2], tag("a"), temporal=True)
  b = FrameSequence(files[2:], tag("b"), temporal=True)
  loads = []
  real = FrameFiles.load
  monkeypatch.setattr(FrameFiles, "load", lambda self: loads.append(self.name) or real(self))
  joined = a + b
  assert loads == [] and joined.names == ("0", "1", "2", "3") and joined.temporal
  got = list(joined)
  assert [f.name for f in got] == ["0a", "1a", "2b", "3b"]
  assert [f.starts_recording for f in got] == [True, False, True, False]
  assert loads == ["0", "1", "2", "3"]  # each frame read once, when indexed
  three = joined + FrameSequence(files[:1], tag("c"))
  assert [f.name for f in three[1:]] == ["1a", "2b", "3b", "0c"]
  assert [f.starts_recording for f in three[1:]] == [False, True, False, True]
  assert [f.name for f in joined.map(tag("!"))] == ["0a!", "1a!", "2b!", "3b!"]


def test_joined_frames_read_each_part_on_access_and_mark_where_parts_start():
  """JoinedFrames (a synthetic test case's parts): frame k is the frame of its part, rendered
  when read (SyntheticSequence), each part's first frame starting a recording; slices (a run
  resumed at frame k) keep the marks of the frames they hold; names without rendering."""
  from pitta_jax.data.sequence import JoinedFrames
  from pitta_jax.data.synthetic import SyntheticConfig, SyntheticSequence, generate_sequence
  cfgs = [SyntheticConfig(height=16, width=24, num_frames=n, seed=s, domain=d)
          for n, s, d in ((3, 1, "fog"), (1, 2, "clear"), (2, 3, "rain"))]
  eager = [f for cfg in cfgs for f in generate_sequence(cfg)]
  joined = JoinedFrames([SyntheticSequence(cfg) for cfg in cfgs])
  assert len(joined) == 6 and joined.names == tuple(f.name for f in eager)
  got = list(joined)
  for a, b in zip(got, eager):
    assert a.name == b.name
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.depth, b.depth)
  assert [f.starts_recording for f in got] == [True, False, False, True, True, False]
  assert [f.name for f in joined[2:5]] == [f.name for f in eager[2:5]]
  assert [f.starts_recording for f in joined[2:]] == [False, True, True, False]
  assert [f.starts_recording for f in joined[4:][1:]] == [False]
  assert joined[-1].name == eager[-1].name and len(joined[6:]) == 0
  with pytest.raises(IndexError):
    joined[6]


@pytest.mark.parametrize("orientation", [1, 3, 6, 8, 2, 5])
def test_exif_orientation_as_pil_turns_it(tmp_path, orientation):
  """A JPEG stored 8x12 with an EXIF orientation (6: a phone held upright) is turned as PIL's
  ImageOps.exif_transpose turns it (the reference; cv2.imread in Depth Anything V2's run.py
  does the same), for rotations and flips; read_image alone keeps the stored pixels."""
  from PIL import Image, ImageOps
  from pitta_jax.data.image_io import exif_upright
  rng = np.random.default_rng(orientation)
  stored = np.repeat(np.repeat(rng.integers(0, 256, (4, 6, 3), dtype=np.uint8), 2, 0), 2, 1)
  img = Image.fromarray(stored)
  exif = img.getexif()
  exif[0x0112] = orientation
  path = tmp_path / "phone.jpg"
  img.save(path, quality=100, exif=exif)
  ours = exif_upright(path, read_image(path))
  with Image.open(path) as im:
    ref = np.asarray(ImageOps.exif_transpose(im).convert("RGB"), np.float32) / 255
  assert read_image(path).shape == (8, 12, 3) and ours.shape == ref.shape
  assert np.abs(ours - ref).mean() < 2 / 255  # two JPEG decoders, the same pixels


def test_exif_orientation_big_endian_and_in_png_and_no_decode_without_it(tmp_path, monkeypatch):
  """The orientation entry as a big-endian (Motorola) TIFF directory stores it, in a JPEG's APP1
  and in a PNG's eXIf chunk, turns the image as PIL does (OpenCV applies both); a file without
  an orientation entry is not decoded again."""
  import struct
  from PIL import Image, ImageOps
  from pitta_jax.data import image_io
  stored = np.repeat(np.repeat(np.random.default_rng(7).integers(0, 256, (4, 6, 3), np.uint8),
                               2, 0), 2, 1)
  tiff = (b"MM\x00\x2a" + struct.pack(">I", 8) + struct.pack(">H", 1)
          + struct.pack(">HHIHH", 0x0112, 3, 1, 6, 0) + struct.pack(">I", 0))
  Image.fromarray(stored).save(tmp_path / "be.jpg", quality=100, exif=b"Exif\x00\x00" + tiff)
  img = Image.fromarray(stored)
  exif = img.getexif()
  exif[0x0112] = 8
  img.save(tmp_path / "turned.png", exif=exif)
  for name in ("be.jpg", "turned.png"):
    ours = image_io.exif_upright(tmp_path / name, read_image(tmp_path / name))
    with Image.open(tmp_path / name) as im:
      ref = np.asarray(ImageOps.exif_transpose(im).convert("RGB"), np.float32) / 255
    assert ours.shape == ref.shape == (12, 8, 3)
    assert np.abs(ours - ref).mean() < 2 / 255
  Image.fromarray(stored).save(tmp_path / "plain.jpg", quality=100)
  image = read_image(tmp_path / "plain.jpg")
  decodes = []
  monkeypatch.setattr(image_io.cv2, "imdecode", lambda *a: decodes.append(a))
  assert image_io.exif_upright(tmp_path / "plain.jpg", image) is image and decodes == []


# ---------------------------------------------------------------------------------------------
# Values that only a non-default setting shows (from a mutation campaign: each of these changed
# nothing the tests above read)


def test_folder_depth_scale_divides_the_stored_values(tmp_path):
  # Hand values: stored 1000 and 250 read as 1.0 and 0.25 m at depth_scale 1000, 1000 / 256 m
  # at the default (KITTI's 256).
  _write_rgb(tmp_path / "img" / "a.png", _rgb(0))
  stored = np.full((H, W), 1000, np.uint16)
  stored[0, :] = 250
  _write_u16(tmp_path / "depth" / "a.png", stored)
  want = np.full((H, W), 1.0, np.float32)
  want[0, :] = 0.25
  frames = readers.open_dataset("folder", tmp_path / "img", depth_dir=tmp_path / "depth",
                                depth_scale=1000)
  np.testing.assert_array_equal(frames[0].depth, want)
  frames = readers.open_dataset("folder", tmp_path / "img", depth_dir=tmp_path / "depth")
  np.testing.assert_array_equal(frames[0].depth, stored.astype(np.float32) / np.float32(256))


def test_a_16_bit_colour_png_is_rgb_over_65535(tmp_path):
  # Hand values: a pure blue, a full white and a mid-grey pixel written by OpenCV (BGR order).
  bgr = np.zeros((1, 3, 3), np.uint16)
  bgr[0, 0] = (65535, 0, 0)            # blue
  bgr[0, 1] = (65535, 65535, 65535)    # white
  bgr[0, 2] = (0, 32768, 65535)        # red 1, green 32768 / 65535, blue 0
  _write_u16(tmp_path / "a.png", bgr)
  got = read_image(tmp_path / "a.png")
  assert got.dtype == np.float32
  np.testing.assert_array_equal(got[0, 0], [0, 0, 1])
  np.testing.assert_array_equal(got[0, 1], [1, 1, 1])
  np.testing.assert_array_equal(got[0, 2], np.float32([1, 32768 / 65535, 0]))


def test_write_depth_png_rounds_and_keeps_small_depths_valid(tmp_path):
  # Hand values at scale 256, read back by OpenCV: 10.999 m -> round(2815.7) = 2816; 0.001 m
  # -> 1 (valid depths never become 0, the invalid mark); 0, negative, NaN, inf -> 0; 300 m ->
  # 65535 (saturates).
  depth = np.array([[10.999, 0.001, 0.0, -1.0, np.nan, np.inf, 300.0]])
  write_depth_png(tmp_path / "d.png", depth)
  stored = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
  assert stored.dtype == np.uint16
  np.testing.assert_array_equal(stored, [[2816, 1, 0, 0, 0, 0, 65535]])


def test_list_images_prefers_png_over_jpeg(tmp_path):
  from pitta_jax.data.image_io import list_images
  for name in ("a.jpg", "a.png", "b.jpeg", "b.jpg", "c.jpg"):
    _write_rgb(tmp_path / name, _rgb(0))
  found = list_images(tmp_path)
  assert {stem: path.name for stem, path in found.items()} == {
      "a": "a.png", "b": "b.jpg", "c": "c.jpg"}


def test_kitti_split_side_3_is_the_right_camera(tmp_path):
  # MonoDepth2's side map: "l" and "2" camera 2, "r" and "3" camera 3.
  folder = "2011_09_26/2011_09_26_drive_0002_sync"
  for camera in (2, 3):
    _write_rgb(tmp_path / "data" / folder / f"image_0{camera}" / "data" / "0000000007.png",
               _rgb(camera))
  split = tmp_path / "test_files.txt"
  split.write_text(f"{folder} 7 3\n{folder} 7 2\n")
  frames = kitti.open_kitti(tmp_path / "data", split, depth=False)
  for frame, camera in zip(frames, (3, 2)):
    np.testing.assert_array_equal(frame.image, _rgb(camera).astype(np.float32) / np.float32(255))


def test_kitti_gt_depths_in_fortran_order(tmp_path):
  # A plain float npz saved from a Fortran-ordered array reads back as the same maps.
  maps = np.asfortranarray(np.arange(3 * H * W, dtype=np.float32).reshape(3, H, W))
  np.savez(tmp_path / "gt.npz", data=maps)
  for got, want in zip(kitti.load_gt_depths(tmp_path / "gt.npz"), maps):
    np.testing.assert_array_equal(got, want)


def _generate_depth_map_upstream(calib_dir: Path, velo_filename: Path, cam: int = 2,
                                 vel_depth: bool = False) -> np.ndarray:
  """MonoDepth2's kitti_utils.generate_depth_map, written as upstream writes it (NumPy,
  float64, its sub2ind and its duplicate loop): the reference for a non-identity R_rect_00."""
  from collections import Counter

  def read_calib_file(path):
    data = {}
    for line in Path(path).read_text().splitlines():
      key, value = line.split(":", 1)
      try:
        data[key] = np.array([float(x) for x in value.split()])
      except ValueError:
        pass
    return data

  cam2cam = read_calib_file(calib_dir / "calib_cam_to_cam.txt")
  velo2cam = read_calib_file(calib_dir / "calib_velo_to_cam.txt")
  velo2cam = np.hstack((velo2cam["R"].reshape(3, 3), velo2cam["T"][..., np.newaxis]))
  velo2cam = np.vstack((velo2cam, np.array([0, 0, 0, 1.0])))
  im_shape = cam2cam["S_rect_02"][::-1].astype(np.int32)
  R_cam2rect = np.eye(4)
  R_cam2rect[:3, :3] = cam2cam["R_rect_00"].reshape(3, 3)
  P_rect = cam2cam["P_rect_0" + str(cam)].reshape(3, 4)
  P_velo2im = np.dot(np.dot(P_rect, R_cam2rect), velo2cam)
  velo = np.fromfile(velo_filename, dtype=np.float32).reshape(-1, 4)
  velo[:, 3] = 1.0
  velo = velo[velo[:, 0] >= 0, :]
  velo_pts_im = np.dot(P_velo2im, velo.T).T
  velo_pts_im[:, :2] = velo_pts_im[:, :2] / velo_pts_im[:, 2][..., np.newaxis]
  if vel_depth:
    velo_pts_im[:, 2] = velo[:, 0]
  velo_pts_im[:, 0] = np.round(velo_pts_im[:, 0]) - 1
  velo_pts_im[:, 1] = np.round(velo_pts_im[:, 1]) - 1
  val_inds = (velo_pts_im[:, 0] >= 0) & (velo_pts_im[:, 1] >= 0)
  val_inds = val_inds & (velo_pts_im[:, 0] < im_shape[1]) & (velo_pts_im[:, 1] < im_shape[0])
  velo_pts_im = velo_pts_im[val_inds, :]
  depth = np.zeros((im_shape[:2]))
  depth[velo_pts_im[:, 1].astype(int), velo_pts_im[:, 0].astype(int)] = velo_pts_im[:, 2]
  m, n = depth.shape
  inds = velo_pts_im[:, 1] * (n - 1) + velo_pts_im[:, 0] - 1
  dupe_inds = [item for item, count in Counter(inds).items() if count > 1]
  for dd in dupe_inds:
    pts = np.where(inds == dd)[0]
    x_loc = int(velo_pts_im[pts[0], 0])
    y_loc = int(velo_pts_im[pts[0], 1])
    depth[y_loc, x_loc] = velo_pts_im[pts, 2].min()
  depth[depth < 0] = 0
  return depth


def test_velodyne_depth_with_a_rotated_rectification_matches_upstream(tmp_path):
  """R_rect_00 a rotation of ~1 degree (KITTI's are of this size; the fixture above has the
  identity), 400 random points in front: the map equals upstream's generate_depth_map, with
  the Velodyne x (export_gt_depth.py) and with the camera's z as depth, for both cameras."""
  from pitta_jax.data.velodyne import velodyne_depth
  a, b = 0.02, -0.015
  Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
  Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
  R = " ".join(f"{x:.9e}" for x in (Rx @ Ry).ravel())
  date = tmp_path / "date"
  date.mkdir()
  (date / "calib_velo_to_cam.txt").write_text(VELO_CALIB)
  (date / "calib_cam_to_cam.txt").write_text(VELO_CAM_CALIB.replace(
      "R_rect_00: 1 0 0 0 1 0 0 0 1", f"R_rect_00: {R}"))
  rng = np.random.default_rng(7)
  points = np.stack([rng.uniform(-1, 20, 400), rng.uniform(-8, 8, 400),
                     rng.uniform(-3, 3, 400)], axis=1)
  _write_velodyne(tmp_path / "scan.bin", [tuple(p) for p in points])
  for camera in (2, 3):
    for vel_depth in (True, False):
      want = _generate_depth_map_upstream(date, tmp_path / "scan.bin", camera, vel_depth)
      got = velodyne_depth(date, tmp_path / "scan.bin", camera=camera, vel_depth=vel_depth)
      assert np.count_nonzero(want) > 10
      np.testing.assert_array_equal(got, want.astype(np.float32))


def test_a_damaged_compressed_gt_depths_names_the_file(tmp_path):
  """MonoDepth2's export_gt_depth.py writes gt_depths.npz with np.savez_compressed; deflate
  data damaged on disk (here a first block of the reserved type 3, which zlib refuses) is a
  one-line DataError naming the file when the split is opened and when the maps load, not
  zlib's own error (a traceback from the commands)."""
  split, _, maps = make_kitti(tmp_path)
  gt = split.parent / "gt_depths.npz"
  _save_object_npz(gt, maps)
  with zipfile.ZipFile(gt) as archive:
    info = archive.getinfo("data.npy")
  assert info.compress_type == zipfile.ZIP_DEFLATED
  raw = bytearray(gt.read_bytes())
  name_len, extra_len = (int.from_bytes(raw[info.header_offset + k:info.header_offset + k + 2],
                                        "little") for k in (26, 28))
  start = info.header_offset + 30 + name_len + extra_len  # the member's compressed bytes
  raw[start:start + 16] = b"\xff" * 16
  gt.write_bytes(bytes(raw))
  pattern = rf"^{re.escape(str(gt))}: not a readable \.npz file \(.*\)$"
  with pytest.raises(DataError, match=pattern):
    kitti.open_kitti(tmp_path / "data", split)
  with pytest.raises(DataError, match=pattern):
    kitti.load_gt_depths(gt)
