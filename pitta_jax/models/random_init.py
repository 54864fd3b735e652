"""Random network variables for tests, benchmarks and `--quick` tables.

`random_monodepth2_variables`, `random_variables`: MonoDepth2's (any conv + BN network's)
variables whose activations stay O(1).
`init_variables`: any Flax module's own initialisers, compiled cheaply.
`jit_init`: `jax.jit(module.init)`, compiled for a program that runs once.

Flax's default init gives a random ResNet whose deep activations explode or vanish without
ImageNet BN statistics; these draws (the same distributions as the PyTorch reference's
`tests/torch_monodepth2.randomize_`) keep every layer's output O(1), so losses, gradients and
timings behave like those of a trained network. NumPy draws on `jax.eval_shape`: no compile.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax.models.depth_decoder import DepthNet


def random_monodepth2_variables(seed: int = 0, num_layers: int = 18) -> dict[str, Any]:
  """{"params", "batch_stats"} of a `DepthNet(num_layers)` (`random_variables`'s draws). The
  variables do not depend on the image size."""
  return random_variables(DepthNet(num_layers), seed, jnp.zeros((1, 64, 64, 3)))


def random_variables(module: Any, seed: int, *inputs: jax.Array) -> dict[str, Any]:
  """{"params", "batch_stats"} of a conv + BatchNorm `module` called on `inputs`.

  Kernels ~ N(0, 1 / fan_in), BN gamma ~ U[0.3, 0.8], biases and beta ~ 0.1 N(0, 1), running
  means ~ 0.2 N(0, 1) and variances ~ U[0.5, 1.5].
  """
  rng = np.random.default_rng(seed)
  shapes = jax.eval_shape(module.init, jax.random.PRNGKey(0), *inputs)

  def draw(path, x):
    name = jax.tree_util.keystr(path)
    if x.ndim == 4:  # conv kernel (kh, kw, in, out)
      return rng.normal(size=x.shape).astype(np.float32) / np.sqrt(np.prod(x.shape[:3]))
    if "mean" in name:
      return (0.2 * rng.normal(size=x.shape)).astype(np.float32)
    if "var" in name:
      return (0.5 + rng.uniform(size=x.shape)).astype(np.float32)
    if "scale" in name:
      return (0.3 + 0.5 * rng.uniform(size=x.shape)).astype(np.float32)
    return (0.1 * rng.normal(size=x.shape)).astype(np.float32)
  return jax.tree_util.tree_map_with_path(draw, shapes)


# Backend optimisation level 1 instead of XLA's default 3 for an init: it runs once, so its
# code need not be fast, and it compiles ~2.6x faster (MonoDepth2 ResNet-18 at 64x96, 2 vCPU:
# 23 s -> 8.7 s). On XLA:CPU the draws are bitwise those of the default compile (threefry's
# hash is integer arithmetic; checked for the depth and pose nets). Only on the CPU, where it
# was checked.
_INIT_OPTIONS_CPU = {"xla_backend_optimization_level": 1}


def jit_init(module: Any, key: jax.Array, *inputs: jax.Array) -> dict[str, Any]:
  """`jax.jit(module.init)(key, *inputs)`, compiled at optimisation level 1 on the CPU
  (`_INIT_OPTIONS_CPU`)."""
  options = _INIT_OPTIONS_CPU if jax.default_backend() == "cpu" else {}
  return jax.jit(module.init).lower(key, *inputs).compile(compiler_options=options)(key, *inputs)


def init_variables(module: Any, seed: int, *inputs: jax.Array) -> dict[str, Any]:
  """`module.init` (its own initialisers' distributions) under `jit_init`, from an RBG key.

  Why not `jax.random.PRNGKey`: XLA compiles a threefry hash kernel for every parameter leaf,
  an RBG key a `RngBitGenerator`; MonoDepth2's init at 64x96 compiles in 17 s with the first and
  7 s with the second (2 vCPU, default level). RBG's bits may differ between backends and JAX
  versions, so this is for weights that only need to be random and seeded within one
  installation, not for a seed that must reproduce a trained model (`pitta-jax train-source`
  keeps threefry).
  """
  return jit_init(module, jax.random.key(seed, impl="rbg"), *inputs)
