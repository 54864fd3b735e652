"""The scanned adaptation engine: predict-then-adapt, reproducibility, resume, guard, reset.

References: the public single-frame loss `pitta_jax.losses.pitta_loss` + `jax.grad` + an
optax Adam step written out in the test (independent of the engine's scan/split plumbing), and
bitwise comparisons between runs. A random-weight MonoDepth2-shaped network (`tiny_net`:
MonoDepth2's layers, a few of each) at 64x96 keeps the compiles short: what is tested here is the
engine, which sees a network only through `Network`; the networks are tested in their own files
and PITTA on MonoDepth2 against PyTorch in test_pitta_torch.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from pitta_jax import losses, trainable
from pitta_jax.adapt import (AdaptConfig, StepInput, adapt_stream, init_state, load_state,
                             make_chunk_runner, make_optimizer, make_step)
from pitta_jax.methods import build
from pitta_jax.methods.depth_refining import DepthRefiningConfig
from pitta_jax.methods.pitta import PittaConfig
from pitta_jax.models.depth_decoder import disp_to_depth

import adapt_frames
from tiny_net import TINY, TinyDepthNet, tiny_variables

H, W, S = adapt_frames.H, adapt_frames.W, adapt_frames.S
_frames = adapt_frames.make_frames


def _slice(x: StepInput, a: int, b: int) -> StepInput:
  return StepInput(*(v[a:b] for v in x))


@pytest.fixture(scope="module")
def variables():
  return tiny_variables(1)  # running statistics away from 0 and 1: "batch" and "running" differ


CFG = AdaptConfig(lr=1e-2, chunk_size=2)
PITTA = PittaConfig(ld=DepthRefiningConfig(max_instances=4, window=3))


def _model():
  return TINY


@pytest.fixture(scope="module")
def engine(variables):
  """One compiled chunk runner shared by the tests that use the default config."""
  model, method = _model(), build("pitta", PITTA)
  tx = make_optimizer(CFG)
  runner = make_chunk_runner(make_step(model, method, CFG, tx))
  return model, method, tx, runner


def _run(init, frames, runner, chunk, **kw):
  """init: (state, consts) as `init_state` returns them."""
  state, consts = init
  outs, n = [], frames.image.shape[0]
  chunks = (_slice(frames, a, a + chunk) for a in range(0, n, chunk))
  for state, out in adapt_stream(state, consts, chunks, runner, **kw):
    outs.append(out)
  stacked = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *outs)
  return state, stacked


def test_predict_then_adapt_matches_manual_adam_steps(variables, engine):
  """Frame t's depth comes from the parameters after frames 0..t-1 updated them, and the update
  is one Adam step on d(eq. 10)/d(encoder BN gamma, beta), computed here without the engine."""
  model, method, tx, runner = engine
  frames = _frames(4)
  state = init_state(variables, method, CFG, tx)
  _, out = _run(state, frames, runner, 2)

  parts = trainable.split(variables)
  net = TinyDepthNet()
  opt = optax.adam(CFG.lr)
  tr, opt_state = parts.trainable, opt.init(parts.trainable)
  dyn = np.array([11, 12, 13, 0], np.int32)
  @jax.jit  # the frozen weights are arguments: closed over, XLA would fold them as constants
  def loss_and_grad(tr_, frozen, stats, image, panoptic):
    def loss_fn(tr_):
      v = trainable.merge(tr_, frozen, stats)
      depth = disp_to_depth(net.apply(v, image[None], train=True)[0][0, ..., 0])
      return losses.pitta_loss(image, depth, panoptic, dyn, s=3, lam=0.2).total, depth
    return jax.value_and_grad(loss_fn, has_aux=True)(tr_)

  for t in range(4):
    (loss, depth), g = loss_and_grad(tr, parts.frozen, parts.batch_stats, frames.image[t],
                                     frames.panoptic[t])
    d = float(np.max(np.abs(np.asarray(depth) - out.depth[t]) / np.asarray(depth)))
    print(f"frame {t}: loss engine {out.loss[t]:.6f} manual {float(loss):.6f}, depth rel diff {d:.1e}")
    assert d < 1e-5
    np.testing.assert_allclose(out.loss[t], float(loss), rtol=1e-5)
    assert out.logs["n_instances"][t] == 3
    updates, opt_state = opt.update(g, opt_state, tr)
    tr = optax.apply_updates(tr, updates)
    # the logged norms: of this gradient and of this update (NumPy, float64)
    for logged, tree in ((out.grad_norm[t], g), (out.update_norm[t], updates)):
      norm = np.sqrt(sum(np.sum(np.square(np.asarray(x, np.float64)))
                         for x in jax.tree_util.tree_leaves(tree)))
      np.testing.assert_allclose(logged, norm, rtol=1e-3)


def test_make_optimizer_is_the_adam_and_sgd_of_the_literal_update_rules():
  """Three steps on gradients of a few 1e-7 (where Adam's eps matters), parameters at 100 and
  -50 (where a weight decay would show), against the update rules written out in NumPy: Adam
  (Kingma & Ba; torch.optim.Adam's defaults: betas 0.9, 0.999, eps 1e-8, bias-corrected, no
  weight decay), SGD with momentum 0.9 (torch.optim.SGD: buf = g, then buf = 0.9 buf + g;
  theta -= lr buf) and plain SGD. Each step's update is compared."""
  grads = [np.float32([1e-7, -2e-7]), np.float32([3e-7, 1e-7]), np.float32([-1e-7, 5e-7])]
  theta0 = np.float32([100.0, -50.0])

  def adam_loop(lr, b1=0.9, b2=0.999, eps=1e-8):
    m, v, out = np.zeros(2), np.zeros(2), []
    for t, g in enumerate(grads, 1):
      m = b1 * m + (1 - b1) * g
      v = b2 * v + (1 - b2) * g * g
      out.append(-lr * (m / (1 - b1 ** t)) / (np.sqrt(v / (1 - b2 ** t)) + eps))
    return out

  def sgd_loop(lr, momentum):
    buf, out = None, []
    for g in grads:
      buf = g if buf is None or not momentum else momentum * buf + g
      out.append(-lr * buf)
    return out

  for cfg, want in ((AdaptConfig(lr=0.01), adam_loop(0.01)),
                    (AdaptConfig(optimizer="sgd", lr=1e5, momentum=0.9), sgd_loop(1e5, 0.9)),
                    (AdaptConfig(optimizer="sgd", lr=1e5), sgd_loop(1e5, 0.0))):
    tx = make_optimizer(cfg)
    theta = jnp.asarray(theta0)
    opt_state = tx.init(theta)
    for g, w in zip(grads, want):
      updates, opt_state = tx.update(jnp.asarray(g), opt_state, theta)
      np.testing.assert_allclose(np.asarray(updates), w, rtol=1e-5, err_msg=str(cfg))
      theta = optax.apply_updates(theta, updates)


def test_the_guard_rejects_a_finite_gradient_that_overflows_the_step():
  """A finite gradient whose step is not: Adam at g = 1e20 (g^2 overflows float32, so the
  second moment is inf while the parameters stay finite: every later step would be 0) and SGD
  at lr 1e30, g = 1e9 (the parameter overflows). Both are skipped, counted, and leave the
  parameters and the optimiser state as they were."""
  from pitta_jax.adapt.engine import AdaptState, optax_update
  for cfg, g in ((AdaptConfig(lr=0.01), 1e20), (AdaptConfig(optimizer="sgd", lr=1e30), 1e9)):
    tx = make_optimizer(cfg)
    w = {"w": jnp.float32([1.0, 2.0])}
    state = AdaptState(trainable=w, opt_state=tx.init(w), method_state={}, source=w,
                       step=jnp.int32(0), rng=jax.random.PRNGKey(0), n_skipped=jnp.int32(0))
    new, skipped, unorm = optax_update(state, {"w": jnp.float32([g, 0.0])}, jnp.float32(1.0),
                                       tx, cfg)
    assert bool(skipped) and int(new.n_skipped) == 1 and float(unorm) == 0.0, cfg
    for a, b in zip(jax.tree_util.tree_leaves((new.trainable, new.opt_state)),
                    jax.tree_util.tree_leaves((state.trainable, state.opt_state))):
      np.testing.assert_array_equal(a, b)


def test_same_config_same_inputs_bitwise_identical(variables, engine):
  model, method, tx, runner = engine
  frames = _frames(4, seed=3)
  results = []
  for _ in range(2):
    state, out = _run(init_state(variables, method, CFG, tx), frames, runner, 2)
    results.append((state, out))
  (s1, o1), (s2, o2) = results
  np.testing.assert_array_equal(o1.depth, o2.depth)
  np.testing.assert_array_equal(o1.loss, o2.loss)
  for a, b in zip(jax.tree_util.tree_leaves(s1.trainable), jax.tree_util.tree_leaves(s2.trainable)):
    np.testing.assert_array_equal(a, b)
  # and the run did adapt: parameters moved
  moved = [np.max(np.abs(np.asarray(a) - np.asarray(b))) for a, b in zip(
      jax.tree_util.tree_leaves(s1.trainable),
      jax.tree_util.tree_leaves(trainable.split(variables).trainable))]
  assert max(moved) > 0


def test_checkpoint_resume_is_bitwise_identical(variables, engine, tmp_path):
  model, method, tx, runner = engine
  frames = _frames(6, seed=5)
  full_state, full = _run(init_state(variables, method, CFG, tx), frames, runner, 2)
  # interrupted: 4 frames, checkpoint, new process-like restart from a fresh init, 2 more frames
  first_state, first = _run(init_state(variables, method, CFG, tx), _slice(frames, 0, 4), runner,
                            2, checkpoint_dir=tmp_path, checkpoint_every=4)
  assert (tmp_path / "state_000004").is_dir()
  fresh, consts = init_state(variables, method, CFG, tx)
  restored = load_state(tmp_path / "state_000004", like=fresh)
  assert int(restored.step) == 4
  last_state, last = _run((restored, consts), _slice(frames, 4, 6), runner, 2)
  np.testing.assert_array_equal(np.concatenate([first.depth, last.depth]), full.depth)
  for a, b in zip(jax.tree_util.tree_leaves(last_state), jax.tree_util.tree_leaves(full_state)):
    np.testing.assert_array_equal(a, b)


def test_padding_frames_leave_the_state_untouched(variables, engine):
  """A padding frame (valid=False) is a no-op whatever it holds: NaNs or another image."""
  model, method, tx, runner = engine
  frames = _frames(3, seed=2)
  states = []
  for filler in (frames.image[-1:], np.full_like(frames.image[-1:], np.nan)):
    padded = StepInput(*(np.concatenate([v, v[-1:]]) for v in frames))
    padded = padded._replace(image=np.concatenate([frames.image, filler]),
                             valid=np.array([True, True, True, False]))
    state, out = _run(init_state(variables, method, CFG, tx), padded, runner, 2)
    assert out.depth.shape[0] == 3 and int(state.step) == 3 and int(state.n_skipped) == 0
    states.append(state)
  for a, b in zip(jax.tree_util.tree_leaves(states[0]), jax.tree_util.tree_leaves(states[1])):
    np.testing.assert_array_equal(a, b)


def test_nonfinite_guard_skips_and_counts(variables, engine):
  model, method, tx, runner = engine
  frames = _frames(4, seed=4)
  bad = frames.image.copy()
  bad[1, 5, 5, 0] = np.nan
  state, out = _run(init_state(variables, method, CFG, tx), frames._replace(image=bad), runner, 2)
  assert list(out.skipped) == [False, True, False, False] and int(state.n_skipped) == 1
  assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(state))
  # the skipped frame changed nothing: frames 0, 2, 3 alone give the same parameters
  clean = StepInput(*(v[[0, 2, 3, 3]] for v in frames))._replace(
      valid=np.array([True, True, True, False]))
  ref, _ = _run(init_state(variables, method, CFG, tx), clean, runner, 2)
  for a, b in zip(jax.tree_util.tree_leaves(state.trainable), jax.tree_util.tree_leaves(ref.trainable)):
    np.testing.assert_array_equal(a, b)


