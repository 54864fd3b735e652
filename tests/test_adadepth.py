"""Ada-Depth (methods/adadepth.py) against a PyTorch Ada-Depth written here from its official code.

Reference (`TorchAdaDepth`): Malefikus/ada-depth `adaptation.py`, `Adapt.process_batch`, on the
PyTorch MonoDepth2 of torch_monodepth2 (random weights) and the MonoDepth2 loss of torch_sfm, the
way upstream writes it: `deepcopy` for the reference and EMA models, the self-supervised branch
(depth + pose encoder + pose decoder) stepped first with its own `torch.optim.Adam`, then the
student's forward, the reference, EMA and updated branch predictions under `no_grad`,
`augment_pseudo` (boolean masks, `torch.median`, `torch.mul`, `torch.clamp`), `compute_losses`
(SILog on `depth[mask]`), the student's Adam step, `update_ema_variables` over `parameters()`,
and the student's prediction after its step. Reduced as methods/adadepth.py documents: every
network in eval mode, the previous frame as the only source frame, depths times the factor to
metres (given to the JAX step as the weights' factor, `resources[METRIC_FACTOR]`).
PITTA's L_d on the student's depth with torch_tta's native-op implementation.

float64 on both sides (Adam's first step is lr * g / (|g| + eps): it needs exact small
gradients), 64x96. The JAX variables come from the torch state dicts through the MonoDepth2
converter's key table. The EMA teacher starts away from the source (its encoder BN parameters
perturbed on both sides); tau is set at the median of the frame's (R - E)^2 / R, so both labels
keep and reject pixels. Checked after one step on a frame with a previous frame: the loss and
its terms, U's loss, both gradient norms, the label fractions and U's scale, the evaluated depth
(the student after its step: `Method.report_after_update`), and the student, the teacher and
U (depth and pose networks) after the step; with ld_weight 0 the loss and the student equal the
original method's, and ld_weight 1 minus 0 is L_d of the same depth. Then a short run on
synthetic frames with intrinsics is finite and bitwise reproducible (the compiled step of the
parity test, called frame by frame: a second compile would double the file's time), and the
tests of U's commits start from that run's states.
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
import torch.nn as nn
from flax.traverse_util import flatten_dict, unflatten_dict

import adapt_frames
import torch_monodepth2 as tm
import torch_sfm
import torch_tta
from xla_options import RUN_OPTIMIZED
from pitta_jax.adapt import AdaptConfig, StepInput, init_state, make_optimizer, make_step
from pitta_jax.adapt.inputs import step_input
from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
from pitta_jax.methods import adadepth
from pitta_jax.methods.base import INPUT_SIZE, METRIC_FACTOR, POSE, PoseNet, ring_push
from pitta_jax.methods.depth_refining import DepthRefiningConfig
from pitta_jax.models.pose import PoseNet as PoseModule
from pitta_jax.models.registry import network
from weights_convert import rules as R
from weights_convert.monodepth2 import depth_decoder_rules, encoder_rules, pose_decoder_rules

torch.set_num_threads(2)

H, W = adapt_frames.H, adapt_frames.W
IDS = [11, 12, 13]      # adapt_frames' dynamic instances (two cars, a person)
LR, EMA, WINDOW, SCALES = 1e-3, 0.9, 3, (0, 1, 2, 3)
CFG = AdaptConfig(bn_stats="running", selector="all", seed=3)  # upstream adapts every parameter
K = np.array([[0.58 * W, 0, 0.5 * W], [0, 1.92 * H, 0.5 * H], [0, 0, 1]])  # KITTI-like


# ----------------------------------------------------------------------------- the reference


class TorchAdaDepth:
  """`Adapt.process_batch` for frame ids (0, -1), batch 1, eval mode, one depth network class."""

  MIN_DEPTH, MAX_DEPTH = 1e-3, 80   # upstream's Adapt constants

  def __init__(self, enc, dec, penc, pdec, teacher, lr, ema, thres, depth_scale, ld_weight, s):
    self.models = {"encoder": enc, "depth": dec}
    self.models_ema = teacher
    self.models_ref = copy.deepcopy(self.models)
    self.reg_models = {"encoder": copy.deepcopy(enc), "depth": copy.deepcopy(dec),
                       "pose_encoder": penc, "pose": pdec}
    params = [p for m in self.models.values() for n, p in m.named_parameters()
              if not n.startswith("encoder.fc")]
    reg_params = [p for m in self.reg_models.values() for n, p in m.named_parameters()
                  if not n.startswith("encoder.fc")]
    self.model_optimizer = torch.optim.Adam(params, lr)
    self.reg_model_optimizer = torch.optim.Adam(reg_params, lr)
    self.sfm = torch_sfm.Monodepth2Loss(1, H, W, SCALES, dtype=torch.float64)
    self.ema, self.thres, self.scale, self.ld_weight, self.s = ema, thres, depth_scale, ld_weight, s

  @staticmethod
  def depth(models, x):
    return torch_sfm.disp_to_depth(models["depth"](models["encoder"](x))[("disp", 0)], 0.1, 100)[1]

  def augment_pseudo(self, reg_depth_sup, reg_depth_unsup, depth_uncrop_ref):
    """Upstream's augment_pseudo (non-KITTI): reg_depth_sup = R, depth_uncrop_ref = E."""
    mask0 = depth_uncrop_ref > self.MIN_DEPTH
    mask0[:, :, :int(0.3 * depth_uncrop_ref.shape[2]), :] = False
    scale_factor = torch.median(depth_uncrop_ref[mask0]) / torch.median(reg_depth_unsup[mask0])
    mask = (((depth_uncrop_ref - reg_depth_unsup * scale_factor) ** 2) / depth_uncrop_ref) < self.thres
    reg_depth_unsup = torch.mul(mask.float(), reg_depth_unsup) * scale_factor
    reg_depth_unsup = torch.clamp(reg_depth_unsup, min=self.MIN_DEPTH, max=self.MAX_DEPTH)
    mask = (((reg_depth_sup - depth_uncrop_ref) ** 2) / reg_depth_sup) < self.thres
    mask = mask * mask0
    reg_depth_sup = torch.mul(mask.float(), depth_uncrop_ref)
    reg_depth_sup = torch.clamp(reg_depth_sup, min=self.MIN_DEPTH, max=self.MAX_DEPTH)
    return reg_depth_sup, reg_depth_unsup, scale_factor

  @staticmethod
  def silog(depth, pseudo):
    mask = pseudo > 1.0
    d = torch.log(depth[mask]) - torch.log(pseudo[mask])
    return torch.sqrt((d ** 2).mean() - 0.85 * (d.mean() ** 2)) * 10.0, int(mask.sum())

  def step(self, image, previous, noise, panoptic):
    for m in [*self.models.values(), *self.reg_models.values(), *self.models_ref.values(),
              *self.models_ema.values()]:
      m.eval()
    x, prev = _image(image), _image(previous)
    # 1. the self-supervised branch
    feats = self.reg_models["encoder"](x)
    disps = self.reg_models["depth"](feats)
    axisangle, translation = self.reg_models["pose"](
        [self.reg_models["pose_encoder"](torch.cat([prev, x], 1))])
    T = torch_sfm.transformation_from_parameters(axisangle[:, 0], translation[:, 0], invert=True)
    K4 = torch.eye(4, dtype=torch.float64)
    K4[:3, :3] = torch.from_numpy(K)
    loss_u = self.sfm(x, [prev], [disps[("disp", s)] for s in SCALES], K4[None],
                      torch.linalg.inv(K4)[None], [T], torch.from_numpy(np.array(noise)))[0]
    self.reg_model_optimizer.zero_grad()
    loss_u.backward()
    u_gnorm = _grad_norm(self.reg_model_optimizer)
    self.reg_model_optimizer.step()
    # 2. pseudo labels (metres)
    depth = self.depth(self.models, x)
    with torch.no_grad():
      unsup = self.depth(self.reg_models, x)
      ref = self.depth(self.models_ref, x)
      ema = self.depth(self.models_ema, x)
      p_sup, p_unsup, u_scale = self.augment_pseudo(self.scale * ref, self.scale * unsup,
                                                    self.scale * ema)
    # 3. the student's step
    l_sup, n_sup = self.silog(self.scale * depth, p_sup)
    l_unsup, n_unsup = self.silog(self.scale * depth, p_unsup)
    loss_ada = l_sup + l_unsup
    l_d = torch_tta.depth_refining(depth[0, 0], panoptic, IDS, self.s)
    total = loss_ada + self.ld_weight * l_d
    self.model_optimizer.zero_grad()
    total.backward()
    gnorm = _grad_norm(self.model_optimizer)
    self.model_optimizer.step()
    # 4. the EMA teacher
    with torch.no_grad():
      for key in ("encoder", "depth"):
        for ema_param, param in zip(self.models_ema[key].parameters(),
                                    self.models[key].parameters()):
          ema_param.data.mul_(self.ema).add_(param.data, alpha=1 - self.ema)
    # 5. the evaluated depth: the student after its step
    with torch.no_grad():
      after = self.depth(self.models, x)[0, 0].numpy()
    pixels = H * W
    return {"loss": total.item(), "loss_adadepth": loss_ada.item(), "loss_sup": l_sup.item(),
            "loss_unsup": l_unsup.item(), "loss_d": l_d.item(), "loss_u": loss_u.item(),
            "grad_norm": gnorm, "u_grad_norm": u_gnorm, "u_scale": float(u_scale),
            "keep_sup": n_sup / pixels, "keep_unsup": n_unsup / pixels, "after": after,
            "before": depth.detach()[0, 0].numpy()}


