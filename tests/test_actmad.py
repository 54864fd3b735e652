"""ActMAD (methods/actmad.py) against the PyTorch reference of tests/torch_tta.py.

Reference: ActMAD as its official code computes it (BN forward hooks, torch.mean/var over the
batch, nn.L1Loss per layer summed, BN in eval mode, torch SGD with Nesterov momentum and weight
decay), with the source statistics of the whole set (ours: upstream averages per-batch ones,
see test_source_stats.py) on the PyTorch MonoDepth2 of torch_monodepth2 with random weights,
converted to Flax with weights_convert.monodepth2; + PITTA's L_d with native ops. float64 on both sides, 64x96.
Checked: the source statistics; 3 online frames with a ring of K = 1 (0, 1, 1 previous frame:
the oldest drops out), per frame the total loss, ActMAD's own loss and L_d, and the adapted
parameters after the 3 updates; with ld_weight 0 one step's loss and parameters equal plain
ActMAD's. Adapted here: every encoder BN and the last 10% of the encoder convs
(`fraction(cnn=10,bn=100)`: conv kernels and their weight decay are exercised, at a third of
the compile time of all 20 convs; ActMAD's own setting is cnn=100).
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from flax.traverse_util import flatten_dict

import adapt_frames
import torch_monodepth2 as tm
import torch_tta
from pitta_jax.adapt import AdaptConfig, StepInput, init_state, make_optimizer, make_step
from pitta_jax.methods import build
from pitta_jax.methods.actmad import RESOURCE, ActmadConfig, source_statistics
from pitta_jax.methods.depth_refining import DepthRefiningConfig
from pitta_jax.models.registry import network
from weights_convert.monodepth2 import convert_monodepth2

H, W = adapt_frames.H, adapt_frames.W
IDS = [11, 12, 13]      # adapt_frames' dynamic instances (two cars, a person)
LR, RING, WINDOW, N_FRAMES = 1e-2, 1, 3, 3
CFG = AdaptConfig(bn_stats="running", selector="fraction(cnn=10,bn=100)")
ACTMAD = ActmadConfig(lr=LR, ring_size=RING, ld=DepthRefiningConfig(max_instances=4, window=WINDOW))


@pytest.fixture(scope="module")
def case(tmp_path_factory):
  root = tmp_path_factory.mktemp("mono")
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  tm.randomize_(enc, 31), tm.randomize_(dec, 32)
  torch.save({**enc.state_dict(), "height": H, "width": W}, root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  _, variables, _ = convert_monodepth2(root / "encoder.pth", root / "depth.pth")
  frames = adapt_frames.make_frames(N_FRAMES, seed=1)
  source = adapt_frames.make_frames(3, seed=7).image * 0.8 + 0.1   # a "clear" source domain
  return enc.double(), dec.double(), variables, frames, source


@pytest.fixture(scope="module")
def jax_run(case):
  """The engine's compiled step over the frames (x64), and one ld_weight 0 step."""
  _, _, variables, frames, source = case
  with jax.enable_x64(True):
    v64 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), variables)
    model = network("monodepth2", {"num_layers": 18})
    stats = source_statistics(model, v64, [source[:2].astype(np.float64), source[2:].astype(np.float64)])
    method = build("actmad", ACTMAD)
    tx = make_optimizer(CFG, method)
    step = jax.jit(make_step(model, method, CFG, tx))
    init, consts = init_state(v64, method, CFG, tx, model, {RESOURCE: stats})
    frame = lambda t: StepInput(*(jnp.asarray(v[t], jnp.float64 if v.dtype == np.float32 else None)
                                  for v in frames))
    state, outs = init, []
    for t in range(N_FRAMES):
      state, out = step(state, frame(t), consts)
      outs.append(jax.tree_util.tree_map(np.asarray, out))
    no_ld = init.replace(method_state={**init.method_state, "ld_weight": jnp.zeros((), jnp.float64)})
    state0, out0 = step(no_ld, frame(0), consts)
    flat = lambda s: {k: np.asarray(v) for k, v in flatten_dict(s.trainable["encoder"], sep="/").items()}
    return ({k: tuple(map(np.asarray, v)) for k, v in stats.items()}, outs, flat(state),
            jax.tree_util.tree_map(np.asarray, out0), flat(state0))


@pytest.fixture(scope="module")
def torch_stats(case):
  enc, dec, _, _, source = case
  return torch_tta.pooled_source_stats(enc, dec, source)


