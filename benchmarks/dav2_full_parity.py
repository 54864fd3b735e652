"""Full-size Depth Anything V2 ViT-S/14 parity against transformers and upstream's layout.

The suite tests a narrow ViT for time; this runs the real ViT-S + DPT sizes (518x518 and 644x196,
both checkpoint formats, float64 LayerNorm gradients), about a minute of CPU:

    python benchmarks/dav2_full_parity.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import test_depth_anything_v2 as t  # noqa: E402  (the test module's references and helpers)

if __name__ == "__main__":
  with tempfile.TemporaryDirectory() as d:
    t.full_size_vits_matches_torch(Path(d))
  print("full-size ViT-S parity: ok")