def _image(x: np.ndarray) -> torch.Tensor:
  return torch.from_numpy(np.asarray(x, np.float64)).permute(2, 0, 1)[None]


def _grad_norm(opt) -> float:
  return float(torch.sqrt(sum((p.grad.double() ** 2).sum() for g in opt.param_groups
                              for p in g["params"] if p.grad is not None)))


# ----------------------------------------------------------------------------- torch <-> Flax


DEPTH_RULES = encoder_rules(18) + depth_decoder_rules()
POSE_RULES = encoder_rules(18) + pose_decoder_rules()


def flat64(modules, rules) -> dict[str, np.ndarray]:
  """The modules' state in Flax layout, float64, keyed by `/`-joined path (collection first)."""
  state = {}
  for m in modules:
    state.update(m.state_dict())
  return {"/".join(r.flax): R.to_flax(state[r.sources[0]].detach().double().numpy(), r.kind)
          for r in rules}


def params_of(flat: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
  return {k[len("params/"):]: v for k, v in flat.items() if k.startswith("params/")}


def variables64(modules, rules) -> dict:
  return unflatten_dict({tuple(k.split("/")): jnp.asarray(v)
                         for k, v in flat64(modules, rules).items()})


def _flat(tree) -> dict[str, np.ndarray]:
  return {k: np.asarray(v) for k, v in flatten_dict(tree, sep="/").items()}


def _worst_rel(ours: dict, ref: dict, start: dict) -> float:
  """max over leaves of max|ours - ref| / max|ref - start| (the difference relative to the
  change), over the leaves that change."""
  assert set(ours) == set(ref)
  worst = 0.0
  for k in ref:
    change = float(np.max(np.abs(ref[k] - start[k])))
    if change > 0:
      worst = max(worst, float(np.max(np.abs(ours[k] - ref[k]))) / change)
    else:
      np.testing.assert_array_equal(ours[k], ref[k])
  return worst


# ----------------------------------------------------------------------------- fixtures


def _teacher(enc, dec):
  """A teacher away from the source: encoder BN gamma and beta perturbed."""
  g = torch.Generator().manual_seed(5)
  teacher = {"encoder": copy.deepcopy(enc), "depth": copy.deepcopy(dec)}
  with torch.no_grad():
    for m in teacher["encoder"].modules():
      if isinstance(m, nn.BatchNorm2d):
        m.weight.mul_(1 + 0.3 * torch.randn(m.weight.shape, generator=g, dtype=m.weight.dtype))
        m.bias.add_(0.1 * torch.randn(m.bias.shape, generator=g, dtype=m.bias.dtype))
  return teacher


@pytest.fixture(scope="module")
def case():
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  penc, pdec = tm.ResnetEncoder(18, num_input_images=2), tm.PoseDecoder(tm.num_ch_enc(18), 1, 2)
  for seed, m in enumerate((enc, dec, penc, pdec)):
    tm.randomize_(m, 61 + seed)
    m.double()
  frames = adapt_frames.make_frames(2, seed=4)
  teacher = _teacher(enc, dec)
  # depth_scale: the teacher's median depth becomes 3 m; tau: the median of (R - E)^2 / R
  with torch.no_grad():
    x = _image(frames.image[1])
    ref = TorchAdaDepth.depth({"encoder": enc.eval(), "depth": dec.eval()}, x)[0, 0].numpy()
    ema = TorchAdaDepth.depth({k: m.eval() for k, m in teacher.items()}, x)[0, 0].numpy()
  scale = float(3.0 / np.median(ema))
  stat = (scale * ref - scale * ema) ** 2 / (scale * ref)
  threshold = float(np.median(stat[int(0.3 * H):]))
  return {"nets": (enc, dec, penc, pdec), "teacher": teacher, "frames": frames,
          "scale": scale, "threshold": threshold}


def _method(case) -> adadepth.AdadepthConfig:
  return adadepth.AdadepthConfig(lr=LR, ema_decay=EMA, threshold=case["threshold"],
                                 ld=DepthRefiningConfig(max_instances=4, window=WINDOW))


def _frame(frames, t: int) -> StepInput:
  """Frame t as the compiled step sees it, float64, with the intrinsics K."""
  f = StepInput(*(np.asarray(v[t]) for v in frames))
  f = f._replace(intrinsics=K, has_intrinsics=np.array(True))
  return StepInput(*(jnp.asarray(v, jnp.float64 if v.dtype.kind == "f" else None) for v in f))


@pytest.fixture(scope="module")
def jax_run(case):
  """The compiled float64 step, its initial state (teacher set, the previous frame in the ring)
  and the step with ld_weight 1 and 0."""
  enc, dec, penc, pdec = case["nets"]
  with jax.enable_x64(True):
    model = network("monodepth2", {"num_layers": 18})
    method = adadepth.build(_method(case))
    tx = make_optimizer(CFG, method)
    step = jax.jit(make_step(model, method, CFG, tx), compiler_options=RUN_OPTIMIZED)
    pose = PoseNet(PoseModule(18), variables64([penc, pdec], POSE_RULES))
    fresh, consts = init_state(variables64([enc, dec], DEPTH_RULES), method, CFG, tx, model,
                               {POSE: pose, INPUT_SIZE: (H, W), METRIC_FACTOR: case["scale"]})
    teacher = params_of(flat64(case["teacher"].values(), DEPTH_RULES))
    ms = fresh.method_state
    init = fresh.replace(method_state={
        **ms, "teacher": unflatten_dict({tuple(k.split("/")): jnp.asarray(teacher[k])
                                         for k in _flat(fresh.trainable)}),
        "frames": ring_push(ms["frames"], jnp.asarray(case["frames"].image[0], jnp.float64))})
    frame = _frame(case["frames"], 1)
    rng = jax.random.fold_in(init.rng, init.step)           # the engine's per-frame key
    noise = np.asarray(jax.random.normal(rng, (len(SCALES), 1, 1, H, W), jnp.float64))
    runs = []
    for w in (1.0, 0.0):
      s0 = init.replace(method_state={**init.method_state, "ld_weight": jnp.asarray(w, jnp.float64)})
      state, out = step(s0, frame, consts)
      runs.append((jax.tree_util.tree_map(np.asarray, out), _flat(state.trainable),
                   _flat(state.method_state["teacher"]),
                   _flat(state.method_state["u"].params), int(state.n_skipped)))
  return {"step": step, "fresh": fresh, "consts": consts, "noise": noise, "runs": runs}


def _torch_step(case, noise, ld_weight):
  enc, dec, penc, pdec = (copy.deepcopy(m) for m in case["nets"])
  ref = TorchAdaDepth(enc, dec, penc, pdec, copy.deepcopy(case["teacher"]), LR, EMA,
                      case["threshold"], case["scale"], ld_weight, WINDOW)
  frames = case["frames"]
  result = ref.step(frames.image[1], frames.image[0], noise, frames.panoptic[1])
  student = params_of(flat64([enc, dec], DEPTH_RULES))
  teacher = params_of(flat64(ref.models_ema.values(), DEPTH_RULES))
  u = {**{f"depth/{k}": v for k, v in params_of(
          flat64([ref.reg_models["encoder"], ref.reg_models["depth"]], DEPTH_RULES)).items()},
       **{f"pose/{k}": v for k, v in params_of(flat64([penc, pdec], POSE_RULES)).items()}}
  return result, student, teacher, u


# ----------------------------------------------------------------------------- tests


def test_one_step_matches_torch(case, jax_run):
  out, student, teacher, u, skipped = jax_run["runs"][0]
  ref, t_student, t_teacher, t_u = _torch_step(case, jax_run["noise"], 1.0)
  assert skipped == 0 and float(out.logs["u_updated"]) == 1.0
  print(f"tau {case['threshold']:.4g}, depth_scale {case['scale']:.4g}")
  for key in ("loss", "loss_adadepth", "loss_sup", "loss_unsup", "loss_d", "loss_u",
              "u_grad_norm", "u_scale", "keep_sup", "keep_unsup"):
    ours = float(out.loss) if key == "loss" else float(out.logs[key])
    print(f"{key}: jax {ours:.12g} torch {ref[key]:.12g} rel diff "
          f"{abs(ours - ref[key]) / abs(ref[key]):.1e}")
    np.testing.assert_allclose(ours, ref[key], rtol=1e-9)
  print(f"grad_norm: jax {float(out.grad_norm):.12g} torch {ref['grad_norm']:.12g}")
  np.testing.assert_allclose(float(out.grad_norm), ref["grad_norm"], rtol=1e-9)
  # both labels keep and reject pixels
  assert 0.1 < ref["keep_sup"] < 0.7 and 0.1 < ref["keep_unsup"] < 0.9
  # the evaluated depth is the student's after its step, not before
  d_after = float(np.max(np.abs(out.depth - ref["after"]) / ref["after"]))
  d_before = float(np.max(np.abs(out.depth - ref["before"]) / ref["before"]))
  print(f"evaluated depth vs torch's student after its step: max rel diff {d_after:.1e} "
        f"(vs before the step: {d_before:.1e})")
  assert d_after < 1e-10 and d_before > 1e-6
  start = params_of(flat64(case["nets"][:2], DEPTH_RULES))
  u_start = {**{f"depth/{k}": v for k, v in start.items()},
             **{f"pose/{k}": v for k, v in params_of(flat64(case["nets"][2:], POSE_RULES)).items()}}
  t_start = params_of(flat64(case["teacher"].values(), DEPTH_RULES))
  rs = _worst_rel(student, t_student, start)
  rt = _worst_rel(teacher, t_teacher, t_start)
  ru = _worst_rel(u, t_u, u_start)
  print(f"after the step, worst max diff / max change: student {rs:.1e}, EMA teacher {rt:.1e}, "
        f"branch U (depth + pose) {ru:.1e}")
  assert rs < 1e-6 and rt < 1e-6 and ru < 1e-6


def test_ld_weight_zero_is_plain_adadepth(case, jax_run):
  out1, _, _, _, _ = jax_run["runs"][0]
  out0, student0, _, _, _ = jax_run["runs"][1]
  ref, t_student, _, _ = _torch_step(case, jax_run["noise"], 0.0)
  # L_d of the same (pre-update) student depth, by torch_tta's native-op eq. 8
  l_d = float(torch_tta.depth_refining(torch.from_numpy(ref["before"]),
                                       case["frames"].panoptic[1], IDS, WINDOW))
  diff = float(out1.loss) - float(out0.loss)
  print(f"ld_weight 0: jax {float(out0.loss):.12g} torch Ada-Depth {ref['loss']:.12g}; "
        f"ld_weight 1 minus 0 {diff:.10g}, L_d of the same depth (torch) {l_d:.10g}")
  np.testing.assert_allclose(float(out0.loss), ref["loss"], rtol=1e-9)
  np.testing.assert_allclose(float(out0.loss), ref["loss_adadepth"], rtol=1e-9)
  np.testing.assert_allclose(diff, l_d, rtol=1e-9)
  assert l_d > 0
  rs = _worst_rel(student0, t_student, params_of(flat64(case["nets"][:2], DEPTH_RULES)))
  print(f"student after one ld_weight-0 step: worst max diff / max change {rs:.1e}")
  assert rs < 1e-6


def _synthetic(n: int) -> list[StepInput]:
  """The first n synthetic frames (seed 2, with intrinsics) as the float64 step takes them."""
  frames = [step_input(f, H, W, adapt_frames.S) for f in generate_sequence(
      SyntheticConfig(height=H, width=W, num_frames=3, seed=2))][:n]
  assert all(bool(f.has_intrinsics) for f in frames)
  with jax.enable_x64(True):
    return [StepInput(*(jnp.asarray(v, jnp.float64 if v.dtype.kind == "f" else None) for v in f))
            for f in frames]


def _run(jax_run, frames: list[StepInput]) -> tuple[list, list]:
  """The step over `frames` from the fresh state: the state and the output after each frame."""
  states, outs, state = [], [], jax_run["fresh"]
  with jax.enable_x64(True):
    for f in frames:
      state, out = jax_run["step"](state, f, jax_run["consts"])
      states.append(state)
      outs.append(jax.tree_util.tree_map(np.asarray, out))
  return states, outs


@pytest.fixture(scope="module")
def synthetic_run(jax_run):
  """Two synthetic frames from the fresh state (empty ring, S = E = R): the state after the
  first, U's parameters after the second, the outputs and the whole final state as NumPy. The
  tests below start from it rather than stepping those frames again (each float64 step takes
  seconds)."""
  states, outs = _run(jax_run, _synthetic(2))
  return {"first": states[0], "u_second": _flat(states[1].method_state["u"].params),
          "outs": outs, "final": jax.tree_util.tree_map(np.asarray, states[1])}


def test_run_is_finite_and_reproducible(jax_run, synthetic_run):
  """Two synthetic frames with intrinsics, from the fresh state; the second frame (a previous
  frame in the ring: every branch of the step runs) once more from the state after the first,
  through the same compiled step: the same bits (each float64 step takes seconds here)."""
  outs_a, state_a = synthetic_run["outs"], synthetic_run["final"]
  with jax.enable_x64(True):
    state_b, out_b = jax_run["step"](synthetic_run["first"], _synthetic(2)[1], jax_run["consts"])
  state_b, out_b = jax.tree_util.tree_map(np.asarray, (state_b, out_b))
  updated = [float(o.logs["u_updated"]) for o in outs_a]
  logs = {k: [round(float(o.logs[k]), 4) for o in outs_a]
          for k in ("loss_sup", "keep_sup", "loss_unsup", "keep_unsup", "loss_u")}
  print(f"losses {[round(float(o.loss), 4) for o in outs_a]}, U updated {updated}, {logs}")
  assert updated == [0.0, 1.0]   # no previous frame for the first one
  # first frame: S = E = R, so SILog(S, P_S) = 0 where P_S keeps pixels, with a zero (not NaN)
  # gradient: no step is skipped
  assert logs["keep_sup"][0] > 0.3 and logs["loss_sup"][0] == 0.0
  assert int(state_a.n_skipped) == 0
  for o in outs_a:
    assert all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(o))
  for a, b in zip(jax.tree_util.tree_leaves((state_a, outs_a[1])),
                  jax.tree_util.tree_leaves((state_b, out_b))):
    np.testing.assert_array_equal(a, b)