def test_a_frames_skipped_log_covers_every_inner_step(variables):
  """With two optimiser steps per frame, SGD at lr 1e37 takes frame 0's first step and the
  network overflows at its second, which the guard skips (and every step of frame 1): frame
  0's `skipped` said False (the first step's) while `n_skipped` counted its second step; the
  log now says whether any update of the frame was skipped, as the count does."""
  model, method = _model(), build("pitta", PITTA)
  cfg = AdaptConfig(optimizer="sgd", lr=1e37, chunk_size=2, steps_per_frame=2)
  tx = make_optimizer(cfg)
  runner = make_chunk_runner(make_step(model, method, cfg, tx))
  state, out = _run(init_state(variables, method, cfg, tx), _frames(2), runner, 2)
  assert np.isfinite(out.loss[0]) and not np.isfinite(out.loss[1])  # frame 0's first step ran
  assert list(out.skipped) == [True, True] and int(state.n_skipped) == 3


def test_all_finite_flags_any_nan_or_inf_leaf():
  """engine.all_finite against NumPy's all(isfinite) over float, int and bool leaves (hand-made
  trees), also under jit."""
  from pitta_jax.adapt.engine import all_finite
  base = {"a": np.ones((3, 2), np.float32), "b": {"c": np.arange(4, dtype=np.int32),
                                                  "d": np.array(True)}, "e": np.zeros(())}
  cases = [base, {**base, "a": np.array([[1.0, np.nan]] * 3, np.float32)},
           {**base, "e": np.array(-np.inf)}, {**base, "a": np.full((3, 2), 3e38, np.float32)},
           {}]
  # leaves of one shape (flags summed before one reduction), of one shape and another dtype
  twin = np.full((3, 2), 3e38, np.float32)
  cases += [{**base, "f": twin}, {**base, "f": twin, "g": twin},
            {**base, "f": np.array([[0.0, np.inf]] * 3, np.float32)},
            {**base, "f": twin, "g": np.array([[np.nan, 0.0]] * 3, np.float16)}]
  for tree in cases:
    want = all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(tree))
    assert bool(all_finite(tree)) == want and bool(jax.jit(all_finite)(tree)) == want


