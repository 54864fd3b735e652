"""CoMoDa (methods/comoda.py) against a PyTorch CoMoDa written here from the official code.

Reference (`TorchCoMoDa`): the official CoMoDA.py step as a PyTorch user writes it: the four
MonoDepth2 modules of torch_monodepth2 (depth encoder + decoder, pairs pose encoder + decoder,
random weights, converted with weights_convert.monodepth2), `set_adapt` (every module in eval
mode, BatchNorm scale/bias excluded from the gradient), one `torch.optim.Adam` over all their
parameters, the test sample concatenated with the replay samples into one batch, MonoDepth2's
loss of tests/torch_sfm.py with the moving-object mask multiplying the minimum reprojection map
(`pixel_weights`), + L_d (eq. 8, torch_tta.depth_refining) on the test frame's depth;
`backward()`, `step()`. The pose pair is MonoDepth2's `predict_poses`; K^-1 is `np.linalg.pinv`
as the official data loader's. The random draws (replay windows, tie-break noise) are the JAX
run's own (`comoda.step_draws` of the step's key), passed to PyTorch. float64 on both sides,
64x64 synthetic fog frames with K and panoptic maps, a replay set of clear frames.

Checked through the engine's compiled chunk (frame 0 has no previous frame: no update): per
frame the loss, CoMoDa's own term, L_d and the evaluated depth, and the depth AND pose
parameters after 2 updates (ld_weight 1) and after 1 update (ld_weight 0, against the reference
without L_d); at the first update loss(ld 1) - loss(ld 0) = L_d. On tiny networks (a second,
cheap compile): latency 1 (no update on frames 0, 1; frame t-1 adapted from (t-2, t), its loss
rebuilt in PyTorch from the tiny networks' outputs as upstream's triplet mode composes it:
sources [t-2, t], poses inverted for the earlier frame; the evaluated depth is frame t's after the update, as
upstream's), two runs bitwise equal,
and the non-finite guard over both networks.
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
import torch.nn as nn
import flax.linen as nn_flax
from flax.traverse_util import flatten_dict

import torch_monodepth2 as tm
import torch_sfm
import torch_tta
from xla_options import RUN_OPTIMIZED
from pitta_jax.adapt import AdaptConfig, init_state, make_chunk_runner, make_optimizer, make_step
from pitta_jax.adapt.inputs import stack, step_input
from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
from pitta_jax.masks import DEFAULT_DYNAMIC_COCO_IDS
from pitta_jax.methods.base import POSE, PoseNet, SourceData
from pitta_jax.methods.comoda import (REPLAY_IMAGES, REPLAY_K, ComodaConfig, build, replay_set,
                                      step_draws)
from pitta_jax.methods.depth_refining import DepthRefiningConfig
from pitta_jax.models.depth_decoder import disp_to_depth
from pitta_jax.models.pose import PoseNet as FlaxPoseNet
from pitta_jax.models.registry import Network, network
from pitta_jax.models.spec import ModelSpec
from weights_convert import rules as R
from weights_convert.monodepth2 import (convert_monodepth2, depth_decoder_rules, encoder_rules,
                                        pose_decoder_rules)

H, W, N_FRAMES, WINDOW = 64, 64, 3, 3
CFG = AdaptConfig(bn_stats="running", selector="no_bn", max_segments=16, chunk_size=N_FRAMES)
CONFIG = ComodaConfig(replay=1, ld=DepthRefiningConfig(window=WINDOW))
SCALES = CONFIG.sfm.scales


def _x64(tree):
  return jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), tree)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
  root = tmp_path_factory.mktemp("mono")
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  penc, pdec = tm.ResnetEncoder(18, 2), tm.PoseDecoder(tm.num_ch_enc(18), 1, 2)
  for seed, m in enumerate((enc, dec, penc, pdec)):
    tm.randomize_(m, 51 + seed)
  paths = [root / f"{n}.pth" for n in ("encoder", "depth", "pose_encoder", "pose")]
  torch.save({**enc.state_dict(), "height": H, "width": W}, paths[0])
  for m, p in zip((dec, penc, pdec), paths[1:]):
    torch.save(m.state_dict(), p)
  _, depth_vars, pose_vars = convert_monodepth2(*paths)
  frames = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=N_FRAMES, seed=3,
                                             domain="fog"))
  chunk = stack([step_input(f, H, W, CFG.max_segments) for f in frames], N_FRAMES)
  clear = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=5, seed=0))
  replay = replay_set(SourceData(sequences=(tuple(clear),)), CONFIG)
  torch_models = tuple(m.double() for m in (enc, dec, penc, pdec))
  return torch_models, depth_vars, pose_vars, frames, chunk, replay


@pytest.fixture(scope="module")
def jax_runs(case):
  """The engine's compiled chunk over the frames (x64), with ld_weight 1 and 0."""
  _, depth_vars, pose_vars, _, chunk, replay = case
  with jax.enable_x64(True):
    model = network("monodepth2", {"num_layers": 18})
    method = build(CONFIG)
    tx = make_optimizer(CFG, method)
    run = make_chunk_runner(make_step(model, method, CFG, tx), RUN_OPTIMIZED)
    resources = {POSE: PoseNet(FlaxPoseNet(18), _x64(pose_vars)), **replay}
    init, consts = init_state(_x64(depth_vars), method, CFG, tx, model, resources)
    chunk = chunk._replace(image=chunk.image.astype(np.float64),
                           intrinsics=chunk.intrinsics.astype(np.float64))
    host = lambda t: jax.tree_util.tree_map(np.asarray, t)
    copy_of = lambda s: jax.tree_util.tree_map(jnp.copy, s)
    runs = [host(run(copy_of(init), chunk, consts))]
    # ld_weight 0: frames 0, 1 (the last one is a padding frame: the state stays after frame 1)
    no_ld = init.replace(method_state={**init.method_state, "ld_weight": jnp.zeros((), jnp.float64)})
    runs.append(host(run(no_ld, chunk._replace(valid=np.arange(N_FRAMES) < 2), consts)))
    draws = [host(step_draws(jax.random.fold_in(jax.random.PRNGKey(CFG.seed), t),
                             replay[REPLAY_IMAGES].shape[0], CONFIG, H, W, jnp.float64))
             for t in range(N_FRAMES)]
    return runs, draws


