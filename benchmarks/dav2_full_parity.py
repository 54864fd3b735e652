"""Full-size Depth Anything V2 ViT-S/14 parity against transformers and upstream's layout.

The suite tests a narrow ViT for time; this runs the real ViT-S + DPT sizes (518x518 and 644x196,
both checkpoint formats, float64 LayerNorm gradients), about a minute of CPU:

    python benchmarks/dav2_full_parity.py
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path


def main(argv=None) -> None:
  argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)  # --help
  sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
  import test_depth_anything_v2 as t  # the test module's references and helpers
  with tempfile.TemporaryDirectory() as d:
    t.full_size_vits_matches_torch(Path(d))
  print("full-size ViT-S parity: ok")


if __name__ == "__main__":
  main()
