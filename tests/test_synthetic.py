"""The synthetic driving benchmark (`pitta_jax.data.synthetic`).

References, independent of the renderer's code path: closed-form pinhole depths of the road
plane, the raised sidewalk and the curb faces (z = h fy / (i - cy), z = (h - 0.15) fy / (i - cy),
z = (X - X_cam) fx / (j - cx)); the ray-plane inequality behind every object standing on the
road; Koschmieder's fog law written out per pixel from the clear image and the depth; files read
back with OpenCV and decoded by hand (uint16 / 256, id = R + 256 G + 256^2 B).
"""

from __future__ import annotations

import dataclasses
import json
import re

import cv2
import numpy as np
import pytest

from pitta_jax.data.frame import Frame
from pitta_jax.data.synthetic import (COCO_BICYCLE, COCO_CAR, COCO_PERSON, COCO_TRUCK, DOMAINS,
                                      FOG_AIRLIGHT, FOG_BETA_MAX, STUFF_CATEGORY, THING_ID_BASE,
                                      SyntheticConfig, SyntheticSequence, export_drivingstereo,
                                      generate_sequence, iter_domains, render_frame)
from pitta_jax.data.synthetic import config as C
from pitta_jax.data.synthetic import scene

H, W = 96, 320
CFG = SyntheticConfig(height=H, width=W, num_frames=4, start=10, seed=3)
FX, FY, CX, CY = 0.58 * W, 1.92 * H, 0.5 * W, 0.5 * H      # MonoDepth2's normalised KITTI K
CAM_H = 1.65


@pytest.fixture(scope="module")
def domains() -> list[dict[str, Frame]]:
  """CFG's frames in every domain: [index][domain] -> Frame."""
  return list(iter_domains(CFG))


def _rows_cols():
  return np.mgrid[0:H, 0:W]


def test_frames_have_the_frame_format(domains):
  for per_domain in domains:
    for d, fr in per_domain.items():
      assert fr.image.shape == (H, W, 3) and fr.image.dtype == np.float32
      assert fr.depth.shape == (H, W) and fr.depth.dtype == np.float32
      assert fr.panoptic.shape == (H, W) and fr.panoptic.dtype == np.int32
      assert np.isfinite(fr.image).all() and fr.image.min() >= 0 and fr.image.max() <= 1
      assert re.fullmatch(rf"{d}/3/\d{{6}}", fr.name)
  assert [f["clear"].name for f in domains] == [f"clear/3/{i:06d}" for i in range(10, 14)]


def test_same_config_is_bitwise_identical_and_seeds_differ():
  cfg = dataclasses.replace(CFG, num_frames=2, domain="rain")
  a, b = generate_sequence(cfg), generate_sequence(cfg)
  for x, y in zip(a, b):
    for field in ("image", "depth", "panoptic"):
      np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
    assert x.segments == y.segments and x.name == y.name
  other = generate_sequence(dataclasses.replace(cfg, seed=4))
  assert not np.array_equal(a[0].image, other[0].image)
  assert not np.array_equal(a[0].panoptic, other[0].panoptic)


def test_random_access_equals_sequential_generation():
  """A frame does not depend on which frames were generated before it (block caches)."""
  cfg = dataclasses.replace(CFG, domain="night", num_frames=3)
  seq = generate_sequence(cfg)
  single = render_frame(cfg, cfg.start + 2)
  np.testing.assert_array_equal(seq[2].image, single.image)
  np.testing.assert_array_equal(seq[2].depth, single.depth)
  np.testing.assert_array_equal(seq[2].panoptic, single.panoptic)


def test_a_long_sequence_is_rendered_as_it_is_read():
  """SyntheticSequence (what `adapt` runs on) holds the frames of generate_sequence, rendered
  on access: a sequence of 10^7 frames opens at once (every frame used to be rendered first),
  its slices (a resumed run) are the same frames, and its names need no render. Beyond what
  the renderer draws exactly (frame 5e7 had non-finite pixels) the config is refused."""
  cfg = dataclasses.replace(CFG, domain="rain", num_frames=4, start=3)
  listed, lazy = generate_sequence(cfg), SyntheticSequence(cfg)
  assert len(lazy) == 4 and lazy.names == tuple(f.name for f in listed)
  for want, got in zip(listed[1:], lazy[1:]):
    assert got.name == want.name
    for field in ("image", "depth", "panoptic", "intrinsics"):
      np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
  np.testing.assert_array_equal(lazy[-1].image, listed[-1].image)
  assert [f.name for f in lazy[::2]] == [listed[0].name, listed[2].name]
  with pytest.raises(IndexError):
    lazy[4]
  huge = SyntheticSequence(dataclasses.replace(cfg, num_frames=10**7 - 3))
  last = huge[-1]
  assert len(huge) == 10**7 - 3 and last.name == f"rain/{cfg.seed}/{10**7 - 1:06d}"
  assert np.isfinite(last.image).all() and np.isfinite(last.depth).all()
  with pytest.raises(ValueError, match="num_frames: frames up to 1000000000 drive"):
    dataclasses.replace(cfg, num_frames=10**9 - 3)