def test_tree_norm_is_the_global_l2_norm():
  """engine.tree_norm against a NumPy float64 loop over the leaves: leaves of one shape (one
  reduction for the group), other shapes and dtypes, integer leaves left out, an empty tree."""
  from pitta_jax.adapt.engine import tree_norm
  rng = np.random.default_rng(0)
  tree = {"a": rng.normal(size=(3, 2)).astype(np.float32),
          "b": [rng.normal(size=(3, 2)).astype(np.float32), rng.normal(size=(5,))],
          "c": np.arange(4, dtype=np.int32), "d": rng.normal(size=(3, 2)).astype(np.float16)}
  want = np.sqrt(sum(float(np.sum(np.asarray(x, np.float64) ** 2))
                     for x in jax.tree_util.tree_leaves(tree) if x.dtype.kind == "f"))
  for fn in (tree_norm, jax.jit(tree_norm)):
    np.testing.assert_allclose(float(fn(tree)), want, rtol=1e-3)  # float16 leaf: 1e-3
  assert float(tree_norm({})) == 0.0 and float(tree_norm({"i": np.arange(3)})) == 0.0


def test_flat_optimiser_gives_the_tree_optimisers_numbers():
  """flat_optim.flat(adam) on a tree against optax.adam on the same tree (the independent,
  per-leaf optimiser): the same updates and moments over three steps, to a few units in the
  last place (XLA:CPU's vectorised loop and its scalar remainder may round differently, and an
  element's path depends on its array's length); flat_step's new parameters are params +
  update, and its finiteness flag sees a NaN gradient."""
  import optax
  from pitta_jax.flat_optim import flat, flat_step
  rng = np.random.default_rng(1)
  params = {"w": jnp.asarray(rng.normal(size=(3, 4)), jnp.float32),
            "b": [jnp.asarray(rng.normal(size=(4,)), jnp.float32)]}
  tree_tx, flat_tx = optax.adam(1e-2), flat(optax.adam(1e-2))
  s_tree, s_flat = tree_tx.init(params), flat_tx.init(params)
  for k in range(3):
    grads = jax.tree_util.tree_map(lambda x: x * (k + 1) - 0.5, params)
    u_tree, s_tree = jax.jit(tree_tx.update)(grads, s_tree, params)
    u_flat, s_flat = jax.jit(flat_tx.update)(grads, s_flat, params)
    for a, b in zip(jax.tree_util.tree_leaves(u_tree), jax.tree_util.tree_leaves(u_flat)):
      np.testing.assert_allclose(a, b, rtol=1e-6, atol=0)
  for moment in ("mu", "nu"):
    tree = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(getattr(s_tree[0],
                                                                                  moment))])
    np.testing.assert_allclose(tree, getattr(s_flat[0], moment), rtol=1e-6, atol=0)
  step = flat_step(optax.adam(1e-2), params, grads, s_flat)
  np.testing.assert_array_equal(step.new, step.old + step.update)
  assert bool(step.finite)
  bad = {**grads, "w": grads["w"].at[0, 0].set(jnp.nan)}
  assert not bool(flat_step(optax.adam(1e-2), params, bad, s_flat).finite)
  back = step.unravel(step.new)
  assert jax.tree_util.tree_structure(back) == jax.tree_util.tree_structure(params)


