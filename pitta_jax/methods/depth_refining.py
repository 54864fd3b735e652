"""The depth-refining term (paper eqs. 3-8) on an engine frame, and its config.

PITTA's L_d; the paper adds the same term, with the same instance masks, to every baseline it
compares with (Sec. 4.1: "these competing methods are adjusted to accommodate our depth-refining
loss with instance-aware masking strategy"), so it lives here, shared, with one config.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from pitta_jax import losses, masks
from pitta_jax.configs import check, check_types, is_int, option
from pitta_jax.median import WINDOW


# The largest N_max taken: more instances than any frame holds (a frame's instances are some
# of its panoptic segments, a few hundred at most); each row costs a map of the frame's size in
# the literal loss (10^9 rows asked for 25 TB).
MAX_INSTANCES = 1024


@dataclasses.dataclass(frozen=True)
class DepthRefiningConfig:
  """Eqs. 3-8: which instances, which masks, which median window."""
  window: int = option(WINDOW, "median window s of eq. 7 (odd); the paper does not state it")
  mask_mode: str = option("binary", "mask value g of eq. 3: binary (1), segment_id (the "
                                    "segmenter's id i, eq. 3 as written) or instance_id (j)")
  dynamic_classes: tuple[int, ...] = option(
      masks.DEFAULT_DYNAMIC_COCO_IDS, "COCO ids (or names) of the dynamic class set O (Sec. 3.1)")
  max_instances: int = option(32, "N_max: size of the padded instance table (static shape)")
  loss_impl: str = option("fast", "fast | literal L_d (same value and gradient; literal costs "
                                  "O(N_max))")

  def __post_init__(self):
    check_types(self)
    check(is_int(self.window) and self.window >= 1 and self.window % 2 == 1,
          f"window must be odd and >= 1 (an int), got {self.window!r}")
    check(self.mask_mode in masks.MASK_MODES,
          f"mask_mode must be one of {', '.join(masks.MASK_MODES)}, got {self.mask_mode!r}")
    check(self.loss_impl in losses.IMPLS,
          f"loss_impl must be one of {', '.join(losses.IMPLS)}, got {self.loss_impl!r}")
    check(is_int(self.max_instances) and 1 <= self.max_instances <= MAX_INSTANCES,
          f"max_instances must be an int in 1..{MAX_INSTANCES}, got {self.max_instances!r}")
    check(isinstance(self.dynamic_classes, (tuple, list)),
          f"dynamic_classes must be a tuple of COCO ids or names, got {self.dynamic_classes!r}")
    check(len(self.dynamic_classes) > 0, "dynamic_classes must name at least one class")
    from pitta_jax.data import coco
    ids = []
    for c in self.dynamic_classes:  # COCO names (e.g. "car") become their ids
      if isinstance(c, str):
        try:
          c = coco.name_to_id(c)
        except KeyError as e:
          check(False, f"dynamic_classes: {e.args[0]}")
      check(is_int(c), f"dynamic_classes: {c!r} is neither a COCO id (int) nor a COCO name")
      ids.append(int(c))
    object.__setattr__(self, "dynamic_classes", tuple(ids))
    unknown = [c for c in self.dynamic_classes if c not in coco.CATEGORY_IDS]
    check(not unknown, f"dynamic_classes: not COCO panoptic category ids: "
                       f"{', '.join(map(str, unknown))} (ids 1-200, 133 of them; names such as "
                       f"car work too)")


def frame_instances(frame, cfg: DepthRefiningConfig) -> tuple[jax.Array, jax.Array, jax.Array]:
  """The frame's dynamic instances (eq. 3): (index_map (H, W) int32, n () int32,
  inst_ids (N_max,) int32 segment ids)."""
  return _instances(frame, cfg, cfg.max_instances)


def _instances(frame, cfg: DepthRefiningConfig, n_max: int
               ) -> tuple[jax.Array, jax.Array, jax.Array]:
  """`frame_instances` with a table of `n_max` rows."""
  inst_ids, inst_valid = masks.instance_table(
      frame.seg_ids, frame.seg_classes, frame.seg_valid,
      jnp.asarray(cfg.dynamic_classes, jnp.int32), n_max)
  index_map = masks.instance_index_map(frame.panoptic, inst_ids, inst_valid)  # (H, W)
  return index_map, jnp.sum(inst_valid.astype(jnp.int32)), inst_ids


def dynamic_pixels(frame, cfg: DepthRefiningConfig) -> jax.Array:
  """(H, W) bool: the pixels of every dynamic segment of the frame's segment table (classes in
  `cfg.dynamic_classes`), not only of the first `cfg.max_instances` that L_d's table keeps."""
  return _instances(frame, cfg, frame.seg_ids.shape[0])[0] > 0


