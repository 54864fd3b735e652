"""CoTTA (methods/cotta.py) against the PyTorch reference of tests/torch_tta.py.

Reference: CoTTA as its official code runs a step (deepcopy teacher, augmented teacher views
averaged into the pseudo label, student loss, Adam step, EMA over parameters(), stochastic
restore `src * mask + p * (1 - mask)`), with the depth adaptations of methods/cotta.py (L1 on
disparity, flip back; the gate 'spread' with `torch.std`) and PITTA's L_d, written with native
ops on the PyTorch MonoDepth2 of torch_monodepth2 (random weights, converted with
weights_convert.monodepth2). float64 on both sides, 64x96, N = 4 views. The random draws are
the JAX run's own (`sample_augment` and `restore_masks` from the step's keys), passed
explicitly to PyTorch. The teacher starts away from the source (its BN parameters perturbed on
both sides). Checked after one step, with the default gate (the views' mean everywhere) on the
encoder's BatchNorm parameters, and with gate 'spread' at a threshold between two of the frame's
spread values (so that it picks both branches) on every weight and bias as upstream adapts
them (selector all): the loss, CoTTA's own term, L_d, the gate fraction, the evaluated depth (the
pseudo label's), the student after Adam + restore and the EMA teacher; with ld_weight 0 the
loss and the student equal plain CoTTA's. And from the source itself, on a frame under a
shift, the default pseudo label is the augmented mean from the first step (a gate on the
anchor's disagreement with the teacher, used before, never fired there).
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from flax.traverse_util import flatten_dict, unflatten_dict

import adapt_frames
import torch_monodepth2 as tm
import torch_tta
from pitta_jax.adapt import AdaptConfig, StepInput, init_state, make_optimizer, make_step
from pitta_jax.methods import build
from pitta_jax.methods.cotta import CottaConfig, restore_masks, sample_augment
from pitta_jax.methods.depth_refining import DepthRefiningConfig
from pitta_jax.models.registry import network
from weights_convert.monodepth2 import convert_monodepth2, depth_decoder_rules, encoder_rules

H, W = adapt_frames.H, adapt_frames.W
IDS = [11, 12, 13]
LR, N_AUG, RESTORE_P, EMA, WINDOW = 1e-3, 4, 0.2, 0.9, 3
CFG = AdaptConfig(bn_stats="running", seed=3)
CFG_ALL = dataclasses.replace(CFG, selector="all")  # upstream's: every weight and bias


# Flax leaf path ("encoder/layer1_0/bn1/scale") -> (the PyTorch parameter of the reference's
# ModuleDict, "enc.encoder.layer1.0.bn1.weight"; whether it is a conv kernel), from the
# converter's key tables (their own parity tests check them).
TORCH_NAMES = {"/".join(r.flax[1:]): (("enc." if r.flax[1] == "encoder" else "dec.") + r.sources[0],
                                      r.kind == "conv")
               for r in encoder_rules(18) + depth_decoder_rules() if r.flax[0] == "params"}


def _torch_tree(model: torch.nn.ModuleDict, paths) -> dict[str, np.ndarray]:
  """The reference model's parameters at the Flax leaf `paths`, conv kernels as HWIO."""
  params = dict(model.named_parameters())
  out = {}
  for path in paths:
    name, conv = TORCH_NAMES[path]
    a = params[name].detach().double().numpy()
    out[path] = a.transpose(2, 3, 1, 0) if conv else a
  return out


def _reference(enc, dec, threshold, ld_weight, every_param=False):
  ref = torch_tta.CoTTA(copy.deepcopy(enc), copy.deepcopy(dec), LR, EMA, threshold, ld_weight,
                        WINDOW, every_param)
  g = torch.Generator().manual_seed(5)
  with torch.no_grad():  # a teacher away from the source
    for m in ref.ema_model.modules():
      if isinstance(m, torch.nn.BatchNorm2d):
        m.weight.mul_(1 + 0.3 * torch.randn(m.weight.shape, generator=g, dtype=m.weight.dtype))
        m.bias.add_(0.1 * torch.randn(m.bias.shape, generator=g, dtype=m.bias.dtype))
  return ref