def test_reset_policy_restores_source_parameters(variables):
  cfg = dataclasses.replace(CFG, reset_every=2)
  model, method = _model(), build("pitta", PITTA)
  tx = make_optimizer(cfg)
  runner = make_chunk_runner(make_step(model, method, cfg, tx))
  frames = _frames(4, seed=6)
  _, out = _run(init_state(variables, method, cfg, tx), frames, runner, 2)
  # frames 2, 3 see the source model again, exactly as frames 0, 1 of a run starting at frame 2
  _, ref = _run(init_state(variables, method, cfg, tx), _slice(frames, 2, 4), runner, 2)
  np.testing.assert_array_equal(out.depth[2:], ref.depth)


def test_no_adaptation_is_the_released_model(variables):
  cfg = dataclasses.replace(CFG, method="none", bn_stats="running")
  model, method = _model(), build("none")
  tx = make_optimizer(cfg)
  runner = make_chunk_runner(make_step(model, method, cfg, tx))
  frames = _frames(2, seed=7)
  state0 = init_state(variables, method, cfg, tx)
  state, out = _run(state0, frames, runner, 2)
  ref = disp_to_depth(jax.jit(functools.partial(TinyDepthNet().apply, train=False))(
      variables, frames.image)[0][..., 0])  # the plain module in eval mode
  np.testing.assert_allclose(out.depth, np.asarray(ref), rtol=1e-6)
  for a, b in zip(jax.tree_util.tree_leaves(state.trainable),
                  jax.tree_util.tree_leaves(state0[0].trainable)):
    np.testing.assert_array_equal(a, b)


