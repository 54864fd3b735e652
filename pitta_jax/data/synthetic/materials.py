"""Surface geometry and per-material albedo of the synthetic benchmark's hit points.

A shader gets the hit points of one material (flat pixel indices) with their world position,
the box face hit (0: x face, 1: y face, 2: z face), and the pixel footprint along each world
axis, and returns (albedo (3, n), emission (n,)); colours are planar (channel-first), which is
several times faster in NumPy than (n, 3). Emission is only used by the night domain (lit
windows, lamp glass, car lights).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from pitta_jax.data.synthetic import scene as S
from pitta_jax.data.synthetic.textures import band, hash01, mix, noise, pulse, rgb, smoothstep

F32 = np.float32


class Surf:
  """Hit points of one material (arrays (n,) float32 unless stated), computed on first use.

  idx: flat pixel indices; a, b: ray slopes (j - cx) / fx, (i - cy) / fy; t: z-depth (1e4 for
  no hit); k: box index (int) or None; face: 0 x face, 1 y face (top or bottom), 2 z face
  (towards the camera); x, h, z: world X, height and Z of the hit; fpx, fph, fpz: pixel
  footprint along world X, height and Z (m), for texture filtering.
  """

  def __init__(self, idx, a, b, t, k, face, cam, intr):
    self.idx, self.a, self.b, self.t, self.k, self.face = idx, a, b, t, k, face
    self._cam, self._fx, self._fy = cam, F32(intr[0]), F32(intr[1])

  @functools.cached_property
  def x(self) -> np.ndarray:
    return self.a * self.t + F32(self._cam[0])

  @functools.cached_property
  def h(self) -> np.ndarray:
    return F32(self._cam[1]) - self.b * self.t

  @functools.cached_property
  def z(self) -> np.ndarray:
    return self.t + F32(self._cam[2])

  @functools.cached_property
  def _grazing(self) -> tuple[np.ndarray, np.ndarray]:
    """Footprint along an x face and along a y face (grows as 1 / slope at grazing angles)."""
    aa = np.maximum(np.abs(self.a), F32(1e-4))
    ab = np.maximum(np.abs(self.b), F32(1e-4))
    return self.t / (aa * self._fx), self.t / (ab * self._fy)

  @functools.cached_property
  def fpx(self) -> np.ndarray:
    tfx = self.t / self._fx
    return np.where(self.face == 1, tfx + np.abs(self.a) * self._grazing[1], tfx)

  @functools.cached_property
  def fph(self) -> np.ndarray:
    tfy = self.t / self._fy
    return np.where(self.face == 0, tfy + np.abs(self.b) * self._grazing[0], tfy)

  @functools.cached_property
  def fpz(self) -> np.ndarray:
    gx, gy = self._grazing
    return np.where(self.face == 0, gx, np.where(self.face == 1, gy, self.t / self._fx))


@dataclasses.dataclass
class Context:
  """Per-frame data the shaders read; boxes_t: the box rows transposed (NUM_FIELDS, K)."""
  street: S.Street
  boxes_t: np.ndarray
  a: np.ndarray           # (H * W,) float32 per-pixel ray slopes
  b: np.ndarray
  t: np.ndarray           # (H * W,) float32 z-depth, inf for no hit
  owner: np.ndarray       # (H * W,) int32
  face: np.ndarray        # (H * W,) uint8 face hit (see Surf.face)
  intr: tuple[float, float, float, float]
  cam: np.ndarray

  def field(self, s: Surf, col: int | list[int]) -> np.ndarray:
    """Box fields of each hit: (n,) for one column, (len(col), n) for a list."""
    return np.take(self.boxes_t[col], s.k, axis=-1)

  def surface(self, idx: np.ndarray, kind: str) -> Surf:
    """Geometry of the hit points `idx`; kind: "box", "ground", "skyline" or "sky"."""
    k = np.take(self.owner, idx) - 4 if kind == "box" else None
    face = np.take(self.face, idx) if kind == "box" else np.full(
        len(idx), 2 if kind == "skyline" else 1, np.uint8)
    return Surf(idx, np.take(self.a, idx), np.take(self.b, idx),
                np.minimum(np.take(self.t, idx), F32(1e4)), k, face, self.cam, self.intr)


def lighting_terms(face: np.ndarray, a: np.ndarray, b: np.ndarray,
                   sun: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Per hit (flat arrays): cosine of the normal with the sun, sky visibility, faces up.

  The normal of the face hit points back at the camera: -sign(a) x for x faces, up for y
  faces seen from above (b > 0) and down otherwise, -z for z faces.
  """
  sun = sun.astype(F32)
  down = b > 0                                                    # ray going down: sees a top
  f0, f1 = face == 0, face == 1
  ndotl = np.where(f0, -np.sign(a) * sun[0],
                   np.where(f1, np.where(down, sun[1], -sun[1]), -sun[2]))
  ambient = np.where(f1, np.where(down, F32(1.0), F32(0.45)), F32(0.75))
  return ndotl, ambient, f1 & down


