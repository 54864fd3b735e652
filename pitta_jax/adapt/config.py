"""`AdaptConfig`: the method-independent knobs of an online adaptation run.

The method's own knobs live in its config (`pitta_jax.methods`, e.g. `PittaConfig`); the
evaluation protocol in `run.EvalConfig`. Where the paper fixes a value it is cited; where it is
silent the default and its reason are in docs/method.md.
"""

from __future__ import annotations

import dataclasses

from pitta_jax.adapt.xla_cpu import check_library
from pitta_jax.configs import check, check_seed, check_types, finite, option
from pitta_jax.trainable import parse_selector


# The largest S_max taken: more segments than any panoptic frame holds (COCO's and Cityscapes'
# most crowded frames hold a few hundred); a larger table only costs memory (10^9 was killed).
MAX_SEGMENTS = 4096
# The most optimiser steps per frame: each is a copy of the step in the compiled program (the
# steps are unrolled), so a few already multiply its compile; past this, a typo.
MAX_STEPS_PER_FRAME = 1024


@dataclasses.dataclass(frozen=True)
class AdaptConfig:
  """Configuration of one adaptation run (one method on one frame sequence)."""
  method: str = option("pitta", "the TTA method: pitta | none | comoda | adadepth | actmad | "
                                 "cotta (registry pitta_jax.methods.METHODS)")
  optimizer: str = option("adam", "adam | sgd (eq. 11 writes a plain gradient step; the paper "
                                  "does not name the optimiser)")
  lr: float = option(1e-4, "learning rate alpha of eq. 11 (not stated in the paper)")
  momentum: float = option(0.0, "SGD momentum (sgd only)")
  steps_per_frame: int = option(1, "optimiser steps per frame (online TTA: one), at most "
                                    f"{MAX_STEPS_PER_FRAME}; each is compiled into the step")
  bn_stats: str = option("batch", "BatchNorm statistics while adapting: batch (the frame's, "
                                  "running ones untouched) | running")
  selector: str = option("encoder_bn", "adapted parameters: encoder_bn (paper Sec. 4.1), "
                                       "encoder_ln, all, no_bn (all but BatchNorm scale/bias), "
                                       "fraction(cnn=a,bn=b) (Table 5)")
  reset_every: int = option(0, "0 = never; K = restore the source parameters every K frames")
  skip_nonfinite: bool = option(True, "skip (and count) an update whose loss, gradient, new "
                                      "parameters or new optimiser state are not finite")
  max_segments: int = option(64, "S_max: panoptic segments per frame kept (padded)")
  chunk_size: int = option(32, "frames per compiled scan; memory is flat in sequence length")
  seed: int = option(0, "PRNG seed of the run (per frame: fold_in(seed, frame index))")
  conv_library: str = option("auto", "XLA:CPU's library for convolutions (speed only): auto "
                                     "(Eigen's, unless the method names its own) | default "
                                     "(XLA's, YNNPACK) | eigen; other backends ignore it")

  def __post_init__(self):
    check_types(self)
    check(self.optimizer in ("adam", "sgd"), f"optimizer must be adam or sgd, got {self.optimizer!r}")
    finite(self.lr, "lr", 0.0)
    finite(self.momentum, "momentum", 0.0)
    check(self.momentum < 1.0, f"momentum must be < 1, got {self.momentum}")
    check(self.momentum == 0 or self.optimizer == "sgd",  # Adam would ignore it
          f"momentum applies to optimizer sgd only, got momentum {self.momentum} with "
          f"{self.optimizer}")
    check(1 <= self.steps_per_frame <= MAX_STEPS_PER_FRAME,
          f"steps_per_frame must be in 1..{MAX_STEPS_PER_FRAME}, got {self.steps_per_frame}")
    check_seed(self.seed)
    check(self.bn_stats in ("batch", "running"),
          f"bn_stats must be batch or running, got {self.bn_stats!r}")
    parse_selector(self.selector)  # raises ValueError naming the selector
    check(0 <= self.reset_every < 2**31,  # compared with the int32 frame counter
          f"reset_every must be in [0, 2^31), got {self.reset_every}")
    check(1 <= self.max_segments <= MAX_SEGMENTS,
          f"max_segments must be in 1..{MAX_SEGMENTS}, got {self.max_segments}")
    check(self.chunk_size >= 1, f"chunk_size must be >= 1, got {self.chunk_size}")
    check_library(self.conv_library)