def test_loss_decreases_under_jit_scan(variables, engine):
  """Adapting repeatedly on one frame with PITTA's loss lowers it (the optimisation works)."""
  model, method, tx, runner = engine
  one = _frames(1, seed=8)
  frames = StepInput(*(np.repeat(v, 10, axis=0) for v in one))
  _, out = _run(init_state(variables, method, CFG, tx), frames, runner, 2)
  print("loss per step:", np.round(out.loss, 3))
  assert np.all(np.diff(out.loss) < 0)  # strictly decreasing over the 10 steps
  assert out.loss[-1] < 0.98 * out.loss[0]


def test_running_a_fresh_state_does_not_consume_the_callers_variables(variables, engine):
  """The chunk runner donates its carry; init_state must hold copies of the variables."""
  model, method, tx, runner = engine
  v = jax.tree_util.tree_map(jnp.asarray, variables)
  state, consts = init_state(v, method, CFG, tx)
  runner(state, _frames(2, seed=9), consts)  # direct call: `state` is donated here
  assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(v))


def test_each_inner_step_draws_its_own_randomness():
  """With steps_per_frame k, every inner step's loss gets its own key (CoTTA draws new views at
  each of upstream's `steps`): a toy loss <w, N(key)> under SGD(1) moves w by -(g_1 + g_2), two
  different draws, where a shared key would move it by -2 g_1. The first step keeps the frame's
  key, so one step per frame is unchanged."""
  from pitta_jax.adapt.engine import AdaptState, Consts, adapt_step
  from pitta_jax.methods.base import Aux, Method

  def loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg):
    del state, consts, frame, model, cfg, mcfg
    draw = jax.random.normal(rng, (3,))
    return jnp.sum(trainable["w"] * draw), Aux(jnp.zeros((2, 2)), {"draw": draw})

  method = Method("toy", None, init=lambda *a: {}, loss=loss)
  tx = optax.sgd(1.0)
  w0 = {"w": jnp.zeros((3,))}
  state = AdaptState(trainable=w0, opt_state=tx.init(w0), method_state={}, source=w0,
                     step=jnp.zeros((), jnp.int32), rng=jax.random.PRNGKey(0),
                     n_skipped=jnp.zeros((), jnp.int32))
  frame = StepInput(*(np.asarray(v[0]) for v in adapt_frames.make_frames(1)))
  moved = {}
  for k in (1, 2):
    new, out = adapt_step(state, frame, Consts({}, {}), model=None, method=method,
                          cfg=AdaptConfig(steps_per_frame=k), tx=tx)
    moved[k] = np.asarray(new.trainable["w"])
    first = np.asarray(out.logs["draw"])     # the reported (first) step's draw
  frame_key = jax.random.fold_in(state.rng, state.step)
  np.testing.assert_array_equal(first, np.asarray(jax.random.normal(frame_key, (3,))))
  np.testing.assert_array_equal(moved[1], -first)
  second = -moved[2] - first                 # the second inner step's draw
  assert np.all(np.abs(second - first) > 1e-3)
  # CoTTA's setting (upstream's forward returns its last `steps` pass): the outputs are the last
  # inner step's, its draw and its loss <w_1, draw_2> with w_1 = -draw_1 after the first step
  last = dataclasses.replace(method, report_last_step=True)
  new, out = adapt_step(state, frame, Consts({}, {}), model=None, method=last,
                        cfg=AdaptConfig(steps_per_frame=2), tx=tx)
  np.testing.assert_array_equal(np.asarray(new.trainable["w"]), moved[2])
  np.testing.assert_allclose(np.asarray(out.logs["draw"]), second, rtol=1e-6)  # w: -(d1 + d2)
  np.testing.assert_allclose(float(out.loss), float(np.dot(-first, second)), rtol=1e-6)
  _, out = adapt_step(state, frame, Consts({}, {}), model=None, method=last,
                      cfg=AdaptConfig(steps_per_frame=1), tx=tx)
  np.testing.assert_array_equal(np.asarray(out.logs["draw"]), first)


