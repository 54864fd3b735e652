"""Many streams in one compiled call (`pitta_jax.adapt.streams`): vmap, lambda sweep, sharding.

References: K separate runs of the single-stream engine (`make_step` + `make_chunk_runner`) on
each stream's frames; the plain engine with `PittaConfig(lam=0.2)` for the lambda sweep; the
unsharded vmapped run for the sharded one (in a subprocess with 4 virtual CPU devices).
A random-weight MonoDepth2-shaped network (`tiny_net`: MonoDepth2's layers, a few of each) at
64x96, 3 frames, keeps the compiles short: the streams' plumbing does not depend on the size of
the network.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pitta_jax.adapt import (AdaptConfig, StepInput, init_state, make_chunk_runner,
                             make_optimizer, make_step)
from pitta_jax.adapt import streams
from pitta_jax.methods import build
from pitta_jax.methods.depth_refining import DepthRefiningConfig
from pitta_jax.methods.pitta import PittaConfig

import adapt_frames
from tiny_net import TINY, tiny_variables

H, W, S, T = adapt_frames.H, adapt_frames.W, adapt_frames.S, 3
# the paper's lr 1e-4: Adam moves every coordinate by ~lr per step, so float noise in a gradient
# coordinate moves parameters by a fraction of lr, which a larger lr would blow up
CFG = AdaptConfig(chunk_size=T)
PITTA = PittaConfig(ld=DepthRefiningConfig(max_instances=4, window=3))
frames = adapt_frames.make_frames


def model_and_method():
  return TINY, build("pitta", PITTA)


SEED = 1  # of the random network weights (`tiny_net.tiny_variables`)


def fresh(state):
  """A copy of a state for a chunk runner, which donates (deletes) its carry argument."""
  return jax.tree_util.tree_map(jnp.copy, state)


@pytest.fixture(scope="module")
def variables():
  return tiny_variables(SEED)


@pytest.fixture(scope="module")
def single_runner():
  model, method = model_and_method()
  return make_chunk_runner(make_step(model, method, CFG, make_optimizer(CFG)))


def _max_diff(a, b) -> float:
  return max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))))
             for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


def _close_but_for_ties(x, y, atol: float, outlier_atol: float, label: str) -> None:
  """|x - y| <= atol on every element but a few (at most 1% of the leaf, at least one), and
  <= outlier_atol on those few.

  Why a few: eq. 8's gradient is discontinuous. sign(D~ - D~') flips at a pixel whose depth is
  within rounding of its window's median, and two programs that round differently (a batch-K
  and a batch-1 convolution, or one code generator and another) flip different pixels, so a
  handful of BN coordinates get a different gradient contribution. Adam then moves such a
  coordinate by about lr whatever its gradient's size. A wrong stream, key or optimiser state
  changes most elements of a leaf, which this still fails on.
  """
  x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
  d = np.abs(x - y)
  out = int(np.sum(d > atol))
  assert out <= max(1, d.size // 100), f"{label}: {out} of {d.size} elements differ by > {atol:.2e}"
  assert float(np.max(d, initial=0.0)) <= outlier_atol, (
      f"{label}: max diff {float(np.max(d)):.2e} > {outlier_atol:.2e}")


# an element whose gradient's sign differs between two runs moves by up to ~lr per Adam step the
# other way in each: 2 T lr apart after T frames (`_close_but_for_ties`)
PARAM_OUTLIER = 2 * T * CFG.lr
MOMENT_OUTLIER = 0.1  # of the leaf's largest |value|


def _assert_state_close(got, want, label: str) -> None:
  """Counters, keys and source parameters exactly; parameters and Adam moments to float noise.

  Tolerances: a batch-K and a batch-1 convolution round differently (depths agree to ~1e-6
  relative), and eq. 8's gradient is discontinuous: sign(D~ - D~') flips at pixels whose depth is
  within rounding of its window's median, so a few pixels' contributions to a BN gamma/beta
  gradient differ. Adam then moves a coordinate by about lr whatever its gradient's size. So
  the Adam moments agree to 1e-2 of each leaf's largest value, and parameters to 0.2 * lr:
  with PyTorch's derivative of |x| (0 at x = 0, so a pixel exactly at its pseudo label adds
  nothing) a coordinate whose gradient is small (a few % of its leaf's largest) moves by
  lr * m / sqrt(v), and batch-K vs batch-1 rounding of its few contributions changes that ratio
  by up to ~8% of lr (measured: 8.5e-6 at lr 1e-4, encoder/layer4_0/bn2/bias, stream 1). A few
  elements per leaf may exceed that (`_close_but_for_ties`): with another code generator
  (`--xla_backend_extra_options=xla_cpu_disable_loop_unrolling`) one Adam first moment in 256
  differed by 12% of itself.
  """
  for name in ("source", "step", "rng", "n_skipped", "method_state"):
    jax.tree_util.tree_map(np.testing.assert_array_equal, getattr(got, name), getattr(want, name))
  print(f"{label}: trainable max abs diff {_max_diff(got.trainable, want.trainable):.2e} "
        f"(lr {CFG.lr:g}), adam moments {_max_diff(got.opt_state, want.opt_state):.2e}")
  jax.tree_util.tree_map_with_path(
      lambda p, x, y: _close_but_for_ties(x, y, 0.2 * CFG.lr, PARAM_OUTLIER,
                                          f"{label} trainable{jax.tree_util.keystr(p)}"),
      got.trainable, want.trainable)

  def moments(p, x, y):
    scale = float(np.max(np.abs(np.asarray(y)))) + 1e-30
    _close_but_for_ties(x, y, 1e-2 * scale, MOMENT_OUTLIER * scale,
                        f"{label} opt_state{jax.tree_util.keystr(p)}")
  jax.tree_util.tree_map_with_path(moments, got.opt_state, want.opt_state)


K = 4  # streams; divisible by the 4 devices of the sharding test


def stream_frames() -> list[StepInput]:
  """Each stream's own frames; stream 1 ends with a padding frame (valid=False)."""
  per_stream = [frames(T, seed=10 + k) for k in range(K)]
  per_stream[1] = per_stream[1]._replace(valid=np.array([True] * (T - 1) + [False]))
  return per_stream


def run_multi(variables) -> tuple:
  """K streams, own frames and seeds, one vmapped compiled call: (states, outputs)."""
  model, method = model_and_method()
  tx = make_optimizer(CFG)
  runner = make_chunk_runner(streams.make_multi_stream_step(model, method, CFG, tx))
  states, consts = streams.init_streams(variables, method, CFG, K, tx)
  return runner(states, streams.stack_stream_inputs(stream_frames()), consts)


@pytest.fixture(scope="module")
def multi_run(variables):
  return run_multi(variables)


def test_multi_stream_step_equals_separate_runs(variables, single_runner, multi_run):
  """K = 4 streams with their own frames (one with a padding frame) and seeds, vmapped, vs 4
  separate runs of the single-stream engine."""
  _, method = model_and_method()
  tx = make_optimizer(CFG)
  states, outs = multi_run
  assert states.trainable["encoder"]["bn1"]["scale"].shape[0] == K
  assert outs.depth.shape == (T, K, H, W)
  np.testing.assert_array_equal(np.asarray(states.step), [T, T - 1, T, T])

  bitwise = True
  for k, own in enumerate(stream_frames()):
    cfg_k = dataclasses.replace(CFG, seed=CFG.seed + k)
    ref_init, consts = init_state(variables, method, cfg_k, tx)
    ref_state, ref_out = single_runner(fresh(ref_init), own, consts)
    got = streams.stream_state(states, k)
    d = float(np.max(np.abs(np.asarray(outs.depth[:, k]) - ref_out.depth) / ref_out.depth))
    print(f"stream {k}: depth max rel diff {d:.2e}, loss {np.asarray(outs.loss[:, k])} "
          f"vs {np.asarray(ref_out.loss)}")
    assert d <= 1e-5
    np.testing.assert_allclose(outs.loss[:, k], ref_out.loss, rtol=1e-5)
    _assert_state_close(got, ref_state, f"stream {k}")
    bitwise &= all(np.array_equal(a, b) for a, b in zip(
        jax.tree_util.tree_leaves((got.trainable, outs.depth[:, k])),
        jax.tree_util.tree_leaves((ref_state.trainable, ref_out.depth))))
  print(f"vmapped vs separate runs bitwise identical: {bitwise}")
  # the streams did adapt, differently
  a, b = (streams.stream_state(states, k).trainable for k in (0, 2))
  assert _max_diff(a, b) > 1e-2 * CFG.lr


def test_lambda_sweep_equals_plain_engine(variables, single_runner):
  """Stream lam = 0.2 of a (0, 0.2, inf) sweep equals the plain engine with PittaConfig(lam=0.2)
  (= PITTA.lam); lam = 0 is L_d alone and lam = inf is L_e alone."""
  assert PITTA.lam == 0.2
  model, method = model_and_method()
  lams = (0.0, 0.2, math.inf)
  sweep = make_chunk_runner(streams.make_lambda_sweep_step(model, CFG, pitta=PITTA))
  states, sweep_consts = streams.init_lambda_sweep(variables, lams, CFG, pitta=PITTA)
  shared = frames(T, seed=4)
  states, outs = sweep(states, shared, sweep_consts)
  np.testing.assert_array_equal(np.asarray(states.method_state["lam"]), np.float32(lams))

  tx = make_optimizer(CFG)
  plain, consts = init_state(variables, method, CFG, tx)
  ref_state, ref_out = single_runner(fresh(plain), shared, consts)
  d = float(np.max(np.abs(np.asarray(outs.depth[:, 1]) - ref_out.depth) / ref_out.depth))
  print(f"lam=0.2 stream vs engine: depth max rel diff {d:.2e}, "
        f"loss diff {np.max(np.abs(np.asarray(outs.loss[:, 1]) - ref_out.loss)):.2e}")
  assert d <= 1e-5
  np.testing.assert_allclose(outs.loss[:, 1], ref_out.loss, rtol=1e-5)
  got = streams.stream_state(states, 1)
  _assert_state_close(got, ref_state, "lam=0.2 stream")
  np.testing.assert_array_equal(outs.loss[:, 0], outs.logs["loss_d"][:, 0])  # lam = 0: L = L_d
  np.testing.assert_array_equal(outs.loss[:, 2], outs.logs["loss_e"][:, 2])  # lam = inf: L = L_e
  assert np.all(np.isfinite(np.asarray(outs.grad_norm))) and np.all(outs.grad_norm[-1] > 0)
  assert not np.any(np.asarray(outs.skipped))


def test_init_streams_takes_one_seed_per_stream(variables):
  """Explicit `seeds` become the streams' PRNG keys in order (stream k: PRNGKey(seeds[k]));
  a list of another length than the number of streams is refused, not cut or padded."""
  _, method = model_and_method()
  states, _ = streams.init_streams(variables, method, CFG, 2, seeds=[5, 9])
  assert streams.num_streams(states) == 2
  for k, seed in enumerate((5, 9)):
    np.testing.assert_array_equal(streams.stream_state(states, k).rng, jax.random.PRNGKey(seed))
  with pytest.raises(ValueError, match="1 seeds for 2 streams"):
    streams.init_streams(variables, method, CFG, 2, seeds=[5])


def test_lambda_sweep_keeps_the_given_order(variables):
  """Stream k of `init_lambda_sweep` carries lams[k] as given (unsorted here: the caller reads
  stream k's results as lambda k's), and otherwise the same start: one seed for all."""
  lams = (0.5, 0.0, math.inf, 0.2)
  states, _ = streams.init_lambda_sweep(variables, lams, CFG, pitta=PITTA)
  assert streams.num_streams(states) == 4
  np.testing.assert_array_equal(np.asarray(states.method_state["lam"]), np.float32(lams))
  # a list of 0-d arrays is its numbers (it was refused: "lam must be a number")
  given = [jnp.asarray(0.5), np.asarray(0.2), jnp.float32(0.0)]
  arrays, _ = streams.init_lambda_sweep(variables, given, CFG, pitta=PITTA)
  np.testing.assert_array_equal(np.asarray(arrays.method_state["lam"]),
                                np.float32([0.5, 0.2, 0.0]))
  for k in range(4):
    np.testing.assert_array_equal(streams.stream_state(states, k).rng,
                                  jax.random.PRNGKey(CFG.seed))


def test_shardings_by_field():
  """Every carried field is split over the "streams" mesh axis; the constants are not carried."""
  P = jax.sharding.PartitionSpec
  mesh = streams.stream_mesh(jax.devices()[:1])
  shard = streams.state_shardings(mesh)
  assert shard.trainable.spec == P("streams") and shard.opt_state.spec == P("streams")
  assert not hasattr(shard, "frozen")
  assert streams.input_sharding(mesh).spec == P(None, "streams")
  assert streams.input_sharding(mesh, shared_frames=True).spec == P()
  with pytest.raises(ValueError, match="cannot be split evenly"):
    streams._check_divisible(6, type("FakeMesh", (), {"size": 4})())


SHARDED_SCRIPT = textwrap.dedent("""
    import sys
    import jax, numpy as np
    sys.path.insert(0, {tests!r})
    import test_streams as ts
    from pitta_jax.adapt import make_optimizer
    from pitta_jax.adapt import streams
    from tiny_net import tiny_variables

    assert len(jax.devices()) == 4, jax.devices()
    (model, method), cfg = ts.model_and_method(), ts.CFG
    tx = make_optimizer(cfg)
    chunk = streams.stack_stream_inputs(ts.stream_frames())
    mesh = streams.stream_mesh()
    runner = streams.make_sharded_chunk_runner(
        streams.make_multi_stream_step(model, method, cfg, tx), mesh)
    states, consts = streams.init_streams(tiny_variables(ts.SEED), method, cfg,
                                          ts.K, tx)
    states, out = runner(streams.shard_streams(states, mesh),
                         streams.shard_stream_inputs(chunk, mesh), streams.replicate(consts, mesh))
    leaf = states.trainable["encoder"]["bn1"]["scale"]
    assert leaf.sharding.spec == jax.sharding.PartitionSpec("streams"), leaf.sharding
    assert [s.data.shape[0] for s in leaf.addressable_shards] == [1, 1, 1, 1]
    assert [s.data.shape[1] for s in out.depth.addressable_shards] == [1, 1, 1, 1]
    leaves = jax.tree_util.tree_leaves((states, out))
    np.savez(sys.argv[1], *[np.asarray(x) for x in leaves])
""")


def _tolerance(path: str) -> float:
  """Scale-relative tolerance of a leaf of (states, outputs) in the sharded comparison."""
  if any(k in path for k in ("opt_state", "grad_norm", "update_norm")):
    return 5e-3  # gradient statistics: eq. 8's gradient is discontinuous (`_assert_state_close`);
    # measured 1.1e-3 with PyTorch's |x| derivative (a tie adds 0, a near-tie +-1)
  if "trainable" in path:
    return 1e-4  # Adam-normalised small gradients (`_assert_state_close`): measured 2.4e-5
  if path.startswith("[1]"):
    return 2e-6  # depths and loss terms
  return 0.0  # counters, keys, source/frozen parameters, lambda: exact


def test_sharded_streams_equal_unsharded_run(multi_run, tmp_path):
  """The K = 4 run of `multi_run` with the stream axis over a 4-device mesh ("streams"; 4
  virtual CPU devices in a subprocess, one stream each) vs the same vmapped run on one device.

  Not bitwise: each device runs batch-1 convolutions where the unsharded run has batch 4, which
  XLA's CPU convolutions round differently. Measured (scale-relative: max |a - b| / max |b| per
  leaf): parameters ~2.4e-5 (one small-gradient coordinate, see `_assert_state_close`), depths ~7e-7, gradient norms ~1e-6, Adam moments ~1.1e-3.
  """
  env = dict(os.environ)
  env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "")
                      + " --xla_force_host_platform_device_count=4").strip()
  env["JAX_PLATFORMS"] = "cpu"
  script = SHARDED_SCRIPT.format(tests=str(Path(__file__).parent))
  out_path = tmp_path / "sharded.npz"
  proc = subprocess.run([sys.executable, "-c", script, str(out_path)], env=env,
                        capture_output=True, text=True, timeout=600)
  assert proc.returncode == 0, proc.stderr[-4000:]
  with np.load(out_path) as data:
    got = [data[f"arr_{i}"] for i in range(len(data.files))]
  with_path = jax.tree_util.tree_leaves_with_path(multi_run)
  assert len(got) == len(with_path)
  worst: dict[float, float] = {}
  bitwise = True
  for a, (path, b) in zip(got, with_path):
    b = np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    bitwise &= bool(np.array_equal(a, b))
    key = jax.tree_util.keystr(path)
    scale = max(float(np.max(np.abs(b.astype(np.float64)), initial=0.0)), 1e-30)
    d = np.abs(a.astype(np.float64) - b.astype(np.float64)) / scale
    tol = _tolerance(key)
    worst[tol] = max(worst.get(tol, 0.0), float(np.max(d, initial=0.0)))
    if "trainable" in key:  # a few tie-flipped coordinates (`_close_but_for_ties`)
      _close_but_for_ties(a, b, tol * scale, PARAM_OUTLIER, key)
    elif "opt_state" in key and a.dtype.kind == "f":
      _close_but_for_ties(a, b, tol * scale, MOMENT_OUTLIER * scale, key)
    else:
      assert float(np.max(d, initial=0.0)) <= tol, (key, float(np.max(d)), tol)
  print(f"sharded vs unsharded: bitwise identical {bitwise}; max scale-relative diff per "
        f"tolerance class: {worst}")


def test_a_lambda_sweep_takes_the_lambdas_pittas_config_takes():
  """Stream k is PITTA with lam = lams[k]: a negative or NaN lambda (maximised L_e, or skipped
  every update) and a lambda table that is not 1-D (lam of shape (1, 2)) are refused before
  any work, as PittaConfig refuses them."""
  from pitta_jax.adapt.streams import init_lambda_sweep
  for lams, message in [([0.1, -1.0], "lam must be >= 0"), ([float("nan")], "lam must be >= 0"),
                        ([[0.1, 0.2]], "lams must be a non-empty 1-D sequence"),
                        ([], "lams must be a non-empty 1-D sequence")]:
    with pytest.raises(ValueError, match=message):
      init_lambda_sweep({}, lams, AdaptConfig())
