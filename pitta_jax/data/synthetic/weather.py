"""Weather and lighting shifts of the synthetic benchmark: the target domains.

Each domain maps a clear render (image, depth, materials, lights) to a new image, as a
deterministic function of (render, severity, seed, frame index); geometry, depth and panoptic
are left unchanged. `severity` in [0, 1] scales every effect (0: almost clear).

- fog:   Koschmieder's law, out = I t + A (1 - t), t = exp(-beta r), r the distance along the
         ray (z-depth * |((j - cx) / fx, (i - cy) / fy, 1)|), beta = FOG_BETA_MAX * severity,
         A = FOG_AIRLIGHT; sky pixels (no hit) get t = 0 (pure airlight) when severity > 0.
         Nothing else changes, so the formula can be checked per pixel.
- rain:  overcast sky, darker and less saturated, light rain haze, wet road (darker, with a
         blurred planar-mirror image of what stands on it), slanted semi-transparent
         streaks, slight blur.
- night: ambient light scaled down with a blue tint, street lamps and the ego headlights
         re-lighting the albedo, lit windows and car lights, glows around the light sources,
         sensor noise.
- snow:  snow cover on upward-facing surfaces (wheel tracks left in the lanes), brighter and
         low-contrast, cold haze, flakes in three depth layers.

Images are planar (3, H, W) float32 until `apply_weather` returns (H, W, 3).
"""

from __future__ import annotations

import cv2
import numpy as np

from pitta_jax.data.synthetic import config as C
from pitta_jax.data.synthetic import scene as S
from pitta_jax.data.synthetic.render import Render
from pitta_jax.data.synthetic.textures import noise

FOG_BETA_MAX = 0.08                                    # 1/m: visibility 3 / beta = 37.5 m
FOG_AIRLIGHT = np.array([0.78, 0.80, 0.82], np.float32)
F32 = np.float32
LUMA = np.array([0.299, 0.587, 0.114], np.float32)


def _rng(seed: int, index: int, domain: str) -> np.random.Generator:
  return np.random.default_rng([seed, 7, index, C.DOMAINS.index(domain)])


def _col(*rgb: float) -> np.ndarray:
  return np.array(rgb, np.float32)[:, None, None]


def _grid(intr: tuple[float, float, float, float], height: int, width: int):
  """Ray slopes a (1, W), b (H, 1) and ray length per unit depth (H, W), float32."""
  fx, fy, cx, cy = intr
  a = ((np.arange(width) - cx) / fx).astype(np.float32)[None, :]
  b = ((np.arange(height) - cy) / fy).astype(np.float32)[:, None]
  return a, b, np.sqrt(1 + a * a + b * b)


def _gauss_bank(n: int) -> np.ndarray:
  """A fixed bank of n + 65536 standard normal float32 samples (sensor noise)."""
  return np.random.default_rng(4242).standard_normal(n + 65536, np.float32)


def transmittance(r: Render, beta: float) -> np.ndarray:
  """(H, W) exp(-beta * distance along the ray); 0 where nothing was hit (sky) if beta > 0."""
  if beta <= 0:
    return np.ones(r.dist.shape, np.float32)
  ray_len = _grid(r.intr, *r.dist.shape)[2]
  arg = np.minimum(r.dist * ray_len, F32(1e6)) * F32(-beta)       # inf (sky) -> exp ~ 0
  t = cv2.exp(arg)
  t[~np.isfinite(r.dist)] = 0.0
  return t


def _scatter(img: np.ndarray, t: np.ndarray, airlight) -> np.ndarray:
  """img t + A (1 - t), planar."""
  air = np.asarray(airlight, np.float32)[:, None, None]
  return (img - air) * t + air


def fog(r: Render, severity: float) -> np.ndarray:
  return _scatter(r.image, transmittance(r, FOG_BETA_MAX * severity), FOG_AIRLIGHT)


def _luma(img: np.ndarray) -> np.ndarray:
  return LUMA[0] * img[0] + LUMA[1] * img[1] + LUMA[2] * img[2]