def test_runners_share_a_compile_by_what_a_method_computes(monkeypatch):
  """`run.Runners` reuses a compiled runner for a method rebuilt from the same config (the
  tables rebuild each row's method per test case), and not for a method of the same name and
  config whose loss differs (a variant in a closure, a redefined loss): it ran the first one's
  compiled step before, with the other's losses."""
  from types import SimpleNamespace

  from pitta_jax import run
  from pitta_jax.adapt import engine
  from pitta_jax.methods.base import Aux, Method

  built = []
  monkeypatch.setattr(engine, "make_chunk_runner",
                      lambda step, options=None: built.append(step) or (lambda *a: None))
  weights = SimpleNamespace(spec=SimpleNamespace(name="net"), config={}, network=lambda: None)

  def scaled(scale: float) -> Method:
    def loss(trainable, **_):
      return scale * jnp.float32(0), Aux(jnp.zeros((1,)), {})
    return Method("mine", PittaConfig(), init=lambda *a: {}, loss=loss)

  runners, cfg = run.Runners(), AdaptConfig()
  first = runners.get(weights, build("pitta"), cfg)[2]
  assert runners.get(weights, build("pitta"), cfg)[2] is first and len(built) == 1
  assert runners.get(weights, build("pitta", PittaConfig(lam=0.3)), cfg)[2] is not first
  a, b = runners.get(weights, scaled(1.0), cfg)[2], runners.get(weights, scaled(1000.0), cfg)[2]
  assert a is not b and runners.get(weights, scaled(1.0), cfg)[2] is a and len(built) == 4


def test_a_method_is_checked_when_it_is_built():
  """A Method without a loss, or whose requires/setting names no AdaptConfig field, is refused
  at construction (it failed when first traced, or with an AttributeError in `check`)."""
  from pitta_jax.methods.base import Method
  with pytest.raises(ValueError, match="method m: loss must be a function, got None"):
    Method("m", None, init=lambda *a: {}, loss=None)
  with pytest.raises(ValueError, match="method m: requires/setting name 'bn_stat', which is no "
                                       "AdaptConfig field"):
    Method("m", None, init=lambda *a: {}, loss=lambda *a: 0,
           requires=(("bn_stat", "running", "runs BN in eval mode"),))
  with pytest.raises(ValueError, match="name 'selecter'"):
    Method("m", None, init=lambda *a: {}, loss=lambda *a: 0, setting=(("selecter", "all"),))


