"""Where the time of one scanned PITTA step goes: an XLA trace of the engine's chunk runner.

    python benchmarks/profile_step.py                  # PITTA, 640x192, N = 8 instances
    python benchmarks/profile_step.py --height 96 --width 320 --top 20
    python benchmarks/profile_step.py --method actmad  # any method, in its own setting

Runs the engine's compiled chunk (`make_chunk_runner`) after warm-up under `jax.profiler`, reads
the trace's per-operation times, and sorts every compiled operation into a part of the step by
the JAX call site XLA keeps in its metadata:
- network forward / network backward (`jvp(DepthNet)` / `transpose(jvp(DepthNet))`, and the
  same for `PoseNet`, the pose network of CoMoDa and Ada-Depth), split into
  convolutions, kernel transposes (the input-gradient kernels of `models.conv_vjp`) and the rest
  (BatchNorm, ReLU/ELU, pads, upsampling, concatenations);
- everything else: masks, median filter, edges, losses, optimiser update, loop bookkeeping.
Prints one JSON line per part (ms per frame, share of the wall-clock time), the wall-clock ms per
frame, and the `--top` most expensive single operations with their call sites.

Eigen's convolutions (`--conv-library eigen`, and `auto` for a step that adapts no convolution
kernel) run asynchronously in Eigen's thread pool: the trace holds only their dispatch (a
fraction of a millisecond each), not the time they compute. What the traced operations do not
cover of the wall-clock time is printed as its own part ("not traced"); with Eigen's
convolutions that is most of their time. `--conv-library default` (YNNPACK's convolutions,
traced whole) attributes the convolutions operation by operation.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import glob
import gzip
import json
import re
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

import bench_common as bc  # noqa: E402
from pitta_jax.adapt import init_state, make_method_runner, make_optimizer  # noqa: E402
from pitta_jax.adapt.xla_cpu import CONV_LIBRARIES  # noqa: E402
from pitta_jax.adapt.xla_cpu import step_compiler_options  # noqa: E402
from pitta_jax.methods import METHODS, build  # noqa: E402

SKIP = ("ThunkExecutor", "Await", "PjitFunction", "while")


def call_sites(hlo_text: str) -> dict[str, str]:
  """Compiled instruction name -> the JAX op_name in its metadata."""
  sites = {}
  for line in hlo_text.splitlines():
    m = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = ", line)
    site = re.search(r'op_name="([^"]*)"', line)
    if m and site:
      sites[m.group(1)] = site.group(1)
  return sites


# the networks' top-level Flax modules, as call sites name them (a method's depth network and
# the pose network of CoMoDa's and Ada-Depth's self-supervised losses)
NETWORKS = ("DepthNet", "PoseNet")


def part_of(name: str, site: str) -> str:
  if site and "/while/" not in site:
    return "outside the scan (once per chunk: hoisted constants, chunk in/out)"
  if any(net in site for net in NETWORKS):
    phase = "network backward" if "transpose(" in site else "network forward"
    if name.startswith(("ynn_fusion", "conv_general_dilated", "convolution")):
      return f"{phase}: convolutions"
    if name.startswith("transpose_copy_fusion") and phase == "network backward":
      return f"{phase}: kernel transposes"
    return f"{phase}: other"
  return "masks, median, edges, losses, update"


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--method", default="pitta", choices=sorted(METHODS))
  p.add_argument("--height", type=int, default=192)
  p.add_argument("--width", type=int, default=640)
  p.add_argument("--instances", type=int, default=8)
  p.add_argument("--frames", type=int, default=4, help="frames in the traced chunk")
  p.add_argument("--top", type=int, default=12, help="single operations to list")
  p.add_argument("--conv-library", choices=CONV_LIBRARIES, default=None,
                 help="XLA:CPU's convolution library (AdaptConfig.conv_library; default: the "
                      "method setting's, auto); the trace holds only the dispatch of Eigen's "
                      "convolutions")
  p.add_argument("--dump", default="", help="also write every operation (ms per frame, call "
                                            "site) as JSON lines to this file")
  args = p.parse_args(argv)

  cfg, mcfg = bc.method_configs(args.method, args.instances, 5, args.frames)
  if args.conv_library is not None:
    cfg = dataclasses.replace(cfg, conv_library=args.conv_library)
  model, method = bc.depth_network(), build(args.method, mcfg)
  tx = make_optimizer(cfg, method)
  runner = make_method_runner(model, method, cfg, tx)  # as `pitta-jax adapt` compiles the step
  chunk = bc.step_inputs(bc.synthetic_frames(args.frames, args.height, args.width,
                                             args.instances, seed=1), cfg.max_segments,
                         intrinsics="intrinsics" in method.needs)
  variables = bc.jax_variables(0)
  resources = bc.method_resources(method, model, variables, args.height, args.width)
  state, consts = init_state(variables, method, cfg, tx, model, resources)
  sites = call_sites(runner.lower(state, chunk, consts).compile().as_text())
  for _ in range(2):  # compile + warm-up
    state, out = runner(state, chunk, consts)
    jax.block_until_ready(out)
  t0 = time.perf_counter()
  state, out = runner(state, chunk, consts)
  jax.block_until_ready(out)
  wall_ms = 1e3 * (time.perf_counter() - t0) / args.frames

  with tempfile.TemporaryDirectory() as tmp:
    jax.profiler.start_trace(tmp)
    state, out = runner(state, chunk, consts)
    jax.block_until_ready(out)
    jax.profiler.stop_trace()
    trace_file = glob.glob(f"{tmp}/plugins/profile/*/*.trace.json.gz")[0]
    events = json.load(gzip.open(trace_file))["traceEvents"]

  per_op: collections.Counter = collections.Counter()
  for e in events:
    if e.get("ph") == "X" and not e["name"].startswith("$") and \
        not any(s in e["name"] for s in SKIP):
      per_op[e["name"]] += e["dur"] / 1e3 / args.frames  # us -> ms per frame
  parts: collections.Counter = collections.Counter()
  for name, ms in per_op.items():
    parts[part_of(name, sites.get(name, ""))] += ms
  traced = sum(parts.values())
  parts["not traced (Eigen's asynchronous convolutions, executor gaps; module docstring)"] = \
      max(wall_ms - traced, 0.0)
  common = {"method": args.method, "H": args.height, "W": args.width, "instances": args.instances,
            "frames": args.frames, "load": bc.load()}
  bc.emit({"wall_ms_per_frame": wall_ms, "traced_ms_per_frame": traced,
           "conv_library": cfg.conv_library,
           "eigen_convolutions": step_compiler_options(cfg, method) is not None, **common})
  for part, ms in sorted(parts.items(), key=lambda kv: -kv[1]):
    share = ms / max(wall_ms, traced)  # operations on the two threads may overlap
    bc.emit({"part": part, "ms_per_frame": round(ms, 2), "share": round(share, 3)})
  for name, ms in per_op.most_common(args.top):
    bc.emit({"op": name, "ms_per_frame": round(ms, 2), "site": sites.get(name, "")[-90:]})
  if args.dump:
    with open(args.dump, "w") as f:
      for name, ms in per_op.most_common():
        f.write(json.dumps({"op": name, "ms_per_frame": ms, "site": sites.get(name, "")}) + "\n")


if __name__ == "__main__":
  main()