def _torch_run(case, stats, trainable, ld_weight, n_frames):
  enc, dec, _, frames, _ = case
  enc, dec = copy.deepcopy(enc), copy.deepcopy(dec)
  ref = torch_tta.ActMAD(enc, dec, stats, LR, RING, ld_weight, WINDOW, set(trainable))
  losses, depths = [], []
  for t in range(n_frames):
    losses.append(ref.step(frames.image[t], frames.panoptic[t], IDS))
    depths.append(ref.depth(frames.image[t]))     # evaluated after the step, as upstream
  params = torch_tta.encoder_params(enc)
  return losses, {k: params[k] for k in trainable}, depths


def _worst_rel(a: dict, b: dict, ref: dict) -> float:
  """max over leaves of max|a - b| / max|b - ref| (the difference relative to the update)."""
  assert set(a) == set(b)
  return max(float(np.max(np.abs(a[k] - b[k])) / max(np.max(np.abs(b[k] - ref[k])), 1e-300))
             for k in b)


def test_source_statistics_match_torch(jax_run, torch_stats):
  stats, *_ = jax_run
  t_stats = torch_stats
  assert len(stats) == len(t_stats) == 20
  names = {torch_tta.flax_path(f"{n}.weight").rsplit("/", 1)[0]: n for n in t_stats}
  worst = 0.0
  for path, (mean, var) in stats.items():
    t_mean, t_var = (x.permute(1, 2, 0).numpy() for x in t_stats[names[path.split("/", 1)[1]]])
    worst = max(worst, np.max(np.abs(mean - t_mean)) / np.max(np.abs(t_mean)),
                np.max(np.abs(var - t_var)) / np.max(np.abs(t_var)))
  print(f"source mean/var vs torch (3 images, batches of 2 + 1): worst max diff / max {worst:.1e}")
  assert worst < 1e-10


def test_online_steps_match_torch(case, jax_run, torch_stats):
  _, outs, params, _, _ = jax_run
  t_losses, t_params, t_depths = _torch_run(case, torch_stats, params, 1.0, N_FRAMES)
  assert len(params) == 40 + 2  # 20 BN (scale, bias) + the last 2 conv kernels
  src = torch_tta.encoder_params(case[0])
  for t, (out, (total, own, l_d)) in enumerate(zip(outs, t_losses)):
    print(f"frame {t}: total jax {float(out.loss):.10f} torch {total:.10f}; actmad "
          f"{float(out.logs['loss_actmad']):.8f} / {own:.8f}; L_d {float(out.logs['loss_d']):.6f} / "
          f"{l_d:.6f}")
    np.testing.assert_allclose(float(out.logs["loss_actmad"]), own, rtol=1e-9)
    np.testing.assert_allclose(float(out.logs["loss_d"]), l_d, rtol=1e-9)
    np.testing.assert_allclose(float(out.loss), total, rtol=1e-9)
    np.testing.assert_allclose(float(out.loss), own + l_d, rtol=1e-12)  # total = own + 1 * L_d
    np.testing.assert_allclose(out.depth, t_depths[t], rtol=1e-7)  # after the frame's step
    assert not bool(out.skipped)
  rel = _worst_rel(params, t_params, src)
  print(f"adapted parameters after {N_FRAMES} steps ({len(t_params)} leaves): worst max diff / max update "
        f"{rel:.1e}")
  assert rel < 1e-6


def test_ld_weight_zero_is_plain_actmad(case, jax_run, torch_stats):
  _, outs, _, out0, params0 = jax_run
  t_losses, t_params, _ = _torch_run(case, torch_stats, params0, 0.0, 1)
  total, own, _ = t_losses[0]
  print(f"ld_weight 0: jax {float(out0.loss):.10f} torch ActMAD {total:.10f}; with ld_weight 1 "
        f"the difference is L_d {float(outs[0].loss) - float(out0.loss):.6f} "
        f"(logged {float(outs[0].logs['loss_d']):.6f})")
  np.testing.assert_allclose(float(out0.loss), own, rtol=1e-9)
  np.testing.assert_allclose(float(outs[0].loss) - float(out0.loss),
                             float(outs[0].logs["loss_d"]), rtol=1e-9)
  rel = _worst_rel(params0, t_params, torch_tta.encoder_params(case[0]))
  print(f"adapted parameters after one ld_weight-0 step: worst max diff / max update {rel:.1e}")
  assert rel < 1e-6