def test_recording_start_has_no_previous_frame(jax_run, synthetic_run):
  """A frame that starts a new recording is a first frame for U (upstream starts each video at
  its second frame): U keeps its weights there, and the next frame pairs with it."""
  f0, f1, f2 = _synthetic(3)
  f1 = f1._replace(starts_recording=jnp.asarray(np.array(True)))
  step, consts = jax_run["step"], jax_run["consts"]
  state = synthetic_run["first"]                    # after frame 0
  u0 = _flat(state.method_state["u"].params)
  updated = [float(synthetic_run["outs"][0].logs["u_updated"])]
  with jax.enable_x64(True):
    state, out = step(state, f1, consts)
    updated.append(float(out.logs["u_updated"]))
    u1 = _flat(state.method_state["u"].params)
    state, out = step(state, f2, consts)
    updated.append(float(out.logs["u_updated"]))
  assert updated == [0.0, 0.0, 1.0]
  for k, v in u0.items():                   # frame 1 left U as frame 0 did (no step at either)
    np.testing.assert_array_equal(u1[k], v)
  ring = state.method_state["frames"]
  assert int(ring["count"]) == 1
  np.testing.assert_array_equal(np.asarray(ring["items"][0]), np.asarray(f2.image))


def test_u_keeps_its_weights_when_the_students_step_is_rejected(jax_run, synthetic_run):
  """A frame whose student step is rejected (S's parameters NaN here) leaves U as it was,
  although U's own step on the frame was finite: U is committed only with S's step (the same
  frame with a finite S moves U: `synthetic_run`'s second frame)."""
  _, f1 = _synthetic(2)
  state = synthetic_run["first"]                    # frame 0: the ring holds it now
  before = _flat(state.method_state["u"].params)
  poisoned = state.replace(trainable=jax.tree_util.tree_map(
      lambda x: jnp.full_like(x, jnp.nan), state.trainable))
  with jax.enable_x64(True):
    after, out = jax_run["step"](poisoned, f1, jax_run["consts"])
  assert bool(out.skipped) and float(out.logs["u_updated"]) == 1.0
  for k, v in _flat(after.method_state["u"].params).items():
    np.testing.assert_array_equal(v, before[k])
  assert any(not np.array_equal(v, before[k]) for k, v in synthetic_run["u_second"].items())


