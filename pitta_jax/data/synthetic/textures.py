"""Procedural, pixel-footprint-filtered textures of the synthetic benchmark (NumPy).

Every pattern takes surface coordinates in metres and the pixel footprint on the surface
(`fp`, metres per pixel), and returns its box-filtered value over that footprint, so that
distant bricks, windows and lane dashes fade to their mean instead of aliasing:
`pulse` (a periodic square wave, filtered in closed form), `band` (an interval), and `noise`
(a tileable Gaussian-filtered noise with one pre-blurred level per octave of footprint).
"""

from __future__ import annotations

import numpy as np

_NOISE_SIZE = 256   # power of two: tiles wrap with a bit mask
_NOISE_LEVELS = 8


def _noise_pyramid() -> np.ndarray:
  """(L, N, N) float32 tileable fractal noise; level l is level 0 blurred by 2**l texels.

  Level 0 sums three octaves (feature sizes about 2, 10 and 40 texels) so that one lookup gives
  fine grain and large blotches; unit standard deviation.
  """
  n = _NOISE_SIZE
  rng = np.random.default_rng(20240531)
  f = np.fft.fftfreq(n)
  k2 = f[:, None] ** 2 + f[None, :] ** 2

  def octave(sigma: float) -> np.ndarray:
    x = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) *
                             np.exp(-2 * np.pi ** 2 * sigma ** 2 * k2)))
    return x / x.std()

  base = np.fft.fft2(octave(1.0) + 0.7 * octave(5.0) + 0.6 * octave(20.0))
  levels = [np.real(np.fft.ifft2(base * np.exp(-2 * np.pi ** 2 * (2.0 ** l - 1) ** 2 * k2)))
            for l in range(_NOISE_LEVELS)]
  out = np.stack(levels)
  out = (out / out[0].std()).astype(np.float32)
  out.setflags(write=False)
  return out


# a constant of the module (1 MB, ~55 ms at import), read-only: every `noise` lookup reads it
_NOISE_PYRAMID = _noise_pyramid()


def noise(s: np.ndarray, r: np.ndarray, fp: np.ndarray, texel: float,
          salt: int = 0) -> np.ndarray:
  """Fractal noise (unit std when magnified) at surface point (s, r) metres.

  texel: size of a noise texel in metres (finest features about 2 texels, coarsest 40).
  fp: pixel footprint in metres; picks the pre-blurred level, so the value tends to the mean
  (0) when texels are smaller than pixels. Nearest-texel lookup.
  """
  pyr = _NOISE_PYRAMID
  inv = np.float32(1.0 / texel)
  # floor(log2(footprint in texels)) from the float32 exponent bits, clamped to the levels
  bits = np.maximum(fp * inv, np.float32(1.0)).astype(np.float32).view(np.int32)
  level = np.minimum((bits >> 23) - 127, _NOISE_LEVELS - 1)
  iu = (np.floor(s * inv).astype(np.int32) + 97 * salt) & (_NOISE_SIZE - 1)
  iv = (np.floor(r * inv).astype(np.int32) + 61 * salt) & (_NOISE_SIZE - 1)
  return np.take(pyr, (level * _NOISE_SIZE + iv) * _NOISE_SIZE + iu)


def _pulse_integral(x: np.ndarray, duty: float | np.ndarray) -> np.ndarray:
  fl = np.floor(x)
  return fl * duty + np.minimum(x - fl, duty)


def pulse(x: np.ndarray, duty: float | np.ndarray, w: np.ndarray) -> np.ndarray:
  """Box-filtered square wave of period 1: 1 on [k, k + duty), 0 elsewhere.

  x and the filter width w are in periods; w >> 1 gives the mean, `duty`.
  """
  w = np.maximum(w, 1e-4)
  return (_pulse_integral(x + 0.5 * w, duty) - _pulse_integral(x - 0.5 * w, duty)) / w


def band(x: np.ndarray, lo: float | np.ndarray, hi: float | np.ndarray,
         w: np.ndarray) -> np.ndarray:
  """Box-filtered indicator of lo <= x < hi, filter width w (same units as x)."""
  w = np.maximum(w, 1e-4)
  return np.clip((np.minimum(x + 0.5 * w, hi) - np.maximum(x - 0.5 * w, lo)) / w, 0.0, 1.0)


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
  t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
  return t * t * (3.0 - 2.0 * t)


def hash01(i: np.ndarray, j: np.ndarray, salt: np.ndarray | int) -> np.ndarray:
  """Deterministic pseudo-random float32 in [0, 1) per integer cell (i, j) and salt.

  i, j: integer-valued arrays (any numeric dtype); uint32 arithmetic wraps modulo 2^32.
  """
  u32 = np.uint32
  with np.errstate(over="ignore"):                                # wrapping is the point
    h = (np.asarray(i).astype(np.int32).view(u32) * u32(73856093)) ^ (
        np.asarray(j).astype(np.int32).view(u32) * u32(19349663)) ^ (
            np.asarray(salt).astype(np.int64).astype(u32) * u32(83492791))
    h = h ^ (h >> u32(13))
    h = h * u32(1274126177)
    h = h ^ (h >> u32(16))
  return (h >> u32(8)).astype(np.float32) * np.float32(1.0 / 16777216)


def mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
  """a + (b - a) * t for planar colours: a, b (3, n) or (3, 1), t (n,)."""
  return a + (b - a) * t


def rgb(r: float, g: float, b: float) -> np.ndarray:
  """A constant colour as a (3, 1) float32 column (broadcasts against planar (3, n))."""
  return np.array([[r], [g], [b]], np.float32)