def test_a_frame_with_too_many_segments_keeps_the_dynamic_classes_first():
  """Beyond max_segments a frame keeps the method's dynamic classes O first, then the other
  things, then stuff (frame order within each): with "things first" alone, 70 traffic lights
  (a COCO thing) listed before 10 cars left no car in the 64 kept, so N was 0."""
  from pitta_jax.adapt.inputs import step_input
  from pitta_jax.data.frame import Frame, Segment
  from pitta_jax.methods.actmad import ActmadConfig
  from pitta_jax.methods.depth_refining import dynamic_classes
  lights = [Segment(1 + k, 10, True) for k in range(70)]              # COCO 10: traffic light
  road = [Segment(100, 149, False)]                                   # COCO 149: road (stuff)
  cars = [Segment(200 + k, 3, True) for k in range(10)]               # COCO 3: car
  ids = np.zeros((4, 96), np.int32)
  ids.reshape(-1)[:81] = [s.id for s in lights + road + cars]
  frame = Frame(np.zeros((4, 96, 3), np.float32), panoptic=ids,
                segments=tuple(lights + road + cars))
  got = step_input(frame, 4, 96, 64)
  kept = [int(i) for i, v in zip(got.seg_ids, got.seg_valid) if v]
  assert kept == [s.id for s in cars] + [s.id for s in lights[:54]]   # road dropped last
  assert list(got.seg_classes[:11]) == [3] * 10 + [10]
  # another dynamic set (the method's ld.dynamic_classes) is kept first instead
  got = step_input(frame, 4, 96, 3, keep_first=(149,))
  assert got.seg_ids.tolist() == [100, 1, 2]
  # no dynamic class among them: the things before the stuff listed first
  got = step_input(Frame(np.zeros((4, 96, 3), np.float32), panoptic=ids,
                         segments=(road[0], lights[0], lights[1])), 4, 96, 2)
  assert got.seg_ids.tolist() == [1, 2]
  # what a run passes: the method's O, or the paper's default for a method without L_d
  assert dynamic_classes(PittaConfig(ld=DepthRefiningConfig(dynamic_classes=("bench",)))) == (15,)
  assert dynamic_classes(ActmadConfig()) == (1, 2, 3, 4, 6, 7, 8)
  assert dynamic_classes(build("none").config) == (1, 2, 3, 4, 6, 7, 8)


def test_chunks_pad_the_last_chunk_and_step_input_carries_each_frames_fields():
  """5 frames in chunks of 2: three chunks, the last one frame and a padding copy of it marked
  invalid; each frame's intrinsics (scaled to the network's size), its 'no intrinsics' and its
  recording start reach the step; the image is resized as the network asks (OpenCV's area or
  cubic interpolation, the references here)."""
  import cv2
  from pitta_jax.adapt.inputs import chunks, step_input
  from pitta_jax.data.frame import Frame
  rng = np.random.default_rng(0)
  K = np.array([[10.0, 0, 5.5], [0, 10.0, 3.5], [0, 0, 1]])
  frames = [Frame(rng.random((8, 12, 3)).astype(np.float32), name=str(i),
                  intrinsics=K if i != 3 else None, starts_recording=i == 2) for i in range(5)]
  got = list(chunks(frames, 4, 6, 2, 3))
  assert [[f.name for f in originals] for _, originals in got] == [["0", "1"], ["2", "3"], ["4"]]
  for chunk, originals in got:
    assert chunk.image.shape == (2, 4, 6, 3)
  assert [c.valid.tolist() for c, _ in got] == [[True, True], [True, True], [True, False]]
  np.testing.assert_array_equal(got[2][0].image[1], got[2][0].image[0])   # the padding copy
  assert [c.has_intrinsics.tolist() for c, _ in got] == [[True, True], [True, False],
                                                         [True, True]]
  assert [c.starts_recording.tolist() for c, _ in got] == [[False, False], [True, False],
                                                           [False, False]]
  # K of the 2x-smaller image, pixel centres kept: f / 2, (c + 0.5) / 2 - 0.5
  np.testing.assert_allclose(got[0][0].intrinsics[0], [[5, 0, 2.5], [0, 5, 1.5], [0, 0, 1]])
  np.testing.assert_array_equal(got[1][0].intrinsics[1], np.zeros((3, 3)))
  image = frames[0].image
  area = step_input(frames[0], 4, 6, 3, "area").image
  cubic = step_input(frames[0], 4, 6, 3, "cubic").image
  np.testing.assert_allclose(area, cv2.resize(image, (6, 4), interpolation=cv2.INTER_AREA),
                             atol=1e-6)
  np.testing.assert_allclose(cubic, cv2.resize(image, (6, 4), interpolation=cv2.INTER_CUBIC),
                             atol=1e-6)
  assert not np.allclose(area, cubic)