def _mcfg(restore_p: float, **kw) -> CottaConfig:
  return CottaConfig(n_augment=N_AUG, ema_decay=EMA, restore_p=restore_p, lr=LR,
                     ld=DepthRefiningConfig(max_instances=4, window=WINDOW), **kw)


def _aug(draws) -> dict:
  return {"order": draws.order, "factors": draws.factors, "sigma": draws.sigma,
          "flip": draws.flip, "noise": draws.noise}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
  root = tmp_path_factory.mktemp("mono")
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  tm.randomize_(enc, 41), tm.randomize_(dec, 42)
  torch.save({**enc.state_dict(), "height": H, "width": W}, root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  _, variables, _ = convert_monodepth2(root / "encoder.pth", root / "depth.pth")
  enc, dec = enc.double(), dec.double()
  frames = adapt_frames.make_frames(1, seed=4)
  return enc, dec, variables, frames, _reference(enc, dec, None, 1.0).ema_model


@pytest.fixture(scope="module")
def step64(case):
  """`_float64_step(case, CFG, RESTORE_P)`: one jitted step (compiled once, on first use) for
  the parity run and the guard test."""
  with jax.enable_x64(True):
    return _float64_step(case, CFG, RESTORE_P)


def _frame(frames, image=None) -> StepInput:
  frame = StepInput(*(jnp.asarray(v[0], jnp.float64 if v.dtype == np.float32 else None)
                      for v in frames))
  return frame if image is None else frame._replace(image=jnp.asarray(image))


def _draws(init, mcfg: CottaConfig):
  """The step's augmentation draws and restore masks (from the engine's per-frame key)."""
  rng = jax.random.fold_in(init.rng, init.step)
  draws = jax.tree_util.tree_map(np.asarray, sample_augment(rng, N_AUG, H, W, mcfg, jnp.float64))
  masks = restore_masks(jax.random.fold_in(rng, 0), init.trainable, RESTORE_P)
  return draws, {k: np.asarray(v) for k, v in flatten_dict(masks, sep="/").items()}


def _run(case, step64, ld_weights):
  """One engine step per ld_weight (one compile), from the perturbed teacher, and its draws."""
  with jax.enable_x64(True):
    step, init, consts, perturbed, mcfg = step64
    init = init.replace(method_state={**init.method_state, "teacher": perturbed})
    draws, masks = _draws(init, mcfg)
    runs = []
    for w in ld_weights:
      s0 = init.replace(method_state={**init.method_state, "ld_weight": jnp.asarray(w, jnp.float64)})
      state, out = step(s0, _frame(case[3]), consts)
      flat = lambda t: {k: np.asarray(v) for k, v in flatten_dict(t, sep="/").items()}
      runs.append((jax.tree_util.tree_map(np.asarray, out), flat(state.trainable),
                   flat(state.method_state["teacher"])))
  return draws, masks, runs


@pytest.fixture(scope="module")
def jax_run(case, step64):
  """The default gate: one engine step with ld_weight 1 and one with 0, and the step's draws."""
  return _run(case, step64, (1.0, 0.0))


@pytest.fixture(scope="module")
def spread_run(case):
  """gate 'spread' at a threshold halfway between the two middle values of the frame's spread
  (the PyTorch teacher's views from the step's draws), adapting every parameter as upstream
  (selector all: Adam, EMA and restore over the encoder's and decoder's weights and biases):
  (threshold, draws, masks, runs)."""
  enc, dec, _, frames, _ = case
  with jax.enable_x64(True):
    draws = _draws(_float64_step(case, CFG, RESTORE_P)[1], _mcfg(RESTORE_P))[0]
  x = torch.from_numpy(frames.image[0].astype(np.float64)).permute(2, 0, 1)[None]
  outs = _reference(enc, dec, None, 1.0).views(x, _aug(draws))
  rel = np.sort((outs.std(0) / outs.mean(0)).numpy().ravel())
  threshold = float(rel[rel.size // 2 - 1] + rel[rel.size // 2]) / 2
  with jax.enable_x64(True):
    step64 = _float64_step(case, CFG_ALL, RESTORE_P, gate="spread", threshold=threshold)
  return (threshold, *_run(case, step64, (1.0,)))


def _torch_step(case, draws, masks, ld_weight, threshold=None):
  """The reference's step with the JAX step's draws and restore `masks` ({Flax path: mask});
  it adapts what the masks cover (every parameter when they reach the decoder)."""
  enc, dec, _, frames, _ = case
  every_param = any(k.startswith("decoder/") for k in masks)
  ref = _reference(enc, dec, threshold, ld_weight, every_param)
  by_name = {TORCH_NAMES[k][0]: m.transpose(3, 2, 0, 1) if TORCH_NAMES[k][1] else m
             for k, m in masks.items()}  # kernels' masks HWIO -> OIHW
  assert set(by_name) == set(ref.trainable)
  result = ref.step(frames.image[0], frames.panoptic[0], IDS, _aug(draws), by_name)
  return result, _torch_tree(ref.model, masks), _torch_tree(ref.ema_model, masks)


def _source(case, paths) -> dict[str, np.ndarray]:
  return _torch_tree(torch.nn.ModuleDict({"enc": case[0], "dec": case[1]}), paths)


def _worst_rel(a: dict, b: dict, ref: dict) -> float:
  """max over leaves of max|a - b| / max|b - ref| (the difference relative to the change)."""
  assert set(a) == set(b)
  return max(float(np.max(np.abs(a[k] - b[k])) / max(np.max(np.abs(b[k] - ref[k])), 1e-300))
             for k in b)


def _check_step(case, draws, masks, run, threshold, gate_range):
  out, student, teacher = run
  (total, own, l_d, pseudo, gate), t_student, t_teacher = _torch_step(case, draws, masks, 1.0,
                                                                      threshold)
  n_restored = sum(int(m.sum()) for m in masks.values())
  print(f"views flipped {draws.flip.tolist()}, orders {draws.order.tolist()}; restored "
        f"{n_restored} of {sum(m.size for m in masks.values())} elements")
  assert 0 < draws.flip.sum() < N_AUG and n_restored > 0
  print(f"loss jax {float(out.loss):.10f} torch {total:.10f}; CoTTA term "
        f"{float(out.logs['loss_cotta']):.10f} / {own:.10f}; L_d {float(out.logs['loss_d']):.6f} / "
        f"{l_d:.6f}; gate fraction {float(out.logs['gate_fraction']):.3f} / {gate:.3f}")
  assert gate_range[0] <= gate <= gate_range[1]
  np.testing.assert_allclose(float(out.logs["gate_fraction"]), gate, rtol=0, atol=0)
  np.testing.assert_allclose(float(out.logs["loss_cotta"]), own, rtol=1e-9)
  np.testing.assert_allclose(float(out.logs["loss_d"]), l_d, rtol=1e-9)
  np.testing.assert_allclose(float(out.loss), total, rtol=1e-9)
  depth = np.asarray(torch_tta.disp_to_depth(torch.from_numpy(pseudo)))
  d = float(np.max(np.abs(out.depth - depth) / depth))
  src = _source(case, masks)
  rs, rt = _worst_rel(student, t_student, src), _worst_rel(teacher, t_teacher, src)
  print(f"evaluated depth (pseudo label) max rel diff {d:.1e}; student after Adam + restore, "
        f"worst max diff / max change {rs:.1e}; EMA teacher {rt:.1e}")
  assert d < 1e-10 and rs < 1e-6 and rt < 1e-6
  # restored elements are exactly the source's
  for k, m in masks.items():
    np.testing.assert_array_equal(student[k][m], src[k][m])


def test_one_step_matches_torch(case, jax_run):
  """The default gate: the pseudo label is the views' mean at every pixel."""
  draws, masks, runs = jax_run
  _check_step(case, draws, masks, runs[0], None, (1.0, 1.0))


def test_one_step_with_the_spread_gate_matches_torch(case, spread_run):
  threshold, draws, masks, runs = spread_run
  print(f"threshold on std / mean of the views: {threshold:.4g}")
  _check_step(case, draws, masks, runs[0], threshold, (0.3, 0.7))


def test_the_augmented_label_acts_from_the_source_on(case, step64):
  """From the source itself (student = teacher = source), the first step's own loss is the
  student's distance to the augmented mean, not 0: under the earlier gate (the anchor's
  disagreement with the teacher) nothing fired there, the label was the student's own
  prediction and the loss 0, and at EMA 0.999 it stayed so for hundreds of frames."""
  with jax.enable_x64(True):
    step, init, consts, _, _ = step64
    _, out = step(init, _frame(case[3]), consts)
  own = float(out.logs["loss_cotta"])
  print(f"first step from the source: CoTTA's own loss {own:.3e}, gate fraction "
        f"{float(out.logs['gate_fraction'])}")
  assert own > 1e-4 and float(out.logs["gate_fraction"]) == 1.0


def test_ld_weight_zero_is_plain_cotta(case, jax_run):
  draws, masks, runs = jax_run
  out0, student0, _ = runs[1]
  (total, own, _, _, _), t_student, _ = _torch_step(case, draws, masks, 0.0)
  print(f"ld_weight 0: jax {float(out0.loss):.10f} torch CoTTA {total:.10f}; ld_weight 1 minus 0 "
        f"{float(runs[0][0].loss) - float(out0.loss):.6f}, L_d {float(runs[0][0].logs['loss_d']):.6f}")
  np.testing.assert_allclose(float(out0.loss), own, rtol=1e-9)
  np.testing.assert_allclose(float(runs[0][0].loss) - float(out0.loss),
                             float(runs[0][0].logs["loss_d"]), rtol=1e-9)
  rs = _worst_rel(student0, t_student, _source(case, masks))
  print(f"student after one ld_weight-0 step: worst max diff / max change {rs:.1e}")
  assert rs < 1e-6


def _float64_step(case, cfg: AdaptConfig, restore_p: float, **mcfg_kw):
  """(a jitted float64 engine step of CoTTA under `cfg` with `restore_p` and the CottaConfig
  fields `mcfg_kw`, its initial state, its constants, the reference's teacher (BN perturbed)
  as a tree of the adapted parameters, the CottaConfig); call it under `jax.enable_x64(True)`."""
  _, _, variables, _, ema = case
  mcfg = _mcfg(restore_p, **mcfg_kw)
  v64 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), variables)
  model, method = network("monodepth2", {"num_layers": 18}), build("cotta", mcfg)
  tx = make_optimizer(cfg, method)
  step = jax.jit(make_step(model, method, cfg, tx))
  init, consts = init_state(v64, method, cfg, tx, model)
  paths = flatten_dict(init.trainable, sep="/")
  perturbed = unflatten_dict({k: jnp.asarray(v) for k, v in _torch_tree(ema, paths).items()},
                             sep="/")
  return step, init, consts, perturbed, mcfg


def test_reset_copies_the_teacher_from_the_source_as_upstream(case):
  """`reset_every` (upstream's `reset()`): the student, its optimiser and the teacher start
  again from the source. A step that resets first, then takes its update (no restore: p = 0),
  leaves teacher = EMA * source + (1 - EMA) * student; without the reset the teacher's own
  (perturbed) values stay in that average."""
  frames = case[3]
  with jax.enable_x64(True):
    step, init, consts, perturbed, _ = _float64_step(
        case, dataclasses.replace(CFG, reset_every=1), restore_p=0.0)
    init = init.replace(step=jnp.asarray(1, init.step.dtype),  # step 1: reset_every 1 resets
                        method_state={**init.method_state, "teacher": perturbed})
    state, _ = step(init, _frame(frames), consts)
  flat = lambda t: flatten_dict(jax.tree_util.tree_map(np.asarray, t)["encoder"], sep="/")
  source, student, got = flat(init.source), flat(state.trainable), flat(
      state.method_state["teacher"])
  kept = flat(perturbed)
  assert any(not np.allclose(kept[k], source[k]) for k in source)  # the reset has work to do
  for k in source:
    np.testing.assert_allclose(got[k], EMA * source[k] + (1 - EMA) * student[k], rtol=1e-12,
                               atol=1e-15, err_msg=k)


def test_nonfinite_step_keeps_the_student_but_not_the_teacher_or_the_restore(case, step64):
  """The non-finite guard (engine.optax_update's semantics, here on the raveled vector): a
  frame with a NaN pixel makes the loss NaN, so the student and Adam's state keep their values
  and n_skipped counts the frame; the teacher's EMA and the stochastic restore still run, as
  upstream's order has them after the optimiser step. Checked against the arithmetic of both
  (teacher = EMA t0 + (1 - EMA) s0; student = source where the step's mask restores, else s0)
  with the mask from `restore_masks` and the step's key, a student away from the source."""
  frames = case[3]
  with jax.enable_x64(True):
    step, init, consts, perturbed, _ = step64
    init = init.replace(trainable=perturbed)  # student != source; teacher = source
    image = np.array(frames.image[0], np.float64)
    image[3, 5, 1] = np.nan
    frame = _frame(frames, image)
    masks = restore_masks(jax.random.fold_in(jax.random.fold_in(init.rng, init.step), 0),
                          init.trainable, RESTORE_P)
    state, out = step(init, frame, consts)
  flat = lambda t: flatten_dict(jax.tree_util.tree_map(np.asarray, t)["encoder"], sep="/")
  assert bool(out.skipped) and int(state.n_skipped) == 1 and float(out.update_norm) == 0.0
  source, s0, t0 = flat(init.source), flat(perturbed), flat(init.method_state["teacher"])
  student, got_teacher, mask = flat(state.trainable), flat(state.method_state["teacher"]), flat(
      masks)
  assert 0 < sum(int(m.sum()) for m in mask.values()) < sum(m.size for m in mask.values())
  for k in source:
    np.testing.assert_array_equal(student[k], np.where(mask[k], source[k], s0[k]), err_msg=k)
    np.testing.assert_allclose(got_teacher[k], EMA * t0[k] + (1 - EMA) * s0[k], rtol=1e-12,
                               atol=1e-15, err_msg=k)
  for a, b in zip(jax.tree_util.tree_leaves(state.opt_state),
                  jax.tree_util.tree_leaves(init.opt_state)):
    np.testing.assert_array_equal(a, b)


def _near(value: float, want: float, sd: float, n: int, what: str) -> None:
  """`value`, a mean of n i.i.d. samples of standard deviation sd, within 5 standard errors."""
  se = sd / np.sqrt(n)
  assert abs(value - want) < 5 * se, f"{what}: {value} against {want} (standard error {se:.2g})"


def test_augmentation_draws_follow_upstream_laws():
  # Reference: the laws of upstream's draws (get_tta_transforms with soft=False; torchvision's
  # samplers): each jitter factor uniform in [1 - b, 1 + b] with its own b, the four jitters in a
  # uniformly random order per view (each of the 24 orders equally likely), blur sigma uniform in
  # [min, max], a flip with probability flip_p, noise N(0, noise_std^2) per value. Moments
  # within 5 standard errors over 20000 views. Every jitter gets a different b, so that a spread
  # in the wrong column fails; the parity tests replay these draws and cannot see their law.
  cfg = CottaConfig(brightness=0.1, contrast=0.2, saturation=0.35, gamma=0.5, flip_p=0.3,
                    noise_std=0.02, blur_sigma_min=0.1, blur_sigma_max=0.4)
  n = 20000
  d = jax.tree_util.tree_map(np.asarray, sample_augment(jax.random.PRNGKey(3), n, 2, 3, cfg))
  for k, (name, b) in enumerate(zip(("brightness", "contrast", "saturation", "gamma"),
                                    (cfg.brightness, cfg.contrast, cfg.saturation, cfg.gamma))):
    x = d.factors[:, k].astype(np.float64) - 1.0  # uniform in [-b, b]
    assert -b <= x.min() < -0.99 * b and 0.99 * b < x.max() <= b, name
    _near(x.mean(), 0.0, b / np.sqrt(3), n, f"{name} mean")
    _near((x ** 2).mean(), b ** 2 / 3, b ** 2 * np.sqrt(4 / 45), n, f"{name} variance")
  np.testing.assert_array_equal(np.sort(d.order, axis=1), np.tile(np.arange(4), (n, 1)))
  orders, counts = np.unique(d.order, axis=0, return_counts=True)
  assert len(orders) == 24
  p = 1 / 24
  assert np.all(np.abs(counts - n * p) < 5 * np.sqrt(n * p * (1 - p))), counts
  s = d.sigma.astype(np.float64)
  assert cfg.blur_sigma_min <= s.min() and s.max() <= cfg.blur_sigma_max
  _near(s.mean(), 0.25, 0.3 / np.sqrt(12), n, "blur sigma mean")
  _near(d.flip.mean(), cfg.flip_p, np.sqrt(cfg.flip_p * (1 - cfg.flip_p)), n, "flip rate")
  z = d.noise.astype(np.float64).ravel() / cfg.noise_std  # N(0, 1) if the std is noise_std
  _near(z.mean(), 0.0, 1.0, z.size, "noise mean")
  _near((z ** 2).mean(), 1.0, np.sqrt(2.0), z.size, "noise variance")


def test_restore_masks_are_bernoulli_p_per_element():
  # Reference: upstream's restore, `torch.rand(p.shape) < rst` per parameter tensor: each
  # element restored with probability p, independently, in every leaf. p = 0.2 (a draw of
  # Bernoulli(1 - p) fails), two leaves of one shape (one pattern repeated across leaves fails).
  tree = {"a": jnp.zeros((40, 250)), "b": {"c": jnp.zeros((40, 250)), "d": jnp.zeros((7,))}}
  masks = jax.tree_util.tree_map(np.asarray, restore_masks(jax.random.PRNGKey(0), tree, 0.2))
  assert jax.tree_util.tree_structure(masks) == jax.tree_util.tree_structure(tree)
  for leaf in (masks["a"], masks["b"]["c"]):
    assert leaf.dtype == bool and leaf.shape == (40, 250)
    _near(leaf.mean(), 0.2, 0.4, leaf.size, "restore fraction")
  assert masks["b"]["d"].shape == (7,)
  both = (masks["a"] & masks["b"]["c"]).mean()  # independent leaves: 0.2 * 0.2
  _near(both, 0.04, np.sqrt(0.04 * 0.96), masks["a"].size, "joint restore fraction")


def test_views_are_clipped_after_the_noise():
  """Upstream's last augmentation clips to [0, 1] after adding the noise: a white image with
  noise +0.01 stays 1, a black one with -0.01 stays 0, a grey 0.5 becomes 0.51 (unit jitter
  factors, a blur of a constant image, no flip). Hand values."""
  from pitta_jax.methods.cotta import AugParams, augment_views
  n, h, w = 3, 4, 5
  images = (jnp.ones((h, w, 3)), jnp.zeros((h, w, 3)), jnp.full((h, w, 3), 0.5))
  noises = (0.01, -0.01, 0.01)
  for image, noise, want in zip(images, noises, (1.0, 0.0, 0.51)):
    params = AugParams(order=jnp.tile(jnp.arange(4), (n, 1)), factors=jnp.ones((n, 4)),
                       sigma=jnp.full((n,), 0.1), flip=jnp.zeros((n,), bool),
                       noise=jnp.full((n, h, w, 3), noise))
    np.testing.assert_allclose(np.asarray(augment_views(image, params)), want, atol=1e-6)
