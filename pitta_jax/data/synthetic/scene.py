"""Procedural street of the synthetic benchmark: a seeded layout of axis-aligned boxes.

World frame (metres): X to the right of the road centre, Z forward along the road, heights above
the road surface. Right-hand traffic: the ego camera drives along +Z in the right lane, oncoming
traffic uses the left lane; each side has a bike lane, a parking strip, a raised sidewalk and a
row of buildings with varying setback and height, and street-light poles at the curb.

Everything is a pure function of (seed, frame time): static content is generated in 64 m blocks
and moving objects live in "streams" (a lane or sidewalk with one speed) whose slots are
generated in blocks of the stream's own moving coordinate `q = Z - speed * time`, so any frame
can be produced without simulating the ones before it. Randomness comes from
`np.random.default_rng([seed, kind, ...])`, never from global state.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from pitta_jax.data.synthetic import config as C

# Columns of a box row: world bounds, material, segment id, base colour, material parameters.
X0, X1, H0, H1, Z0, Z1, MAT, SEG, CAT, R, G, B, P0, P1, P2, P3, P4, P5 = range(18)
NUM_FIELDS = 18

# Materials (per box; GROUND, SKY and BACKDROP are not boxes).
SKY, GROUND, SIDEWALK, BUILDING, BACKDROP, POLE, LAMP = 0, 1, 2, 3, 4, 5, 6
BODY, CABIN, WHEEL, CARGO, CLOTH, HEAD, BIKE = 7, 8, 9, 10, 11, 12, 13
NUM_MATERIALS = 14
SHADOW_CASTERS = (BUILDING, BODY, CABIN, CARGO, CLOTH)

BLOCK = 64.0            # length of a static block, m
SLOTS_PER_BLOCK = 32
FAR_STATIC = 200.0      # static content rendered up to this distance ahead, m
FAR_DYNAMIC = 130.0     # moving objects rendered up to this distance ahead, m
BACKDROP_Z = 260.0      # distant skyline plane, m ahead
SIDEWALK_HEIGHT = 0.15  # curb height, m
LEAD_CODE = 10          # instance-id code of the lead cars (streams use 1..8, riders 9)

_FACADES = np.array([[0.62, 0.36, 0.28], [0.72, 0.62, 0.48], [0.80, 0.76, 0.66],
                     [0.55, 0.55, 0.57], [0.70, 0.52, 0.40], [0.85, 0.82, 0.74],
                     [0.45, 0.40, 0.38], [0.66, 0.70, 0.72], [0.78, 0.66, 0.52]])
_CAR_PAINT = np.array([[0.85, 0.85, 0.86], [0.08, 0.08, 0.09], [0.55, 0.56, 0.58],
                       [0.70, 0.08, 0.07], [0.10, 0.20, 0.55], [0.30, 0.32, 0.35],
                       [0.92, 0.92, 0.90], [0.15, 0.35, 0.20], [0.85, 0.65, 0.10],
                       [0.45, 0.12, 0.10]])
_TROUSERS = np.array([[0.10, 0.14, 0.30], [0.06, 0.06, 0.07], [0.35, 0.35, 0.37],
                      [0.55, 0.47, 0.33], [0.20, 0.22, 0.40]])
_SKIN = np.array([[0.88, 0.70, 0.58], [0.72, 0.52, 0.40], [0.45, 0.30, 0.22], [0.95, 0.80, 0.70]])
_HAIR = np.array([[0.08, 0.06, 0.05], [0.35, 0.22, 0.12], [0.75, 0.62, 0.40], [0.5, 0.5, 0.5]])


def _tag(rows: list[list[float]], cat: int) -> list[list[float]]:
  """Sets the COCO category of an object's rows."""
  for r in rows:
    r[CAT] = cat
  return rows


def _zig(k: int) -> int:
  """Signed block index -> non-negative int (SeedSequence entropy must be >= 0)."""
  return 2 * k if k >= 0 else -2 * k - 1


def _row(x0, x1, h0, h1, z0, z1, mat, seg, rgb, params=(), cat=0) -> list[float]:
  """One box row; `cat` (COCO category) defaults to the stuff class of `seg`."""
  p = list(params) + [0.0] * (6 - len(params))
  return [x0, x1, h0, h1, z0, z1, mat, seg, cat or C.STUFF_CATEGORY.get(seg, 0), *rgb, *p]


