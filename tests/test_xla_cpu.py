"""XLA:CPU's convolution library per compiled step (`pitta_jax.adapt.xla_cpu`).

- the rule: which steps get Eigen's convolutions (`auto`: no conv kernel adapts; `eigen`:
  always; `default`: never; never on another backend), and which selectors adapt conv kernels;
- the option reaches the compile: in the compiled program of a convolution that XLA:CPU hands
  to YNNPACK by default (a `__ynn_fusion` around it), Eigen's option leaves it a plain
  convolution, and both agree with a literal NumPy loop of the convolution;
- the engine's callers pass it: `run.Runners` compiles PITTA's step with Eigen's option,
  ActMAD's (encoder kernels adapt) and Ada-Depth's (its own branch's kernels) without, CoTTA's
  and CoMoDa's with (their own choice); a bad `--conv-library` or method choice is refused
  before any work.
"""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pitta_jax.adapt import AdaptConfig
from pitta_jax.adapt.xla_cpu import (YNN_FUSION_FLAG, YNN_WITHOUT_CONVOLUTIONS,
                                     conv_library_options)

EIGEN = {YNN_FUSION_FLAG: YNN_WITHOUT_CONVOLUTIONS}


@pytest.mark.parametrize("library, platform, expected", [
    ("auto", "cpu", EIGEN),
    ("eigen", "cpu", EIGEN),
    ("default", "cpu", None),
    ("eigen", "gpu", None),
    ("auto", "tpu", None),
])
def test_conv_library_options(library, platform, expected):
  assert conv_library_options(library, platform) == expected


def test_method_choice_overrides_auto_only():
  """`auto` is Eigen's library, or the method's `cpu_conv_library` where it names one; an
  explicit config wins over the method's choice."""
  from types import SimpleNamespace

  from pitta_jax.adapt.xla_cpu import step_compiler_options
  from pitta_jax.methods import METHODS, build
  if jax.default_backend() != "cpu":
    pytest.skip("XLA:CPU's option")
  plain = SimpleNamespace(cpu_conv_library="auto")
  prefers_default = SimpleNamespace(cpu_conv_library="default")
  every = AdaptConfig(selector="all")
  assert step_compiler_options(every, plain) == EIGEN
  assert step_compiler_options(AdaptConfig(), plain) == EIGEN
  assert step_compiler_options(every, prefers_default) is None
  assert step_compiler_options(dataclasses.replace(every, conv_library="eigen"),
                               prefers_default) == EIGEN
  assert step_compiler_options(dataclasses.replace(every, conv_library="default"),
                               plain) is None
  for name in METHODS:  # every built-in method's step compiles with Eigen's by default
    assert step_compiler_options(AdaptConfig(), build(name)) == EIGEN, name


def test_unknown_library_is_refused():
  with pytest.raises(ValueError, match="conv_library must be one of auto, default, eigen"):
    conv_library_options("mkl", "cpu")
  with pytest.raises(ValueError, match="conv_library"):
    AdaptConfig(conv_library="ynn")
  from pitta_jax.methods import build
  with pytest.raises(ValueError, match="cpu_conv_library"):
    dataclasses.replace(build("none"), cpu_conv_library="mkl")


def _conv(x, k):  # (B, H, W, Cin), (3, 3, Cin, Cout) -> (B, H, W, Cout), zero padding 1
  return jax.lax.conv_general_dilated(x, k, (1, 1), ((1, 1), (1, 1)),
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


def _numpy_conv(x: np.ndarray, k: np.ndarray) -> np.ndarray:
  """The convolution as a literal loop over output pixels and taps (cross-correlation)."""
  b, h, w, _ = x.shape
  xp = np.pad(x.astype(np.float64), ((0, 0), (1, 1), (1, 1), (0, 0)))
  out = np.zeros((b, h, w, k.shape[-1]))
  for i in range(h):
    for j in range(w):
      for di in range(3):
        for dj in range(3):
          out[:, i, j] += xp[:, i + di, j + dj] @ k[di, dj]
  return out


def _convs_in_ynn_fusions(hlo: str) -> int:
  """Number of YNNPACK custom fusions whose called computation contains a convolution."""
  comps = {m.group(1): m.group(2) for m in
           re.finditer(r"^%(\S+) \([^\n]*\{\n(.*?)\n\}", hlo, flags=re.M | re.S)}
  calls = re.findall(r"kind=kCustom, calls=%([\w.]+)[^\n]*__ynn_fusion", hlo)
  return sum("convolution(" in comps.get(c, "") for c in calls)


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA:CPU's option")
def test_eigen_option_reaches_the_compile():
  rng = np.random.default_rng(0)
  x = rng.standard_normal((2, 8, 8, 32)).astype(np.float32)  # (B, H, W, C)
  k = (rng.standard_normal((3, 3, 32, 32)) / 17).astype(np.float32)
  expected = _numpy_conv(x, k)
  counts = {}
  for name, options in (("default", None), ("eigen", conv_library_options("eigen", "cpu"))):
    compiled = jax.jit(_conv, compiler_options=options).lower(x, k).compile()
    counts[name] = _convs_in_ynn_fusions(compiled.as_text())
    np.testing.assert_allclose(np.asarray(compiled(jnp.asarray(x), jnp.asarray(k))), expected,
                               rtol=1e-4, atol=1e-4)
  # jaxlib 0.10's XLA:CPU hands this convolution to YNNPACK; the option must take it away
  assert counts == {"default": 1, "eigen": 0}


def test_runners_pass_the_step_options(monkeypatch):
  """`run.Runners.get` compiles each method's chunk with `step_compiler_options` (through
  `engine.make_method_runner`)."""
  from types import SimpleNamespace

  from pitta_jax import run
  from pitta_jax.adapt import engine
  from pitta_jax.methods import build, method_setting

  seen = []
  monkeypatch.setattr(engine, "make_chunk_runner",
                      lambda step, options=None: seen.append(options) or (lambda *a: None))
  # what Runners.get reads of a Weights; the network is not traced (the runner is stubbed)
  weights = SimpleNamespace(spec=SimpleNamespace(name="net"), config={}, network=lambda: None)
  runners = run.Runners()
  for name in ("pitta", "actmad", "cotta", "adadepth", "comoda"):
    method = build(name)
    runners.get(weights, method, AdaptConfig(**method_setting(name)))
  runners.get(weights, build("actmad"), AdaptConfig(**method_setting("actmad"),
                                                    conv_library="default"))
  eigen = EIGEN if jax.default_backend() == "cpu" else None
  # `auto`: Eigen's convolutions for every method; the config's `default`: XLA's own
  assert seen == [eigen] * 5 + [None]
