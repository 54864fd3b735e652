"""Analytic ray casting, shadows and shading of one synthetic frame (NumPy, one ray per pixel).

Camera: x right, y down, z forward, at `camera_height` above the road, looking along the road;
pixel (i, j) casts the ray t * ((j - cx) / fx, (i - cy) / fy, 1), so the ray parameter t of a
hit *is* its z-depth. Hits: the road plane y = h (closed form t = h / b), axis-aligned boxes
(slab test; the x- and y-slab entries of a box depend on the column and on the row only, so a
box costs two 1-D divisions and a few 2-D max/min over its screen rectangle), and a distant
skyline plane. Shading: Lambert with the seed's sun, sun shadows by a slab test from every
visible point towards the sun against the boxes whose shadow volume covers it, contact
darkening under vehicles, a slight aerial haze; textures from `textures`.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from pitta_jax.data.frame import Segment
from pitta_jax.data.synthetic import config as C
from pitta_jax.data.synthetic import materials
from pitta_jax.data.synthetic import scene as S
from pitta_jax.data.synthetic import textures as T

NEAR = 0.1
SMALL_RECT = 400          # boxes covering at most this many pixels are ray-cast in one batch
SHADE_CHUNK = 32768       # pixels shaded per call
SHADOW_RANGE = 90.0       # boxes starting farther ahead cast no shadow (small and hazy there)
# owner codes of a pixel: sky, road plane (road part), road plane (beyond the curbs), skyline,
# then 4 + k for box k
OWN_SKY, OWN_ROAD, OWN_PAVE, OWN_BACKDROP, OWN_BOX = 0, 1, 2, 3, 4
HAZE = 0.002              # clear-weather aerial perspective, 1/m
SUN_RGB = np.array([1.0, 0.96, 0.88])
SKYLIGHT_RGB = np.array([0.82, 0.9, 1.05])
HORIZON_RGB = np.array([0.80, 0.86, 0.93])


@dataclasses.dataclass
class Render:
  """A rendered clear-weather frame and what the weather models need.

  image:    (3, H, W) float32 in [0, 1], clear weather, planar (channel-first: NumPy colour
            arithmetic is several times faster than on (H, W, 3)).
  albedo:   (3, H, W) float32 unlit surface colour (night lighting re-lights it).
  dist:     (H, W) float32 z-depth of the hit, inf for sky (not capped at max_depth).
  panoptic: (H, W) int32 segment ids; `segments` lists them.
  material: (H, W) uint8 `scene` material codes.
  up:       (H, W) bool, surface faces up (road, sidewalk, roofs): where snow settles.
  emissive: (H, W) float32 in [0, 1], lit windows, lamp glass, car lights (night).
  lights:   (L, 7) point lights in camera coordinates x, y, z, r, g, b, intensity.
  intr:     (fx, fy, cx, cy).
  camera_x, camera_z: world X and Z of the camera (world positions of the hits).
  tracks:   world X of the wheel tracks on the road (snow).
  """
  image: np.ndarray
  albedo: np.ndarray
  dist: np.ndarray
  panoptic: np.ndarray
  segments: tuple[Segment, ...]
  material: np.ndarray
  up: np.ndarray
  emissive: np.ndarray
  lights: np.ndarray
  intr: tuple[float, float, float, float]
  camera_x: float
  camera_z: float
  tracks: tuple[float, ...]


def _cam_boxes(boxes: np.ndarray, cam: np.ndarray) -> np.ndarray:
  """(K, 6) x0, x1, y0, y1, z0, z1 of the boxes in camera coordinates (y down)."""
  return np.stack([boxes[:, S.X0] - cam[0], boxes[:, S.X1] - cam[0], cam[1] - boxes[:, S.H1],
                   cam[1] - boxes[:, S.H0], boxes[:, S.Z0] - cam[2], boxes[:, S.Z1] - cam[2]], 1)


def _box_rects(cb: np.ndarray, intr, height: int, width: int):
  """Inclusive pixel rectangles (i0, i1, j0, j1) of the boxes, empty when i0 > i1 or j0 > j1."""
  fx, fy, cx, cy = intr
  x0, x1, y0, y1, z0, z1 = cb.T
  zn = np.maximum(z0, NEAR)
  with np.errstate(divide="ignore", invalid="ignore"):
    us = cx + fx * np.stack([x0 / zn, x0 / z1, x1 / zn, x1 / z1])
    vs = cy + fy * np.stack([y0 / zn, y0 / z1, y1 / zn, y1 / z1])
  ok = z1 > NEAR
  j0 = np.maximum(np.ceil(np.where(ok, us.min(0), np.inf) - 1e-6), 0)
  j1 = np.minimum(np.floor(np.where(ok, us.max(0), -np.inf) + 1e-6), width - 1)
  i0 = np.maximum(np.ceil(np.where(ok, vs.min(0), np.inf) - 1e-6), 0)
  i1 = np.minimum(np.floor(np.where(ok, vs.max(0), -np.inf) + 1e-6), height - 1)
  return [np.nan_to_num(v, nan=-1, posinf=1e9, neginf=-1e9).astype(np.int64)
          for v in (i0, i1, j0, j1)]


def raycast(cb: np.ndarray, a: np.ndarray, b: np.ndarray, cam_h: float,
            intr) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Nearest hit per pixel: t (H, W) float32 (inf = nothing), owner (H, W) int32 and the
  face hit (H, W) uint8 (0: an x face, 1: a y face, 2: a z face; the road plane is 1).

  The owner is OWN_ROAD for the road plane (split into road / pavement by the caller),
  OWN_BOX + k for box k, OWN_SKY for no hit. Per box, within its screen rectangle, the ray
  enters at max(x-slab entry (per column), y-slab entry (per row), z0) and leaves at the
  min of the exits; the camera is never inside a box, so z0 is clamped to NEAR.
  """
  height, width = len(b), len(a)
  t = np.full((height, width), np.inf, np.float32)
  owner = np.zeros((height, width), np.int32)
  face = np.ones((height, width), np.uint8)
  below = b > 0
  with np.errstate(divide="ignore", invalid="ignore"):
    t[below] = (cam_h / b[below])[:, None]
    ia, ib = (1.0 / a).astype(np.float32), (1.0 / b).astype(np.float32)
  owner[below] = OWN_ROAD
  if len(cb) == 0:
    return t, owner, face
  i0, i1, j0, j1 = _box_rects(cb, intr, height, width)
  cb32 = cb.astype(np.float32)
  cb32[:, 4] = np.maximum(cb32[:, 4], NEAR)
  area = np.maximum(i1 - i0 + 1, 0) * np.maximum(j1 - j0 + 1, 0)
  with np.errstate(invalid="ignore", over="ignore"):
    small = np.nonzero((area > 0) & (area <= SMALL_RECT))[0]
    if len(small):
      _raycast_small(t.ravel(), owner.ravel(), face.ravel(), small, area[small], i0, j0, j1,
                     cb32, ia, ib, width)
    for k in np.nonzero(area > SMALL_RECT)[0]:
      rows, cols = slice(i0[k], i1[k] + 1), slice(j0[k], j1[k] + 1)
      x0, x1, y0, y1, z0, z1 = cb32[k]
      txa, txb = x0 * ia[cols], x1 * ia[cols]                       # (c,)
      tya, tyb = y0 * ib[rows], y1 * ib[rows]                       # (r,)
      txn, tyn = np.minimum(txa, txb), np.minimum(tya, tyb)[:, None]
      enter_xz = np.maximum(txn, z0)
      tn = np.maximum(enter_xz, tyn)
      tf = np.minimum(np.minimum(np.maximum(txa, txb), z1), np.maximum(tya, tyb)[:, None])
      sub = t[rows, cols]
      upd = (tn <= tf) & (tn < sub)
      np.copyto(sub, tn, where=upd)
      np.copyto(owner[rows, cols], OWN_BOX + k, where=upd)
      np.copyto(face[rows, cols], np.where(tyn > enter_xz, np.uint8(1),
                                           np.where(txn >= z0, np.uint8(0), np.uint8(2))),
                where=upd)
  return t, owner, face