@dataclasses.dataclass(frozen=True)
class Stream:
  """Objects sharing a lateral position and a speed (a lane or a sidewalk walking direction)."""
  code: int         # 1..8 (9: riders, 10: lead cars), part of the instance ids
  kind: str         # "parked", "oncoming", "ped", "cyclist"
  x: float          # lateral centre, m
  speed: float      # m/s along +Z
  slot: float       # slot length, m: at most one object per slot
  occupancy: float  # probability that a slot holds an object
  facing: int       # +1: the object's front points to +Z
  max_len: float    # longest object of the stream: jitter within the slot keeps them apart


@dataclasses.dataclass
class FrameScene:
  """The content of one frame, in world coordinates.

  boxes:  (K, NUM_FIELDS) box rows.
  lights: (L, 7) point lights for the night domain: X, height, Z, r, g, b, intensity.
  footprints: (F, 4) X0, X1, Z0, Z1 of the vehicles (contact darkening on the road).
  camera: (3,) world X, height, Z of the camera.
  """
  boxes: np.ndarray
  lights: np.ndarray
  footprints: np.ndarray
  camera: np.ndarray


class Street:
  """The seeded street of one sequence; `frame(index)` lays out one frame (cached blocks)."""

  def __init__(self, cfg: C.SyntheticConfig):
    self.cfg = cfg
    rng = np.random.default_rng([cfg.seed, 0])
    self.lane_w = float(rng.uniform(3.2, 3.7))
    self.bike_w = float(rng.uniform(1.2, 1.8))
    self.park_w = float(rng.uniform(2.1, 2.5))
    self.curb = self.lane_w + self.bike_w + self.park_w           # road half width
    self.front = self.curb + float(rng.uniform(2.8, 4.5))        # building line
    self.ego_x = self.lane_w / 2
    elev = math.radians(rng.uniform(28, 60))
    azim = math.radians(rng.uniform(-150, 150))
    # direction to the sun in world axes (X, up, Z)
    self.sun = np.array([math.cos(elev) * math.sin(azim), math.sin(elev),
                         math.cos(elev) * math.cos(azim)])
    self.asphalt = float(rng.uniform(0.26, 0.38))
    self.pavement = np.array([0.60, 0.58, 0.55]) * rng.uniform(0.85, 1.1)
    self.centre_line = int(rng.integers(0, 2))                   # 0 white dashes, 1 double yellow
    self.crosswalk_period = float(rng.uniform(120, 220))
    self.crosswalk_offset = float(rng.uniform(30, 90))
    self.cloudiness = float(rng.uniform(0.1, 0.8))
    self.skyline_salt = int(rng.integers(0, 2**30))
    n_car, n_ped = cfg.n_cars, cfg.n_pedestrians

    def occ(expected: float, slot: float) -> float:
      return float(min(0.95, expected * slot / 100.0))

    ped_v = rng.uniform(1.0, 1.6, 4)
    # walking lines: clear of the poles (curb + 0.5) and of the facades (front), >= 0.9 m apart
    ped_x = (self.curb + 1.2, self.front - 0.7)
    self.streams = (
        Stream(1, "parked", self.curb - self.park_w / 2 - 0.15, 0.0, 6.5,
               occ(0.35 * n_car, 6.5), 1, 4.8),
        Stream(2, "parked", -(self.curb - self.park_w / 2 - 0.15), 0.0, 6.5,
               occ(0.30 * n_car, 6.5), -1, 4.8),
        Stream(3, "oncoming", -self.lane_w / 2, -float(rng.uniform(8, 13)), 18.0,
               occ(0.35 * n_car, 18.0), -1, 10.2),
        Stream(4, "ped", ped_x[0], ped_v[0], 3.0, occ(0.3 * n_ped, 3.0), 1, 0.8),
        Stream(5, "ped", ped_x[1], -ped_v[1], 3.0, occ(0.2 * n_ped, 3.0), -1, 0.8),
        Stream(6, "ped", -ped_x[0], ped_v[2], 3.0, occ(0.2 * n_ped, 3.0), 1, 0.8),
        Stream(7, "ped", -ped_x[1], -ped_v[3], 3.0, occ(0.3 * n_ped, 3.0), -1, 0.8),
        Stream(8, "cyclist", self.lane_w + self.bike_w / 2, float(rng.uniform(4, 6)), 20.0,
               occ(cfg.n_cyclists, 20.0), 1, 1.8),
    )
    self.lead = [np.random.default_rng([cfg.seed, 3, j]).uniform(0, 1, 16)
                 for j in range(cfg.n_lead_cars)]
    self._static: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    self._slots: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

  # --- static content -----------------------------------------------------------------------

  def _static_block(self, side: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(box rows, lamp lights) of one side (0 right, 1 left) in [k * BLOCK, (k + 1) * BLOCK)."""
    key = (side, k)
    if key in self._static:
      return self._static[key]
    rng = np.random.default_rng([self.cfg.seed, 1, side, _zig(k)])
    sign = 1.0 if side == 0 else -1.0
    rows, lamps = [], []
    z, end = k * BLOCK, (k + 1) * BLOCK
    while z < end - 1.0:
      if rng.random() < 0.12:                                     # alley
        z += rng.uniform(3.0, 7.0)
        continue
      z1 = min(z + rng.uniform(8.0, 26.0), end)
      setback = 0.0 if rng.random() < 0.6 else rng.uniform(0.5, 4.0)
      height = float(np.clip(rng.lognormal(math.log(13.0), 0.45), 5.0, 40.0))
      xin, xout = self.front + setback, self.front + setback + 14.0
      x0, x1 = (xin, xout) if sign > 0 else (-xout, -xin)
      style = int(rng.integers(0, 3))                             # brick, plaster, office glass
      rgb = _FACADES[rng.integers(len(_FACADES))] * rng.uniform(0.85, 1.12, 3)
      if style == 2:
        rgb = rgb * 0.6 + np.array([0.12, 0.16, 0.2])
      # floor height, window spacing, window width and height (fractions), salt, style
      params = (rng.uniform(2.9, 3.6), rng.uniform(2.0, 3.6), rng.uniform(0.35, 0.65),
                rng.uniform(0.4, 0.65), rng.integers(0, 2**20), style)
      if style == 2:                                              # glass office: big windows
        params = params[:2] + (0.88, 0.8) + params[4:]
      rows.append(_row(x0, x1, 0.0, height, z, z1, BUILDING, C.BUILDING_ID,
                       np.clip(rgb, 0, 1), params))
      z = z1 + (rng.uniform(0.0, 0.6) if rng.random() < 0.3 else 0.0)
    zp = k * BLOCK + rng.uniform(2.0, 20.0)
    while zp < end:                                               # street lights at the curb
      xs = sign * (self.curb + 0.5)
      top = rng.uniform(6.5, 8.0)
      arm_end = xs - sign * 1.8
      rows.extend([
          _row(xs - 0.08, xs + 0.08, 0.0, top, zp - 0.08, zp + 0.08, POLE, C.POLE_ID,
               (0.42, 0.43, 0.45)),
          _row(min(xs, arm_end), max(xs, arm_end), top - 0.12, top, zp - 0.05, zp + 0.05,
               POLE, C.POLE_ID, (0.42, 0.43, 0.45)),
          _row(arm_end - 0.3, arm_end + 0.3, top - 0.3, top - 0.08, zp - 0.15, zp + 0.15,
               LAMP, C.POLE_ID, (0.35, 0.36, 0.38)),
      ])
      lamps.append([arm_end, top - 0.32, zp, 1.0, 0.8, 0.55, 6.0])
      zp += rng.uniform(22.0, 34.0)
    if len(self._static) > 256:
      self._static.clear()
    out = (np.asarray(rows, np.float64).reshape(-1, NUM_FIELDS),
           np.asarray(lamps, np.float64).reshape(-1, 7))
    self._static[key] = out
    return out

  # --- moving objects -----------------------------------------------------------------------

  def _slot_block(self, code: int, blk: int) -> tuple[np.ndarray, np.ndarray]:
    """(occupied (32,) bool, uniforms (32, 16)) of one block of a stream's slots."""
    key = (code, blk)
    if key not in self._slots:
      rng = np.random.default_rng([self.cfg.seed, 2, code, _zig(blk)])
      if len(self._slots) > 1024:
        self._slots.clear()
      self._slots[key] = (rng.random(SLOTS_PER_BLOCK), rng.random((SLOTS_PER_BLOCK, 16)))
    return self._slots[key]

  def frame(self, index: int) -> FrameScene:
    """Lays out frame `index` (time = index / fps)."""
    cfg = self.cfg
    time = index / cfg.fps
    cam_z = cfg.speed * time
    rows: list[list[float]] = []      # moving objects
    lights: list[list[float]] = []
    feet: list[list[float]] = []
    # raised sidewalks (the curb faces the road) from just behind the camera to far away
    static = [np.asarray([_row(*sorted((sign * self.curb, sign * 80.0)), 0.0, SIDEWALK_HEIGHT,
                               cam_z - 5.0, cam_z + FAR_STATIC, SIDEWALK, C.PAVEMENT_ID,
                               self.pavement)
                          for sign in (1.0, -1.0)])]
    lamps = []
    for side in (0, 1):
      for k in range(math.floor((cam_z - 20.0) / BLOCK),
                     math.floor((cam_z + FAR_STATIC) / BLOCK) + 1):
        bx, lt = self._static_block(side, k)
        static.append(bx[(bx[:, Z1] > cam_z - 15.0) & (bx[:, Z0] < cam_z + FAR_STATIC)])
        lamps.append(lt)
    lo, hi = cam_z - 15.0, cam_z + FAR_DYNAMIC
    for st in self.streams:
      q = st.speed * time
      i0, i1 = math.floor((lo - q) / st.slot) - 1, math.floor((hi - q) / st.slot) + 2
      blocks = range(i0 // SLOTS_PER_BLOCK, (i1 - 1) // SLOTS_PER_BLOCK + 1)
      occ = np.concatenate([self._slot_block(st.code, blk)[0] for blk in blocks])
      uni = np.concatenate([self._slot_block(st.code, blk)[1] for blk in blocks])
      first = blocks[0] * SLOTS_PER_BLOCK
      idx = np.arange(i0, i1)
      zc = (idx + 0.5) * st.slot + (uni[idx - first, 0] - 0.5) * (st.slot - st.max_len) + q
      keep = (occ[idx - first] < st.occupancy) & (zc > lo) & (zc < hi)
      for i, z in zip(idx[keep].tolist(), zc[keep].tolist()):
        seg = C.THING_ID_BASE + st.code * C.ID_STRIDE + i % C.ID_STRIDE
        self._add_object(st, z, uni[i - first].tolist(), seg, time, rows, lights, feet)
    for j, u in enumerate(self.lead):
      rel = 12.0 + 28.0 * j + 8.0 * u[0] + (2.0 + 4.0 * u[1]) * math.sin(
          2 * math.pi * time / (8.0 + 12.0 * u[2]) + 6.283 * u[3])
      seg = C.THING_ID_BASE + LEAD_CODE * C.ID_STRIDE + j
      self._car(self.ego_x, cam_z + rel, 1, u[4:].tolist(), seg, rows, lights, feet, lit=True)
    boxes = np.concatenate(static + [np.asarray(rows, np.float64).reshape(-1, NUM_FIELDS)])
    lights = np.concatenate(lamps + [np.asarray(lights, np.float64).reshape(-1, 7)])
    return FrameScene(boxes, lights[(lights[:, 2] > cam_z) & (lights[:, 2] < cam_z + FAR_STATIC)],
                      np.asarray(feet, np.float64).reshape(-1, 4),
                      np.array([self.ego_x, cfg.camera_height, cam_z]))

  def _add_object(self, st: Stream, zc: float, u: np.ndarray, seg: int, time: float,
                  out, lights, feet) -> None:
    if st.kind == "parked":
      self._car(st.x + (u[1] - 0.5) * 0.2, zc, st.facing, u[2:], seg, out, lights, feet,
                lit=False)
    elif st.kind == "oncoming":
      if u[1] < self.cfg.truck_fraction:
        self._truck(st.x, zc, st.facing, u[2:], seg, out, lights, feet)
      else:
        self._car(st.x + (u[1] - 0.5) * 0.3, zc, st.facing, u[2:], seg, out, lights, feet,
                  lit=True)
    elif st.kind == "ped":
      walked = abs(st.speed) * time + 7.0 * u[1]
      _person(st.x + (u[2] - 0.5) * 0.3, zc, st.facing, u[3:], seg, walked, out,
              base=SIDEWALK_HEIGHT)
    else:
      self._cyclist(st.x + (u[1] - 0.5) * 0.4, zc, u[2:], seg, out, lights)

  def _car(self, x, zc, facing, u, seg, out, lights, feet, lit: bool) -> None:
    length, width = 3.9 + 0.9 * u[0], 1.72 + 0.18 * u[1]
    top = 1.0 + 0.25 * u[2]
    roof = top + 0.42 + 0.16 * u[3]
    rgb = np.clip(_CAR_PAINT[int(u[4] * len(_CAR_PAINT))] * (0.9 + 0.2 * u[5]), 0, 1)
    cab = length * (0.45 + 0.1 * u[6])
    cz = zc - facing * length * (0.06 + 0.06 * u[7])
    z0, z1, w = zc - length / 2, zc + length / 2, width / 2
    rows = [_row(x - w, x + w, 0.3, top, z0, z1, BODY, seg, rgb, (facing, float(lit))),
            _row(x - w + 0.07, x + w - 0.07, top, roof, cz - cab / 2, cz + cab / 2, CABIN, seg,
                 rgb, (facing,))]
    for za in (zc - length / 2 + 0.82, zc + length / 2 - 0.82):
      rows.append(_row(x - w - 0.02, x + w + 0.02, 0.0, 0.64, za - 0.32, za + 0.32, WHEEL,
                       seg, (0.05, 0.05, 0.05)))
    out.extend(_tag(rows, C.COCO_CAR))
    feet.append([x - w, x + w, z0, z1])
    if lit:
      # the camera sees the -Z end: headlights when the car faces -Z, tail lights otherwise
      col, inten = ((1.0, 0.95, 0.8), 2.5) if facing < 0 else ((1.0, 0.1, 0.05), 0.8)
      hl = 0.3 + 0.72 * (top - 0.3)
      for dx in (-w + 0.22, w - 0.22):
        lights.append([x + dx, hl, z0, *col, inten])

  def _truck(self, x, zc, facing, u, seg, out, lights, feet) -> None:
    width = 2.45
    w = width / 2
    cab_len, box_len = 2.3, 5.5 + 2.0 * u[0]
    total = cab_len + 0.3 + box_len
    z0 = zc - total / 2
    zc_cab = z0 + cab_len / 2 if facing < 0 else z0 + total - cab_len / 2
    zc_box = z0 + total - box_len / 2 if facing < 0 else z0 + box_len / 2
    cab_rgb = np.clip(_CAR_PAINT[int(u[1] * len(_CAR_PAINT))] * (0.9 + 0.2 * u[2]), 0, 1)
    box_rgb = np.clip(np.array([0.9, 0.9, 0.88]) * (0.75 + 0.25 * u[3]), 0, 1)
    rows = [_row(x - w + 0.05, x + w - 0.05, 0.5, 2.9, zc_cab - cab_len / 2, zc_cab + cab_len / 2,
                 CABIN, seg, cab_rgb, (facing, 1.0)),
            _row(x - w + 0.05, x + w - 0.05, 0.5, 1.45, zc_cab - cab_len / 2 - 0.02,
                 zc_cab + cab_len / 2 + 0.02, BODY, seg, cab_rgb, (facing, 1.0)),
            _row(x - w, x + w, 0.95, 3.7, zc_box - box_len / 2, zc_box + box_len / 2, CARGO, seg,
                 box_rgb, (facing,))]
    for za in (zc_cab, zc_box - box_len / 2 + 1.2, zc_box + box_len / 2 - 1.2):
      rows.append(_row(x - w + 0.05, x + w - 0.05, 0.0, 1.0, za - 0.5, za + 0.5, WHEEL, seg,
                       (0.05, 0.05, 0.05)))
    out.extend(_tag(rows, C.COCO_TRUCK))
    feet.append([x - w, x + w, z0, z0 + total])
    zl = zc_cab - cab_len / 2 if facing < 0 else zc_cab + cab_len / 2
    for dx in (-w + 0.3, w - 0.3):
      lights.append([x + dx, 0.9, zl, 1.0, 0.95, 0.8, 2.5])

  def _cyclist(self, x, zc, u, seg, out, lights) -> None:
    frame_rgb = np.clip(_CAR_PAINT[int(u[0] * len(_CAR_PAINT))], 0, 1)
    rows = []
    for za in (zc - 0.52, zc + 0.52):
      rows.append(_row(x - 0.03, x + 0.03, 0.0, 0.68, za - 0.34, za + 0.34, WHEEL, seg,
                       (0.05, 0.05, 0.05)))
    rows += [_row(x - 0.025, x + 0.025, 0.76, 0.82, zc - 0.4, zc + 0.42, BIKE, seg, frame_rgb),
             _row(x - 0.025, x + 0.025, 0.32, 0.36, zc - 0.52, zc + 0.1, BIKE, seg, frame_rgb),
             _row(x - 0.025, x + 0.025, 0.34, 0.9, zc - 0.3, zc - 0.25, BIKE, seg, frame_rgb),
             _row(x - 0.025, x + 0.025, 0.34, 1.0, zc + 0.4, zc + 0.45, BIKE, seg, frame_rgb),
             _row(x - 0.28, x + 0.28, 1.0, 1.04, zc + 0.42, zc + 0.47, BIKE, seg,
                  (0.1, 0.1, 0.1))]
    out.extend(_tag(rows, C.COCO_BICYCLE))
    lights.append([x, 0.7, zc - 0.86, 1.0, 0.1, 0.05, 0.4])
    rider = seg + C.ID_STRIDE                                     # stream code 9: riders
    shirt = np.clip(np.array(u[1:4]) * 0.8 + 0.1, 0, 1)
    legs = _TROUSERS[int(u[4] * len(_TROUSERS))]
    hair = _HAIR[int(u[5] * len(_HAIR))]
    skin = _SKIN[int(u[6] * len(_SKIN))]
    out.extend(_tag([
        _row(x - 0.2, x - 0.06, 0.45, 0.95, zc - 0.3, zc - 0.05, CLOTH, rider, legs),
        _row(x + 0.06, x + 0.2, 0.45, 0.95, zc - 0.25, zc, CLOTH, rider, legs),
        _row(x - 0.2, x + 0.2, 0.95, 1.5, zc - 0.3, zc - 0.05, CLOTH, rider, shirt),
        _row(x - 0.25, x + 0.25, 1.05, 1.15, zc - 0.05, zc + 0.4, CLOTH, rider, shirt),
        _row(x - 0.1, x + 0.1, 1.52, 1.78, zc - 0.22, zc - 0.02, HEAD, rider, skin,
             (1.0, *hair)),
    ], C.COCO_PERSON))


def _person(x, zc, facing, u, seg, walked, out, base: float = 0.0) -> None:
  """A pedestrian standing at height `base`: two legs and two arms swinging with the walk
  phase, torso, head."""
  sc = 0.9 + 0.2 * u[0]
  phase = 2 * math.pi * walked / 1.5
  swing = 0.22 * math.sin(phase)
  legs = _TROUSERS[int(u[1] * len(_TROUSERS))]
  shirt = np.clip(np.array(u[2:5]) * 0.85 + 0.08, 0, 1)
  skin = _SKIN[int(u[5] * len(_SKIN))]
  hair = _HAIR[int(u[6] * len(_HAIR))]
  hw = 0.2 * sc
  leg_top, torso_top = 0.86 * sc, 1.45 * sc
  rows = []
  for dx, s in ((-0.1, 1.0), (0.1, -1.0)):
    zl = zc + s * swing
    rows.append(_row(x + dx - 0.065, x + dx + 0.065, 0.0, leg_top, zl - 0.08, zl + 0.08, CLOTH,
                     seg, legs))
    za = zc - s * 0.7 * swing
    xa = x + np.sign(dx) * (hw + 0.05)
    rows.append(_row(xa - 0.045, xa + 0.045, leg_top + 0.05, torso_top - 0.03, za - 0.05,
                     za + 0.05, CLOTH, seg, shirt))
  rows.append(_row(x - hw, x + hw, leg_top - 0.02, torso_top, zc - 0.12, zc + 0.12, CLOTH, seg,
                   shirt))
  rows.append(_row(x - 0.095, x + 0.095, torso_top + 0.03, torso_top + 0.3 * sc, zc - 0.105,
                   zc + 0.105, HEAD, seg, skin, (facing, *hair)))
  for r in rows:
    r[H0] += base
    r[H1] += base
  out.extend(_tag(rows, C.COCO_PERSON))