def test_step_input_refuses_an_8_bit_image():
  """`Frame.image` is RGB in [0, 1]: a uint8 frame built in memory (an image read with PIL or
  imageio) became floats of 0..255 at the network's size, or an all-white image once resized
  (the area resize clips to [0, 1]), and the run adapted on that without a word; the same
  image divided by 255 gives the network's input (the reference: the frame's own pixels / 255)."""
  from pitta_jax.adapt.inputs import chunks, step_input
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.frame import Frame
  pixels = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3) * 3   # 0..213
  for height, width in ((4, 6), (2, 3)):                                # as it is, and resized
    with pytest.raises(DataError, match=r"mine: image must be floating RGB in \[0, 1\], got "
                                        r"uint8 \(divide 8-bit images by 255\)"):
      step_input(Frame(pixels, name="mine"), height, width, 3)
  with pytest.raises(DataError, match="got bool"):
    next(chunks([Frame(pixels > 100, name="mask")], 4, 6, 1, 3))
  got = step_input(Frame(pixels / np.float32(255), name="mine"), 4, 6, 3).image
  assert got.dtype == np.float32
  np.testing.assert_array_equal(got, pixels.astype(np.float32) / np.float32(255))


def test_step_input_refuses_float_images_on_another_scale():
  """Floats of 0..255 (a cast without the division) or a mean/std-normalised image went to
  the network, which normalises [0, 1] RGB itself, without a word; refused naming the frame and
  the range. Values within float rounding of [0, 1] pass as they are."""
  from pitta_jax.adapt.inputs import step_input
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.frame import Frame
  pixels = np.arange(4 * 6 * 3, dtype=np.float32).reshape(4, 6, 3) * 3   # 0..213
  with pytest.raises(DataError, match=r"^cast: image values must be RGB in \[0, 1\], got "
                                      r"0\.\.213 \(divide 8-bit values by 255"):
    step_input(Frame(pixels, name="cast"), 4, 6, 3)
  normalised = (pixels / 255 - 0.45) / 0.225
  with pytest.raises(DataError, match=r"^norm: image values must be RGB in \[0, 1\], got -2"):
    step_input(Frame(normalised, name="norm"), 4, 6, 3)
  edge = np.clip(pixels / 213, 0, 1) * np.float32(1.0004)                    # 0..1.0004
  np.testing.assert_array_equal(step_input(Frame(edge), 4, 6, 3).image, edge)


def test_step_input_refuses_a_float_panoptic_map():
  """A float panoptic map was cast to int32 on its way to the step, so segment 3.7 became
  segment 3 (a car's id, here) without a word, where the pure functions refuse float ids
  (`masks.segment_id_array`). Reference: the same map as int32 passes through as it is."""
  from pitta_jax.adapt.inputs import step_input
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.frame import Frame, Segment
  ids = np.zeros((4, 6), np.int32)
  ids[1:3, 2:5] = 3
  image = np.full((4, 6, 3), 0.5, np.float32)
  with pytest.raises(DataError, match="cars: panoptic must be an integer map of segment ids, "
                                      "got float32"):
    step_input(Frame(image, panoptic=(ids + 0.7).astype(np.float32), segments=(Segment(3, 3),),
                     name="cars"), 4, 6, 3)
  got = step_input(Frame(image, panoptic=ids.astype(np.uint16), segments=(Segment(3, 3),)),
                   4, 6, 3)
  np.testing.assert_array_equal(got.panoptic, ids)
  assert got.seg_ids.tolist() == [3, 0, 0] and got.seg_valid.tolist() == [True, False, False]


def test_step_input_refuses_a_panoptic_map_of_another_size():
  """An in-memory frame whose panoptic map is not the image's size (here transposed) had its
  map resized on its own to the network's size, labelling other pixels, where the readers
  refuse such a pair. Reference: the map of the image's size passes through as it is."""
  from pitta_jax.adapt.inputs import step_input
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.frame import Frame, Segment
  ids = np.zeros((4, 6), np.int32)
  ids[1:3, 2:5] = 3
  image = np.full((4, 6, 3), 0.5, np.float32)
  with pytest.raises(DataError, match=r"cars: panoptic map is \(6, 4\) but the image is "
                                      r"\(4, 6\) \(H, W\)"):
    step_input(Frame(image, panoptic=ids.T.copy(), segments=(Segment(3, 3),), name="cars"),
               4, 6, 3)
  np.testing.assert_array_equal(
      step_input(Frame(image, panoptic=ids, segments=(Segment(3, 3),)), 4, 6, 3).panoptic, ids)
