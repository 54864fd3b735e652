"""Configuration, camera and category tables of the synthetic driving benchmark."""

from __future__ import annotations

import dataclasses
import math

DOMAINS = ("clear", "fog", "rain", "night", "snow")  # "clear" is the source domain

# COCO panoptic category ids (panoptic_coco_categories.json, as in detectron2's
# `builtin_meta.COCO_CATEGORIES`). COCO has no "pole": street-light poles are labelled
# "fence-merged", the closest thin man-made stuff class (to reconcile with `data/coco.py`).
COCO_PERSON, COCO_BICYCLE, COCO_CAR, COCO_TRUCK = 1, 2, 3, 8  # things
COCO_ROAD = 149                 # "road"
COCO_PAVEMENT = 191             # "pavement-merged" (sidewalks, curbs)
COCO_BUILDING = 197             # "building-other-merged"
COCO_FENCE = 185                # "fence-merged" (our poles)
COCO_SKY = 187                  # "sky-other-merged"

# Segment ids of the stuff classes in every id map (one segment per stuff class, as in COCO
# panoptic). Thing ids are THING_ID_BASE + code * ID_STRIDE + slot % ID_STRIDE, with `code` the
# object's stream (lane or sidewalk, `scene`): unique within a frame, stable across the frames
# of a sequence (over 4096 slots, i.e. kilometres), and below 2^16.
ROAD_ID, PAVEMENT_ID, BUILDING_ID, POLE_ID, SKY_ID = 1, 2, 3, 4, 5
STUFF_CATEGORY = {ROAD_ID: COCO_ROAD, PAVEMENT_ID: COCO_PAVEMENT, BUILDING_ID: COCO_BUILDING,
                  POLE_ID: COCO_FENCE, SKY_ID: COCO_SKY}
THING_ID_BASE = 16
ID_STRIDE = 4096


# The longest drive a sequence may cover: the renderer's float arithmetic holds to about 4e7 m
# and 3e6 s at the default speed (frame 5e7 had non-finite pixels); at the defaults (10 fps,
# 8 m/s) these allow 1e7 frames, 11.6 days of driving
MAX_SECONDS = 1e6
MAX_METRES = 1e7


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
  """One synthetic sequence.

  Geometry, depth and panoptic depend on (seed, sizes, traffic fields, frame index) only;
  `domain` and `severity` change the image alone, so a seed gives the same street in every
  domain and the effect of the shift can be measured.
  """
  height: int = 192                 # MonoDepth2 input 640x192
  width: int = 640
  num_frames: int = 100
  start: int = 0                    # index of the first frame (chunked generation)
  seed: int = 0
  domain: str = "clear"             # one of DOMAINS
  severity: float = 0.7             # weather strength in [0, 1]; ignored by "clear"
  fps: float = 10.0                 # KITTI records at 10 Hz
  speed: float = 8.0                # ego speed along the road, m/s
  camera_height: float = 1.65       # KITTI camera height above the road, m
  max_depth: float = 80.0           # ground truth farther than this is 0 (invalid), as LiDAR
  n_cars: float = 8.0               # expected cars and trucks within 100 m ahead
  n_pedestrians: float = 6.0        # expected pedestrians within 100 m ahead
  n_cyclists: float = 1.0           # expected cyclists within 100 m ahead
  n_lead_cars: int = 1              # cars ahead in the ego lane (0..2)
  truck_fraction: float = 0.2       # share of trucks among the oncoming vehicles

  def __post_init__(self):
    if self.domain not in DOMAINS:
      raise ValueError(f"domain {self.domain!r} not in {DOMAINS}")
    if not 0.0 <= self.severity <= 1.0:
      raise ValueError(f"severity {self.severity} not in [0, 1]")
    for name, low in (("height", 8), ("width", 8), ("num_frames", 0), ("start", 0)):
      if getattr(self, name) < low:
        raise ValueError(f"{name} must be >= {low}, got {getattr(self, name)}")
    if not 0 <= self.n_lead_cars <= 2:
      raise ValueError("n_lead_cars must be 0, 1 or 2")
    if self.seed < 0:
      raise ValueError(f"seed must be >= 0, got {self.seed}")
    for name, low, strict in (("fps", 0.0, True), ("speed", 0.0, False),
                              ("camera_height", 0.0, True), ("max_depth", 0.0, True),
                              ("n_cars", 0.0, False), ("n_pedestrians", 0.0, False),
                              ("n_cyclists", 0.0, False)):
      value = getattr(self, name)
      if not (math.isfinite(value) and (value > low if strict else value >= low)):
        raise ValueError(f"{name} must be finite and {'>' if strict else '>='} {low:g}, got "
                         f"{value}")
    end = (self.start + self.num_frames) / self.fps  # seconds of driving to the last frame
    if end > MAX_SECONDS or end * self.speed > MAX_METRES:
      longest = min(MAX_SECONDS, MAX_METRES / self.speed if self.speed > 0 else math.inf)
      raise ValueError(f"num_frames: frames up to {self.start + self.num_frames} drive "
                       f"{end:.3g} s and {end * self.speed:.3g} m, beyond the street the "
                       f"renderer draws exactly ({MAX_SECONDS:.0e} s, {MAX_METRES:.0e} m: "
                       f"{int(longest * self.fps)} frames at fps {self.fps:g} and speed "
                       f"{self.speed:g})")
    if not 0.0 <= self.truck_fraction <= 1.0:
      raise ValueError(f"truck_fraction must be in [0, 1], got {self.truck_fraction}")


def intrinsics(height: int, width: int) -> tuple[float, float, float, float]:
  """(fx, fy, cx, cy) in pixels: MonoDepth2's normalised KITTI matrix scaled to the image.

  Pixel (row i, column j) looks along the ray ((j - cx) / fx, (i - cy) / fy, 1) in camera
  coordinates (x right, y down, z forward), so the horizon is the row i = cy = H / 2.
  """
  return 0.58 * width, 1.92 * height, 0.5 * width, 0.5 * height
