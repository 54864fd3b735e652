"""Time one adaptation step of a method: the JAX engine vs PyTorch, interleaved, same process.

    python benchmarks/step.py                           # PITTA at 640x192, N = 8, s = 5
    python benchmarks/step.py --method actmad           # any method in pitta_jax.methods.METHODS
    python benchmarks/step.py --sweep-instances 1,8,32  # PITTA's N side by side
    python benchmarks/step.py --quick                   # 320x96, fewer frames
    python benchmarks/step.py --profile                 # + FLOPs and the parts of the step

Implementations (`--impls`; the default is every one that exists for the method):
- `jax`: the engine's compiled chunk runner (`make_method_runner`: jit of a `lax.scan` of
  `adapt_step` over `--frames` frames, carry donated, compiled with the step's XLA options), the
  method in its own setting (`pitta_jax.methods.method_setting`);
- `torch-eager`: the same step as a performance-minded PyTorch user writes it
  (`benchmarks/torch_reference.py`: upstream MonoDepth2 modules, NCHW as upstream);
- `torch-eager-cl`: the same with `memory_format=torch.channels_last` (oneDNN's layout: the
  networks and the frames), every method;
- `torch-compile`: the same under `torch.compile` (inductor), PITTA and none (`TORCH_COMPILED`).
Methods without a PyTorch step in `torch_reference.TORCH_STEPS` get a line saying so.

Timing: every implementation is set up first (compile, first chunk, one warm-up chunk), then
`--reps` rounds time one chunk per implementation, in a rotating order, so that a shared
machine's load drifts over all of them alike. A JAX chunk is the engine's default chunk
(`AdaptConfig.chunk_size` = 32 frames, `--jax-frames`: the per-chunk work, e.g. the hoisted
kernel transposes, is spread as in a run), a PyTorch chunk `--frames` frames (the first of the
same generated sequence). Per implementation: the median and
the best ms per frame (wall), the median CPU ms per frame of the process (all threads; less
sensitive to other jobs on the machine), and the compile time. Then a `ratio` line: the
fastest PyTorch configuration's ms per frame / JAX's (median and best), a loss-parity line for
deterministic methods (the same random weights and frames: the first chunk's losses must
agree), and the load average before and after.

`--compare-conv-rule`, `--compare-conv-library` and `--compare-kernel-grads` time variants of
the JAX step against each other in the same interleaved way (one `check` line each: median and
best ms per frame, ratios, compile seconds, first losses' difference);
`--compare-torch-optimizers` does the same for the PyTorch eager step with fused optimiser
kernels (the references' default, `torch_reference.FUSED_OPTIMIZERS`) and with PyTorch's default
for-loop ones; `--compare-only` skips the JAX vs PyTorch comparison.

With `--profile` (PITTA): XLA's FLOP count of the step (`cost_analysis`), a FLOP floor at this
machine's measured matmul/conv rate, and the time of the parts (network forward only, forward +
backward, loss with its gradient w.r.t. the depth only, whole step) in both frameworks.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import bench_common as bc  # noqa: E402
import torch_reference as tr  # noqa: E402
from pitta_jax import flat_optim  # noqa: E402
from pitta_jax import trainable as trainable_lib  # noqa: E402
from pitta_jax.adapt import (AdaptConfig, StepInput, init_state,  # noqa: E402
                             make_method_runner, make_optimizer, make_step)
from pitta_jax.adapt.xla_cpu import CONV_LIBRARIES, step_compiler_options  # noqa: E402
from pitta_jax.methods import METHODS, adadepth, build  # noqa: E402
from pitta_jax.methods.actmad import RESOURCE as ACTMAD_STATS  # noqa: E402
from pitta_jax.methods.depth_refining import frame_loss  # noqa: E402
from pitta_jax.models import conv_vjp  # noqa: E402

TORCH_IMPLS = ("torch-eager", "torch-eager-cl", "torch-compile")
# the methods with a `torch.compile` variant (the baselines' Python-level loops, hooks and
# RNG-driven augmentations stay eager: inductor would recompile or graph-break on them)
TORCH_COMPILED = ("pitta", "none")
DETERMINISTIC = ("pitta", "actmad")  # same weights and frames => same losses in both frameworks
# frames per timed chunk and rounds, per method (CoTTA's step runs 1 + 32 views: ~30x PITTA's)
DEFAULT_FRAMES = {"cotta": 2, "comoda": 4, "adadepth": 4}
DEFAULT_JAX_FRAMES = {"cotta": 4, "comoda": 8, "adadepth": 8}
DEFAULT_REPS = {"cotta": 3, "comoda": 3, "adadepth": 3}


def batched_forms_kernel_grads(x, g, kernel_size, strides, padding, rhs_dilation, precision):
  """What `conv_vjp._kernel_grad` chose until 2026-12-05, tuned for XLA's default convolution
  library, for `--compare-kernel-grads`: at batch >= 2 the patches product where both sides
  have >= 64 features, one convolution per image where only the input has; the patches product
  for an input of <= `PATCHES_MAX_INPUT_FEATURES` features at any batch; the convolution form
  otherwise. `_kernel_grad` now takes the convolution form at batch >= 2 (fastest on Eigen's
  library, which `auto` gives the one step that takes batched kernel gradients, CoMoDa's)."""
  args = (x, g, kernel_size, strides, padding, rhs_dilation, precision)
  n, c, o = x.shape[0], x.shape[3], g.shape[3]
  if c <= conv_vjp.PATCHES_MAX_INPUT_FEATURES or (n >= 2 and min(c, o) >= 64):
    return conv_vjp.kernel_grad_patches(*args)
  if n >= 2 and c >= 64 > o:
    return bc.per_image_kernel_grad(*args)
  return conv_vjp.kernel_grad_conv(*args)


KERNEL_GRAD_CHOICES = {"model": None, "batched": batched_forms_kernel_grads,
                       "rows": bc.row_tap_kernel_grads,
                       "padding_inside": bc.padding_inside_kernel_grads,
                       "one_convolution": bc.one_convolution_kernel_grads}


class JaxImpl:
  """The engine's compiled chunk runner for one method and config; state carried over chunks."""

  def __init__(self, name: str, variables, configs, resources, conv_rule: str = "loop_friendly",
               conv_library: str | None = None, kernel_grads: str = "model",
               flat_optimizer: bool = False, xla_options: dict | None = None,
               patches_input_grad: bool = True):
    self.cfg, mcfg = configs
    if conv_library is not None:
      self.cfg = dataclasses.replace(self.cfg, conv_library=conv_library)
    self.model, self.method = bc.depth_network(conv_rule), build(name, mcfg)
    self.tx = make_optimizer(self.cfg, self.method)
    if flat_optimizer:  # the engine's optimiser stepped on the raveled trainable tree
      self.tx = flat_optim.flat(self.tx)
    self.compiler_options = step_compiler_options(self.cfg, self.method)
    self.xla_options = xla_options or {}  # added to the step's own options for this compile
    self.runner = make_method_runner(self.model, self.method, self.cfg, self.tx)
    self.state, self.consts = init_state(variables, self.method, self.cfg, self.tx, self.model,
                                         resources)
    self.compiled = None
    self.compile_s = None
    self.kernel_grads = KERNEL_GRAD_CHOICES[kernel_grads]
    self.patches_input_grad = patches_input_grad

  def first(self, chunk: StepInput) -> list[float]:
    """Compile, run the first chunk (losses from the fresh weights) and one warm-up chunk."""
    t0 = time.perf_counter()
    model_choice, input_grad_choice = conv_vjp._kernel_grad, conv_vjp._patches_input_grad
    if self.kernel_grads is not None:  # read while the step is traced (a benchmark's swap)
      conv_vjp._kernel_grad = self.kernel_grads
    if not self.patches_input_grad:  # the convolution form with its transposed kernel copy
      conv_vjp._patches_input_grad = conv_vjp._conv_input_grad
    try:
      lowered = self.runner.lower(self.state, chunk, self.consts)
      self.compiled = (lowered.compile(compiler_options={**(self.compiler_options or {}),
                                                         **self.xla_options})
                       if self.xla_options else lowered.compile())
    finally:
      conv_vjp._kernel_grad, conv_vjp._patches_input_grad = model_choice, input_grad_choice
    self.compile_s = time.perf_counter() - t0
    losses = np.asarray(self.chunk(chunk).loss).tolist()
    self.chunk(chunk)
    return losses

  def chunk(self, chunk: StepInput):
    self.state, outs = self.compiled(self.state, chunk, self.consts)
    jax.block_until_ready(outs)
    return outs


class TorchImpl:
  """A PyTorch step object (`torch_reference.TORCH_STEPS`) run frame by frame."""

  def __init__(self, step, memory_format=torch.contiguous_format):
    self.step, self.memory_format = step, memory_format
    self.compile_s = None

  def inputs(self, frames: list[bc.BenchFrame]) -> list[tuple]:
    return [(tr.to_input(f.image, self.memory_format), torch.from_numpy(f.panoptic),
             list(f.segments)) for f in frames]

  def first(self, frames: list[bc.BenchFrame]) -> list[float]:
    t0 = time.perf_counter()
    losses = [self.step.step(*x)[1] for x in self.inputs(frames)]  # torch.compile compiles here
    self.compile_s = time.perf_counter() - t0
    self.chunk(frames)
    return losses

  def chunk(self, frames: list[bc.BenchFrame]) -> None:
    for x in self.inputs(frames):
      self.step.step(*x)


def torch_impl(impl: str, method: str, configs, resources: dict, height_width: tuple[int, int],
               seed: int = 0, fused: bool = tr.FUSED_OPTIMIZERS):
  """The PyTorch implementation `impl` of `method` with the JAX side's (AdaptConfig, method
  config) on fresh copies of the benchmark weights, or None when torch_reference has no step
  for the method (or this variant of it). fused: PyTorch's fused optimiser kernels, else the
  for-loop implementation (PyTorch's default on CPU)."""
  make = tr.TORCH_STEPS.get(method)
  if make is None or (impl == "torch-compile" and method not in TORCH_COMPILED):
    return None
  enc, dec = tr.build(seed)
  fmt = torch.channels_last if impl == "torch-eager-cl" else torch.contiguous_format
  for net in (enc, dec):  # the steps' copies (EMA teachers, sources) inherit the format
    net.to(memory_format=fmt)
  extra = {}
  if ACTMAD_STATS in resources:  # {JAX layer path: (mean, var) (h, w, c)} -> torch (c, h, w)
    stats = resources[ACTMAD_STATS]
    extra["source_stats"] = {
        name: tuple(torch.from_numpy(np.ascontiguousarray(np.moveaxis(np.asarray(a), -1, 0)))
                    for a in stats[tr.jax_bn_path(name)]) for name, _ in tr.encoder_bns(enc)}
  if method == "adadepth":  # the factor to metres the JAX step takes
    extra["depth_scale"] = adadepth.depth_scale(configs[1], resources)
  if method in tr.NEEDS_POSE:  # a random pose net, KITTI's K, consecutive source frames
    h, w = height_width
    pose = tr.build_pose()
    extra.update(pose=tuple(m.to(memory_format=fmt) for m in pose), K=bc.intrinsics_matrix(h, w),
                 height=h, width=w)
    source = bc.synthetic_frames(bc.SOURCE_FRAMES, h, w, 4, seed=2)
    extra["replay_pairs"] = torch.stack([torch.stack([tr.to_input(a.image)[0],
                                                      tr.to_input(b.image)[0]])
                                         for a, b in zip(source[:-1], source[1:])])
  return TorchImpl(make(enc, dec, configs[1], lr=configs[0].lr, memory_format=fmt,
                        compile=impl == "torch-compile", fused=fused, **extra), fmt)


def time_interleaved(impls: dict, jax_chunk: StepInput, frames: list[bc.BenchFrame],
                     reps: int) -> dict[str, dict]:
  """`reps` rounds of one chunk per implementation, order rotated each round."""
  names = list(impls)
  wall, cpu = bc.interleaved_ms(
      {n: (lambda n=n: impls[n].chunk(jax_chunk if n == "jax" else frames)) for n in names}, reps,
      {n: len(jax_chunk.valid) if n == "jax" else len(frames) for n in names})
  return {n: {"ms_per_frame": float(np.median(wall[n])), "min_ms_per_frame": float(np.min(wall[n])),
              "cpu_ms_per_frame": float(np.median(cpu[n]))} for n in names}


def method_inputs(method: str, n: int, variables, args):
  """Generated frames (--jax-frames of them), the method's configs and resources, and the JAX
  chunk of those frames."""
  frames = bc.synthetic_frames(args.jax_frames, args.height, args.width, n, seed=1)
  configs = bc.method_configs(method, n, args.window, args.jax_frames)
  m = build(method, configs[1])
  resources = bc.method_resources(m, bc.depth_network(), variables, args.height, args.width)
  chunk = bc.step_inputs(frames, configs[0].max_segments, intrinsics="intrinsics" in m.needs)
  return frames, configs, resources, chunk


def run_config(method: str, n: int, impls_wanted: list[str], variables, args, common) -> dict:
  """Sets up, times and reports every implementation for N = n instances."""
  jax_frames, configs, resources, jax_chunk = method_inputs(method, n, variables, args)
  frames = jax_frames[:args.frames]
  impls, losses, compile_s = {}, {}, {}
  for impl in impls_wanted:
    if impl == "jax":
      obj = JaxImpl(method, variables, configs, resources, conv_library=args.conv_library)
      losses[impl] = obj.first(jax_chunk)
    else:
      obj = torch_impl(impl, method, configs, resources, (args.height, args.width))
      if obj is None:
        bc.emit({"impl": impl, "method": method, "skipped": "no PyTorch step for this method "
                 "(or this variant of it) in benchmarks/torch_reference.py"})
        continue
      losses[impl] = obj.first(frames)
    impls[impl], compile_s[impl] = obj, round(obj.compile_s, 2)
  load_start = bc.load()
  results = time_interleaved(impls, jax_chunk, frames, args.reps)
  for impl, r in results.items():
    extra = ({"conv_library": impls[impl].cfg.conv_library,
              "eigen_convolutions": impls[impl].compiler_options is not None}
             if impl == "jax" else {})
    bc.emit({"impl": impl, "method": method, **common, "instances": n, **r, **extra,
             "compile_s": compile_s[impl], "load": load_start})
  torch_names = [i for i in results if i != "jax"]
  if "jax" in results and torch_names:
    fastest = min(torch_names, key=lambda i: results[i]["ms_per_frame"])
    best = min(torch_names, key=lambda i: results[i]["min_ms_per_frame"])
    bc.emit({"ratio": "fastest torch ms / jax ms", "method": method, **common, "instances": n,
             "fastest_torch": fastest, "value": results[fastest]["ms_per_frame"]
             / results["jax"]["ms_per_frame"],
             "value_best": results[best]["min_ms_per_frame"] / results["jax"]["min_ms_per_frame"],
             "value_cpu": min(results[i]["cpu_ms_per_frame"] for i in torch_names)
             / results["jax"]["cpu_ms_per_frame"],
             "per_impl": {i: results[i]["ms_per_frame"] / results["jax"]["ms_per_frame"]
                          for i in torch_names}, "load": bc.load()})
  if method in DETERMINISTIC and "jax" in losses:
    for impl in torch_names:  # the frames both saw: the first `--frames` of the sequence
      a, b = np.asarray(losses["jax"][:len(losses[impl])]), np.asarray(losses[impl])
      bc.emit({"check": f"loss parity jax vs {impl}, first chunk from the same weights",
               "method": method, "instances": n,
               "max_rel_diff": float(np.max(np.abs(a - b) / np.abs(b))),
               "jax_loss_0": float(a[0]), "torch_loss_0": float(b[0])})
  return results


def matmul_and_conv_rate(reps: int = 5) -> dict:
  """This machine's float32 GFLOP/s in XLA: a 1024^3 matmul and a 64->64 3x3 conv at 96x320."""
  a = jnp.ones((1024, 1024), jnp.float32)
  mm = jax.jit(lambda x: x @ x)
  mm(a).block_until_ready()
  t_mm, _ = bc.median_time(lambda: mm(a).block_until_ready(), reps)
  x = jnp.ones((1, 96, 320, 64), jnp.float32)
  k = jnp.ones((3, 3, 64, 64), jnp.float32) * 0.01
  conv = jax.jit(lambda x, k: jax.lax.conv_general_dilated(
      x, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")))
  conv(x, k).block_until_ready()
  t_conv, _ = bc.median_time(lambda: conv(x, k).block_until_ready(), reps)
  return {"matmul_gflops": 2 * 1024 ** 3 / t_mm / 1e9,
          "conv_gflops": 2 * 96 * 320 * 64 * 64 * 9 / t_conv / 1e9}


def jax_profile(impl: JaxImpl, frame: StepInput, reps: int) -> dict:
  """FLOPs and time of the parts of one PITTA step (each part jitted alone, not scanned)."""
  model, method, cfg = impl.model, impl.method, impl.cfg
  pitta = method.config
  state, consts = impl.state, impl.consts
  step = make_step(model, method, cfg, impl.tx)

  def forward(st, image, cs):
    variables = trainable_lib.merge(st.trainable, cs.frozen, cs.batch_stats)
    return model.depth(variables, image[None], True)[0]

  def forward_backward(st, fr, cs):
    def loss_fn(t):
      return method.loss(t, state=st, consts=cs, frame=fr, rng=None, model=model, cfg=cfg,
                         mcfg=method.config)
    return jax.value_and_grad(loss_fn, has_aux=True)(st.trainable)

  def loss_only(depth, fr):
    return jax.value_and_grad(lambda d: frame_loss(d, fr, pitta.ld, pitta.lam).total)(depth)

  depth = jax.jit(forward)(state, frame.image, consts)
  parts = {"forward": (forward, (state, frame.image, consts)),
           "forward_backward": (forward_backward, (state, frame, consts)),
           "loss_and_depth_grad": (loss_only, (depth, frame)),
           "step": (step, (state, frame, consts))}
  out = {}
  for name, (fn, fn_args) in parts.items():
    compiled = jax.jit(fn).lower(*fn_args).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    jax.block_until_ready(compiled(*fn_args))
    med, _ = bc.median_time(lambda: jax.block_until_ready(compiled(*fn_args)), reps)
    out[name] = {"ms": 1e3 * med, "gflop": float(cost.get("flops", float("nan"))) / 1e9}
  return out


def torch_profile(frame: bc.BenchFrame, window: int, reps: int) -> dict:
  enc, dec = tr.build()
  model = tr.TorchPitta(enc, dec, window=window)
  image = tr.to_input(frame.image)
  pan, segs = torch.from_numpy(frame.panoptic), list(frame.segments)

  def forward():
    with torch.no_grad():
      model.depth(image)

  def forward_backward():
    model.optimizer.zero_grad(set_to_none=True)
    masks = tr.instance_masks(pan, segs)
    tr.pitta_loss(image[0], model.depth(image), masks, window)[0].backward()

  with torch.no_grad():
    depth0 = model.depth(image)

  def loss_only():
    d = depth0.clone().requires_grad_(True)
    tr.pitta_loss(image[0], d, tr.instance_masks(pan, segs), window)[0].backward()

  out = {}
  for name, fn in (("forward", forward), ("forward_backward", forward_backward),
                   ("loss_and_depth_grad", loss_only),
                   ("step", lambda: model.step(image, pan, segs))):
    fn()
    out[name] = {"ms": 1e3 * bc.median_time(fn, reps)[0]}
  return out


def library_and_kernel_grads(other: str) -> dict[str, dict]:
  """`compare_jax` variants: XLA's default and Eigen's convolution library, each with the
  model's kernel gradients and with `KERNEL_GRAD_CHOICES[other]`."""
  return {f"{lib}+{grads}": {"conv_library": lib, "kernel_grads": grads}
          for lib in ("default", "eigen") for grads in ("model", other)}


def compare_jax(method: str, variants: dict[str, dict], what: str, variables, args,
                common) -> None:
  """The method's JAX step in several variants (`JaxImpl` keyword arguments), interleaved."""
  _, configs, resources, chunk = method_inputs(method, args.instances, variables, args)
  impls, losses, compile_s = {}, {}, {}
  for name, kwargs in variants.items():
    impls[name] = JaxImpl(method, variables, configs, resources, **kwargs)
    losses[name] = np.asarray(impls[name].first(chunk))
    compile_s[name] = round(impls[name].compile_s, 2)
  load = bc.load()
  times, _ = bc.interleaved_ms({name: (lambda name=name: impls[name].chunk(chunk))
                                for name in variants}, args.reps, len(chunk.valid))
  med = {name: float(np.median(t)) for name, t in times.items()}
  first, *rest = variants
  bc.emit({"check": what, "method": method, **common, "instances": args.instances,
           "ms_per_frame": med, "min_ms_per_frame": {n: float(np.min(t)) for n, t in times.items()},
           **{f"ratio_{n}_vs_{first}": med[n] / med[first] for n in rest},
           "compile_s": compile_s,
           "loop_kernels": {n: impls[n].compiled.as_text().count("kind=kLoop") for n in variants},
           # relative to the largest loss (`none` computes no loss: 0)
           "max_rel_loss_diff": {n: float(np.max(np.abs(losses[n] - losses[first]))
                                          / max(np.max(np.abs(losses[first])), 1e-30))
                                 for n in rest},
           "load": load, "load_end": bc.load()})


def compare_torch_optimizers(method: str, variables, args, common) -> None:
  """The method's PyTorch eager step with fused optimiser kernels and with PyTorch's default
  for-loop ones (CPU), interleaved: what `torch_reference.FUSED_OPTIMIZERS` is worth."""
  frames, configs, resources, _ = method_inputs(method, args.instances, variables, args)
  frames = frames[:args.frames]
  impls, losses = {}, {}
  for name, fused in (("fused", True), ("for-loop", False)):
    impls[name] = torch_impl("torch-eager", method, configs, resources,
                             (args.height, args.width), fused=fused)
    if impls[name] is None:
      bc.emit({"check": "PyTorch optimisers", "method": method, "skipped": "no PyTorch step"})
      return
    losses[name] = np.asarray(impls[name].first(frames))
  load = bc.load()
  times, _ = bc.interleaved_ms({name: (lambda name=name: impls[name].chunk(frames))
                                for name in impls}, args.reps, len(frames))
  med = {name: float(np.median(t)) for name, t in times.items()}
  bc.emit({"check": "PyTorch optimisers", "method": method, **common,
           "instances": args.instances, "ms_per_frame": med,
           "min_ms_per_frame": {n: float(np.min(t)) for n, t in times.items()},
           "ratio_for-loop_vs_fused": med["for-loop"] / med["fused"],
           # NaN where both are NaN (Ada-Depth's SILog at S = E = R, as upstream's) counts as 0
           "max_rel_loss_diff": float(np.nanmax(np.abs(losses["for-loop"] - losses["fused"]))
                                      / max(np.nanmax(np.abs(losses["fused"])), 1e-30)),
           "same_nan_losses": bool(np.array_equal(np.isnan(losses["for-loop"]),
                                                  np.isnan(losses["fused"]))),
           "load": load, "load_end": bc.load()})


def compile_parts(method: str, n: int, variables, args, common) -> None:
  """Where a step's compile goes: JAX's trace and lowering, then XLA's compile; then XLA's
  compile again with each `--xla-option` added to the step's options."""
  _, configs, resources, chunk = method_inputs(method, n, variables, args)
  impl = JaxImpl(method, variables, configs, resources)
  t0 = time.perf_counter()
  lowered = impl.runner.lower(impl.state, chunk, impl.consts)
  trace_lower_s = round(time.perf_counter() - t0, 2)
  for option in [None, *args.xla_option]:
    extra = {} if option is None else dict([option])
    load = bc.load()
    t1, c1 = time.perf_counter(), time.process_time()
    compiled = lowered.compile(compiler_options={**(impl.compiler_options or {}), **extra})
    t2, c2 = time.perf_counter(), time.process_time()
    text = compiled.as_text()
    # XLA:CPU's compile time grows with the number of generated loop kernels (fusions): a count
    # that, unlike the seconds, does not move with the machine's load
    bc.emit({"compile": "jax", "method": method, **common, "instances": n, "xla_option": extra,
             "trace_lower_s": trace_lower_s, "xla_compile_s": round(t2 - t1, 2),
             "xla_compile_cpu_s": round(c2 - c1, 2), "loop_kernels": text.count("kind=kLoop"),
             "load": load})


def xla_option(text: str) -> tuple[str, bool | int | str]:
  """`KEY=VALUE` -> (KEY, VALUE as a bool, an int or the string)."""
  key, sep, value = text.partition("=")
  if not sep or not key:
    raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
  if value.lower() in ("true", "false"):
    return key, value.lower() == "true"
  try:
    return key, int(value)
  except ValueError:
    return key, value


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--method", default="pitta", choices=sorted(METHODS))
  p.add_argument("--height", type=int, default=192)
  p.add_argument("--width", type=int, default=640)
  p.add_argument("--instances", type=int, default=8, help="dynamic instances N per frame")
  p.add_argument("--sweep-instances", default="", help="comma list of N, e.g. 1,8,32")
  p.add_argument("--window", type=int, default=5, help="median window s")
  p.add_argument("--frames", type=int, default=None,
                 help=f"frames per timed PyTorch chunk (default 8; {DEFAULT_FRAMES})")
  p.add_argument("--jax-frames", type=int, default=None,
                 help=f"frames per timed JAX chunk (default: the engine's chunk size, "
                      f"{AdaptConfig().chunk_size}; {DEFAULT_JAX_FRAMES})")
  p.add_argument("--reps", type=int, default=None,
                 help=f"timed rounds, one chunk per implementation each (default 5; {DEFAULT_REPS})")
  p.add_argument("--threads", type=int, default=os.cpu_count(), help="PyTorch threads")
  p.add_argument("--impls", default="", help="comma list among jax," + ",".join(TORCH_IMPLS)
                 + " (default: all that exist for the method)")
  p.add_argument("--profile", action="store_true", help="FLOPs and per-part times (PITTA)")
  p.add_argument("--quick", action="store_true", help="320x96, 4 frames, 3 rounds")
  p.add_argument("--compile-only", action="store_true",
                 help="only trace, lower and compile the JAX chunk runner and print the seconds "
                      "of each part (no timing of steps)")
  p.add_argument("--xla-option", type=xla_option, action="append", default=[],
                 metavar="KEY=VALUE",
                 help="with --compile-only: compile the step again with this XLA option added "
                      "(repeatable, one compile each), e.g. xla_llvm_disable_expensive_passes=true")
  p.add_argument("--compare-xla-option", type=xla_option, action="append", default=[],
                 metavar="KEY=VALUE",
                 help="also time the method's JAX step with this XLA option added to its own "
                      "(repeatable, one variant each) against the step as it is, interleaved, "
                      "with each compile, e.g. xla_backend_optimization_level=2")
  p.add_argument("--compare-conv-rule", action="store_true",
                 help="also time the PITTA step with JAX's own convolution input-gradient rule "
                      "(what pitta_jax.models.conv_vjp replaces) and print the ratio")
  p.add_argument("--conv-library", choices=CONV_LIBRARIES, default=None,
                 help="XLA:CPU's convolution library for the JAX step (AdaptConfig.conv_library; "
                      "default: the method setting's, auto)")
  p.add_argument("--compare-conv-library", action="store_true",
                 help="also time the method's JAX step with XLA's default convolution library "
                      "and with Eigen's, interleaved, and print the ratio")
  p.add_argument("--compare-kernel-grads", action="store_true",
                 help="also time the method's JAX step three ways, interleaved: XLA's default "
                      "library and Eigen's with the model's kernel-gradient forms "
                      "(models.conv_vjp), and XLA's default library with the batched forms "
                      "conv_vjp used until 2026-12-05 (patches products and per-image "
                      "convolutions at batch >= 2)")
  p.add_argument("--compare-padded-kernel-grads", action="store_true",
                 help="time the step with kernel gradients of the input padded first (the "
                      "model's) and with the padding inside the convolution (before "
                      "2026-12-08), on XLA's default and on Eigen's convolution library, "
                      "interleaved")
  p.add_argument("--compare-strided-kernel-grads", action="store_true",
                 help="time the step with strided layers' kernel gradients per stride phase "
                      "(conv_vjp.kernel_grad_phases, the model's) and as one convolution with "
                      "the stride-dilated cotangent (before 2026-12-08, 04:00 UTC), "
                      "interleaved")
  p.add_argument("--compare-patches-input-grad", action="store_true",
                 help="time the step with the few-pixel layers' input gradients as the "
                      "transposed patches product (conv_vjp._patches_input_grad, the model's) "
                      "and as the patches product of a transposed kernel copy (before "
                      "2026-12-08), interleaved")
  p.add_argument("--compare-row-taps", action="store_true",
                 help="also time the method's JAX step four ways, interleaved: XLA's default "
                      "library and Eigen's, each with the model's kernel-gradient forms "
                      "(models.conv_vjp) and with products of row taps for ResNet's stages "
                      "(bench_common.row_tap_kernel_grads, tried 2026-12-06)")
  p.add_argument("--compare-flat-optimizer", action="store_true",
                 help="also time the method's JAX step with the engine's optimiser stepped leaf "
                      "by leaf (the default) and on the raveled trainable tree "
                      "(pitta_jax.flat_optim.flat), interleaved, with each compile")
  p.add_argument("--compare-torch-optimizers", action="store_true",
                 help="also time the method's PyTorch eager step with fused optimiser kernels "
                      "(the references' default) and with PyTorch's default for-loop ones, "
                      "interleaved, and print the ratio")
  p.add_argument("--compare-only", action="store_true",
                 help="with --compare-xla-option/--compare-conv-rule/--compare-conv-library/"
                      "--compare-kernel-grads/--compare-padded-kernel-grads/"
                      "--compare-strided-kernel-grads/--compare-patches-input-grad/"
                      "--compare-row-taps/--compare-flat-optimizer/--compare-torch-optimizers: "
                      "skip the JAX vs PyTorch timing")
  args = p.parse_args(argv)
  if args.frames is None:
    args.frames = DEFAULT_FRAMES.get(args.method, 8)
  if args.jax_frames is None:
    args.jax_frames = DEFAULT_JAX_FRAMES.get(args.method, AdaptConfig().chunk_size)
  if args.reps is None:
    args.reps = DEFAULT_REPS.get(args.method, 5)
  if args.quick:
    args.height, args.width, args.frames, args.reps = 96, 320, min(args.frames, 4), 3
    args.jax_frames = min(args.jax_frames, 8)
  if min(args.frames, args.jax_frames, args.reps) < 1:
    p.error("--frames, --jax-frames and --reps must be >= 1")
  args.jax_frames = max(args.jax_frames, args.frames)
  torch.set_num_threads(args.threads)
  impls = [s.strip() for s in args.impls.split(",") if s.strip()] or ["jax", *TORCH_IMPLS]
  unknown = set(impls) - {"jax", *TORCH_IMPLS}
  if unknown:
    p.error(f"--impls: unknown {sorted(unknown)}; use jax,{','.join(TORCH_IMPLS)}")
  sweep = [int(n) for n in args.sweep_instances.split(",") if n.strip()] or [args.instances]

  _, _, variables = bc.torch_and_jax_weights(seed=0)
  common = {"H": args.height, "W": args.width, "window": args.window, "threads": args.threads,
            "frames": args.frames, "jax_frames": args.jax_frames, "reps": args.reps,
            "device": jax.devices()[0].platform}
  if args.compile_only:
    compile_parts(args.method, sweep[0], variables, args, common)
    return
  bc.emit({"start": "step", "method": args.method, "impls": impls, "load": bc.load()})
  results = {} if args.compare_only else {
      n: run_config(args.method, n, impls, variables, args, common) for n in sweep}
  if len(results) > 1:
    bc.emit({"sweep_instances": sweep, **{f"{impl}_ms_per_frame": [
        results[n][impl]["ms_per_frame"] for n in sweep] for impl in results[sweep[0]]}})
  if args.compare_conv_rule:  # JAX's own conv input-gradient rule vs `models.conv_vjp`'s
    compare_jax("pitta", {rule: {"conv_rule": rule} for rule in bc.CONV_RULES},
                "conv input-gradient rule", variables, args, common)
  if args.compare_conv_library:
    compare_jax(args.method, {lib: {"conv_library": lib} for lib in ("default", "eigen")},
                "XLA:CPU convolution library", variables, args, common)
  if args.compare_kernel_grads:
    compare_jax(args.method, {
        "default+batched": {"conv_library": "default", "kernel_grads": "batched"},
        "default+model": {"conv_library": "default"},
        "eigen+model": {"conv_library": "eigen"}},
        "XLA:CPU convolution library and kernel-gradient forms", variables, args, common)
  if args.compare_padded_kernel_grads:
    compare_jax(args.method, library_and_kernel_grads("padding_inside"),
                "kernel gradients: input padded first or padding inside the convolution",
                variables, args, common)
  if args.compare_strided_kernel_grads:
    compare_jax(args.method, {"phases": {}, "one convolution": {"kernel_grads": "one_convolution"}},
                "strided kernel gradients: per stride phase or one convolution", variables, args,
                common)
  if args.compare_patches_input_grad:
    compare_jax(args.method, {"transposed product": {},
                              "kernel copy": {"patches_input_grad": False}},
                "few-pixel input gradients: transposed patches product or the transposed kernel "
                "copy", variables, args, common)
  if args.compare_row_taps:
    compare_jax(args.method, library_and_kernel_grads("rows"),
                "kernel gradients: row-tap products or the convolution form", variables, args,
                common)
  if args.compare_flat_optimizer:
    compare_jax(args.method, {"per-leaf": {}, "raveled": {"flat_optimizer": True}},
                "the engine's optimiser per leaf or on the raveled tree", variables, args, common)
  if args.compare_xla_option:
    compare_jax(args.method, {"as is": {}, **{f"{k}={v}": {"xla_options": {k: v}}
                                            for k, v in args.compare_xla_option}},
                "XLA options added to the step's", variables, args, common)
  if args.compare_torch_optimizers:
    compare_torch_optimizers(args.method, variables, args, common)
  if args.profile and args.method == "pitta":
    n = sweep[0]
    frames = bc.synthetic_frames(1, args.height, args.width, n, seed=1)
    configs = bc.method_configs("pitta", n, args.window, args.frames)
    impl = JaxImpl("pitta", variables, configs, {})
    frame = bc.step_inputs(frames, configs[0].max_segments)
    frame = StepInput(*(x[0] for x in frame))
    rates = matmul_and_conv_rate()
    prof = {"profile": "jax", "instances": n, **common, **jax_profile(impl, frame, args.reps),
            **{k: round(v, 1) for k, v in rates.items()}}
    prof["flop_floor_ms"] = prof["step"]["gflop"] / max(rates.values()) * 1e3
    bc.emit(prof)
    bc.emit({"profile": "torch", "instances": n, **common,
             **torch_profile(frames[0], args.window, args.reps)})
  bc.emit({"load_end": bc.load()})


if __name__ == "__main__":
  main()