def test_lower_median_is_torch_median_of_the_masked_values():
  """Hand cases and random ones against torch.median(x[mask]) (the lower middle value of an
  even count), with ties and a NaN inside the mask (torch: NaN; the sort skipped it) or only
  outside it (no effect); an empty mask gives NaN."""
  r = np.random.default_rng(0)
  cases = [(np.array([[1.0, np.nan], [3.0, 2.0]]), np.ones((2, 2), bool)),
           (np.array([[1.0, np.nan], [3.0, 2.0]]), np.array([[True, False], [True, True]]))]
  for _ in range(20):
    x = r.integers(0, 4, (3, 5)).astype(np.float64)  # ties
    x[r.random((3, 5)) < 0.1] = np.nan
    cases.append((x, r.random((3, 5)) < 0.6))
  for _ in range(10):  # float32 maps of signed values with infinities, as the step has them
    x = (r.standard_normal((24, 40)) * 10.0 ** r.integers(-3, 4, (24, 40))).astype(np.float32)
    x[r.random((24, 40)) < 0.05] = np.inf
    x[r.random((24, 40)) < 0.05] = -np.inf
    cases.append((x, r.random((24, 40)) < r.uniform(0.05, 1.0)))
  for x, mask in cases:
    with jax.enable_x64(x.dtype == np.float64):
      got = float(adadepth.lower_median(jnp.asarray(x), jnp.asarray(mask)))
    want = (float(torch.median(torch.from_numpy(x)[torch.from_numpy(mask)])) if mask.any()
            else float("nan"))
    np.testing.assert_equal(got, want)