def _take(c: np.ndarray, sel: np.ndarray) -> np.ndarray:
  return np.take(c, sel, axis=-1)


def put_planar(dst: np.ndarray, sel: np.ndarray, val: np.ndarray) -> None:
  """dst[:, sel] = val for planar colours, one flat scatter per channel (fast)."""
  for ch in range(3):
    dst[ch][sel] = val[ch] if val.shape[-1] != 1 else val[ch, 0]


def _zeros(s: Surf) -> np.ndarray:
  return np.zeros(len(s.idx), F32)


def _sky(c: Context, s: Surf):
  elev = -s.b / np.sqrt(1 + s.a * s.a + s.b * s.b)
  col = mix(rgb(0.80, 0.86, 0.93), rgb(0.32, 0.52, 0.84), np.clip(elev / 0.45, 0, 1) ** 0.7)
  inv = 1.0 / np.maximum(-s.b, F32(0.03))                         # cloud layer coordinates
  fp = inv * F32(1 / c.intr[0]) * (1 + np.abs(s.a) * inv)
  n = noise(s.a * inv * 6.0 + 0.3, inv * 6.0, fp * 6.0, 0.25)
  cloud = smoothstep(0.4, 1.6, n + 2.0 * (c.street.cloudiness - 0.5)) * np.clip(elev * 6, 0, 1)
  return mix(col, rgb(0.95, 0.95, 0.97), 0.85 * cloud), _zeros(s)


def _asphalt(c: Context, x, z, fpx, fpz) -> np.ndarray:
  st = c.street
  fp = np.minimum(fpx, fpz)
  n = noise(x, z, fp, 0.03)
  v = 1.0 + 0.14 * n - 0.10 * smoothstep(1.0, 2.0, noise(x, z, fp, 0.25, 2))
  ax = np.abs(x)
  wear = band(np.abs(x - st.ego_x), 0.45, 1.15, fpx) + band(np.abs(x + st.lane_w / 2), 0.45,
                                                             1.15, fpx)
  v = v * (1.0 - 0.07 * wear) * F32(st.asphalt)
  col = rgb(0.97, 0.98, 1.02) * v
  wz = np.maximum(fpz, F32(1e-3))
  edge = band(ax, st.lane_w - 0.08, st.lane_w + 0.08, fpx)
  park = band(ax, st.lane_w + st.bike_w - 0.06, st.lane_w + st.bike_w + 0.06, fpx) * pulse(
      z / 2.5, 0.5, wz / 2.5)
  zc = np.mod(z - st.crosswalk_offset, st.crosswalk_period)
  zebra = band(zc, 0.0, 4.0, wz) * pulse(x / 1.1 + 0.25, 0.5, fpx / 1.1) * (ax < st.lane_w)
  worn = np.clip(0.8 + 0.3 * n, 0, 1)
  if st.centre_line == 0:
    white = edge + park + zebra + band(x, -0.07, 0.07, fpx) * pulse(z / 9.0, 1 / 3, wz / 9.0)
    return mix(col, rgb(0.85, 0.85, 0.83), np.minimum(white, 1) * worn)
  col = mix(col, rgb(0.85, 0.85, 0.83), np.minimum(edge + park + zebra, 1) * worn)
  return mix(col, rgb(0.85, 0.68, 0.18), band(ax, 0.07, 0.2, fpx) * worn)