def _raycast_small(t, owner, face, boxes, area, i0, j0, j1, cb32, ia, ib, width) -> None:
  """The raycast of many boxes with small screen rectangles in one vectorised pass.

  t, owner, face: flat views, updated in place (nearest hit wins, as in the per-box loop).
  """
  wid = (j1 - j0 + 1)[boxes]
  box = np.repeat(boxes, area)
  local = np.arange(area.sum()) - np.repeat(np.cumsum(area) - area, area)
  w = np.repeat(wid, area)
  ii, jj = i0[box] + local // w, j0[box] + local % w
  x0, x1, y0, y1, z0, z1 = cb32[box].T
  txa, txb, tya, tyb = x0 * ia[jj], x1 * ia[jj], y0 * ib[ii], y1 * ib[ii]
  txn, tyn = np.minimum(txa, txb), np.minimum(tya, tyb)
  enter_xz = np.maximum(txn, z0)
  tn = np.maximum(enter_xz, tyn)
  tf = np.minimum(np.minimum(np.maximum(txa, txb), z1), np.maximum(tya, tyb))
  pix = ii * width + jj
  hit = (tn <= tf) & (tn < t[pix])
  pix, tn, box = pix[hit], tn[hit], box[hit]
  fc = np.where(tyn[hit] > enter_xz[hit], 1, np.where(txn[hit] >= z0[hit], 0, 2))
  np.minimum.at(t, pix, tn)
  won = tn == t[pix]
  owner[pix[won]] = OWN_BOX + box[won]
  face[pix[won]] = fc[won]