# ----------------------------------------------------------------------------- the reference


class TorchCoMoDa:
  """One CoMoDa step per call, as the official CoMoDA.py (adapt_seq / process_batch /
  compute_losses) with the pairs pose network, no velocity loss, no speed gating."""

  def __init__(self, enc, dec, penc, pdec, lr, ld_weight):
    self.enc, self.dec, self.penc, self.pdec = enc, dec, penc, pdec
    params = []
    for m in (enc, dec, penc, pdec):                  # set_adapt: BN eval mode, BN params frozen
      m.eval()
      for mod in m.modules():
        if isinstance(mod, nn.BatchNorm2d):
          mod.weight.requires_grad_(False)
          mod.bias.requires_grad_(False)
      params += list(m.parameters())
    self.optimizer = torch.optim.Adam(params, lr)
    self.ld_weight = ld_weight
    self.loss = torch_sfm.Monodepth2Loss(1 + CONFIG.replay, H, W, scales=SCALES,
                                         dtype=torch.float64)

  def depth(self, image: np.ndarray) -> np.ndarray:
    with torch.no_grad():
      disp = self.dec(self.enc(_chw(image[None])))[("disp", 0)]
    return torch_tta.disp_to_depth(disp[0, 0]).numpy()

  def step(self, target, source, K, mask, noise, panoptic, ids):
    """target, source (B, H, W, 3), K (B, 3, 3), mask (B, H, W), noise (S, B, 1, H, W), the
    test frame's panoptic map and dynamic ids -> (total, own, L_d, the test frame's depth)."""
    target, source = _chw(target), _chw(source)
    K4 = np.tile(np.eye(4), (K.shape[0], 1, 1))
    K4[:, :3, :3] = K
    inv_K = torch.from_numpy(np.stack([np.linalg.pinv(k) for k in K4]))
    outputs = self.dec(self.enc(target))
    disps = [outputs[("disp", s)] for s in SCALES]
    axisangle, translation = self.pdec([self.penc(torch.cat([source, target], 1))])
    pose = torch_sfm.transformation_from_parameters(axisangle[:, 0], translation[:, 0],
                                                    invert=True)   # frame -1: (source, target)
    own, *_ = self.loss(target, [source], disps, torch.from_numpy(K4), inv_K, [pose],
                        torch.from_numpy(np.array(noise)), pixel_weights=torch.from_numpy(mask))
    depth = torch_tta.disp_to_depth(disps[0][0, 0])
    l_d = torch_tta.depth_refining(depth, panoptic, ids, WINDOW)
    total = own + self.ld_weight * l_d
    self.optimizer.zero_grad()
    total.backward()
    self.optimizer.step()
    return float(total.detach()), float(own.detach()), float(l_d.detach()), depth.detach().numpy()


