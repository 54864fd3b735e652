"""Loop-invariant code motion of the scanned step (`pitta_jax.adapt.hoist`).

Checked on a small convolutional step (two `layers.Conv` with train-mode BatchNorm, gradient
w.r.t. the BN parameters only, as PITTA's; the conv kernels are the invariant constants):
- the hoisted scan gives exactly the outputs and carry of the plain scan;
- in the compiled program, the input-gradient kernels (`conv_vjp`'s flipped, transposed kernels)
  are computed outside the while loop, where the plain scan computes them in every iteration
  (if XLA starts hoisting them itself, the second assertion says so);
- size-inflating work (a broadcast of an invariant bias to the feature map's shape) stays in
  the loop, and work that touches the carry is never hoisted;
- the engine's chunk runner uses it: its compiled program has no kernel transpose in the loop.
"""

from __future__ import annotations

import re

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pitta_jax.adapt.hoist import hoist_invariants
from pitta_jax.models.layers import BatchNorm, Conv


class TinyNet(nn.Module):
  @nn.compact
  def __call__(self, x):
    x = nn.relu(BatchNorm(name="bn1")(Conv(8, (3, 3), padding=((1, 1), (1, 1)), name="c1")(x),
                                      True))
    return BatchNorm(name="bn2")(Conv(4, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)),
                                      name="c2")(x), True)


@pytest.fixture(scope="module")
def setup():
  net = TinyNet()
  rng = np.random.default_rng(0)
  frames = jnp.asarray(rng.standard_normal((3, 1, 12, 16, 3)).astype(np.float32))
  variables = net.init(jax.random.PRNGKey(0), frames[0])
  params = variables["params"]
  bn = {k: v for k, v in params.items() if k.startswith("bn")}  # adapted
  consts = ({k: v for k, v in params.items() if k.startswith("c")}, variables["batch_stats"])

  def step(consts, carry, frame):
    kernels, stats = consts

    def loss(bn):
      y = net.apply({"params": {**kernels, **bn}, "batch_stats": stats}, frame)
      return jnp.sum(jnp.sin(y))
    value, grads = jax.value_and_grad(loss)(carry)
    return jax.tree_util.tree_map(lambda p, g: p - 0.1 * g, carry, grads), value

  @jax.jit
  def plain(carry, frames, consts):
    return jax.lax.scan(lambda c, f: step(consts, c, f), carry, frames)

  @jax.jit
  def hoisted(carry, frames, consts):
    one = jax.ShapeDtypeStruct(frames.shape[1:], frames.dtype)
    body, _ = hoist_invariants(step, consts, carry, one)
    return jax.lax.scan(body, carry, frames)
  return plain, hoisted, bn, frames, consts


def transposes(compiled_text: str) -> tuple[list[str], list[str]]:
  """op_names of the kernel transposes: (inside the while loop, outside it)."""
  names = re.findall(r'op_name="([^"]*/transpose)"', compiled_text)
  return [n for n in names if "/while/" in n], [n for n in names if "/while/" not in n]


def test_same_results_as_the_plain_scan(setup):
  plain, hoisted, bn, frames, consts = setup
  (c0, v0), (c1, v1) = plain(bn, frames, consts), hoisted(bn, frames, consts)
  np.testing.assert_array_equal(np.asarray(v0), np.asarray(v1))
  for a, b in zip(jax.tree_util.tree_leaves(c0), jax.tree_util.tree_leaves(c1)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_kernel_transposes_leave_the_loop(setup):
  plain, hoisted, bn, frames, consts = setup
  inside, outside = transposes(hoisted.lower(bn, frames, consts).compile().as_text())
  assert outside and not inside, (inside, outside)
  inside_plain, _ = transposes(plain.lower(bn, frames, consts).compile().as_text())
  assert inside_plain, "XLA now hoists the kernel transposes itself: hoist.py may be dropped"


def test_inflating_and_carry_dependent_work_stays():
  def fn(consts, carry, x):
    bias, scale = consts
    big = jnp.broadcast_to(bias, x.shape)  # inflating: stays
    s2 = scale * 2.0                       # same size: hoisted
    return carry + jnp.sum((x + big) * s2 * carry), None

  consts = (jnp.ones((5,)), jnp.full((5,), 3.0))
  x = jax.ShapeDtypeStruct((4, 5), jnp.float32)
  body, hoisted = hoist_invariants(fn, consts, jnp.zeros(()), x)
  # scale * 2 and its (5,) -> (1, 5) reshaping broadcast; not the (5,) -> (4, 5) broadcast
  assert hoisted == ("mul", "convert_element_type", "broadcast_in_dim"), hoisted
  carry, _ = body(jnp.ones(()), jnp.ones((4, 5)))
  np.testing.assert_allclose(float(carry), 1.0 + 4 * 5 * 2.0 * 6.0)


def test_engine_chunk_runner_hoists():
  from pitta_jax.adapt import engine
  calls = []
  real = engine.hoist_invariants

  def spy(*args, **kwargs):
    out = real(*args, **kwargs)
    calls.append(out[1])
    return out
  engine.hoist_invariants = spy
  try:
    def step(state, frame, consts):
      return state + jnp.sum(frame * jnp.transpose(consts)), None
    runner = engine.make_chunk_runner(step)
    state, _ = runner(jnp.zeros(()), jnp.ones((2, 3, 3)), jnp.arange(9.0).reshape(3, 3))
  finally:
    engine.hoist_invariants = real
  assert calls == [("transpose",)]
  np.testing.assert_allclose(float(state), 2 * 36.0)


def test_engine_chunk_runner_passes_compiler_options():
  """`make_chunk_runner(step, compiler_options)` compiles with those XLA options: a valid one
  gives the same sums, an unknown one is refused by XLA (so it did reach the compile)."""
  from pitta_jax.adapt import engine

  def step(state, frame, consts):
    return state + jnp.sum(frame * consts), state

  frames, consts = jnp.arange(6.0).reshape(3, 2), jnp.array([1.0, 10.0])
  state, before = engine.make_chunk_runner(step, {"xla_backend_optimization_level": 0})(
      jnp.zeros(()), frames, consts)
  assert float(state) == 0 + 10 + 2 + 30 + 4 + 50 and list(np.asarray(before)) == [0, 10, 42]
  with pytest.raises(Exception, match="xla_no_such_option"):
    engine.make_chunk_runner(step, {"xla_no_such_option": 1})(jnp.zeros(()), frames, consts)
