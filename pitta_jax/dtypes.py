"""The types of the pure functions' arguments: their float type (float32, or float64 when the
input already is) and the static ints that fix their shapes.

Losses, edges and the median filter compute in the input's precision (at least float32), so that
a float64 run (`jax.enable_x64`) is float64 end to end: gradient checks against a float64
reference then measure the method, not float32 rounding.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def as_float(x) -> jax.Array:
  """`x` as float32, or as float64 if it is float64 (integers and bools become float32)."""
  x = jnp.asarray(x)
  return x.astype(jnp.float64 if x.dtype == jnp.float64 else jnp.float32)


def tree_dtype(tree) -> jnp.dtype:
  """The float type of a parameter tree (its first leaf's): the method state that mixes with
  the parameters takes it, so that a float64 run stays float64."""
  return jax.tree_util.tree_leaves(tree)[0].dtype


def static_int(value, name: str, what: str, kind: str = "an int") -> int:
  """`value` as a Python int for a shape (a window, a table size): ValueError naming `name` (a
  parameter, `what` it is) when it is traced (say how to make it static) or not an int (the
  message asks for `kind`)."""
  if isinstance(value, jax.core.Tracer):
    raise ValueError(f"{what} {name} must be a Python int, not a traced value: pass it as a "
                     f"static argument of jax.jit (static_argnames=('{name}',)) or close over it")
  if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
    raise ValueError(f"{what} {name} must be {kind}, got {value!r}")
  return int(value)
