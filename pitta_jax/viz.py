"""Images for people: colour-mapped disparity/depth, panoptic colours, image grids (host NumPy).

MonoDepth2's convention for disparity pictures: the magma colour map normalised by the 95th
percentile of the disparity.
"""

from __future__ import annotations

import cv2
import numpy as np

from pitta_jax.metrics import MAX_DEPTH


def colorize(values: np.ndarray, vmin: float | None = None, vmax: float | None = None,
             colormap: str = "magma") -> np.ndarray:
  """(H, W) float -> (H, W, 3) uint8 RGB. Defaults: vmin = min, vmax = 95th percentile.

  As MonoDepth2's `test_simple.py` writes its disparity pictures: matplotlib's colour map
  through `Normalize(vmin, vmax)` (values above vmax take its top colour), RGBA * 255 cut to
  uint8; non-finite values take vmin's colour."""
  import matplotlib
  from matplotlib.colors import Normalize
  values = np.asarray(values)
  if not np.issubdtype(values.dtype, np.floating):
    values = values.astype(np.float64)
  finite = np.isfinite(values)
  if not finite.any():
    return np.zeros(values.shape + (3,), np.uint8)
  lo = np.min(values[finite]) if vmin is None else vmin
  hi = np.percentile(values[finite], 95) if vmax is None else vmax
  hi = max(hi, lo)  # (a vmin above the percentile: every value takes the bottom colour)
  mapped = matplotlib.colormaps[colormap](Normalize(vmin=lo, vmax=hi)(np.where(finite, values,
                                                                               lo)))
  return (mapped[..., :3] * 255).astype(np.uint8)


def colorize_depth(depth: np.ndarray, max_depth: float = MAX_DEPTH) -> np.ndarray:
  """Depth (H, W) metres -> RGB via its disparity (near = bright), 0/invalid -> black."""
  depth = np.asarray(depth, np.float64)
  valid = depth > 0
  disp = np.where(valid, 1.0 / np.maximum(depth, 1e-6), np.nan)
  rgb = colorize(disp, vmin=1.0 / max_depth)
  rgb[~valid] = 0
  return rgb


def colorize_ids(ids: np.ndarray, seed: int = 0) -> np.ndarray:
  """Integer id map (H, W) -> RGB, a fixed pseudo-random colour per id, 0 -> black."""
  ids = np.asarray(ids, np.int64)
  uniq, inverse = np.unique(ids, return_inverse=True)
  rng = np.random.default_rng(seed)
  palette = rng.integers(40, 256, size=(len(uniq), 3), dtype=np.uint8)
  palette[uniq == 0] = 0
  return palette[inverse.reshape(ids.shape)]


def label(image: np.ndarray, text: str) -> np.ndarray:
  """A copy of a uint8 RGB image with `text` in its top-left corner (white on a dark band)."""
  out = image.copy()
  scale = max(0.35, image.shape[0] / 400)
  (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
  out[: th + 8, : tw + 8] = (out[: th + 8, : tw + 8] * 0.3).astype(np.uint8)
  cv2.putText(out, text, (4, th + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
              cv2.LINE_AA)
  return out


def grid(rows: list[list[np.ndarray]], pad: int = 4) -> np.ndarray:
  """Tiles uint8 RGB images (resized to the first image's size) into a grid."""
  h, w = rows[0][0].shape[:2]
  ncol = max(len(r) for r in rows)
  out = np.full((len(rows) * (h + pad) - pad, ncol * (w + pad) - pad, 3), 255, np.uint8)
  for i, row in enumerate(rows):
    for j, img in enumerate(row):
      if img.shape[:2] != (h, w):
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_NEAREST)
      out[i * (h + pad): i * (h + pad) + h, j * (w + pad): j * (w + pad) + w] = img
  return out


def to_uint8(image: np.ndarray) -> np.ndarray:
  """float RGB in [0, 1] -> uint8 (rounded)."""
  return np.clip(np.rint(np.asarray(image, np.float64) * 255.0), 0, 255).astype(np.uint8)
