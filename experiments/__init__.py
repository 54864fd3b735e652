"""The paper's experiments, one command each (`pitta-jax experiment NAME`, or
`python -m experiments.NAME`):

  table1       MonoDepth2 on DrivingStereo (Foggy, Rainy, All): No adaptation, the four
               baselines with L_d, Depth Anything V2, PITTA
  table2       the same methods on Waymo
  table3       PITTA on SGDepth, HR-Depth, MonoViT, Lite-Mono, Depth Anything V2
  table4       lambda of eq. 10 from 0 to 1 and infinity (one vmapped run)
  table5       which parameters adapt ("CNN a% + BN b%")
  sensitivity  where PITTA's loss matters on the synthetic benchmark (lr, steps per frame,
               lambda, sequence length, BN mode, traffic density)

Each writes NAME.md / NAME.csv / NAME.tex / results.json (+ figures, but the sensitivity
study) to --out, runs on the embedded synthetic benchmark by default and on the real dataset
with --dataset/--root, caches every finished row, and runs a tiny version with --quick.
"""

from __future__ import annotations

import importlib
import sys
from typing import Sequence

NAMES = ("table1", "table2", "table3", "table4", "table5", "sensitivity")


def main(argv: Sequence[str] | None = None) -> int:
  """`NAME [args]` -> experiments.NAME.main(args)."""
  argv = list(sys.argv[1:] if argv is None else argv)
  if argv and argv[0] not in NAMES + ("-h", "--help"):
    print(f"error: unknown experiment {argv[0]!r}; choose from {', '.join(NAMES)}",
          file=sys.stderr)
    return 2
  if not argv or argv[0] in ("-h", "--help"):  # asked for: stdout, 0; a usage error: stderr, 2
    print(__doc__, file=sys.stdout if argv else sys.stderr)
    if not argv:  # the overview, then the one line that says what went wrong
      print(f"error: name an experiment: {', '.join(NAMES)}", file=sys.stderr)
    return 0 if argv else 2
  return importlib.import_module(f"experiments.{argv[0]}").main(argv[1:])
