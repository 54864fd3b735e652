"""Element-wise optimisers stepped on a parameter tree raveled into one vector.

Why: an element-wise optimiser (Adam, SGD) gives the same numbers on the tree and on the
raveled vector (to a few units in the last place: XLA:CPU's vectorised loop and its scalar
remainder may round differently, and an element's path depends on its array's length), but
XLA:CPU compiles one kernel per leaf for each of its operations and for the non-finite guard's
selects: Adam + guard over MonoDepth2's 88 leaves compiled in 45 s of CPU time, over the
raveled vector in 3 s (measured before the guard grouped leaves by shape, `engine.all_finite`;
per leaf it costs less now). The price is memory traffic: each step concatenates the
gradient and the parameters and slices the result back, which for a whole network is a
visible share of the step (Ada-Depth's branch: 10-17% of its frame time, so it stays per
leaf). CoMoDa steps its depth and pose networks with this: its batch-4 step hides the traffic
(320x96, 2 vCPU, one interleaved pair: raveled 1831 ms/frame and a 51 s compile, per leaf 1854
ms/frame and 60 s).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import optax
from jax.flatten_util import ravel_pytree

Tree = Any


def flat(tx: optax.GradientTransformation) -> optax.GradientTransformation:
  """`tx` applied to the tree raveled into one vector: its state is the vector's; `update`
  takes and returns trees."""
  def init(params):
    return tx.init(ravel_pytree(params)[0])

  def update(updates, state, params=None):
    g, unravel = ravel_pytree(updates)
    u, state = tx.update(g, state, None if params is None else ravel_pytree(params)[0])
    return unravel(u), state

  return optax.GradientTransformation(init, update)


class FlatStep(NamedTuple):
  """`flat_step`'s result; vectors are (P,), P the number of parameter elements."""
  old: jax.Array                    # the parameters before the step
  new: jax.Array                    # after it
  update: jax.Array                 # new - old as the optimiser gave it
  opt_state: Tree                   # the new optimiser state (of the raveled vector)
  finite: jax.Array                 # () bool: gradient, new parameters and new state all finite
  unravel: Callable[[jax.Array], Tree]  # (P,) -> a tree of the parameters' structure


def flat_step(tx: optax.GradientTransformation, params: Tree, grads: Tree,
              opt_state: Tree) -> FlatStep:
  """One step of `tx` on the raveled `params` (`opt_state` is `flat(tx)`'s state), nothing
  committed: the caller chooses between `old` and `new` (a guard, an inactive frame)."""
  from pitta_jax.adapt.engine import all_finite  # the engine imports the methods
  p, unravel = ravel_pytree(params)
  g, _ = ravel_pytree(grads)
  u, new_opt = tx.update(g, opt_state, p)
  new = p + u
  return FlatStep(p, new, u, new_opt, all_finite((g, new, new_opt)), unravel)
