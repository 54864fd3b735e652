"""`python -m pitta_jax.cli` (run as `-m` runs it) with the tiny network (`tiny_net`) registered
as a user registers a network of their own (`MODELS[spec.name] = spec`): the command the fault
tests start as a subprocess and then kill, on weights of the tiny network.

`PITTA_JAX_TEST_SECONDS_PER_FRAME` (optional) makes each scored frame take at least that long:
a test that kills the run after its first checkpoint then finds it still running (the tiny
network runs the rest of a short sequence in a fraction of a second).
"""

from __future__ import annotations

import os
import runpy
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tiny_net import SPEC  # noqa: E402

from pitta_jax import run  # noqa: E402
from pitta_jax.models.registry import MODELS  # noqa: E402

MODELS[SPEC.name] = SPEC
_PAUSE = float(os.environ.get("PITTA_JAX_TEST_SECONDS_PER_FRAME", "0"))
if _PAUSE > 0:
  _scored = run.frame_metrics

  def _slow_frame_metrics(*args, **kwargs):
    time.sleep(_PAUSE)
    return _scored(*args, **kwargs)
  run.frame_metrics = _slow_frame_metrics

if __name__ == "__main__":
  runpy.run_module("pitta_jax.cli", run_name="__main__", alter_sys=True)