def test_reset_empties_the_ring_and_keeps_the_source_statistics():
  """`reset_every` puts the weights back; the ring's activations came from the discarded
  weights, so it is emptied as at the start (it kept them, and the first frames after a reset
  were aligned with a batch of the old network's activations)."""
  from pitta_jax.methods.base import ring_init, ring_push, ring_valid
  method = build("actmad", ActmadConfig(ring_size=3))
  mean, var = jnp.ones((2, 3, 4)), jnp.full((2, 3, 4), 2.0)
  ring = ring_push(ring_push(ring_init(mean, 3), mean), 3 * mean)
  state = {"source": {"enc/bn1": (mean, var)}, "rings": {"enc/bn1": ring},
           "ld_weight": jnp.asarray(0.5)}
  assert ring_valid(ring).tolist() == [True, True, False]
  after = method.reset(state, None)
  assert ring_valid(after["rings"]["enc/bn1"]).tolist() == [False, False, False]
  assert after["source"] is state["source"] and after["ld_weight"] is state["ld_weight"]
  pushed = ring_push(after["rings"]["enc/bn1"], 5 * mean)  # the next frame is the only entry
  assert ring_valid(pushed).tolist() == [True, False, False]
  np.testing.assert_array_equal(pushed["items"][0], 5 * mean)


def test_a_non_finite_frame_does_not_enter_the_ring():
  """A frame whose activations are not finite is not pushed (it would make the mean and
  variance of the next ring_size frames NaN, and with them their losses); a finite one is."""
  from pitta_jax.adapt.engine import AdaptState
  from pitta_jax.methods.base import Aux, ring_init, ring_push, ring_valid
  cfg = AdaptConfig(optimizer="sgd", lr=0.1, bn_stats="running", selector="all")
  method = build("actmad", ActmadConfig(ring_size=3))
  tx = make_optimizer(cfg, method)
  mean = jnp.ones((2, 3, 4))
  ms = {"source": {"enc/bn1": (mean, 2 * mean)},
        "rings": {"enc/bn1": ring_push(ring_init(mean, 3), mean)}, "ld_weight": jnp.asarray(0.5)}
  w = {"w": jnp.ones(2)}
  state = AdaptState(trainable=w, opt_state=tx.init(w), method_state=ms, source=w,
                     step=jnp.int32(0), rng=jax.random.PRNGKey(0), n_skipped=jnp.int32(0))
  grads, loss = {"w": jnp.zeros(2)}, jnp.asarray(1.0)
  for value, pushed in ((jnp.nan, False), (jnp.inf, False), (4.0, True)):
    aux = Aux(jnp.ones((2, 2)), {}, {"enc/bn1": jnp.full((2, 3, 4), value)})
    new, _, _ = method.update(state, grads, loss, aux, jax.random.PRNGKey(1), tx, cfg)
    ring = new.method_state["rings"]["enc/bn1"]
    assert ring_valid(ring).tolist() == [True, pushed, False]
    np.testing.assert_array_equal(ring["items"][0], 4 * mean if pushed else mean)
    if pushed:
      np.testing.assert_array_equal(ring["items"][1], mean)
    else:
      assert np.all(np.isfinite(np.asarray(ring["items"])))


def test_the_callers_source_statistics_survive_the_runners_donation():
  """Statistics given as the caller's own JAX arrays are copied into the method state: the
  runner donates its carry, and the caller's arrays had been deleted by the first chunk (a
  second init_state with them then failed)."""
  from tiny_net import TINY, tiny_variables
  from pitta_jax.adapt import init_state
  from pitta_jax.methods.actmad import RESOURCE, source_statistics
  from pitta_jax.methods.base import INPUT_SIZE
  variables = tiny_variables(0)
  cfg = AdaptConfig(method="actmad", optimizer="sgd", lr=1e-4, bn_stats="running",
                    selector="all")
  method = build("actmad")
  images = np.random.default_rng(0).uniform(size=(2, 64, 96, 3)).astype(np.float32)
  stats = {k: (jnp.asarray(m), jnp.asarray(v))
           for k, (m, v) in source_statistics(TINY, variables, [images]).items()}
  state, _ = init_state(variables, method, cfg, make_optimizer(cfg, method), TINY,
                        {INPUT_SIZE: (64, 96), RESOURCE: stats})
  k = next(iter(stats))
  assert state.method_state["source"][k][0] is not stats[k][0]
  jax.block_until_ready(jax.jit(lambda s: jax.tree_util.tree_map(lambda x: x + 1, s),
                                donate_argnums=0)(state.method_state))
  assert all(np.isfinite(float(m.sum())) and np.isfinite(float(v.sum()))
             for m, v in stats.values())