def test_road_depth_is_the_pinhole_closed_form(domains):
  ii, _ = _rows_cols()
  for per_domain in domains:
    fr = per_domain["clear"]
    road = fr.panoptic == C.ROAD_ID
    assert road.sum() > 0.1 * H * W
    assert (ii[road] > CY).all()
    expected = CAM_H * FY / (ii[road] - CY)
    got = fr.depth[road]
    near = expected <= CFG.max_depth
    np.testing.assert_allclose(got[near], expected[near], rtol=2e-6)
    assert (got[~near] == 0).all()                                # beyond max_depth: invalid
    print("max |road depth - closed form|:", np.abs(got[near] - expected[near]).max())


def test_pavement_depth_is_sidewalk_top_ground_or_curb(domains):
  street = scene.Street(CFG)
  ii, jj = _rows_cols()
  for per_domain in domains:
    fr = per_domain["clear"]
    pave = (fr.panoptic == C.PAVEMENT_ID) & (fr.depth > 0)
    i, j, z = ii[pave], jj[pave], fr.depth[pave].astype(np.float64)
    candidates = [CAM_H * FY / (i - CY), (CAM_H - 0.15) * FY / (i - CY)]
    for x_curb in (street.curb, -street.curb):
      with np.errstate(divide="ignore"):
        candidates.append((x_curb - street.ego_x) * FX / (j - CX))
    err = np.min([np.abs(z - c) / z for c in candidates], axis=0)
    assert err.max() < 1e-5, err.max()


def test_sky_is_invalid_and_above_the_horizon(domains):
  ii, _ = _rows_cols()
  for per_domain in domains:
    fr = per_domain["clear"]
    sky = fr.panoptic == C.SKY_ID
    assert sky.any()
    assert (fr.depth[sky] == 0).all() and (ii[sky] <= CY).all()   # row cy: parallel rays
    valid = fr.depth > 0
    assert valid.mean() > 0.5
    assert fr.depth[valid].min() > 0.1 and fr.depth.max() <= CFG.max_depth


def test_panoptic_segments_match_the_id_map(domains):
  for per_domain in domains:
    fr = per_domain["clear"]
    ids = set(np.unique(fr.panoptic).tolist())
    assert 0 not in ids and max(ids) < 2 ** 16                     # all labelled, small ids
    assert ids == {s.id for s in fr.segments}
    for s in fr.segments:
      if s.id < THING_ID_BASE:
        assert not s.isthing and s.category_id == STUFF_CATEGORY[s.id]
      else:
        assert s.isthing and s.category_id in (COCO_PERSON, COCO_BICYCLE, COCO_CAR, COCO_TRUCK)
  things = [s for f in domains for s in f["clear"].segments if s.isthing]
  n_per_frame = len(things) / len(domains)
  assert 3 <= n_per_frame <= 60, n_per_frame
  cats = {s.category_id for s in things}
  assert COCO_CAR in cats and COCO_PERSON in cats


def test_objects_occlude_the_road_behind_them(domains):
  """A point above the road plane on a downward ray is nearer than the ray's road hit."""
  ii, _ = _rows_cols()
  for per_domain in domains:
    fr = per_domain["clear"]
    thing = (fr.panoptic >= THING_ID_BASE) & (ii > CY) & (fr.depth > 0)
    assert thing.any()
    road_behind = CAM_H * FY / (ii[thing] - CY)
    assert (fr.depth[thing] <= road_behind * (1 + 1e-6)).all()