def _paving(c: Context, x, z, fpx, fpz) -> np.ndarray:
  fp = np.minimum(fpx, fpz)
  v = 1.0 + 0.09 * noise(x, z, fp, 0.04, 7)
  grid = pulse(x / 0.9, 0.94, fpx / 0.9) * pulse(z / 0.9, 0.94, fpz / 0.9)
  v = v * (0.72 + 0.28 * grid)
  return c.street.pavement.astype(F32)[:, None] * v


def _ground(c: Context, s: Surf):
  col = np.empty((3, len(s.idx)), F32)
  road = np.abs(s.x) < c.street.curb
  for sel, fn in ((np.nonzero(road)[0], _asphalt), (np.nonzero(~road)[0], _paving)):
    if len(sel):
      put_planar(col, sel, fn(c, _take(s.x, sel), _take(s.z, sel), _take(s.fpx, sel),
                              _take(s.fpz, sel)))
  return col, _zeros(s)


def _sidewalk(c: Context, s: Surf):
  col = _paving(c, s.x, s.z, s.fpx, s.fpz)
  curb = np.nonzero(s.face != 1)[0]
  if len(curb):
    v = 1.05 + 0.08 * noise(_take(s.z, curb), _take(s.h, curb), _take(s.fpz, curb), 0.03, 9)
    put_planar(col, curb, rgb(0.72, 0.71, 0.69) * v)
  return col, _zeros(s)


def _building(c: Context, s: Surf):
  x0, x1, top, z0, z1, salt, style = c.field(s, [S.X0, S.X1, S.H1, S.Z0, S.Z1, S.P4, S.P5])
  facade = s.face == 0
  u = np.where(facade, s.z - z0, np.where(s.x > 0, s.x - x0, x1 - s.x))  # along the wall
  fpu = np.where(facade, s.fpz, s.t * F32(1 / c.intr[0]))        # roofs: not textured
  r, fpr = s.h, s.fph
  v = 1.0 + 0.08 * noise(u, r, np.minimum(fpu, fpr), 0.05, 11)
  v = v * (1.0 - 0.25 * np.clip(1.0 - r / 1.2, 0, 1) ** 2) * np.where(r > top - 0.35, 0.75, 1.0)
  brick = np.nonzero(style == 0)[0]
  if len(brick):
    rb, ub = _take(r, brick) / F32(0.077), _take(u, brick) / F32(0.24)
    mortar = 1.0 - pulse(rb, 0.84, _take(fpr, brick) / F32(0.077)) * pulse(
        ub + 0.5 * (np.floor(rb) % 2), 0.92, _take(fpu, brick) / F32(0.24))
    v[brick] *= 1.0 - 0.28 * mortar
  v[s.face == 1] = 0.5                                            # roofs: dark
  col = c.field(s, [S.R, S.G, S.B]) * v
  emit = _zeros(s)
  gf = F32(3.6)                                                   # ground floor height
  sel = np.nonzero(facade & (r > gf) & (r < top - 1.0) & (u > 0.5) & (u < z1 - z0 - 0.5))[0]
  if len(sel):                                                    # windows, upper floors
    ks = _take(s.k, sel)
    fhs, wss, wws, whs, salts, br, bg, bb = np.take(
        c.boxes_t[[S.P0, S.P1, S.P2, S.P3, S.P4, S.R, S.G, S.B]], ks, axis=1)
    iws, ifh = 1.0 / wss, 1.0 / fhs
    us, rs = _take(u, sel) * iws, (_take(r, sel) - gf) * ifh     # in window periods
    win = pulse(us - (1 - wws) / 2, wws, _take(fpu, sel) * iws) * pulse(
        rs - (1 - whs) / 2, whs, _take(fpr, sel) * ifh)
    hv = hash01(np.floor(us), np.floor(rs), salts.astype(np.int64))
    glass = mix(rgb(0.07, 0.09, 0.12), rgb(0.48, 0.58, 0.68), 0.15 + 0.55 * hv)
    put_planar(col, sel, mix(np.stack([br, bg, bb]) * _take(v, sel), glass, win))
    emit[sel] = win * (np.modf(hv * F32(7.31))[0] < 0.35)      # a third of the windows lit
  shop = np.nonzero(facade & (r < gf) & ((salt.astype(np.int64) & 1) == 1))[0]
  if len(shop):
    ks = _take(s.k, shop)
    wss, br, bg, bb = np.take(c.boxes_t[[S.P1, S.R, S.G, S.B]], ks, axis=1)
    us, rs = _take(u, shop), _take(r, shop)
    isalt = _take(salt, shop).astype(np.int64)
    win = pulse(us / (2 * wss) - 0.12, 0.76, _take(fpu, shop) / (2 * wss)) * band(
        rs, 0.5, 2.9, _take(fpr, shop))
    hv = hash01(np.floor(us / (2 * wss)), 0, isalt)
    wall = np.stack([br, bg, bb]) * _take(v, shop)
    cs = mix(wall, mix(rgb(0.05, 0.06, 0.07), rgb(0.3, 0.35, 0.4), 0.3 * hv), win)
    awning = band(rs, 2.95, 3.35, _take(fpr, shop)) * ((isalt & 2) == 2)
    tint = np.stack([0.2 + 0.6 * hash01(isalt, 1, 5), 0.15 + 0.3 * hash01(isalt, 2, 5),
                     0.1 + 0.3 * hash01(isalt, 3, 5)])
    put_planar(col, shop, mix(cs, tint, awning))
    emit[shop] = win * (0.3 + 0.5 * (hv > 0.4))                 # some shops closed
  return col, emit