def _blur(img: np.ndarray, sx: float, sy: float | None = None) -> np.ndarray:
  """Gaussian blur of a planar image, channel by channel."""
  sy = sx if sy is None else sy
  return np.stack([cv2.GaussianBlur(np.ascontiguousarray(ch), (0, 0), sx, sigmaY=sy)
                   for ch in img])


def _streaks(shape, rng, count: int, length: float, angle: float, width: int,
             value: float) -> np.ndarray:
  """(H, W) float32 layer of anti-aliased slanted line segments."""
  h, w = shape
  layer = np.zeros(shape, np.float32)
  if count <= 0:
    return layer
  start = rng.uniform([-w * 0.1, -length], [w * 1.1, h], (count, 2))
  end = start + length * rng.uniform(0.6, 1.2, (count, 1)) * np.array(
      [np.sin(angle), np.cos(angle)])
  segs = np.stack([start, end], 1).round().astype(np.int32)
  cv2.polylines(layer, list(segs), False, (value,), width, cv2.LINE_AA)
  return layer


def rain(r: Render, severity: float, seed: int, index: int) -> np.ndarray:
  rng = _rng(seed, index, "rain")
  s = F32(severity)
  h, w = r.dist.shape
  sky = r.material == S.SKY
  img = _scatter(r.image, transmittance(r, 0.012 * severity), (0.60, 0.62, 0.65))
  grey = _col(0.55, 0.57, 0.60)
  img = np.where(sky, img * (1 - 0.8 * s) + 0.8 * s * grey, img)
  img = img * (1.0 - 0.35 * s)
  img = img + (0.35 * s) * (_luma(img) - img)                       # desaturate
  wet = r.up & np.isin(r.material, (S.GROUND, S.SIDEWALK))
  cy = int(round(r.intr[3]))
  rows = np.arange(h, dtype=np.int16)[:, None]
  # planar mirror: a point at height Y above the road shows at row 2 v0 - v, v0 the row where
  # the object behind meets the road (the lowest non-road row above); the horizon if none
  above = np.maximum.accumulate(np.where(wet, np.int16(-1), rows), axis=0)
  src = np.clip(np.where(above >= 0, 2 * above - rows, 2 * cy - rows), 0, h - 1)
  pix = np.flatnonzero(wet)
  src_pix = src.ravel()[pix].astype(np.int64) * w + pix % w
  fresnel = 0.15 + 0.85 * np.exp(-np.clip(pix // w - cy, 0, None) / (0.2 * h))
  wgt = (0.55 * severity * fresnel).astype(np.float32)
  keep = (1.0 - 0.25 * s) * (1.0 - 0.4 * wgt)                      # wet asphalt is darker
  for ch in range(3):                                             # img is a fresh array here
    rough = cv2.blur(img[ch], (3, 7)).ravel()                     # rippled reflection
    flat = img[ch].reshape(-1)
    flat[pix] = flat[pix] * keep + wgt * rough[src_pix]
  img = _blur(img, 0.4 + 0.7 * severity)
  angle = np.deg2rad(np.random.default_rng([seed, 8]).uniform(-20, 20))
  far = _streaks((h, w), rng, int(severity * 0.003 * h * w), 0.06 * h, angle, 1, 0.35)
  near = _streaks((h, w), rng, int(severity * 0.0005 * h * w), 0.2 * h, angle, 2, 0.5)
  alpha = np.clip(far + cv2.GaussianBlur(near, (0, 0), 1.0), 0, 0.7)
  return img + alpha * (_col(0.82, 0.84, 0.88) - img)


def night(r: Render, severity: float, seed: int, index: int) -> np.ndarray:
  rng = _rng(seed, index, "night")
  s = F32(severity)
  h, w = r.dist.shape
  fx, fy, cx, cy = r.intr
  a, b, _ = _grid(r.intr, h, w)
  valid = np.isfinite(r.dist) & (r.dist < 150)
  t = np.where(valid, r.dist, F32(0))
  ambient = F32(0.22 - 0.22 * severity)
  # ego headlights: a cone ahead, falling off with distance
  head = (F32(1.6) * cv2.exp(-(a / F32(0.4)) ** 2 - ((b - F32(0.05)) / F32(0.1)) ** 2)
          / (1.0 + (t * F32(1 / 18.0)) ** 2) * valid)
  light = np.empty((3, h, w), np.float32)
  for ch, (tint, hc) in enumerate(zip((0.75, 0.85, 1.2), (1.0, 0.97, 0.9))):
    light[ch] = ambient * F32(tint) + head * F32(hc)
  # street lamps light the scene within ~12 m; smooth, so computed at half resolution
  hh, hw = h // 2, w // 2
  th = t[:2 * hh:2, :2 * hw:2]
  vh = valid[:2 * hh:2, :2 * hw:2]
  px, py = a[:, :2 * hw:2] * th, b[:2 * hh:2] * th
  lamp = np.zeros((3, hh, hw), np.float32)
  for lx, ly, lz, cr, cg, cb, inten in r.lights:
    if inten < 3.0 or lz > 100.0:                                 # street lamps only
      continue
    rad = 12.0                                                    # influence radius, m
    if lz - rad < 0.2:
      j0, j1, i0, i1 = 0, hw, 0, hh
    else:
      us = [(cx + fx * (lx + e) / (lz - rad)) / 2 for e in (-rad, rad)]
      vs = [(cy + fy * (ly + e) / (lz - rad)) / 2 for e in (-rad, rad)]
      j0, j1 = int(np.clip(min(us), 0, hw)), int(np.clip(max(us) + 1, 0, hw))
      i0, i1 = int(np.clip(min(vs), 0, hh)), int(np.clip(max(vs) + 1, 0, hh))
    if j0 >= j1 or i0 >= i1:
      continue
    rs, cs = slice(i0, i1), slice(j0, j1)
    d2 = (px[rs, cs] - lx) ** 2 + (py[rs, cs] - ly) ** 2 + (th[rs, cs] - lz) ** 2
    f = (F32(0.22 * inten) / (1.0 + d2 * F32(1 / 9.0))) * vh[rs, cs]
    for ch, cc in enumerate((cr, cg, cb)):
      lamp[ch, rs, cs] += f * F32(cc)
  for ch in range(3):
    light[ch] += cv2.resize(lamp[ch], (w, h), interpolation=cv2.INTER_LINEAR)
  img = r.albedo * light
  sky = r.material == S.SKY
  glow_rows = np.exp(-np.clip(cy - np.arange(h), 0, None) / (0.15 * h)).astype(np.float32)
  sky_col = _col(0.015, 0.02, 0.045) + glow_rows[None, :, None] * _col(0.06, 0.05, 0.045)
  img = np.where(sky, sky_col, img)
  em = np.flatnonzero(r.emissive)                                 # lit windows, lamps, car lights
  lamp_like = np.isin(r.material.ravel()[em], (S.BODY, S.LAMP))
  for ch, warm in enumerate((1.0, 0.78, 0.45)):
    flat = img[ch].reshape(-1)
    glow_col = np.where(lamp_like, 0.4 + r.albedo[ch].ravel()[em], 0.75 * warm)
    flat[em] += r.emissive.ravel()[em] * glow_col
  # glows around visible light sources, drawn at half resolution (they are smooth)
  glow = np.zeros((hh, hw, 3), np.float32)
  for lx, ly, lz, cr, cg, cb, inten in r.lights:
    if lz < 0.5:
      continue
    u, v = cx + fx * lx / lz, cy + fy * ly / lz
    if not (0 <= u < w and 0 <= v < h) or r.dist[int(v), int(u)] < lz - 0.6:
      continue
    amp = min(1.0, inten * 6.0 / lz)
    cv2.circle(glow, (int(u / 2), int(v / 2)), max(1, int(0.06 * fx / lz)),
               (cr * amp, cg * amp, cb * amp), -1, cv2.LINE_AA)
  small = cv2.resize(glow, (hw // 4, hh // 4), interpolation=cv2.INTER_AREA)
  halo = cv2.resize(cv2.GaussianBlur(small, (0, 0), 1.0), (hw, hh), interpolation=cv2.INTER_LINEAR)
  glow = cv2.resize(cv2.GaussianBlur(glow, (0, 0), 1.0) + 0.6 * halo, (w, h),
                    interpolation=cv2.INTER_LINEAR)
  img = _blur(img + glow.transpose(2, 0, 1), 0.5)
  bank = _gauss_bank(3 * h * w)
  off = int(rng.integers(0, 65536))
  gauss = bank[off:off + 3 * h * w].reshape(3, h, w)
  return img + (0.01 + 0.035 * s) * np.sqrt(np.clip(img, 0, 1) + F32(0.05)) * gauss


def snow(r: Render, severity: float, seed: int, index: int) -> np.ndarray:
  rng = _rng(seed, index, "snow")
  s = F32(severity)
  h, w = r.dist.shape
  fx = r.intr[0]
  a, _, _ = _grid(r.intr, h, w)
  img = r.image
  up = (r.up & np.isfinite(r.dist)).ravel()
  sel = np.nonzero(up)[0]
  if len(sel):
    t = r.dist.ravel()[sel]
    xw = np.broadcast_to(a, (h, w)).ravel()[sel] * t + F32(r.camera_x)
    patch = noise(xw, t + F32(r.camera_z), t * F32(1 / fx), 0.04, 21)
    cover = np.clip(0.85 + 0.25 * patch, 0, 1)
    road = r.material.ravel()[sel] == S.GROUND
    for tx in r.tracks:                                           # wheel tracks: slush
      cover = np.where(road & (np.abs(xw - tx) < 0.16), cover * 0.4, cover)
    amount = np.zeros(h * w, np.float32)
    amount[sel] = s * cover
    amount = amount.reshape(h, w)
    shade = np.clip(_luma(img) / np.maximum(_luma(r.albedo), 0.05), 0.6, 1.3)
    target = np.where(amount > 0.3 * s, _col(0.92, 0.94, 0.98) * np.minimum(shade, 1.1),
                      _col(0.45, 0.46, 0.48) * shade)
    img = img + amount * (target - img)
  img = _scatter(img, transmittance(r, 0.015 * severity), (0.85, 0.87, 0.9))
  sky = r.material == S.SKY
  img = np.where(sky, img * (1 - 0.85 * s) + 0.85 * s * _col(0.82, 0.84, 0.87), img)
  img = img + (0.25 * s) * (_col(0.8, 0.82, 0.86) - img)           # low contrast
  layers = np.zeros((h, w), np.float32)
  for density, sigma, gain in ((0.004, 0.6, 2.5), (0.0012, 1.2, 6.0), (0.00025, 2.5, 20.0)):
    n = int(severity * density * h * w)
    pts = np.zeros(h * w, np.float32)
    np.add.at(pts, rng.integers(0, h * w, n), rng.uniform(0.5, 1.0, n).astype(np.float32))
    layers += gain * cv2.GaussianBlur(pts.reshape(h, w), (0, 0), sigma)
  alpha = np.clip(layers, 0, 0.9)
  return img + alpha * (_col(0.95, 0.96, 0.98) - img)


def apply_weather(r: Render, domain: str, severity: float, seed: int, index: int) -> np.ndarray:
  """(H, W, 3) float32 image in [0, 1] of the clear render `r` under `domain`."""
  if domain == "clear":
    img = r.image
  elif domain == "fog":
    img = fog(r, severity)
  elif domain == "rain":
    img = rain(r, severity, seed, index)
  elif domain == "night":
    img = night(r, severity, seed, index)
  elif domain == "snow":
    img = snow(r, severity, seed, index)
  else:
    raise ValueError(f"unknown domain {domain!r}; expected one of {C.DOMAINS}")
  return np.ascontiguousarray(np.clip(img, 0.0, 1.0, dtype=np.float32).transpose(1, 2, 0))