def test_objects_move_between_frames(domains):
  """Instances within 25 m (ego motion 0.8 m / frame, most also move themselves) shift in the
  image; the lead car (stream 10) drives with the camera and is left out."""
  def centroids(fr):
    out = {}
    for i in np.unique(fr.panoptic[fr.panoptic >= THING_ID_BASE]):
      ys, xs = np.nonzero(fr.panoptic == i)
      if len(ys) >= 20 and np.median(fr.depth[ys, xs]) < 25 and (i - THING_ID_BASE) // 4096 != 10:
        out[int(i)] = (ys.mean(), xs.mean())
    return out
  shifts = []
  for f0, f1 in zip(domains[:-1], domains[1:]):
    c0, c1 = centroids(f0["clear"]), centroids(f1["clear"])
    shifts += [np.hypot(*np.subtract(c0[k], c1[k])) for k in c0.keys() & c1.keys()]
  assert len(shifts) >= 3
  assert min(shifts) > 0.05, shifts


def test_world_motion_of_objects():
  """Parked cars keep their world position; oncoming cars and pedestrians move by v / fps."""
  street = scene.Street(CFG)
  a, b = street.frame(20), street.frame(21)

  def centres(sc):
    out = {}
    for seg in np.unique(sc.boxes[:, scene.SEG]):
      if seg >= THING_ID_BASE:
        rows = sc.boxes[sc.boxes[:, scene.SEG] == seg]
        out[int(seg)] = 0.5 * (rows[:, scene.Z0].min() + rows[:, scene.Z1].max())
    return out
  ca, cb = centres(a), centres(b)
  speeds = {st.code: st.speed for st in street.streams}
  checked = 0
  for seg in ca.keys() & cb.keys():
    code = (seg - THING_ID_BASE) // 4096                           # the object's stream
    if code in speeds:
      assert cb[seg] - ca[seg] == pytest.approx(speeds[code] / CFG.fps, abs=1e-6), code
      checked += 1
  assert checked >= 3
  assert b.camera[2] - a.camera[2] == pytest.approx(CFG.speed / CFG.fps)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_objects_do_not_interpenetrate(seed):
  """No two objects (bounding boxes of their boxes) and no object and a static box (building,
  pole, sidewalk) overlap in volume, except a rider on a bicycle (stream codes 8 and 9;
  thing ids are 16 + 4096 code + slot)."""
  street = scene.Street(dataclasses.replace(CFG, seed=seed, n_cars=14, n_pedestrians=12,
                                            n_cyclists=3, n_lead_cars=2))
  eps = 1e-6
  for index in (0, 37, 250, 1234):
    sc = street.frame(index)
    bx = sc.boxes
    thing = bx[:, scene.SEG] >= THING_ID_BASE
    objs = {}
    for seg in np.unique(bx[thing, scene.SEG]).astype(int):
      rows = bx[bx[:, scene.SEG] == seg]
      objs[seg] = np.concatenate([rows[:, [scene.X0, scene.H0, scene.Z0]].min(0),
                                  rows[:, [scene.X1, scene.H1, scene.Z1]].max(0)])
    lo_hi = np.array(list(objs.values()))                         # (n, 6): mins, maxs
    overlap = ((lo_hi[:, None, :3] < lo_hi[None, :, 3:] - eps)
               & (lo_hi[None, :, :3] < lo_hi[:, None, 3:] - eps)).all(-1)
    segs = np.array(list(objs))
    for i, j in zip(*np.nonzero(np.triu(overlap, 1))):
      assert abs(segs[i] - segs[j]) == 4096, (index, segs[i], segs[j])   # rider on bike
    static = bx[~thing][:, [scene.X0, scene.H0, scene.Z0, scene.X1, scene.H1, scene.Z1]]
    tb = bx[thing][:, [scene.X0, scene.H0, scene.Z0, scene.X1, scene.H1, scene.Z1]]
    hit = ((tb[:, None, :3] < static[None, :, 3:] - eps)
           & (static[None, :, :3] < tb[:, None, 3:] - eps)).all(-1)
    assert not hit.any(), (index, np.argwhere(hit)[:3])


@pytest.mark.parametrize("domain", DOMAINS[1:])
def test_domains_change_the_image_only(domains, domain):
  for per_domain in domains:
    clear, fr = per_domain["clear"], per_domain[domain]
    np.testing.assert_array_equal(fr.depth, clear.depth)
    np.testing.assert_array_equal(fr.panoptic, clear.panoptic)
    assert fr.segments == clear.segments
    assert np.abs(fr.image - clear.image).mean() > 0.02