def _backdrop(c: Context, s: Surf):
  tone = 0.8 + 0.35 * hash01(np.floor(s.x / 14.0), 5, c.street.skyline_salt)
  win = pulse(s.x / 3.0, 0.5, s.fpx / 3.0) * pulse(s.h / 3.2, 0.5, s.fph / 3.2) * (s.h > 3.0)
  col = rgb(0.50, 0.53, 0.58) * (tone * (1.0 - 0.25 * win))
  emit = win * (hash01(np.floor(s.x / 3.0), np.floor(s.h / 3.2), 17) < 0.3)
  return col, emit.astype(F32)


def _pole(c: Context, s: Surf):
  v = 1.0 + 0.06 * noise(s.z + s.x, s.h, s.fph, 0.05, 13)
  return c.field(s, [S.R, S.G, S.B]) * v, _zeros(s)


def _lamp(c: Context, s: Surf):
  glass = ((s.face == 1) & (s.b < 0)).astype(F32)
  return mix(c.field(s, [S.R, S.G, S.B]), rgb(0.95, 0.93, 0.85), glass), glass


def _local(c: Context, s: Surf):
  """Box-relative coordinates: (along the face, up the face, face width, face height, fp)."""
  x0, x1, h0, h1, z0, z1 = c.field(s, [S.X0, S.X1, S.H0, S.H1, S.Z0, S.Z1])
  side = s.face == 0
  return (np.where(side, s.z - z0, s.x - x0), s.h - h0, np.where(side, z1 - z0, x1 - x0),
          h1 - h0, np.where(side, s.fpz, s.fpx))


def _body(c: Context, s: Surf):
  u, r, w, hgt, fpu = _local(c, s)
  facing, lit = c.field(s, [S.P0, S.P1])
  ur, rr, fu, fr = u / w, r / hgt, fpu / w, s.fph / hgt
  side, end = s.face == 0, s.face == 2
  seams = np.minimum(band(ur, 0.44, 0.45, fu) + band(ur, 0.7, 0.71, fu), 1) * side
  v = (1.0 + 0.04 * noise(s.x + s.z, s.h, s.fph, 0.1, 14)) * (1.0 - 0.6 * seams)
  col = c.field(s, [S.R, S.G, S.B]) * v
  col = mix(col, rgb(0.08, 0.08, 0.09), band(rr, -1.0, 0.14, fr) * (side | end))
  front = facing < 0                                              # we see the -Z end
  lamps = (band(ur, 0.06, 0.24, fu) + band(ur, 0.76, 0.94, fu)) * band(rr, 0.6, 0.84, fr) * end
  lamp_rgb = np.where(front, rgb(0.92, 0.92, 0.86), rgb(0.75, 0.06, 0.05))
  col = mix(col, lamp_rgb, lamps)
  col = mix(col, rgb(0.1, 0.1, 0.11), band(ur, 0.3, 0.7, fu) * band(rr, 0.45, 0.72, fr) * end
            * front)
  col = mix(col, rgb(0.9, 0.9, 0.85), band(ur, 0.4, 0.6, fu) * band(rr, 0.2, 0.38, fr) * end)
  col = mix(col, rgb(0.75, 0.82, 0.92), 0.15 * (s.face == 1))
  return col, (lamps * lit).astype(F32)