def _upstream_kitti_pseudo(sup, unsup, ref, thres, lo=1e-3, hi=80.0):
  """Upstream's augment_pseudo with `opt.dataset == "kitti"`, (1, 1, H, W) tensors: the scale
  from mask0, then mask0 replaced by the Garg/Eigen crop for P_S."""
  mask0 = ref > lo
  mask0[:, :, :int(0.3 * ref.shape[2]), :] = False
  scale = torch.median(ref[mask0]) / torch.median(unsup[mask0])
  h, w = ref.shape[2], ref.shape[3]
  crop = torch.zeros_like(mask0)
  crop[:, :, int(0.40810811 * h):int(0.99189189 * h), int(0.03594771 * w):int(0.96405229 * w)] = 1
  mask = ((ref - unsup * scale) ** 2 / ref) < thres
  p_u = torch.clamp(torch.mul(mask.float(), unsup) * scale, min=lo, max=hi)
  mask = (((sup - ref) ** 2) / sup < thres) * crop
  p_s = torch.clamp(torch.mul(mask.float(), ref), min=lo, max=hi)
  return p_s[0, 0].numpy(), p_u[0, 0].numpy(), float(scale)


def test_garg_crop_labels_are_upstreams_kitti_branch():
  """`label_region="garg_crop"` against upstream's KITTI branch of augment_pseudo: P_S is kept
  inside the Garg crop (not in rows 30-41% nor the side columns, which the default keeps), P_U
  and the scale as on other targets."""
  r = np.random.default_rng(3)
  h, w = 37, 53
  ref, ema, unsup = (r.uniform(0.5, 30.0, (h, w)) for _ in range(3))
  ema[int(0.5 * h), 10:14] = 1e-4                     # E below min_depth inside the crop
  cfg = adadepth.AdadepthConfig(threshold=4.0, label_region="garg_crop")
  t = lambda x: torch.from_numpy(x)[None, None]
  want_s, want_u, want_scale = _upstream_kitti_pseudo(t(ref), t(unsup), t(ema), 4.0)
  with jax.enable_x64(True):
    got = adadepth.pseudo_labels(*(jnp.asarray(x) for x in (ref, ema, unsup)), cfg)
    default = adadepth.pseudo_labels(*(jnp.asarray(x) for x in (ref, ema, unsup)),
                                     adadepth.AdadepthConfig(threshold=4.0))
  np.testing.assert_allclose(np.asarray(got.sup), want_s, rtol=1e-12)
  np.testing.assert_allclose(np.asarray(got.unsup), want_u, rtol=1e-12)
  np.testing.assert_allclose(float(got.scale), want_scale, rtol=1e-12)
  band = slice(int(0.3 * h), int(0.40810811 * h))       # rows the default keeps, the crop not
  assert np.any(np.asarray(default.sup)[band] > 1e-3) and np.all(np.asarray(got.sup)[band] == 1e-3)
  np.testing.assert_array_equal(np.asarray(default.unsup), np.asarray(got.unsup))
  with pytest.raises(ValueError, match="label_region must be one of top_rows, garg_crop"):
    adadepth.AdadepthConfig(label_region="kitti")


