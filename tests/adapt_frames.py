"""Small adaptation frames shared by the engine and multi-stream tests (64x96, 8 segments)."""

from __future__ import annotations

import numpy as np

from pitta_jax.adapt import StepInput

H, W, S = 64, 96, 8
CAR, PERSON, ROAD = 3, 1, 149


def make_frames(n: int, seed: int = 0) -> StepInput:
  """n frames: smooth random images, two cars + a person touching each other, a road."""
  rng = np.random.default_rng(seed)
  yy, xx = np.mgrid[0:H, 0:W]
  images, pans = [], []
  for t in range(n):
    base = 0.5 + 0.3 * np.sin(xx / (7 + t) + rng.uniform(0, 6))[..., None] * np.array([1, .8, .6])
    images.append(np.clip(base + 0.05 * rng.normal(size=(H, W, 3)), 0, 1))
    pan = np.full((H, W), 7, np.int32)           # road (stuff)
    pan[30:50, 10 + t:40 + t] = 11               # car
    pan[30:50, 40 + t:60 + t] = 12               # car touching the first
    pan[20:50, 70:76] = 13                       # person
    pans.append(pan)
  seg_ids = np.zeros((n, S), np.int32)
  seg_cls = np.zeros((n, S), np.int32)
  seg_valid = np.zeros((n, S), bool)
  seg_ids[:, :4] = [7, 11, 12, 13]
  seg_cls[:, :4] = [ROAD, CAR, CAR, PERSON]
  seg_valid[:, :4] = True
  return StepInput(np.stack(images).astype(np.float32), np.stack(pans), seg_ids, seg_cls,
                   seg_valid, np.ones((n,), bool), np.zeros((n, 3, 3), np.float32),
                   np.zeros((n,), bool), np.zeros((n,), bool))