def test_fog_is_koschmieder_law(domains):
  ii, jj = _rows_cols()
  ray = np.sqrt(1 + ((jj - CX) / FX) ** 2 + ((ii - CY) / FY) ** 2)
  beta = FOG_BETA_MAX * CFG.severity
  for per_domain in domains:
    clear, fog = per_domain["clear"], per_domain["fog"]
    valid = clear.depth > 0
    t = np.exp(-beta * clear.depth * ray)[..., None]
    expected = clear.image * t + FOG_AIRLIGHT * (1 - t)
    np.testing.assert_allclose(fog.image[valid], expected[valid], atol=2e-5)
    sky = clear.panoptic == C.SKY_ID
    np.testing.assert_allclose(fog.image[sky], np.broadcast_to(FOG_AIRLIGHT, (sky.sum(), 3)),
                               atol=1e-6)
    print("max |fog - I t - A (1 - t)|:", np.abs(fog.image[valid] - expected[valid]).max())


def test_severity_scales_the_shift():
  cfg = dataclasses.replace(CFG, num_frames=1)
  clear = render_frame(cfg, cfg.start).image
  diffs = {}
  for sev in (0.2, 0.9):
    for d in DOMAINS[1:]:
      img = render_frame(dataclasses.replace(cfg, domain=d, severity=sev), cfg.start).image
      diffs[d, sev] = np.abs(img - clear).mean()
  for d in DOMAINS[1:]:
    assert diffs[d, 0.9] > diffs[d, 0.2], d


def test_any_size_renders():
  cfg = SyntheticConfig(height=37, width=101, num_frames=2, seed=9, domain="snow")
  frames = generate_sequence(cfg)
  assert len(frames) == 2 and frames[0].image.shape == (37, 101, 3)
  assert frames[1].depth.shape == (37, 101)


def test_config_validation():
  with pytest.raises(ValueError):
    SyntheticConfig(domain="hail")
  with pytest.raises(ValueError):
    SyntheticConfig(severity=1.5)


def test_export_drivingstereo_layout_round_trip(domains, tmp_path):
  frames = [f["rain"] for f in domains[:2]]
  stems = export_drivingstereo(frames, tmp_path, "rainy")
  assert stems[0] == "2018-10-25-07-37-26_2018-10-25-07-37-26-000"
  assert stems[1] == "2018-10-25-07-37-26_2018-10-25-07-37-26-100"
  base = tmp_path / "rainy"
  for name, fr in zip(stems, frames):
    assert re.fullmatch(r"(\d{4}(-\d\d){5})_\1-\d{3}", name)
    bgr = cv2.imread(str(base / "left-image-full-size" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    assert bgr.dtype == np.uint8
    np.testing.assert_array_equal(bgr[..., ::-1], np.round(fr.image * 255).astype(np.uint8))
    dep = cv2.imread(str(base / "depth-map-full-size" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    assert dep.dtype == np.uint16 and dep.shape == (H, W)
    np.testing.assert_array_equal(dep == 0, fr.depth == 0)
    assert np.abs(dep / 256.0 - fr.depth).max() <= 0.5 / 256 + 1e-6
    pan = cv2.imread(str(base / "panoptic" / f"{name}.png"), cv2.IMREAD_UNCHANGED).astype(np.int64)
    ids = pan[..., 2] + 256 * pan[..., 1] + 256 ** 2 * pan[..., 0]      # file is BGR
    np.testing.assert_array_equal(ids, fr.panoptic)
    info = json.loads((base / "panoptic" / f"{name}.json").read_text())["segments_info"]
    assert {s["id"] for s in info} == set(np.unique(fr.panoptic).tolist())
    for s in info:
      ys, xs = np.nonzero(fr.panoptic == s["id"])
      assert s["area"] == len(ys) and s["iscrowd"] == 0
      assert s["bbox"] == [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
      assert s["isthing"] == int(s["id"] >= THING_ID_BASE)


@pytest.mark.parametrize("field, value, message", [
    ("fps", 0.0, "fps must be finite and > 0"), ("fps", float("nan"), "fps must be finite"),
    ("speed", float("nan"), "speed must be finite and >= 0"),
    ("camera_height", -1.0, "camera_height must be finite and > 0"),
    ("n_cars", -3.0, "n_cars must be finite and >= 0"),
    ("n_cars", float("inf"), "n_cars must be finite"),
    ("truck_fraction", 5.0, "truck_fraction must be in [0, 1]"),
    ("seed", -1, "seed must be >= 0"), ("num_frames", -3, "num_frames must be >= 0, got -3"),
    ("start", -5, "start must be >= 0, got -5"), ("height", 4, "height must be >= 8, got 4")])
def test_config_refuses_values_that_would_fail_later_or_render_nonsense(field, value, message):
  with pytest.raises(ValueError, match=re.escape(message)):
    SyntheticConfig(**{field: value})