def test_requirements_fail_before_work():
  """BN eval mode and one step per frame are required (one-line errors naming the flag), and a
  missing pose network or input size is named at init."""
  method = adadepth.build()
  for cfg, flag in [(AdaptConfig(), "--bn-stats running"),
                    (AdaptConfig(bn_stats="running", steps_per_frame=2), "--steps-per-frame 1")]:
    with pytest.raises(ValueError, match=flag):
      method.check(cfg)
  method.check(AdaptConfig(bn_stats="running"))
  with pytest.raises(ValueError, match="use --bn-stats running --steps-per-frame 1$"):
    method.check(AdaptConfig(steps_per_frame=2))  # every unmet requirement in one line
  assert method.needs == ("pose", "intrinsics", "previous_frame") and method.report_after_update
  model = network("monodepth2", {"num_layers": 18})
  for resources, missing in [({INPUT_SIZE: (H, W)}, "resources\\['pose'\\]"),
                             ({POSE: None}, "resources\\['input_size'\\]")]:
    with pytest.raises(ValueError, match=missing):
      method.init(model, None, AdaptConfig(bn_stats="running"), resources)


def test_factor_to_metres_comes_from_the_weights():
  """`run.metric_factor`: 1 for a metric network and for our source models (supervised in
  metres), MonoDepth2's 5.4 for stereo-trained weights (its evaluate_depth.py's
  STEREO_SCALE_FACTOR), none for monocular weights; Ada-Depth takes its config's depth_scale
  first, then the weights' factor, then 1."""
  from pitta_jax.models.depth_anything_v2 import METRIC_SPEC, SPEC as DAV2
  from pitta_jax.models.registry import MODELS
  from pitta_jax.run import metric_factor
  md2 = MODELS["monodepth2"]
  assert metric_factor(md2, {"num_layers": 18, "use_stereo": True}) == 5.4
  assert metric_factor(md2, {"num_layers": 18, "use_stereo": False}) is None
  assert metric_factor(md2, {"num_layers": 18, "source": {"encoder": "encoder.pth"}}) is None
  assert metric_factor(md2, {"source": {"trained_by": "pitta-jax train-source"}}) == 1.0
  assert metric_factor(METRIC_SPEC, {}) == 1.0 and metric_factor(DAV2, {}) is None
  cfg = adadepth.AdadepthConfig()
  assert cfg.depth_scale is None and adadepth.build().metres
  assert adadepth.depth_scale(cfg, {METRIC_FACTOR: 5.4}) == 5.4
  assert adadepth.depth_scale(cfg, {METRIC_FACTOR: None}) == 1.0
  assert adadepth.depth_scale(cfg, {}) == 1.0
  assert adadepth.depth_scale(adadepth.AdadepthConfig(depth_scale=2.0), {METRIC_FACTOR: 5.4}) == 2.0
  with pytest.raises(ValueError, match="depth_scale must be > 0"):
    adadepth.AdadepthConfig(depth_scale=0.0)
