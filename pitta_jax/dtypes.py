"""The float type of the pure functions: float32, or float64 when the input already is.

Losses, edges and the median filter compute in the input's precision (at least float32), so that
a float64 run (`jax.enable_x64`) is float64 end to end: gradient checks against a float64
reference then measure the method, not float32 rounding.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def as_float(x) -> jax.Array:
  """`x` as float32, or as float64 if it is float64 (integers and bools become float32)."""
  x = jnp.asarray(x)
  return x.astype(jnp.float64 if x.dtype == jnp.float64 else jnp.float32)


def tree_dtype(tree) -> jnp.dtype:
  """The float type of a parameter tree (its first leaf's): the method state that mixes with
  the parameters takes it, so that a float64 run stays float64."""
  return jax.tree_util.tree_leaves(tree)[0].dtype