def _chw(x: np.ndarray) -> torch.Tensor:
  return torch.from_numpy(np.asarray(x, np.float64)).permute(0, 3, 1, 2).contiguous()


def _torch_run(case, draws, ld_weight, n_frames):
  """The reference over frames 0..n_frames-1 on one thread (float64 convolutions take 5x the
  CPU time on two threads of a shared machine); returns per-frame terms and the models."""
  threads = torch.get_num_threads()
  torch.set_num_threads(1)
  try:
    return _torch_frames(case, draws, ld_weight, n_frames)
  finally:
    torch.set_num_threads(threads)


def _torch_frames(case, draws, ld_weight, n_frames):
  models, _, _, frames, chunk, replay = case
  models = copy.deepcopy(models)
  ref = TorchCoMoDa(*models, 1e-4, ld_weight)
  images, Ks = replay[REPLAY_IMAGES].astype(np.float64), replay[REPLAY_K].astype(np.float64)
  results = [(0.0, 0.0, 0.0, ref.depth(chunk.image[0]))]        # frame 0: no previous frame
  for t in range(1, n_frames):
    idx, noise = draws[t]
    ids = [s.id for s in frames[t].segments if s.category_id in DEFAULT_DYNAMIC_COCO_IDS]
    mask = np.concatenate([(~np.isin(chunk.panoptic[t], ids))[None], np.ones((len(idx), H, W))])
    results.append(ref.step(
        np.concatenate([chunk.image[t][None], images[idx, 1]]),
        np.concatenate([chunk.image[t - 1][None], images[idx, 0]]),
        np.concatenate([chunk.intrinsics[t][None], Ks[idx]]), mask.astype(np.float64), noise,
        chunk.panoptic[t], ids))
  return results, models


def _torch_params(module, rules) -> dict[str, np.ndarray]:
  """A PyTorch module's float64 parameters at their Flax paths (the converter's key table)."""
  state = {k: v.detach().numpy() for k, v in module.state_dict().items()}
  return {"/".join(r.flax[1:]): R.to_flax(state[r.sources[0]], r.kind)
          for r in rules if r.flax[0] == "params"}


def _requiring_grad(module, rules) -> set[str]:
  """Flax paths of the module's parameters that PyTorch trains (after `set_adapt`)."""
  to_flax = {r.sources[0]: "/".join(r.flax[1:]) for r in rules if r.flax[0] == "params"}
  names = {n for n, p in module.named_parameters() if p.requires_grad and n in to_flax}
  return {to_flax[n] for n in names}


def _flat(tree) -> dict[str, np.ndarray]:
  return {k: np.asarray(v) for k, v in flatten_dict(tree, sep="/").items()}


def _worst_rel(ours: dict, ref: dict, start: dict) -> float:
  """max over leaves of max|ours - ref| / max|ref - start| (the difference relative to the update)."""
  assert set(ours) == set(ref)
  return max(float(np.max(np.abs(ours[k] - ref[k])) / max(np.max(np.abs(ref[k] - start[k])), 1e-300))
             for k in ref)


