"""Which library runs a compiled step's convolutions on XLA:CPU.

XLA:CPU hands convolutions to one of two libraries: YNNPACK (jaxlib 0.10's default, through its
"YNN fusions") or Eigen's tensor contractions (XLA's older path). `auto` takes Eigen's for every
step on a CPU: measured on 2-core AMD EPYC and Intel Xeon guests at 640x192, each step
interleaved with itself (docs/performance.md), its forward convolutions and input gradients are
faster (no adaptation 4-16%, PITTA, which adapts only BatchNorm parameters, 1-12%), and since
the kernel gradients of a single image convolve the input padded first
(`models.conv_vjp._kernel_grad`, 2026-12-08) so are the steps that adapt convolution kernels:
ActMAD 733 against 799 ms/frame with XLA's default library, Ada-Depth 1841 against 2040, CoMoDa
(kernel gradients of a batch of four) 3151 against 4625, CoTTA (35 forward passes per kernel
gradient) 4567 against 7654. A method may still name its own choice
(`Method.cpu_conv_library`), and `default` is one flag away (`--conv-library default`).
The choice is per compiled program (`jax.jit(..., compiler_options=...)`), never process-wide,
and fixed before the compile: no run-time autotuning, so that a run's numerics do not depend on
timings.

Both libraries compute the same float32 convolutions up to the order of summation (a PITTA
loss differs by 1e-7 to 1e-6 relative between them).
"""

from __future__ import annotations

from typing import Any

import jax


CONV_LIBRARIES = ("auto", "default", "eigen")
# XLA:CPU's flag: the kinds of operations it hands to YNNPACK. Its default also lists
# LIBRARY_FUSION_TYPE_INDIVIDUAL_CONVOLUTION; leaving that out sends convolutions to Eigen.
YNN_FUSION_FLAG = "xla_cpu_experimental_ynn_fusion_type"
YNN_WITHOUT_CONVOLUTIONS = "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT,LIBRARY_FUSION_TYPE_REDUCE"


def check_library(value: str, what: str = "conv_library") -> None:
  """ValueError (one line naming `what`) unless `value` is one of CONV_LIBRARIES."""
  if value not in CONV_LIBRARIES:
    raise ValueError(f"{what} must be one of {', '.join(CONV_LIBRARIES)}, got {value!r}")


def conv_library_options(library: str, platform: str | None = None) -> dict[str, Any] | None:
  """XLA compiler options (for `jax.jit(..., compiler_options=...)`) that put a step's
  convolutions on `library`, or None for XLA's own choice.

  library: `default` (XLA's own choice), `eigen`, or `auto` (Eigen's on a CPU; module
    docstring).
  platform: the backend the program compiles for (default: JAX's default backend). The options
    are XLA:CPU's: on any other backend the result is None.
  """
  check_library(library)
  platform = platform or jax.default_backend()
  if platform != "cpu" or library == "default":
    return None
  return {YNN_FUSION_FLAG: YNN_WITHOUT_CONVOLUTIONS}


def step_compiler_options(cfg: Any, method: Any) -> dict[str, Any] | None:
  """`conv_library_options` for the step of `method` (a `methods.Method`) under `cfg` (an
  `AdaptConfig`): what `make_chunk_runner` takes as `compiler_options`. `auto` takes the
  method's own choice (`Method.cpu_conv_library`) where it has one."""
  library = cfg.conv_library
  if library == "auto":
    library = method.cpu_conv_library
  return conv_library_options(library)
