"""Which library runs a compiled step's convolutions on XLA:CPU.

XLA:CPU hands convolutions to one of two libraries: YNNPACK (jaxlib 0.10's default, through its
"YNN fusions") or Eigen's tensor contractions (XLA's older path). Neither is faster everywhere.
Measured on a 2-core AMD EPYC (Zen 3, AVX2) host, each step interleaved with itself, 640x192
(docs/performance.md): Eigen's forward convolutions and input gradients are faster (no
adaptation 16% and PITTA, which adapts only BatchNorm parameters, 6-12% faster per frame), its
kernel gradients slower (ActMAD and CoMoDa, which adapt convolution kernels, 8% slower by the
median; Ada-Depth 1-3%), unless forward passes dominate the step (CoTTA: 35 forward passes per
kernel gradient, 21% faster). Hence `auto`: Eigen for a step that differentiates no convolution
kernel, XLA's default otherwise, or the method's own measured choice (`Method.cpu_conv_library`:
CoTTA; CoMoDa, whose kernel gradients of a batch are fastest as Eigen's convolutions). On a
2-core Intel Xeon (AVX-512) the same rule holds with smaller gains for the forward passes (1-4%)
and the same losses for kernel gradients (ActMAD, Ada-Depth 12% slower on Eigen).
The choice is per compiled program (`jax.jit(..., compiler_options=...)`), never process-wide,
and fixed before the compile: no run-time autotuning, so that a run's numerics do not depend on
timings.

Both libraries compute the same float32 convolutions up to the order of summation (a PITTA
loss differs by 1e-7 to 1e-6 relative between them).
"""

from __future__ import annotations

from typing import Any

import jax

from pitta_jax.trainable import parse_selector

CONV_LIBRARIES = ("auto", "default", "eigen")
# XLA:CPU's flag: the kinds of operations it hands to YNNPACK. Its default also lists
# LIBRARY_FUSION_TYPE_INDIVIDUAL_CONVOLUTION; leaving that out sends convolutions to Eigen.
YNN_FUSION_FLAG = "xla_cpu_experimental_ynn_fusion_type"
YNN_WITHOUT_CONVOLUTIONS = "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT,LIBRARY_FUSION_TYPE_REDUCE"


def check_library(value: str, what: str = "conv_library") -> None:
  """ValueError (one line naming `what`) unless `value` is one of CONV_LIBRARIES."""
  if value not in CONV_LIBRARIES:
    raise ValueError(f"{what} must be one of {', '.join(CONV_LIBRARIES)}, got {value!r}")


def adapts_conv_kernels(selector: str, adapts: bool = True) -> bool:
  """Whether a step differentiates convolution kernels: the method updates parameters and the
  selector (`AdaptConfig.selector`) includes conv kernels (all, no_bn, fraction with cnn > 0)."""
  sel = parse_selector(selector)
  return adapts and (sel.kind in ("all", "no_bn") or (sel.kind == "fraction" and sel.cnn > 0))


def conv_library_options(library: str, conv_kernel_grads: bool,
                         platform: str | None = None) -> dict[str, Any] | None:
  """XLA compiler options (for `jax.jit(..., compiler_options=...)`) that put a step's
  convolutions on `library`, or None for XLA's own choice.

  library: `default` (XLA's own choice), `eigen`, or `auto`: Eigen on CPU for a step that
    differentiates no convolution kernel (`conv_kernel_grads` False), XLA's own choice otherwise
    (where Eigen was measured faster and slower, respectively; module docstring).
  platform: the backend the program compiles for (default: JAX's default backend). The options
    are XLA:CPU's: on any other backend the result is None.
  """
  check_library(library)
  platform = platform or jax.default_backend()
  eigen = library == "eigen" or (library == "auto" and not conv_kernel_grads)
  if platform != "cpu" or not eigen:
    return None
  return {YNN_FUSION_FLAG: YNN_WITHOUT_CONVOLUTIONS}


def step_compiler_options(cfg: Any, method: Any) -> dict[str, Any] | None:
  """`conv_library_options` for the step of `method` (a `methods.Method`) under `cfg` (an
  `AdaptConfig`): what `make_chunk_runner` takes as `compiler_options`. `auto` takes the
  method's own choice (`Method.cpu_conv_library`) where it has one. A method whose step
  differentiates kernels of its own networks (`Method.own_conv_kernel_grads`) counts as
  adapting conv kernels whatever the selector."""
  library = cfg.conv_library
  if library == "auto":
    library = method.cpu_conv_library
  kernel_grads = adapts_conv_kernels(cfg.selector, method.adapts) or method.own_conv_kernel_grads
  return conv_library_options(library, kernel_grads)