def _cabin(c: Context, s: Surf):
  u, r, w, hgt, fpu = _local(c, s)
  truck = c.field(s, S.P1) > 0
  ur, rr, fu = u / w, r / hgt, fpu / w
  lo = np.where(truck, F32(0.45), F32(0.08))
  glass = band(rr, lo, 0.92, s.fph / hgt) * band(ur, 0.07, 0.93, fu) * (s.face != 1)
  glass = glass * (1.0 - band(ur, 0.47, 0.53, fu) * ((s.face == 0) & ~truck))
  g = mix(rgb(0.06, 0.07, 0.09), rgb(0.45, 0.52, 0.6), 0.15 + 0.5 * np.clip(rr, 0, 1))
  return mix(c.field(s, [S.R, S.G, S.B]), g, glass), _zeros(s)


def _wheel(c: Context, s: Surf):
  h1, z0, z1 = c.field(s, [S.H1, S.Z0, S.Z1])
  rad = h1 / 2
  d = np.hypot(s.z - 0.5 * (z0 + z1), s.h - rad)
  hub = (1.0 - smoothstep(0.0, 1.0, (d - 0.5 * rad) / np.maximum(s.fph, 0.01) + 0.5)) * (
      s.face == 0)
  return mix(rgb(0.05, 0.05, 0.05), rgb(0.55, 0.56, 0.58), hub), _zeros(s)


def _cargo(c: Context, s: Surf):
  u, r, w, hgt, fpu = _local(c, s)
  ribs = pulse(u / 0.6, 0.12, fpu / 0.6) * (s.face == 0)
  stripe = band(r / hgt, 0.35, 0.45, s.fph / hgt) * (s.face != 1)
  door = band(u / w, 0.495, 0.505, fpu / w) * (s.face == 2)
  col = c.field(s, [S.R, S.G, S.B]) * (1.0 - 0.15 * ribs - 0.5 * door)
  return mix(col, rgb(0.7, 0.15, 0.1), stripe), _zeros(s)


def _cloth(c: Context, s: Surf):
  v = 1.0 + 0.12 * noise(s.x + s.z, s.h, s.fph, 0.03, 15)
  return c.field(s, [S.R, S.G, S.B]) * v, _zeros(s)


def _head(c: Context, s: Surf):
  _, r, _, hgt, _ = _local(c, s)
  back = (c.field(s, S.P0) > 0) & (s.face == 2)                  # walking away: back of head
  hair = np.where(back, r / hgt > 0.2, r / hgt > 0.7) | (s.face == 1)
  return np.where(hair, c.field(s, [S.P1, S.P2, S.P3]), c.field(s, [S.R, S.G, S.B])), _zeros(s)


def _plain(c: Context, s: Surf):
  return c.field(s, [S.R, S.G, S.B]), _zeros(s)


SHADERS = {S.SKY: _sky, S.GROUND: _ground, S.SIDEWALK: _sidewalk, S.BUILDING: _building,
           S.BACKDROP: _backdrop, S.POLE: _pole, S.LAMP: _lamp, S.BODY: _body, S.CABIN: _cabin,
           S.WHEEL: _wheel, S.CARGO: _cargo, S.CLOTH: _cloth, S.HEAD: _head, S.BIKE: _plain}
SURFACE_KIND = {S.SKY: "sky", S.GROUND: "ground", S.BACKDROP: "skyline"}
