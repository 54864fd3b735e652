"""`AdaptConfig`: every knob of an online adaptation run, with the paper's defaults.

Where the paper fixes a value it is cited; where it is silent SPEC.md fixes the default.
"""

from __future__ import annotations

import dataclasses

from pitta_jax.masks import DEFAULT_DYNAMIC_COCO_IDS


@dataclasses.dataclass(frozen=True)
class AdaptConfig:
  """Configuration of one adaptation run (one method on one frame sequence)."""
  method: str = "pitta"            # pitta | none (registry `pitta_jax.adapt.methods.METHODS`)
  optimizer: str = "adam"          # adam | sgd (paper eq. 11 writes plain SGD; SPEC: Adam default)
  lr: float = 1e-4                 # learning rate alpha of eq. 11 (SPEC step 10)
  momentum: float = 0.0            # sgd only
  steps_per_frame: int = 1         # optimiser steps per frame (SPEC step 10)
  lam: float = 0.2                 # paper Table 4: best lambda (eq. 10)
  window: int = 5                  # median window s (eq. 7), SPEC step 5
  mask_mode: str = "binary"        # binary | instance_id (eq. 3 literally)
  dynamic_classes: tuple[int, ...] = DEFAULT_DYNAMIC_COCO_IDS  # COCO ids of the set O
  loss_impl: str = "fast"          # fast | literal depth-refining loss (same value and gradient)
  bn_stats: str = "batch"          # batch (TENT-style, running stats untouched) | running
  selector: str = "encoder_bn"     # paper Sec. 4.1; or all, fraction(cnn=a,bn=b) (Table 5)
  reset_every: int = 0             # 0 = never; K = restore the source parameters every K frames
  skip_nonfinite: bool = True      # skip (and count) an update whose loss or gradient is not finite
  max_instances: int = 32          # N_max: size of the padded instance table
  max_segments: int = 64           # S_max: panoptic segments per frame kept (padded)
  chunk_size: int = 32             # frames per compiled scan; memory is flat in sequence length
  seed: int = 0

  def __post_init__(self):
    checks = [
        (self.optimizer in ("adam", "sgd"), f"optimizer must be adam or sgd, got {self.optimizer!r}"),
        (self.lr >= 0, f"lr must be >= 0, got {self.lr}"),
        (self.steps_per_frame >= 1, f"steps_per_frame must be >= 1, got {self.steps_per_frame}"),
        (self.lam >= 0, f"lam must be >= 0, got {self.lam}"),
        (self.window >= 1 and self.window % 2 == 1, f"window must be odd and >= 1, got {self.window}"),
        (self.mask_mode in ("binary", "instance_id"), f"mask_mode must be binary or instance_id, got {self.mask_mode!r}"),
        (self.loss_impl in ("fast", "literal"), f"loss_impl must be fast or literal, got {self.loss_impl!r}"),
        (self.bn_stats in ("batch", "running"), f"bn_stats must be batch or running, got {self.bn_stats!r}"),
        (self.reset_every >= 0, f"reset_every must be >= 0, got {self.reset_every}"),
        (self.max_instances >= 1, f"max_instances must be >= 1, got {self.max_instances}"),
        (self.max_segments >= 1, f"max_segments must be >= 1, got {self.max_segments}"),
        (self.chunk_size >= 1, f"chunk_size must be >= 1, got {self.chunk_size}"),
    ]
    for ok, message in checks:
      if not ok:
        raise ValueError(message)