def _check_window(cfg: DepthRefiningConfig, shape: tuple[int, ...]) -> None:
  """A window wider than the frame's smaller side is refused when the step is traced (before
  any frame): its median would take most of the frame, at a cost growing with the window's
  area (641 on 320x96 frames did not finish two frames in two minutes)."""
  check(cfg.window <= min(shape), f"window {cfg.window} exceeds the frame's smaller side "
                                  f"({min(shape)} pixels of {shape[1]}x{shape[0]})")


LD_IS_ZERO = "L_d (eq. 8) is 0"  # what a frame without instances means to a loss holding L_d


def instance_uses(config) -> tuple[str, ...]:
  """What a method config's loss takes from the frames' dynamic instances, each as what a frame
  without any means (a note's phrase): `LD_IS_ZERO` where the loss holds L_d (eq. 8: an `ld`
  field weighted by its `ld_weight` > 0, a baseline + L_d, or by eq. 10 unless lambda = inf,
  PITTA with L_e only), then the method's own use (its config class's `INSTANCE_USE`, e.g.
  CoMoDa's moving-object mask, which needs the instances with or without L_d)."""
  if not isinstance(getattr(config, "ld", None), DepthRefiningConfig):
    return ()
  if hasattr(config, "ld_weight"):
    holds_ld = config.ld_weight > 0
  else:
    holds_ld = not math.isinf(getattr(config, "lam", 0.0))
  own = getattr(type(config), "INSTANCE_USE", None)
  return ((LD_IS_ZERO,) if holds_ld else ()) + ((own,) if own else ())


def uses_instances(config) -> bool:
  """Whether a method config's loss needs panoptic maps (`instance_uses`)."""
  return bool(instance_uses(config))


def dynamic_classes(config) -> tuple[int, ...]:
  """The COCO ids of a method config's dynamic set O (its `ld`), else the paper's default: the
  classes whose segments a frame keeps first (`adapt.inputs.step_input`)."""
  ld = getattr(config, "ld", None)
  if isinstance(ld, DepthRefiningConfig):
    return ld.dynamic_classes
  return masks.DEFAULT_DYNAMIC_COCO_IDS


def frame_loss(depth: jax.Array, frame, cfg: DepthRefiningConfig,
               lam: float | jax.Array) -> losses.PittaLoss:
  """Eq. 10 on an engine frame: L_d (eqs. 3-8) + lam * L_e (eqs. 5-6, 9) of `depth` (H, W)."""
  _check_window(cfg, depth.shape)
  index_map, n, inst_ids = frame_instances(frame, cfg)
  return losses.pitta_loss_from_index(
      frame.image, depth, index_map, n, s=cfg.window, lam=lam, mode=cfg.mask_mode,
      impl=cfg.loss_impl, n_max=cfg.max_instances, inst_ids=inst_ids)


def depth_refining_term(depth: jax.Array, frame, cfg: DepthRefiningConfig
                        ) -> tuple[jax.Array, jax.Array]:
  """L_d (eq. 8) of `depth` (H, W) on an engine frame, and N."""
  _check_window(cfg, depth.shape)
  index_map, n, inst_ids = frame_instances(frame, cfg)
  l_d = losses.depth_refining_loss_from_index(
      depth, index_map, n, s=cfg.window, mode=cfg.mask_mode, impl=cfg.loss_impl,
      n_max=cfg.max_instances, inst_ids=inst_ids)
  return l_d, n
