"""Loop-invariant code motion for the engine's scanned step (XLA:CPU does not do it).

Why: the step runs inside `lax.scan`, i.e. an XLA while loop, and the frozen weights (`Consts`)
enter every iteration unchanged. Work that depends on them alone is the same in every frame:
above all the input-gradient kernels of `models.conv_vjp` (each frozen conv kernel flipped and
with its input/output features swapped, a physical transpose of every kernel of the network,
~45 ms of the PITTA step at 640x192 on 2 CPU cores). XLA:CPU's pipeline leaves such work inside
the loop body (checked on the compiled HLO in tests/test_hoist.py), so it is moved out here, at
the jaxpr level, before XLA sees the program.

How: the step is traced once to a jaxpr with the invariant arguments as separate inputs. An
equation is hoisted when all its variable inputs are invariant (the invariant arguments, the
jaxpr's constants, or outputs of hoisted equations), it has no effects, and its outputs are not
larger in bytes than its variable inputs. The last rule keeps broadcasts (a bias to a feature
map's shape, an iota) inside the loop, where XLA fuses them into their consumers, instead of
materialising them once and reading them every frame. The hoisted equations run once, before
the loop; the remaining ones form the loop body, which receives the hoisted values (the
"residuals") as extra loop constants. Values are unchanged: the same primitives run on the
same inputs, only their place in the program moves.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import jax
import numpy as np
from jax.extend import core as jcore

Tree = Any


def _nbytes(atoms) -> int:
  """Bytes of the array values of `atoms` (variables); -1 when one has no plain array type."""
  total = 0
  for v in atoms:
    aval = v.aval
    try:
      total += math.prod(aval.shape) * np.dtype(aval.dtype).itemsize
    except (AttributeError, TypeError):
      return -1
  return total


def _hoistable(eqn, invariant: set) -> bool:
  ins = [v for v in eqn.invars if not isinstance(v, jcore.Literal)]
  if not ins or eqn.effects or not all(v in invariant for v in ins):
    return False
  in_bytes, out_bytes = _nbytes(ins), _nbytes(eqn.outvars)
  return 0 <= out_bytes <= in_bytes


def hoist_invariants(fn: Callable[..., Tree], invariant: Tree, *example: Tree
                     ) -> tuple[Callable[..., Tree], tuple[str, ...]]:
  """`fn(invariant, *args)` as `body(*args)` with its invariant, non-inflating work done now.

  Call it inside a traced function (e.g. the jitted chunk, before `lax.scan`): the hoisted work
  is emitted at the call site, once, and `body` (the scan body) receives its results as
  constants.

  Args:
    fn: the function; `invariant` is its first argument.
    invariant: the loop-invariant argument (arrays or tracers), e.g. the engine's `Consts`.
    example: arrays or `jax.ShapeDtypeStruct`s shaped like the other arguments of one call.

  Returns:
    (body, hoisted): body(*args) == fn(invariant, *args); hoisted = the primitive names of the
    hoisted equations, in order.
  """
  inv_leaves = jax.tree_util.tree_leaves(invariant)
  closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(invariant, *example)
  out_tree = jax.tree_util.tree_structure(out_shape)
  jaxpr = closed.jaxpr
  n_inv = len(inv_leaves)
  invariant_vars = set(jaxpr.constvars) | set(jaxpr.invars[:n_inv])
  hoisted, rest = [], []
  for eqn in jaxpr.eqns:
    if _hoistable(eqn, invariant_vars):
      hoisted.append(eqn)
      invariant_vars.update(eqn.outvars)
    else:
      rest.append(eqn)
  used = {v for e in rest for v in e.invars if not isinstance(v, jcore.Literal)}
  used |= {v for v in jaxpr.outvars if not isinstance(v, jcore.Literal)}
  residuals = [v for e in hoisted for v in e.outvars if v in used]

  # the split jaxprs keep the function's name; their arguments and results are new
  info = jaxpr.debug_info._replace(arg_names=None, result_paths=None)
  pre = jcore.Jaxpr(jaxpr.constvars, jaxpr.invars[:n_inv], residuals, hoisted, debug_info=info)
  res_vals = jcore.jaxpr_as_fun(jcore.ClosedJaxpr(pre, closed.consts))(*inv_leaves)
  body_jaxpr = jcore.Jaxpr(jaxpr.constvars,
                           list(jaxpr.invars[:n_inv]) + residuals + list(jaxpr.invars[n_inv:]),
                           jaxpr.outvars, rest, jaxpr.effects, debug_info=info)
  body_closed = jcore.ClosedJaxpr(body_jaxpr, closed.consts)

  def body(*args: Tree) -> Tree:
    outs = jcore.jaxpr_as_fun(body_closed)(*inv_leaves, *res_vals,
                              *jax.tree_util.tree_leaves(args))
    return jax.tree_util.tree_unflatten(out_tree, outs)

  return body, tuple(e.primitive.name for e in hoisted)
