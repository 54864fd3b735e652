"""Shared pieces of the benchmark scripts: synthetic frames, weights for both frameworks, output.

The frames are generated (no data needed): a smooth random image and a panoptic map with a road,
a sky and N dynamic instances (cars and persons, COCO ids 3 and 1) laid out on a grid in the
lower part of the image, moving a pixel per frame. The same frames feed the JAX engine (as
`StepInput`s) and the PyTorch reference (as tensors).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterator

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from pitta_jax.adapt.engine import StepInput
from pitta_jax.adapt.xla_cpu import conv_library_options
from pitta_jax.models import conv_vjp
from pitta_jax.models.depth_decoder import DepthNet
from pitta_jax.models.random_init import jit_init
from pitta_jax.models.random_init import random_monodepth2_variables as jax_variables  # noqa: F401
from pitta_jax.models.registry import Network, network

ROAD, SKY, CAR, PERSON = 149, 187, 3, 1  # COCO panoptic category ids


@dataclasses.dataclass(frozen=True)
class BenchFrame:
  """One generated frame. image (H, W, 3) float32 in [0, 1]; panoptic (H, W) int32 ids;
  segments: (segment id, COCO category id) of every segment in the map."""
  image: np.ndarray
  panoptic: np.ndarray
  segments: tuple[tuple[int, int], ...]


def synthetic_frame(t: int, height: int, width: int, instances: int, seed: int = 0) -> BenchFrame:
  """Frame t of a generated sequence with `instances` dynamic instances (0 allowed)."""
  rng = np.random.default_rng((seed, t))
  yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
  phase = rng.uniform(0, 6, size=3)
  base = 0.5 + 0.25 * np.sin(xx / (9.0 + t % 5) + yy / 13.0 + phase[:, None, None])  # (3, H, W)
  image = np.clip(np.moveaxis(base, 0, -1) + 0.04 * rng.normal(size=(height, width, 3)), 0, 1)
  pan = np.full((height, width), 2, np.int32)  # sky
  pan[height // 3:] = 1  # road
  segments = [(1, ROAD), (2, SKY)]
  if instances:
    cols = int(np.ceil(np.sqrt(instances * 3)))  # wide grid, cells about 3:1
    rows = int(np.ceil(instances / cols))
    top, bottom = int(0.4 * height), int(0.97 * height)
    cell_h, cell_w = (bottom - top) / rows, width / cols
    for j in range(instances):
      r, c = divmod(j, cols)
      y0 = top + int(r * cell_h + 0.1 * cell_h)
      y1 = top + int((r + 1) * cell_h - 0.1 * cell_h)
      x0 = int(c * cell_w + 0.1 * cell_w) + t % 3
      x1 = min(int((c + 1) * cell_w - 0.1 * cell_w) + t % 3, width)
      seg_id = 10 + j
      pan[y0:max(y1, y0 + 1), x0:max(x1, x0 + 1)] = seg_id
      segments.append((seg_id, CAR if j % 3 else PERSON))
  return BenchFrame(image.astype(np.float32), pan, tuple(segments))


def synthetic_frames(n: int, height: int, width: int, instances: int, seed: int = 0,
                     start: int = 0) -> list[BenchFrame]:
  return [synthetic_frame(start + t, height, width, instances, seed) for t in range(n)]


# MonoDepth2's KITTI intrinsics, normalised by the image width (row 0) and height (row 1)
KITTI_K_NORMALISED = ((0.58, 0.0, 0.5), (0.0, 1.92, 0.5), (0.0, 0.0, 1.0))


def intrinsics_matrix(height: int, width: int) -> np.ndarray:
  """(3, 3) float32 camera matrix K of a `height` x `width` image (KITTI's, scaled)."""
  return (np.asarray(KITTI_K_NORMALISED) * np.array([[width], [height], [1.0]])).astype(np.float32)


def step_inputs(frames: list[BenchFrame], max_segments: int, valid: int | None = None,
                intrinsics: bool = False) -> StepInput:
  """Frames -> a stacked (T, ...) `StepInput`; frames from index `valid` on are padding.
  intrinsics: give every frame K (`intrinsics_matrix`), for methods that need it."""
  n = len(frames)
  ids = np.zeros((n, max_segments), np.int32)
  cls = np.zeros((n, max_segments), np.int32)
  ok = np.zeros((n, max_segments), bool)
  for t, f in enumerate(frames):
    if len(f.segments) > max_segments:
      raise ValueError(f"{len(f.segments)} segments > max_segments {max_segments}")
    for k, (seg_id, cat) in enumerate(f.segments):
      ids[t, k], cls[t, k], ok[t, k] = seg_id, cat, True
  valid_mask = np.arange(n) < (n if valid is None else valid)
  h, w = frames[0].image.shape[:2]
  # without a camera: intrinsics zeros, has_intrinsics False (PITTA does not use them)
  k = np.broadcast_to(intrinsics_matrix(h, w), (n, 3, 3)) if intrinsics else np.zeros((n, 3, 3))
  return StepInput(np.stack([f.image for f in frames]), np.stack([f.panoptic for f in frames]),
                   ids, cls, ok, valid_mask, np.asarray(k, np.float32),
                   np.full((n,), intrinsics, bool), np.zeros((n,), bool))


SOURCE_FRAMES = 8  # generated source-domain frames a method's `prepare` gets


def method_resources(method, model: Network, variables, height: int, width: int,
                     seed: int = 2) -> dict:
  """A method's host-side inputs for a benchmark, from generated data: a random pose network
  when it needs one, and `Method.prepare` on `SOURCE_FRAMES` generated frames (as images and as
  one consecutive sequence with K), e.g. ActMAD's source statistics; always the frames'
  (H, W) (`run.run_sequence` gives it too)."""
  from pitta_jax.data.frame import Frame, Segment
  from pitta_jax.methods.base import INPUT_SIZE, POSE, PoseNet, SourceData
  resources: dict = {INPUT_SIZE: (height, width)}
  if "pose" in method.needs:
    from pitta_jax.models.pose import PoseNet as PoseModule
    module = PoseModule(18)
    resources[POSE] = PoseNet(module, jit_init(
        module, jax.random.PRNGKey(seed), np.zeros((1, height, width, 6), np.float32)))
  if method.prepare is not None:
    frames = synthetic_frames(SOURCE_FRAMES, height, width, 4, seed=seed)
    sequence = tuple(Frame(image=f.image, panoptic=f.panoptic,
                           segments=tuple(Segment(i, c) for i, c in f.segments),
                           name=f"source/{t}", intrinsics=intrinsics_matrix(height, width))
                     for t, f in enumerate(frames))
    source = SourceData(tuple(f.image for f in frames), (sequence,))
    resources.update(method.prepare(model, variables, source))
  return resources


def chunk_stream(n_frames: int, chunk: int, height: int, width: int, instances: int,
                 max_segments: int, seed: int = 0) -> Iterator[StepInput]:
  """A long generated sequence as padded chunks, generated lazily (host memory: one chunk)."""
  for start in range(0, n_frames, chunk):
    n = min(chunk, n_frames - start)
    frames = synthetic_frames(n, height, width, instances, seed, start)
    frames += [frames[-1]] * (chunk - n)
    yield step_inputs(frames, max_segments, valid=n)


def torch_and_jax_weights(seed: int = 0, num_layers: int = 18):
  """Random MonoDepth2 weights in both frameworks: (torch encoder, torch decoder, jax variables).

  The PyTorch modules (`torch_monodepth2`, upstream layout) are saved as `encoder.pth` /
  `depth.pth` and converted by the project's converter, so both run the same network.
  """
  import torch
  import torch_reference
  from weights_convert.monodepth2 import convert_monodepth2
  encoder, decoder = torch_reference.build(seed, num_layers)
  with tempfile.TemporaryDirectory() as tmp:
    torch.save(encoder.state_dict(), Path(tmp) / "encoder.pth")
    torch.save(decoder.state_dict(), Path(tmp) / "depth.pth")
    _, variables, _ = convert_monodepth2(Path(tmp) / "encoder.pth", Path(tmp) / "depth.pth",
                                         num_layers=num_layers)
  return encoder, decoder, variables


def method_configs(name: str, instances: int, window: int, frames: int):
  """(AdaptConfig in method `name`'s own setting with chunks of `frames`, the method's default
  config with the depth-refining term's window `window` and room for `instances` instances)."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.methods import method_config_class, method_setting
  from pitta_jax.methods.depth_refining import DepthRefiningConfig
  cls = method_config_class(name)
  mcfg = cls()
  if any(f.name == "ld" for f in dataclasses.fields(cls)):
    ld = DepthRefiningConfig(window=window, max_instances=max(mcfg.ld.max_instances, instances))
    mcfg = dataclasses.replace(mcfg, ld=ld)
  cfg = AdaptConfig(method=name, **{**method_setting(name), "chunk_size": frames,
                                    "max_segments": max(AdaptConfig().max_segments,
                                                        instances + 2)})
  return cfg, mcfg


CONV_RULES = ("loop_friendly", "jax")


def depth_network(rule: str = "loop_friendly", num_layers: int = 18) -> Network:
  """The MonoDepth2 network whose convolutions use input-gradient rule `rule`:
  "loop_friendly" (the project's `models.conv_vjp` via `layers.Conv`, the default) or "jax"
  (JAX's own transpose rule, `flax.linen.Conv`, slow inside `lax.scan` on XLA:CPU), so that one
  run can time both side by side. Both have the same parameter tree (same variables)."""
  if rule not in CONV_RULES:
    raise ValueError(f"conv rule must be one of {CONV_RULES}, got {rule!r}")
  if rule == "loop_friendly":
    return network("monodepth2", {"num_layers": num_layers})
  return network("monodepth2", module=DepthNet(num_layers, conv=nn.Conv))


def timed_chunks(runner, state, chunk, consts, reps: int):
  """Times a chunk runner `runner(state, chunk, consts)` that donates its carry: the first call
  (compile + chunk), one warm-up call, then `reps` steady calls.
  -> (first_s, first_outputs, median_s, min_s, state)."""
  t0 = time.perf_counter()
  state, first_outs = runner(state, chunk, consts)
  jax.block_until_ready(first_outs)
  first_s = time.perf_counter() - t0
  state, outs = runner(state, chunk, consts)  # warm-up
  jax.block_until_ready(outs)
  holder = [state]

  def one():
    holder[0], o = runner(holder[0], chunk, consts)
    jax.block_until_ready(o)
  med, best = median_time(one, reps)
  return first_s, first_outs, med, best, holder[0]


def interleaved_ms(runs: dict[str, Callable[[], object]], reps: int,
                   units: int | dict[str, int] = 1
                   ) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
  """`reps` rounds of one call of each of `runs` (each must block until its work is done), the
  order rotated every round so that a shared machine's load drifts over all of them alike.

  units: what one call does (frames, updates), for all or per name. Returns (wall, cpu): by
  name, the ms per unit of each call, wall-clock and the process's CPU time (all threads)."""
  names = list(runs)
  wall: dict[str, list[float]] = {n: [] for n in names}
  cpu: dict[str, list[float]] = {n: [] for n in names}
  for r in range(reps):
    for n in names[r % len(names):] + names[:r % len(names)]:
      count = units[n] if isinstance(units, dict) else units
      c0, t0 = time.process_time(), time.perf_counter()
      runs[n]()
      wall[n].append(1e3 * (time.perf_counter() - t0) / count)
      cpu[n].append(1e3 * (time.process_time() - c0) / count)
  return wall, cpu


def median_time(fn: Callable[[], object], reps: int) -> tuple[float, float]:
  """(median, min) wall seconds of `fn()` over `reps` calls; fn must block until done."""
  times = []
  for _ in range(reps):
    t0 = time.perf_counter()
    fn()
    times.append(time.perf_counter() - t0)
  return float(np.median(times)), float(np.min(times))


# XLA:CPU's two convolution libraries as per-program compiler options, for the per-layer
# benchmarks (`kernel_grad.py`, `conv_forward.py`)
CONV_LIBRARY_OPTIONS: dict[str, Callable[[], dict | None]] = {
    "default": lambda: None, "eigen": lambda: conv_library_options("eigen", "cpu")}


# `conv_vjp._kernel_grad` with the padding inside the convolution form at every batch size and
# strided layers as one convolution: the model's choice until the morning of 2026-12-08
# (`step.py --compare-padded-kernel-grads`). Bound to the function itself, not looked up, so
# that it still calls it while a benchmark swaps it in.
padding_inside_kernel_grads = functools.partial(conv_vjp._kernel_grad, pad_first=False,
                                                phases=False)
# strided layers' kernel gradients as one convolution with the stride-dilated cotangent, not
# per stride phase: the model's choice until 2026-12-08, 04:00 UTC
# (`step.py --compare-strided-kernel-grads`)
one_convolution_kernel_grads = functools.partial(conv_vjp._kernel_grad, phases=False)


def per_image_kernel_grad(x: jax.Array, g: jax.Array, *conv_args) -> jax.Array:
  """A convolution's kernel gradient as the sum over the batch of `conv_vjp.kernel_grad_conv`
  of one image each (x: (N, H, W, C), g: (N, Ho, Wo, O); `conv_args`: kernel size, strides,
  padding, kernel dilation[, precision]): what `conv_vjp` used for the decoder's wide, shallow
  layers at batch >= 2 until 2026-12-05, kept for comparisons."""
  return sum(conv_vjp.kernel_grad_conv(x[i:i + 1], g[i:i + 1], *conv_args)
             for i in range(x.shape[0]))


def _column_taps(x: jax.Array, kw: int, stride: int, dilation: int, padding, wo: int
                 ) -> jax.Array:
  """x (N, H, W, C) zero-padded, its kw column taps side by side: (N, Hp, Wo, kw C), where
  [n, r, j, b C + c] = x_pad[n, r, j s + b d, c]: a kw times larger copy of the input."""
  xp = lax.pad(x, jnp.zeros((), x.dtype),
               ((0, 0, 0), *((lo, hi, 0) for lo, hi in padding), (0, 0, 0)))  # (N, Hp, Wp, C)
  return jnp.concatenate(
      [lax.slice_in_dim(xp, b * dilation, b * dilation + stride * (wo - 1) + 1, stride, axis=2)
       for b in range(kw)], axis=3)                                     # (N, Hp, Wo, kw C)


def kernel_grad_rows(x: jax.Array, g: jax.Array, kernel_size, strides, padding, rhs_dilation,
                     precision=None) -> jax.Array:
  """A convolution's kernel gradient (`conv_vjp._kernel_grad`'s arguments) as kh products, one
  per kernel row a: the column taps (`_column_taps`) read at row offset a with the row stride,
  (N, Ho, Wo, kw C), contracted with g over (N, Ho, Wo) -> (kw C, O). Each row's view is a
  (strided) copy of the column taps. Tried in the model on 2026-12-06, not kept (docs/performance.md)."""
  kh, kw = kernel_size
  n, ho, wo, o = g.shape
  cols = _column_taps(x, kw, strides[1], rhs_dilation[1], padding, wo)  # (N, Hp, Wo, kw C)
  dh, sh = rhs_dilation[0], strides[0]
  dk = [lax.dot_general(lax.slice_in_dim(cols, a * dh, a * dh + sh * (ho - 1) + 1, sh, axis=1),
                        g, (((0, 1, 2), (0, 1, 2)), ((), ())), precision=precision)
        for a in range(kh)]                                             # kh x (kw C, O)
  return jnp.stack(dk).reshape(kh, kw, x.shape[3], o)


def kernel_grad_stacked(x: jax.Array, g: jax.Array, kernel_size, strides, padding,
                        rhs_dilation, precision=None) -> jax.Array:
  """The kernel gradient of a convolution with row stride 1 as one product: the column taps
  (`_column_taps`, (N, Hp, Wo, kw C)) with g shifted down by each row tap's offset a d and
  zero-filled to Hp rows, the kh shifts side by side ((N, Hp, Wo, kh O)), contracted over
  (N, Hp, Wo) -> (kw C, kh O): no copy per row as in `kernel_grad_rows`, a kh times larger copy
  of g instead. Tried in the model on 2026-12-06, not kept (docs/performance.md)."""
  kh, kw = kernel_size
  n, ho, wo, o = g.shape
  if strides[0] != 1:
    raise ValueError(f"kernel_grad_stacked takes a row stride of 1, not {strides[0]}")
  cols = _column_taps(x, kw, strides[1], rhs_dilation[1], padding, wo)  # (N, Hp, Wo, kw C)
  hp, dh = cols.shape[1], rhs_dilation[0]
  shifted = jnp.concatenate(
      [lax.pad(g, jnp.zeros((), g.dtype),
               ((0, 0, 0), (a * dh, hp - ho - a * dh, 0), (0, 0, 0), (0, 0, 0)))
       for a in range(kh)], axis=3)                                     # (N, Hp, Wo, kh O)
  dk = lax.dot_general(cols, shifted, (((0, 1, 2), (0, 1, 2)), ((), ())),
                       precision=precision)                             # (kw C, kh O)
  return jnp.transpose(dk.reshape(kw, x.shape[3], kh, o), (2, 0, 1, 3))


# both sides' features from which `row_tap_kernel_grads` takes the row-tap forms
ROW_TAPS_MIN_FEATURES = 64
# the model's choice, held here: `step.JaxImpl` swaps `conv_vjp._kernel_grad` for
# `row_tap_kernel_grads` while tracing, which falls back to this
_MODEL_KERNEL_GRAD = conv_vjp._kernel_grad


def row_tap_kernel_grads(x, g, kernel_size, strides, padding, rhs_dilation, precision):
  """The rule tried in `conv_vjp._kernel_grad` on 2026-12-06 (`step.py --compare-row-taps`):
  with >= `ROW_TAPS_MIN_FEATURES` features on both sides, a strided or 1x1 convolution's kernel
  gradient as `kernel_grad_rows` and a zero-padded single image's as `kernel_grad_stacked`;
  otherwise the model's forms (ResNet's stages get the row-tap forms, the decoders keep the
  convolution form)."""
  args = (x, g, kernel_size, strides, padding, rhs_dilation, precision)
  if min(x.shape[3], g.shape[3]) >= ROW_TAPS_MIN_FEATURES:
    if strides != (1, 1) or kernel_size == (1, 1):
      return kernel_grad_rows(*args)
    if x.shape[0] == 1 and any(p for pair in padding for p in pair):
      return kernel_grad_stacked(*args)
  return _MODEL_KERNEL_GRAD(*args)


def add_per_layer_args(parser: argparse.ArgumentParser, layers, forms, libraries, *,
                       default_libraries: str, loops: int, reps: int, per_loop: str) -> None:
  """The options the per-layer benchmarks share (`kernel_grad.py`, `conv_forward.py`): which
  layers, JAX forms and XLA:CPU libraries to time, loop length, timed runs, PyTorch threads."""
  parser.add_argument("--layers", default=",".join(layers),
                      help="comma-separated, of: " + ", ".join(layers))
  parser.add_argument("--forms", default=",".join(forms),
                      help="comma-separated JAX forms, of: " + ", ".join(forms))
  parser.add_argument("--libraries", default=default_libraries,
                      help="comma-separated XLA:CPU convolution libraries to compile each form "
                           "with, of: " + ", ".join(libraries))
  parser.add_argument("--loops", type=int, default=loops, help=f"{per_loop} per compiled loop")
  parser.add_argument("--reps", type=int, default=reps,
                      help="timed runs per form (best reported)")
  parser.add_argument("--threads", type=int, default=os.cpu_count(), help="PyTorch threads")


def parse_per_layer_args(parser: argparse.ArgumentParser, argv, layers, forms, libraries
                         ) -> tuple[argparse.Namespace, list[str], list[str], list[str]]:
  """Parses `argv` with the options of `add_per_layer_args` and checks them before any work:
  (args, layers, forms, libraries), or `parser.error` (one line naming the flag, exit 2) on an
  unknown name or on libraries other than XLA's default on a backend other than XLA:CPU."""
  args = parser.parse_args(argv)
  chosen = []
  for flag, value, known in (("--layers", args.layers, layers), ("--forms", args.forms, forms),
                             ("--libraries", args.libraries, libraries)):
    names = value.split(",")
    unknown = [n for n in names if n not in known]
    if unknown:
      parser.error(f"{flag}: unknown {unknown}; of {', '.join(known)}")
    chosen.append(names)
  if jax.default_backend() != "cpu" and chosen[2] != ["default"]:
    parser.error("--libraries: the convolution libraries are XLA:CPU's; this backend is "
                 + jax.default_backend())
  return args, *chosen


def load() -> list[float]:
  """1, 5, 15 minute load averages (the machine is shared: read timings with them)."""
  return [round(x, 2) for x in os.getloadavg()]


def emit(record: dict) -> None:
  """One JSON line on stdout."""
  print(json.dumps(record), flush=True)
