"""Procedural synthetic driving benchmark: the project's embedded default dataset.

A camera 1.65 m above a straight street drives forward (8 m/s, 10 fps by default) past
buildings, street lights, parked and oncoming cars, trucks, a lead car, cyclists and walking
pedestrians (right-hand traffic; `scene`). Intrinsics are MonoDepth2's normalised KITTI ones,
fx = 0.58 W, fy = 1.92 H, cx = W / 2, cy = H / 2, with pixel (i, j) looking along
((j - cx) / fx, (i - cy) / fy, 1): the camera looks along the road, so row cy is the horizon.
Everything is rendered analytically, one ray per pixel, against the road plane and
axis-aligned boxes (`render`), with procedural pixel-footprint-filtered textures
(`textures`, `materials`), Lambert shading, sun shadows and contact darkening, so the per-pixel
ground truth is exact:

- depth: z-depth along the optical axis in metres (KITTI / MonoDepth2 convention), 0 =
  invalid: the sky and anything farther than `max_depth` (80 m by default, like a LiDAR's
  range; the image still shows it). A road pixel below the horizon has depth h fy / (i - cy).
- panoptic: int32 segment ids, never 0 (every pixel is a stuff class or a thing), with COCO
  category ids: things person 1, bicycle 2, car 3, truck 8 (ids in [16, 2^16), stable across
  the frames of a sequence); stuff road 149, pavement-merged 191 (sidewalks and curbs),
  building-other-merged 197, sky-other-merged 187, and the poles as fence-merged 185 (COCO has
  no pole class; see `config`).

Domains (`weather`): "clear" is the source; "fog", "rain", "night" and "snow" are shifts with
a severity in [0, 1] (default 0.7). A seed gives the same street, depth and panoptic in every
domain, and a frame is a deterministic function of (config, index): `render_frame` equals the
frame of `generate_sequence`. Usage::

  cfg = SyntheticConfig(seed=0, num_frames=200, domain="fog")
  frames = generate_sequence(cfg)            # list[Frame], names "fog/0/000000", ...
  export_drivingstereo(frames, "/data/synth", "foggy")
  for per_domain in iter_domains(cfg):       # {"clear": Frame, "fog": Frame, ...}, one render
    ...
"""

from pitta_jax.data.synthetic.config import (COCO_BICYCLE, COCO_BUILDING, COCO_CAR, COCO_FENCE,
                                             COCO_PAVEMENT, COCO_PERSON, COCO_ROAD, COCO_SKY,
                                             COCO_TRUCK, DOMAINS, STUFF_CATEGORY, THING_ID_BASE,
                                             SyntheticConfig, intrinsics)
from pitta_jax.data.synthetic.export import encode_panoptic, export_drivingstereo
from pitta_jax.data.synthetic.generate import (SyntheticSequence, generate_sequence,
                                               ground_truth_depth, iter_domains, iter_frames,
                                               render_clear, render_frame)
from pitta_jax.data.synthetic.weather import FOG_AIRLIGHT, FOG_BETA_MAX, apply_weather

__all__ = [
    "COCO_BICYCLE", "COCO_BUILDING", "COCO_CAR", "COCO_FENCE", "COCO_PAVEMENT", "COCO_PERSON",
    "COCO_ROAD", "COCO_SKY", "COCO_TRUCK", "DOMAINS", "FOG_AIRLIGHT", "FOG_BETA_MAX",
    "STUFF_CATEGORY", "THING_ID_BASE", "SyntheticConfig", "SyntheticSequence", "apply_weather",
    "encode_panoptic", "export_drivingstereo", "generate_sequence", "ground_truth_depth",
    "intrinsics", "iter_domains", "iter_frames", "render_clear", "render_frame",
]