def _skyline(t, owner, face, a, b, cam, street: S.Street) -> None:
  """The distant skyline plane at z = BACKDROP_Z, in place where nothing nearer was hit."""
  zb = S.BACKDROP_Z
  rows = np.nonzero(b < cam[1] / zb)[0]
  if len(rows) == 0:
    return
  xw = a * zb + cam[0]                                            # (W,)
  cell = np.floor(xw / 14.0)
  top = 6.0 + 34.0 * T.hash01(cell, 3, street.skyline_salt) ** 2
  top = np.where(np.abs(xw) < street.curb + 3.0, 0.0, top)         # the street stays open
  hgt = cam[1] - b[rows, None] * zb                               # (r, 1)
  hit = (hgt >= 0) & (hgt < top[None]) & (t[rows] > zb)
  sub_t, sub_o, sub_f = t[rows], owner[rows], face[rows]
  sub_t[hit] = zb
  sub_o[hit] = OWN_BACKDROP
  sub_f[hit] = 2
  t[rows], owner[rows], face[rows] = sub_t, sub_o, sub_f


def _shadow_rects(cb: np.ndarray, sun_c: np.ndarray, cam_h: float, intr, height, width):
  """Pixel rectangles of the shadow volumes (box swept along -sun to the ground)."""
  fx, fy, cx, cy = intr
  xs = cb[:, [0, 0, 0, 0, 1, 1, 1, 1]]
  ys = cb[:, [2, 2, 3, 3, 2, 2, 3, 3]]
  zs = cb[:, [4, 5, 4, 5, 4, 5, 4, 5]]
  top = np.stack([xs, ys, zs], -1)                                 # (n, 8, 3)
  drop = (cam_h - ys) / -sun_c[1]                                  # sun_c[1] < 0 (y down)
  pts = np.concatenate([top, top - drop[..., None] * sun_c], 1)    # (n, 16, 3): + on the ground
  z = pts[..., 2]
  behind = z < NEAR
  pi, pj = pts[:, :, None], pts[:, None, :]
  with np.errstate(divide="ignore", invalid="ignore"):
    lam = (NEAR - pi[..., 2]) / (pj[..., 2] - pi[..., 2])
    q = pi + lam[..., None] * (pj - pi)                            # (n, 16, 16, 3)
  cross = behind[:, :, None] & ~behind[:, None, :]
  allp = np.concatenate([pts, q.reshape(len(cb), -1, 3)], 1)
  okp = np.concatenate([~behind, cross.reshape(len(cb), -1)], 1)
  zc = np.where(okp, np.maximum(allp[..., 2], NEAR), 1.0)
  u = cx + fx * allp[..., 0] / zc
  v = cy + fy * allp[..., 1] / zc
  j0 = np.maximum(np.ceil(np.where(okp, u, np.inf).min(1)), 0)
  j1 = np.minimum(np.floor(np.where(okp, u, -np.inf).max(1)), width - 1)
  i0 = np.maximum(np.ceil(np.where(okp, v, np.inf).min(1)), 0)
  i1 = np.minimum(np.floor(np.where(okp, v, -np.inf).max(1)), height - 1)
  return [np.nan_to_num(v, nan=-1, posinf=1e9, neginf=-1e9).astype(np.int64)
          for v in (i0, i1, j0, j1)]