def _compare(case, run, draws, ld_weight, label, n_frames):
  (state, out) = run
  models = case[0]
  results, trained = _torch_run(case, draws, ld_weight, n_frames)
  for t, (total, own, l_d, depth) in enumerate(results):
    print(f"{label} frame {t}: loss jax {float(out.loss[t]):.12f} torch {total:.12f}; comoda "
          f"{float(out.logs['loss_comoda'][t]):.10f} / {own:.10f}; L_d "
          f"{float(out.logs['loss_d'][t]):.8f} / {l_d:.8f}")
    np.testing.assert_allclose(float(out.loss[t]), total, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(float(out.logs["loss_comoda"][t]), own, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(float(out.logs["loss_d"][t]), l_d, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(out.depth[t], depth, rtol=1e-9)
    assert not bool(out.skipped[t])
  assert float(out.update_norm[0]) == 0.0 and float(out.update_norm[1]) > 0.0
  enc_rules, dec_rules = encoder_rules(18), depth_decoder_rules()
  ref_depth = {**_torch_params(trained[0], enc_rules), **_torch_params(trained[1], dec_rules)}
  start_depth = {**_torch_params(models[0], enc_rules), **_torch_params(models[1], dec_rules)}
  ours_depth = _flat(state.trainable)
  # the selector no_bn = the parameters PyTorch trains after set_adapt (every one but BN's)
  trainable = _requiring_grad(trained[0], enc_rules) | _requiring_grad(trained[1], dec_rules)
  assert set(ours_depth) == trainable and len(ref_depth) - len(trainable) == 2 * 20
  rel_depth = _worst_rel(ours_depth, {k: ref_depth[k] for k in trainable}, start_depth)
  ref_pose = {**_torch_params(trained[2], encoder_rules(18)),
              **_torch_params(trained[3], pose_decoder_rules())}
  start_pose = {**_torch_params(models[2], encoder_rules(18)),
                **_torch_params(models[3], pose_decoder_rules())}
  ours_pose = _flat(state.method_state["pose"].trainable)
  assert set(ours_pose) == (_requiring_grad(trained[2], encoder_rules(18))
                            | _requiring_grad(trained[3], pose_decoder_rules()))
  rel_pose = _worst_rel(ours_pose, {k: ref_pose[k] for k in ours_pose}, start_pose)
  for k in ref_depth.keys() - trainable:       # BN scale/bias did not move in PyTorch either
    np.testing.assert_array_equal(ref_depth[k], start_depth[k])
  print(f"{label}: after {n_frames - 1} update(s), worst max diff / max update: depth net {rel_depth:.1e} "
        f"({len(ours_depth)} leaves), pose net {rel_pose:.1e} ({len(ours_pose)} leaves)")
  assert rel_depth < 1e-6 and rel_pose < 1e-6


def test_steps_match_torch_comoda_with_ld(case, jax_runs):
  runs, draws = jax_runs
  _compare(case, runs[0], draws, 1.0, "ld_weight 1", N_FRAMES)


def test_ld_weight_zero_is_plain_comoda(case, jax_runs):
  runs, draws = jax_runs
  _compare(case, runs[1], draws, 0.0, "ld_weight 0", 2)
  with_ld, without = runs[0][1], runs[1][1]
  diff = float(with_ld.loss[1]) - float(without.loss[1])   # first update: the same parameters
  print(f"frame 1: loss(ld 1) - loss(ld 0) = {diff:.10f}, L_d = {float(with_ld.logs['loss_d'][1]):.10f}")
  np.testing.assert_allclose(diff, float(with_ld.logs["loss_d"][1]), rtol=1e-9)
  assert float(with_ld.logs["loss_d"][1]) > 0
  np.testing.assert_array_equal(with_ld.logs["loss_comoda"][1], without.logs["loss_comoda"][1])


def test_replay_set_windows():
  """Hand-counted: sequences of 3 and 4 frames hold 2 + 3 pairs; 3 kept, evenly spaced
  (windows 0, 2, 4 = pair (0, 1) of the first, (0, 1) and (2, 3) of the second)."""
  seq_a = generate_sequence(SyntheticConfig(height=32, width=32, num_frames=3, seed=1))
  seq_b = generate_sequence(SyntheticConfig(height=32, width=32, num_frames=4, seed=2))
  out = replay_set(SourceData(sequences=(tuple(seq_a), tuple(seq_b))),
                   ComodaConfig(replay_size=3))
  expect = [(seq_a, 0), (seq_b, 0), (seq_b, 2)]
  assert out[REPLAY_IMAGES].shape == (3, 2, 32, 32, 3)
  for k, (seq, i) in enumerate(expect):
    np.testing.assert_array_equal(out[REPLAY_IMAGES][k, 0], seq[i].image)
    np.testing.assert_array_equal(out[REPLAY_IMAGES][k, 1], seq[i + 1].image)
    np.testing.assert_array_equal(out[REPLAY_K][k], seq[i + 1].intrinsics.astype(np.float32))
  triplets = replay_set(SourceData(sequences=(tuple(seq_b),)), ComodaConfig(latency=1))
  assert triplets[REPLAY_IMAGES].shape == (2, 3, 32, 32, 3)
  with pytest.raises(ValueError, match="--replay-root"):
    replay_set(SourceData(images=(seq_a[0].image,)), ComodaConfig())


def test_step_draws_follow_their_laws():
  """The draws the parity tests replay, by their law. Replay: `replay` distinct windows of the
  set when it holds enough (each window in a given step's batch with probability replay / R,
  within 5 standard errors over 4000 steps), with repetition only from a smaller set. Tie-break
  noise: one standard-normal draw per step (upstream's `torch.randn` of the identity losses),
  the same at every scale (upstream repeats it over the scales)."""
  cfg = ComodaConfig(replay=3, sfm=dataclasses.replace(ComodaConfig().sfm, scales=(0, 1, 2)))
  draw = jax.jit(jax.vmap(lambda k: step_draws(k, 10, cfg, 4, 6)))
  steps = 4000
  idx, noise = (np.asarray(a) for a in draw(jax.random.split(jax.random.PRNGKey(7), steps)))
  assert idx.shape == (steps, 3) and noise.shape == (steps, 3, 4, 1, 4, 6)
  assert idx.min() >= 0 and idx.max() < 10
  assert np.all(np.sort(idx, axis=1)[:, 1:] != np.sort(idx, axis=1)[:, :-1])  # no repetition
  p = 0.3
  counts = np.bincount(idx.ravel(), minlength=10)
  assert np.all(np.abs(counts - steps * p) < 5 * np.sqrt(steps * p * (1 - p))), counts
  np.testing.assert_array_equal(noise, np.broadcast_to(noise[:, :1], noise.shape))
  z = noise[:, 0].astype(np.float64).ravel()
  assert abs(z.mean()) < 5 / np.sqrt(z.size)
  assert abs((z ** 2).mean() - 1.0) < 5 * np.sqrt(2.0 / z.size)
  small, _ = step_draws(jax.random.PRNGKey(1), 2, cfg, 4, 6)  # 3 from a set of 2: repeats
  assert small.shape == (3,) and set(np.asarray(small).tolist()) <= {0, 1}


def test_requires_bn_eval_and_no_bn_selector():
  method = build(ComodaConfig())
  with pytest.raises(ValueError, match="--bn-stats running"):
    method.check(AdaptConfig(selector="no_bn"))
  with pytest.raises(ValueError, match="--selector no_bn"):
    method.check(AdaptConfig(bn_stats="running"))
  method.check(AdaptConfig(bn_stats="running", selector="no_bn"))


def test_the_moving_object_mask_covers_every_dynamic_segment_beyond_ld_instances():
  """Upstream multiplies the minimum reprojection map by its whole mask of possibly moving
  objects: the test sample's weights are 0 on every dynamic segment of the frame (here 5 cars
  and a person, with L_d's table cut to 2 instances), 1 elsewhere (a static pole, void)."""
  from pitta_jax.adapt.engine import StepInput
  from pitta_jax.methods.comoda import _frame_ring, build_sample
  h, w, s_max = 8, 12, 10
  panoptic = np.zeros((h, w), np.int32)
  segs = [(3, 3), (5, 3), (7, 3), (9, 3), (11, 3), (13, 1), (21, 10)]  # (id, COCO class)
  for k, (sid, _) in enumerate(segs):
    panoptic[k, 1 + k:4 + k] = sid
  ids = np.zeros(s_max, np.int32)
  classes = np.zeros(s_max, np.int32)
  ids[:len(segs)], classes[:len(segs)] = zip(*segs)
  frame = StepInput(image=jnp.full((h, w, 3), 0.5), panoptic=jnp.asarray(panoptic),
                    seg_ids=jnp.asarray(ids), seg_classes=jnp.asarray(classes),
                    seg_valid=jnp.asarray(np.arange(s_max) < len(segs)),
                    valid=jnp.array(True), intrinsics=jnp.eye(3), has_intrinsics=jnp.array(True),
                    starts_recording=jnp.array(False))
  cfg = ComodaConfig(replay=0, ld=DepthRefiningConfig(max_instances=2, window=3))
  ms = {"ring": _frame_ring((h, w), s_max, 1, jnp.float32),
        "replay_images": jnp.zeros((0, 2, h, w, 3)), "replay_K": jnp.zeros((0, 3, 3))}
  sample = build_sample(frame, ms, jnp.zeros((0,), jnp.int32), cfg)
  dynamic = [sid for sid, c in segs if c in DEFAULT_DYNAMIC_COCO_IDS]
  assert len(dynamic) == 6
  np.testing.assert_array_equal(np.asarray(sample.weights[0]), ~np.isin(panoptic, dynamic))


# ------------------------------------------------------- latency 1 and the guard, on tiny networks


class TinyDepth(nn_flax.Module):
  """A 4-scale sigmoid-disparity network small enough to compile in a second."""

  @nn_flax.compact
  def __call__(self, images, train=False):
    x = jnp.tanh(nn_flax.Conv(4, (3, 3), padding=1, name="conv")(images - 0.45))
    return tuple(nn_flax.sigmoid(nn_flax.Conv(1, (1, 1), name=f"disp_{s}")(
        x if s == 0 else nn_flax.avg_pool(x, (2 ** s, 2 ** s), (2 ** s, 2 ** s))))
        for s in range(4))


class TinyPose(nn_flax.Module):
  """(B, H, W, 6) pairs -> axisangle, translation (B, 2, 1, 3), as MonoDepth2's pose decoder."""

  @nn_flax.compact
  def __call__(self, pairs, train=False):
    x = jnp.mean(jnp.tanh(nn_flax.Conv(8, (3, 3), strides=2, name="conv")(pairs)), axis=(1, 2))
    x = 0.01 * nn_flax.Dense(12, name="out")(x).reshape(-1, 2, 1, 6)
    return x[..., :3], x[..., 3:]


TINY_H, TINY_W = 32, 48
TINY = Network(ModelSpec(name="tiny", build=lambda c: TinyDepth(), output="sigmoid_disparity",
                         size_multiple=8, default_size=(TINY_H, TINY_W)), TinyDepth())
LATENCY1 = ComodaConfig(latency=1, replay=2, lr=1e-2, ld=DepthRefiningConfig(window=WINDOW))


def _random_variables(module, channels: int, seed: int):
  """float64 variables of `module` for a (1, TINY_H, TINY_W, channels) input: kernels normal
  with std 1/sqrt(fan-in), biases 0.1 * normal (shapes by tracing: nothing compiles)."""
  shapes = jax.eval_shape(module.init, jax.random.PRNGKey(0),
                          jax.ShapeDtypeStruct((1, TINY_H, TINY_W, channels), jnp.float32))
  rng = np.random.default_rng(seed)
  return jax.tree_util.tree_map(
      lambda x: rng.standard_normal(x.shape) * (np.prod(x.shape[:-1]) ** -0.5 if len(x.shape) > 1
                                                 else 0.1), shapes)


@pytest.fixture(scope="module")
def tiny_case():
  """4 frames with latency 1 through the engine's compiled chunk (x64): twice; frames 0-2 only
  (the parameters before step 3); from a pose network holding a NaN; with frame 1 starting a
  new recording."""
  frames = generate_sequence(SyntheticConfig(height=TINY_H, width=TINY_W, num_frames=4, seed=5,
                                             domain="rain"))
  clear = generate_sequence(SyntheticConfig(height=TINY_H, width=TINY_W, num_frames=5, seed=0))
  inputs = [step_input(f, TINY_H, TINY_W, CFG.max_segments) for f in frames]
  inputs = [i._replace(image=i.image.astype(np.float64), intrinsics=i.intrinsics.astype(np.float64))
            for i in inputs]
  chunk = stack(inputs, len(inputs))
  with jax.enable_x64(True):
    replay = replay_set(SourceData(sequences=(tuple(clear),)), LATENCY1)
    depth_vars = _random_variables(TinyDepth(), 3, seed=1)
    pose_vars = _random_variables(TinyPose(), 6, seed=2)
    method = build(LATENCY1)
    tx = make_optimizer(CFG, method)
    init, consts = init_state(depth_vars, method, CFG, tx, TINY,
                              {POSE: PoseNet(TinyPose(), pose_vars), **replay})
    run = make_chunk_runner(make_step(TINY, method, CFG, tx))
    host = lambda t: jax.tree_util.tree_map(np.asarray, t)
    copy_of = lambda s: jax.tree_util.tree_map(jnp.copy, s)
    runs = [host(run(copy_of(init), chunk, consts)) for _ in range(2)]
    before_3 = host(run(copy_of(init), chunk._replace(valid=np.arange(4) < 3), consts)[0])
    pose = init.method_state["pose"]
    bad = jax.tree_util.tree_map(lambda x: x.at[(0,) * x.ndim].set(jnp.nan), pose.trainable)
    nan_init = init.replace(method_state={**init.method_state, "pose": pose.replace(trainable=bad)})
    nan_run = host(run(copy_of(nan_init), chunk, consts))
    cut = host(run(copy_of(init), chunk._replace(starts_recording=np.arange(4) == 1), consts))
    return (frames, inputs, replay, [host(init), before_3], runs, (host(nan_init), nan_run),
            cut)


@jax.jit
def _tiny_outputs(depth_params, pose_params, target, before, after):
  """The tiny networks' outputs the reference needs: the targets' 4 disparities (B, h, w) and
  the pose decoder's (axisangle, translation) (B, 2, 1, 3) of MonoDepth2's `predict_poses`
  pairs: frame -1 as (source, target), frame +1 as (target, source)."""
  disps = [d[..., 0] for d in TinyDepth().apply({"params": depth_params, "batch_stats": {}},
                                                target)]
  pose_vars = {"params": pose_params, "batch_stats": {}}
  return (disps, TinyPose().apply(pose_vars, jnp.concatenate([before, target], -1)),
          TinyPose().apply(pose_vars, jnp.concatenate([target, after], -1)))


@jax.jit
def _tiny_depth(depth_params, image):
  """The tiny network's depth (H, W) of one image, as MonoDepth2's disp_to_depth(0.1, 100)."""
  disp = TinyDepth().apply({"params": depth_params, "batch_stats": {}}, image[None])[0]
  return disp_to_depth(disp[0, ..., 0], 0.1, 100.0)


def _expected_latency1_loss(case, t, state=None):
  """Step t's terms in PyTorch, as upstream's triplet mode composes them: MonoDepth2's loss
  (tests/torch_sfm.py) of frame t-1 from sources [t-2, t] and of the replay triplets' centres
  from their neighbours, poses by `transformation_from_parameters` with `invert=True` for the
  earlier frame and `invert=False` for the later one, K of frame t-1, frame t-1's moving
  objects masked, + L_d (torch_tta) of frame t-1's depth; the tiny networks' outputs come from
  the parameters before step t (`state`, by default the uninterrupted run's)."""
  frames, inputs, replay, states, _, _, _ = case
  if state is None:
    state = states[t - 2]                # the parameters before step t (none moved before 2)
  idx, noise = step_draws(jax.random.fold_in(jax.random.PRNGKey(CFG.seed), t),
                          replay[REPLAY_IMAGES].shape[0], LATENCY1, TINY_H, TINY_W, jnp.float64)
  idx = np.asarray(idx)
  images, Ks = replay[REPLAY_IMAGES].astype(np.float64), replay[REPLAY_K].astype(np.float64)
  K = np.tile(np.eye(4), (len(idx) + 1, 1, 1))
  K[:, :3, :3] = np.concatenate([inputs[t - 1].intrinsics[None], Ks[idx]])
  ids = [s.id for s in frames[t - 1].segments if s.category_id in DEFAULT_DYNAMIC_COCO_IDS]
  mask = np.concatenate([(~np.isin(inputs[t - 1].panoptic, ids))[None],
                         np.ones((len(idx), TINY_H, TINY_W))])
  target = np.concatenate([inputs[t - 1].image[None], images[idx, 1]])
  before = np.concatenate([inputs[t - 2].image[None], images[idx, 0]])
  after = np.concatenate([inputs[t].image[None], images[idx, 2]])
  disps, (a_b, t_b), (a_a, t_a) = jax.tree_util.tree_map(np.asarray, _tiny_outputs(
      state.trainable, state.method_state["pose"].trainable, target, before, after))
  f64 = lambda x: torch.from_numpy(np.array(x, np.float64))  # a writable copy
  poses = [torch_sfm.transformation_from_parameters(f64(a_b)[:, 0], f64(t_b)[:, 0], invert=True),
           torch_sfm.transformation_from_parameters(f64(a_a)[:, 0], f64(t_a)[:, 0])]
  loss = torch_sfm.Monodepth2Loss(len(target), TINY_H, TINY_W, dtype=torch.float64)
  own, *_ = loss(_chw(target), [_chw(before), _chw(after)], [f64(d)[:, None] for d in disps],
                 f64(K), f64(np.linalg.inv(K)), poses, f64(noise), pixel_weights=f64(mask))
  depth = torch_tta.disp_to_depth(f64(disps[0][0]))
  l_d = torch_tta.depth_refining(depth, inputs[t - 1].panoptic, ids, WINDOW)
  return float(own), float(l_d)


def test_latency_1_adapts_the_previous_frame_one_frame_late(tiny_case):
  """Frame t's depth is evaluated after step t (the parameters before step t + 1: the initial
  ones for frames 0-1, after step 2 for frame 2, the final ones for frame 3), as upstream."""
  _, inputs, _, states, runs, _, _ = tiny_case
  state, out = runs[0]
  after = [states[0], states[0], states[1], state]
  for t in (0, 1):                          # frame t-1 has no t-2 yet: no update, loss 0
    assert float(out.loss[t]) == 0.0 and float(out.update_norm[t]) == 0.0
  for t in range(4):
    with jax.enable_x64(True):
      evaluated = _tiny_depth(after[t].trainable, inputs[t].image)
    np.testing.assert_allclose(out.depth[t], evaluated, rtol=1e-12)
  for t in (2, 3):
    with jax.enable_x64(True):
      own, l_d = _expected_latency1_loss(tiny_case, t)
    own, l_d = float(own), float(l_d)
    print(f"latency 1, frame {t}: comoda {float(out.logs['loss_comoda'][t]):.10f} / {own:.10f}, "
          f"L_d {float(out.logs['loss_d'][t]):.8f} / {l_d:.8f}")
    np.testing.assert_allclose(float(out.logs["loss_comoda"][t]), own, rtol=1e-12)
    np.testing.assert_allclose(float(out.logs["loss_d"][t]), l_d, rtol=1e-12)
    np.testing.assert_allclose(float(out.loss[t]), own + l_d, rtol=1e-12)
    assert float(out.update_norm[t]) > 0 and not bool(out.skipped[t])
  assert int(state.opt_state[0].count) == 2 == int(state.method_state["pose"].opt_state[0].count)
  assert int(state.method_state["ring"]["image"]["count"]) == 2


def test_recording_start_has_no_previous_frame(tiny_case):
  """Frame 1 starts a new recording: with latency 1, frames 1 and 2 lack a neighbour in their
  recording (no update, as at a video's start); frame 3 adapts frame 2 from (1, 3) with the
  parameters no step has moved."""
  _, inputs, _, (init, _), _, _, (state, out) = tiny_case
  assert out.loss.tolist()[:3] == [0.0, 0.0, 0.0] and out.update_norm.tolist()[:3] == [0.0] * 3
  with jax.enable_x64(True):
    own, l_d = _expected_latency1_loss(tiny_case, 3, state=init)
    evaluated = _tiny_depth(state.trainable, inputs[3].image)
  np.testing.assert_allclose(float(out.logs["loss_comoda"][3]), float(own), rtol=1e-12)
  np.testing.assert_allclose(float(out.logs["loss_d"][3]), float(l_d), rtol=1e-12)
  np.testing.assert_allclose(out.depth[3], evaluated, rtol=1e-12)
  assert float(out.update_norm[3]) > 0
  assert int(state.opt_state[0].count) == 1 == int(state.method_state["pose"].opt_state[0].count)
  assert int(state.method_state["ring"]["image"]["count"]) == 2


def test_engine_run_is_finite_and_bitwise_reproducible(tiny_case):
  _, _, _, _, ((a_state, a_out), (b_state, b_out)), _, _ = tiny_case
  leaves_a = jax.tree_util.tree_leaves((a_state, a_out))
  leaves_b = jax.tree_util.tree_leaves((b_state, b_out))
  assert len(leaves_a) == len(leaves_b)
  for x, y in zip(leaves_a, leaves_b):
    np.testing.assert_array_equal(x, y)
  assert np.all(np.isfinite(a_out.depth)) and np.all(np.isfinite(a_out.loss))
  assert int(a_state.n_skipped) == 0 and int(a_state.step) == 4


def test_nonfinite_pose_step_skips_both_networks(tiny_case):
  """engine.optax_update's guard over both networks: with a NaN in the pose network, the depth
  network, both Adam states and the pose network stay as they were, and each skip is counted
  (frames 2 and 3; frames 0 and 1 make no update)."""
  _, _, _, _, _, (init, (state, out)), _ = tiny_case
  assert out.skipped.tolist() == [False, False, True, True] and int(state.n_skipped) == 2
  for a, b in zip(jax.tree_util.tree_leaves((state.trainable, state.opt_state,
                                             state.method_state["pose"])),
                  jax.tree_util.tree_leaves((init.trainable, init.opt_state,
                                             init.method_state["pose"]))):
    np.testing.assert_array_equal(a, b)
