"""Peak memory of an adaptation run vs its length: flat, since the engine streams in chunks.

    python benchmarks/memory.py                       # 100 and 1000 frames at 320x96
    python benchmarks/memory.py --lengths 100,1000 --height 192 --width 640

Each length runs in a fresh subprocess (peak RSS is a per-process high-water mark): the engine's
chunk runner (`make_chunk_runner`, `AdaptConfig.chunk_size` frames per compiled scan) driven by
`adapt_stream` over generated frames, themselves generated chunk by chunk; per frame only the
loss is kept (the depth maps are dropped after each chunk, as an evaluation loop would do after
scoring them). Reported: `ru_maxrss` of the child after its first chunk (compile included) and
at the end, and the ratio of the end peaks of the longest and the shortest run. The default size
is 320x96 (not the paper's 640x192) so that 1000 frames take a few minutes on a 2-core CPU;
nothing in the engine depends on the size.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _peak_mb() -> float:
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _current_mb() -> float:
  with open("/proc/self/status") as f:
    for line in f:
      if line.startswith("VmRSS:"):
        return int(line.split()[1]) / 1024.0
  return float("nan")


def child(args) -> None:
  import jax  # noqa: F401  (imported here: the parent process never touches JAX)
  import bench_common as bc
  from pitta_jax.adapt import (AdaptConfig, adapt_stream, init_state, make_method_runner,
                               make_optimizer)
  from pitta_jax.methods import build

  cfg = AdaptConfig(chunk_size=args.chunk)
  model, method = bc.depth_network(), build("pitta")
  tx = make_optimizer(cfg)
  runner = make_method_runner(model, method, cfg, tx)  # as `pitta-jax adapt` compiles the step
  state, consts = init_state(bc.jax_variables(seed=0), method, cfg, tx, model)
  chunks = bc.chunk_stream(args.frames, cfg.chunk_size, args.height, args.width, args.instances,
                           cfg.max_segments, seed=2)
  losses, peak_first = [], None
  t0 = time.perf_counter()
  for state, out in adapt_stream(state, consts, chunks, runner):
    losses.extend(out.loss.tolist())
    if peak_first is None:
      peak_first = _peak_mb()
  wall = time.perf_counter() - t0
  print(json.dumps({"frames": len(losses), "peak_rss_first_chunk_mb": round(peak_first, 1),
                    "peak_rss_mb": round(_peak_mb(), 1), "rss_end_mb": round(_current_mb(), 1),
                    "wall_s": round(wall, 1), "final_loss": losses[-1]}), flush=True)


def _lengths(text: str) -> list[int]:
  """--lengths: a comma list of sequence lengths, each >= 1."""
  try:
    lengths = [int(x) for x in text.split(",")]
  except ValueError:
    raise argparse.ArgumentTypeError(f"expected a comma list of integers, got {text!r}") from None
  if min(lengths) < 1:
    raise argparse.ArgumentTypeError(f"each length must be >= 1, got {text!r}")
  return lengths


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--lengths", type=_lengths, default="100,1000",
                 help="comma list of sequence lengths")
  p.add_argument("--height", type=int, default=96)
  p.add_argument("--width", type=int, default=320)
  p.add_argument("--instances", type=int, default=8)
  p.add_argument("--chunk", type=int, default=32, help="frames per compiled scan (chunk_size)")
  p.add_argument("--frames", type=int, help=argparse.SUPPRESS)  # child mode
  args = p.parse_args(argv)
  if args.frames is not None:
    child(args)
    return

  lengths = args.lengths
  peaks = {}
  for n in lengths:
    cmd = [sys.executable, __file__, "--frames", str(n), "--height", str(args.height),
           "--width", str(args.width), "--instances", str(args.instances),
           "--chunk", str(args.chunk)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
    if proc.returncode:
      sys.exit(f"child for {n} frames failed:\n{proc.stderr[-3000:]}")
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    peaks[n] = rec["peak_rss_mb"]
    print(json.dumps({"H": args.height, "W": args.width, "instances": args.instances,
                      "chunk": args.chunk, **rec, "load": [round(x, 2) for x in os.getloadavg()]}),
          flush=True)
  lo, hi = min(lengths), max(lengths)
  print(json.dumps({"ratio": f"peak_rss({hi}) / peak_rss({lo})", "value": peaks[hi] / peaks[lo]}),
        flush=True)


if __name__ == "__main__":
  main()