def sun_visibility(cb, mats, px, py, pz, sun_c, cam_h, intr) -> np.ndarray:
  """(H, W) 1 where the sun is visible from the hit point, 0 in a box's shadow.

  Slab test of the ray p + s * sun_c, s > 0, against each shadow-casting box whose shadow
  volume's screen rectangle holds the pixel. The hit points p must be nudged towards the
  camera (off their own surface) and put far away where nothing was hit.
  """
  height, width = px.shape
  vis = np.ones((height, width), np.float32)
  # buildings on the side away from the sun shadow only their own backs: skipped
  away = (mats == S.BUILDING) & (cb[:, 0] * sun_c[0] < 0)
  sel = np.nonzero(np.isin(mats, S.SHADOW_CASTERS) & ~away & (cb[:, 5] > -40.0)
                   & (cb[:, 4] < SHADOW_RANGE))[0]
  if len(sel) == 0:
    return vis
  i0, i1, j0, j1 = _shadow_rects(cb[sel], sun_c, cam_h, intr, height, width)
  with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
    inv = 1.0 / sun_c
    # per axis, the bound entered first along the sun ray, scaled by 1 / sun_c
    near_b = np.where(inv >= 0, [0, 2, 4], [1, 3, 5])
    far_b = np.where(inv >= 0, [1, 3, 5], [0, 2, 4])
    qx, qy, qz = (px * inv[0]).astype(np.float32), (py * inv[1]).astype(np.float32), (
        pz * inv[2]).astype(np.float32)
    lo = (cb[:, near_b] * inv).astype(np.float32)                  # (K, 3)
    hi = (cb[:, far_b] * inv).astype(np.float32)
    area = np.maximum(i1 - i0 + 1, 0) * np.maximum(j1 - j0 + 1, 0)
    small = np.nonzero((area > 0) & (area <= SMALL_RECT))[0]
    if len(small):                                                # one batch, as in raycast
      n = np.repeat(small, area[small])
      local = np.arange(len(n)) - np.repeat(np.cumsum(area[small]) - area[small], area[small])
      w = (j1 - j0 + 1)[n]
      pix = (i0[n] + local // w) * width + j0[n] + local % w
      k = sel[n]
      sx, sy, sz = qx.ravel()[pix], qy.ravel()[pix], qz.ravel()[pix]
      tn = np.maximum(np.maximum(lo[k, 0] - sx, lo[k, 1] - sy), lo[k, 2] - sz)
      tf = np.minimum(np.minimum(hi[k, 0] - sx, hi[k, 1] - sy), hi[k, 2] - sz)
      vis.ravel()[pix[(tn <= tf) & (tf > 0)]] = 0.0
    for n in np.nonzero(area > SMALL_RECT)[0]:
      k = sel[n]
      rs, cs = slice(i0[n], i1[n] + 1), slice(j0[n], j1[n] + 1)
      sx, sy, sz = qx[rs, cs], qy[rs, cs], qz[rs, cs]
      tn = np.maximum(np.maximum(lo[k, 0] - sx, lo[k, 1] - sy), lo[k, 2] - sz)
      tf = np.minimum(np.minimum(hi[k, 0] - sx, hi[k, 1] - sy), hi[k, 2] - sz)
      vis[rs, cs][(tn <= tf) & (tf > 0)] = 0.0
  return vis


def contact_darkening(feet, cam, hgt, xw, zw, intr, height, width) -> np.ndarray:
  """(H, W) factor in (0, 1]: soft darkening of the ground under and around vehicles."""
  fx, fy, cx, cy = intr
  ao = np.ones((height, width), np.float32)
  for x0, x1, z0, z1 in feet:
    e0, e1 = z0 - 0.7 - cam[2], z1 + 0.7 - cam[2]
    if e1 < NEAR or e0 > SHADOW_RANGE:
      continue
    zn = max(e0, NEAR)
    us = [cx + fx * (x - cam[0]) / z for x in (x0 - 0.7, x1 + 0.7) for z in (zn, e1)]
    vs = [cy + fy * cam[1] / z for z in (zn, e1)]
    j0, j1 = max(int(np.ceil(min(us))), 0), min(int(np.floor(max(us))), width - 1)
    i0, i1 = max(int(np.ceil(min(vs))) - 2, 0), min(int(np.floor(max(vs))), height - 1)
    if i0 > i1 or j0 > j1:
      continue
    rs, cs = slice(i0, i1 + 1), slice(j0, j1 + 1)
    dx = np.maximum(np.maximum(x0 - xw[rs, cs], xw[rs, cs] - x1), 0.0)
    dz = np.maximum(np.maximum(z0 - zw[rs, cs], zw[rs, cs] - z1), 0.0)
    f = 1.0 - 0.55 * np.exp(-np.sqrt(dx * dx + dz * dz) / 0.35)
    ao[rs, cs] *= np.where(hgt[rs, cs] < 0.2, f, 1.0).astype(np.float32)
  return ao


def _rays(height: int, width: int) -> tuple[np.ndarray, ...]:
  """Ray slopes a (W,), b (H,) in float64, their flat per-pixel float32 copies and the ray
  lengths per unit z-depth (H * W,) float32."""
  fx, fy, cx, cy = C.intrinsics(height, width)
  a = (np.arange(width) - cx) / fx
  b = (np.arange(height) - cy) / fy
  a_flat, b_flat = np.tile(a, height), np.repeat(b, width)
  return (a, b, a_flat.astype(np.float32), b_flat.astype(np.float32),
          np.sqrt(1 + a_flat ** 2 + b_flat ** 2).astype(np.float32))


def render(street: S.Street, sc: S.FrameScene, height: int, width: int) -> Render:
  """Renders one frame in clear weather (see the module docstring)."""
  intr = C.intrinsics(height, width)
  a, b, a_flat, b_flat, ray_len = _rays(height, width)
  cam = sc.camera
  cb = _cam_boxes(sc.boxes, cam)
  t, owner, face = raycast(cb, a, b, cam[1], intr)
  below = b > 0
  with np.errstate(divide="ignore"):
    xw = a[None, :] * (cam[1] / b[below])[:, None] + cam[0]       # road-plane X, (rows, W)
  road = owner[below]
  road[(road == OWN_ROAD) & (np.abs(xw) >= street.curb)] = OWN_PAVE
  owner[below] = road
  _skyline(t, owner, face, a, b, cam, street)

  # hit points in camera coordinates, nudged off their surface for the shadow rays
  nudged = np.where(t < 150.0, t * np.float32(1 - 2e-4), np.float32(1e4))
  px = a_flat.reshape(height, width) * nudged
  py, pz = b_flat.reshape(height, width) * nudged, nudged
  sun_c = np.array([street.sun[0], -street.sun[1], street.sun[2]])
  mats = sc.boxes[:, S.MAT].astype(np.int64)
  vis = sun_visibility(cb, mats, px, py, pz, sun_c, cam[1], intr)
  ao = contact_darkening(sc.footprints, cam, cam[1] - py, px + cam[0], pz + cam[2], intr,
                         height, width)

  mat_of_owner = np.concatenate([[S.SKY, S.GROUND, S.GROUND, S.BACKDROP], mats]).astype(np.uint8)
  mat = mat_of_owner[owner]
  ctx = materials.Context(street=street, boxes_t=np.ascontiguousarray(sc.boxes.T, np.float32),
                          a=a_flat, b=b_flat,
                          t=t.ravel(), owner=owner.ravel(), face=face.ravel(), intr=intr,
                          cam=cam)
  npix = height * width
  flat_mat = mat.ravel()
  order = np.argsort(flat_mat, kind="stable")                     # pixels grouped by material
  bounds = np.concatenate([[0], np.cumsum(np.bincount(flat_mat, minlength=S.NUM_MATERIALS))])
  albedo_sorted = np.empty((3, npix), np.float32)
  emissive_sorted = np.empty(npix, np.float32)
  for m in range(S.NUM_MATERIALS):
    # chunks keep the shaders' temporaries in cache (about 1.5x faster than whole materials)
    for start in range(bounds[m], bounds[m + 1], SHADE_CHUNK):
      part = slice(start, min(start + SHADE_CHUNK, bounds[m + 1]))
      surf = ctx.surface(order[part], materials.SURFACE_KIND.get(m, "box"))
      albedo_sorted[:, part], emissive_sorted[part] = materials.SHADERS[m](ctx, surf)
  albedo = np.empty((3, npix), np.float32)
  materials.put_planar(albedo, order, albedo_sorted)
  emissive = np.empty(npix, np.float32)
  emissive[order] = emissive_sorted
  ndotl, ambient, up = materials.lighting_terms(face.ravel(), a_flat, b_flat, street.sun)
  up &= flat_mat != S.SKY
  light = (vis * ao).ravel()
  amb = ambient * np.minimum(light + np.float32(0.6), np.float32(1.0))
  sun = np.maximum(ndotl, np.float32(0.0)) * light
  haze = cv2.exp(np.minimum(t.ravel() * ray_len, np.float32(1e6)) * np.float32(-HAZE)).ravel()
  image = np.empty((3, npix), np.float32)
  for ch in range(3):
    shade = amb * np.float32(0.42 * SKYLIGHT_RGB[ch]) + sun * np.float32(0.8 * SUN_RGB[ch])
    hor = np.float32(HORIZON_RGB[ch])
    image[ch] = (albedo[ch] * shade - hor) * haze + hor
  sky = order[:bounds[1]]
  materials.put_planar(image, sky, np.take(albedo, sky, axis=1))
  image = np.clip(image, 0.0, 1.0).reshape(3, height, width)

  seg_of_owner = np.concatenate([[C.SKY_ID, C.ROAD_ID, C.PAVEMENT_ID, C.BUILDING_ID],
                                 sc.boxes[:, S.SEG]]).astype(np.int32)
  cat_of_owner = np.concatenate([[C.COCO_SKY, C.COCO_ROAD, C.COCO_PAVEMENT, C.COCO_BUILDING],
                                 sc.boxes[:, S.CAT]]).astype(np.int32)
  present = np.nonzero(np.bincount(owner.ravel(), minlength=len(seg_of_owner)))[0]
  segs = {int(seg_of_owner[o]): int(cat_of_owner[o]) for o in present}
  segments = tuple(Segment(i, segs[i], i >= C.THING_ID_BASE) for i in sorted(segs))

  lights = sc.lights.copy()
  lights[:, 0] -= cam[0]
  lights[:, 1] = cam[1] - lights[:, 1]
  lights[:, 2] -= cam[2]
  lights = lights[lights[:, 2] > NEAR]
  hw = (height, width)
  return Render(image=image, albedo=albedo.reshape(3, height, width),
                dist=t, panoptic=seg_of_owner[owner], segments=segments,
                material=mat, up=up.reshape(hw), emissive=emissive.reshape(hw), lights=lights,
                intr=intr, camera_x=float(cam[0]), camera_z=float(cam[2]),
                tracks=(street.ego_x - 0.8, street.ego_x + 0.8, -street.lane_w / 2 - 0.8,
                        -street.lane_w / 2 + 0.8))
