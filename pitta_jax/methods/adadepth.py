"""Ada-Depth (Li et al., ICRA 2023) as a baseline of the paper, with PITTA's L_d added (Sec. 4.1).

Upstream (Malefikus/ada-depth `adaptation.py`, `Adapt.process_batch`), per frame, in this order:
1. the self-supervised branch U (a MonoDepth2 depth network + pose network) takes one Adam step
   on MonoDepth2's photometric loss of the frame and its neighbours;
2. the student S, the frozen source copy R, the EMA teacher E and the *updated* U predict the
   frame's depth; `augment_pseudo` turns them into two pseudo labels (below);
3. S takes one Adam step on SILog(S, P_S) + SILog(S, P_U) (`compute_losses`);
4. E moves towards S (`update_ema_variables`, decay 0.99, over the parameters);
5. S, after its step, is the depth that is evaluated.

Pseudo labels (all depths in metres; `augment_pseudo` on a non-KITTI target; on KITTI upstream
keeps P_S inside the Garg crop instead of mask0, `label_region` "garg_crop"):
    mask0 = (E > min_depth) and not in the top `top_fraction` of the rows
    s     = median(E[mask0]) / median(U[mask0])            (torch.median: the lower middle value)
    P_U   = clamp(1[(E - s U)^2 / E < tau] * s U, min_depth, max_depth)
    P_S   = clamp(1[(R - E)^2 / R < tau and mask0] * E, min_depth, max_depth)
    SILog(S, P) = 10 sqrt(mean g^2 - 0.85 (mean g)^2),  g = log S - log P  over pixels with P > 1
A rejected pixel's label is clamped to min_depth, so `P > 1` removes it from the loss.

Reduced to this setting (our choices where upstream's setting does not carry over):
- S is the engine's trainable tree (`AdaptConfig.selector`; upstream adapts every parameter of
  its depth network, the method's setting `--selector all`), R is `state.source`, E is an EMA copy of the trainable
  leaves (the frozen ones are the same in S, R and E). U starts as a copy of the whole source
  depth network plus the weights' pose network (`resources["pose"]`), with its own Adam state;
  upstream's U is a separately trained self-supervised MonoDepth2 and its S a supervised NeWCRFs.
- Metric depth: tau, the clamp range and the `P > 1` mask are in metres; our depths are
  multiplied by one fixed factor `depth_scale`, by default the weights' own
  (`resources["metric_factor"]`, `run.metric_factor`: 1 for a network that predicts metres, as
  our synthetic source models; 5.4 for MonoDepth2 weights trained with stereo pairs).
  Monocular weights are up to scale and give none: the factor is then 1 (the network's units
  taken as metres, with a note from the CLI) unless `depth_scale` is given. s cancels U's
  scale, so the factor matters for S, R and E.
- Sources of U's loss: the previous frame only (upstream uses frames -1 and +1; online, the next
  frame is not there yet), from a one-image ring in the method state; K is the frame's intrinsics.
  On the first frame of a recording (no previous frame; `StepInput.starts_recording` marks the
  first frame of a recording that follows another one) and on a frame without K, U does not
  update (its labels still come from its current weights).
- BatchNorm runs in eval mode (running statistics) in every network: the method requires
  `AdaptConfig.bn_stats == "running"`. Upstream's S and U take their loss passes in train mode,
  accumulating running statistics that its eval-mode passes of U (its labels) and of S (the
  evaluated depth) then use (R and E are eval-mode copies whose statistics never move); the
  engine never accumulates running statistics, so a train-mode pass here would
  train S and U on statistics that none of the other passes sees.
- The evaluated depth is S after the frame's update (`Method.report_after_update`).
- U's step is taken inside `loss` (its loss does not depend on S) and committed by `update`,
  unless the engine's non-finite guard rejects S's step: then U stays too. E moves every frame.
- An empty pseudo label (no pixel above 1 m) contributes 0 (upstream's mean of nothing is NaN);
  SILog at g = 0 (S equals the label, e.g. S = E = R on the first frame) is 0 with a zero
  gradient (upstream's is NaN: sqrt at 0).
- `AdaptConfig.reset_every` resets S and its optimiser; E and U are not reset.
- One update per frame (`AdaptConfig.steps_per_frame == 1`): U's frame ring moves per update.
- U's warp samples with PyTorch's align_corners=False, what upstream's `F.grid_sample` call
  computed on its PyTorch 1.7.1 (`SfmLossConfig.align_corners`); the smoothness term's colour
  images at scales 1-3 are block means of the frame (upstream: its loader's PIL antialiasing
  resize).

The paper's comparison adds L_d (eq. 8) on S's depth with weight `ld_weight` (0 = the original).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from pitta_jax import trainable as trainable_lib
from pitta_jax.configs import check, check_types, is_number, finite, option
from pitta_jax.dtypes import tree_dtype
from pitta_jax.methods.base import (INPUT_SIZE, METRIC_FACTOR, POSE, Aux, Method, ring_init,
                                    ring_push, ring_restart, variables_of)
from pitta_jax.median import select_middles
from pitta_jax.methods.depth_refining import DepthRefiningConfig, depth_refining_term
from pitta_jax.metrics import garg_crop_mask
from pitta_jax.models.pose import transformation_from_parameters
from pitta_jax.sfm import SfmLossConfig, check_scales, monodepth2_loss

Tree = Any
LABEL_REGIONS = ("top_rows", "garg_crop")


@dataclasses.dataclass(frozen=True)
class AdadepthConfig:
  """Ada-Depth's knobs (upstream adaptation.py, options.py, README) and the paper's L_d."""
  lr: float = option(1e-5, "Adam learning rate of S and of U (upstream README's adaptation "
                           "command: --learning_rate 1e-5, one rate for both optimisers)")
  ema_decay: float = option(0.99, "decay of the EMA teacher E (upstream update_ema_variables "
                                  "with alpha 0.99, no warm-up)")
  threshold: float = option(0.4, "tau: a pixel keeps its pseudo label where (a - b)^2 / a < tau, "
                                 "depths in metres (upstream README: --thres 0.4)")
  depth_scale: float | None = option(None, "fixed factor from the network's depth to metres; "
                                          "unset: the weights' own (1 for a metric network, 5.4 "
                                          "for stereo-trained MonoDepth2), 1 for weights up to "
                                          "scale")
  min_depth: float = option(1e-3, "metres: labels are clamped to [min_depth, max_depth]; E must "
                                  "exceed it to enter the scale median (upstream MIN_DEPTH)")
  max_depth: float = option(80.0, "metres: upper clamp of the labels (upstream MAX_DEPTH)")
  label_min: float = option(1.0, "metres: SILog uses the pixels whose label exceeds this "
                                 "(upstream compute_losses: > 1.0)")
  top_fraction: float = option(0.3, "top share of the rows left out of the scale median and of "
                                    "P_S (upstream augment_pseudo's mask0)")
  label_region: str = option("top_rows", "where P_S may keep a label: top_rows (E > min_depth "
                                         "below the top rows, upstream's non-KITTI targets) or "
                                         "garg_crop (the Garg/Eigen crop, upstream's KITTI "
                                         "branch); the scale median takes top_rows either way")
  variance_focus: float = option(0.85, "SILog's weight of (mean g)^2 (upstream compute_losses)")
  silog_factor: float = option(10.0, "SILog's factor (upstream compute_losses)")
  sfm: SfmLossConfig = SfmLossConfig()  # U's MonoDepth2 loss (upstream options.py defaults)
  ld_weight: float = option(1.0, "weight of PITTA's L_d (eq. 8) added to the loss (paper Sec. 4.1)")
  ld: DepthRefiningConfig = DepthRefiningConfig()

  def __post_init__(self):
    check_types(self)
    finite(self.lr, "lr", 0.0)
    check(0.0 <= self.ema_decay <= 1.0, f"ema_decay must be in [0, 1], got {self.ema_decay}")
    finite(self.threshold, "threshold", 0.0)
    if self.depth_scale is not None:
      finite(self.depth_scale, "depth_scale", 0.0)
      check(self.depth_scale > 0, f"depth_scale must be > 0, got {self.depth_scale}")
    finite(self.min_depth, "min_depth", 0.0)
    finite(self.max_depth, "max_depth", 0.0)
    check(0 < self.min_depth < self.max_depth,
          f"need 0 < min_depth < max_depth, got {self.min_depth}, {self.max_depth}")
    finite(self.label_min, "label_min", 0.0)
    check(0.0 <= self.top_fraction < 1.0,
          f"top_fraction must be in [0, 1), got {self.top_fraction}")
    check(self.label_region in LABEL_REGIONS,
          f"label_region must be one of {', '.join(LABEL_REGIONS)}, got {self.label_region!r}")
    check(is_number(self.variance_focus) and 0.0 <= self.variance_focus <= 1.0,
          f"variance_focus must be in [0, 1], got {self.variance_focus!r}")
    finite(self.silog_factor, "silog_factor", 0.0)
    finite(self.ld_weight, "ld_weight", 0.0)


@struct.dataclass
class Branch:
  """The self-supervised branch U in the method state: its trainable weights, Adam state, the
  pose network's constants and (static, not an array) the pose module."""
  params: Tree       # {"depth": the depth network's params, "pose": the pose network's params}
  opt_state: Tree    # Adam's state of `params`
  pose_consts: Tree  # the pose network's other collections (BN running statistics)
  pose_module: Any = struct.field(pytree_node=False)


class PseudoLabels(NamedTuple):
  """`pseudo_labels`' result: two (H, W) labels in metres and U's scale ()."""
  sup: jax.Array
  unsup: jax.Array
  scale: jax.Array


# ----------------------------------------------------------------------------- pure pieces


def lower_median(x: jax.Array, mask: jax.Array) -> jax.Array:
  """`torch.median(x[mask])`: the middle value, the lower of the two for an even count.

  x, mask: (H, W). NaN when the mask is empty (upstream's median of nothing fails too), and
  when a masked value is NaN (torch.median propagates it; the selection puts NaN last, which
  would skip it).

  The element a sort of the masked values (the others as +inf) puts at slot (n - 1) // 2, found
  by bisection over the values' order keys (`median.select_middles`: 32 counting passes in
  float32) instead of a sort: XLA:CPU sorted the 640x192 map in 25 ms, twice per Ada-Depth
  frame (`benchmarks/profile_step.py --method adadepth`). Same element, same gradient.
  """
  n = jnp.sum(mask.astype(jnp.int32))
  rank = jnp.maximum((n - 1) // 2, 0)
  middle, _ = select_middles(jnp.where(mask, x, jnp.inf).ravel(), rank, rank)
  nan = jnp.any(mask & jnp.isnan(x))
  return jnp.where((n > 0) & ~nan, middle, jnp.nan)


def pseudo_labels(ref: jax.Array, ema: jax.Array, unsup: jax.Array,
                  config: AdadepthConfig) -> PseudoLabels:
  """Upstream's `augment_pseudo`: P_S from E where R and E agree (inside mask0, or with
  `label_region` garg_crop inside the Garg crop, upstream's KITTI branch), P_U from the
  median-scaled U where it agrees with E. ref, ema, unsup: (H, W) depths in metres."""
  h, w = ref.shape
  below_top = (jnp.arange(h) >= int(config.top_fraction * h))[:, None]      # (H, 1)
  mask0 = (ema > config.min_depth) & below_top
  scale = lower_median(ema, mask0) / lower_median(unsup, mask0)
  if config.label_region == "garg_crop":  # upstream's crop_mask: MonoDepth2's Garg crop
    mask0 = jnp.asarray(garg_crop_mask(h, w))                                # (H, W)
  scaled = unsup * scale
  keep_unsup = (ema - scaled) ** 2 / ema < config.threshold
  keep_sup = ((ref - ema) ** 2 / ref < config.threshold) & mask0
  lo, hi = config.min_depth, config.max_depth
  return PseudoLabels(jnp.clip(jnp.where(keep_sup, ema, 0.0), lo, hi),
                      jnp.clip(jnp.where(keep_unsup, scaled, 0.0), lo, hi), scale)


def silog(pred: jax.Array, label: jax.Array, config: AdadepthConfig
          ) -> tuple[jax.Array, jax.Array]:
  """Upstream's `compute_losses` term: factor * sqrt(mean g^2 - focus (mean g)^2), g = log pred -
  log label over the pixels whose label exceeds `label_min`; 0 when there is none.

  At g = 0 (the prediction equals the label on every pixel, e.g. the student's first frame, when
  S = E = R in eval mode) the term is 0, its minimum, and its gradient is taken as 0: sqrt's
  derivative there is infinite and upstream's gradient NaN (its student, in train mode, never
  equals the eval-mode teacher exactly).

  pred, label: (H, W) in metres. Returns (loss (), number of pixels () int32).
  """
  valid = label > config.label_min
  n = jnp.sum(valid.astype(jnp.int32))
  g = jnp.where(valid, jnp.log(pred) - jnp.log(jnp.where(valid, label, 1.0)), 0.0)
  count = jnp.maximum(n, 1).astype(pred.dtype)
  mean, mean_sq = jnp.sum(g) / count, jnp.sum(g * g) / count
  inner = mean_sq - config.variance_focus * mean ** 2
  positive = (n > 0) & (inner > 0)
  return jnp.where(positive, config.silog_factor * jnp.sqrt(jnp.where(positive, inner, 1.0)),
                   0.0), n


def intrinsics_4x4(K: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(3, 3) camera matrix -> MonoDepth2's homogeneous K and inv_K, (4, 4) each."""
  K4 = jnp.eye(4, dtype=K.dtype).at[:3, :3].set(K)
  return K4, jnp.linalg.inv(K4)


def branch_loss(params: Tree, branch: Branch, batch_stats: Tree, image: jax.Array,
                previous: jax.Array, K: jax.Array, rng: jax.Array, model,
                config: SfmLossConfig) -> jax.Array:
  """U's MonoDepth2 loss of the frame (target) with the previous frame as the only source.

  image, previous: (H, W, 3); K: (3, 3). The pose network sees the pair in temporal order
  (previous, current), and its motion is inverted (upstream `predict_poses` for a negative frame
  id); disparities of every `config.scales` from U's depth network.
  """
  outs = model.outputs({"params": params["depth"], "batch_stats": batch_stats}, image[None], False)
  check_scales(config.scales, len(outs), "adadepth.sfm.scales")
  disps = [outs[s][..., 0] for s in config.scales]                  # (1, H / 2**s, W / 2**s)
  pair = jnp.concatenate([previous, image], axis=-1)[None]           # (1, H, W, 6)
  axisangle, translation = branch.pose_module.apply(
      {"params": params["pose"], **branch.pose_consts}, pair, False)
  T = transformation_from_parameters(axisangle[:, 0], translation[:, 0], invert=True)  # (1, 4, 4)
  K4, inv_K = intrinsics_4x4(K)
  value, _ = monodepth2_loss(image[None], previous[None, None], disps, K4[None], inv_K[None],
                             T[:, None], cfg=config, rng=rng)
  return value


def branch_step(branch: Branch, batch_stats: Tree, frame, previous: jax.Array,
                has_previous: jax.Array, rng: jax.Array, model, config: AdadepthConfig
                ) -> tuple[Branch, jax.Array, jax.Array, jax.Array]:
  """One Adam step of U on `branch_loss` (upstream step 1). It is kept only with a previous
  frame, the frame's K and finite results. Returns (branch, loss, gradient norm, updated).

  Adam runs leaf by leaf. On the raveled vector (`pitta_jax.flat_optim`, as CoMoDa) the step
  compiled 25-30% faster (320x96, 2 vCPU: 81-91 s -> 58-64 s with the first chunk) but every
  frame moved both networks' gradients and parameters through a concatenation and back:
  1076-1100 vs 946-1055 ms/frame."""
  from pitta_jax.adapt.engine import all_finite, select, tree_norm
  value, grads = jax.value_and_grad(branch_loss)(
      branch.params, branch, batch_stats, frame.image, previous, frame.intrinsics, rng, model,
      config.sfm)
  updates, opt_state = optax.adam(config.lr).update(grads, branch.opt_state, branch.params)
  params = optax.apply_updates(branch.params, updates)
  ok = (has_previous & frame.has_intrinsics & jnp.isfinite(value)
        & all_finite((grads, params, opt_state)))
  params, opt_state = select(ok, (params, opt_state), (branch.params, branch.opt_state))
  return branch.replace(params=params, opt_state=opt_state), value, tree_norm(grads), ok


# ----------------------------------------------------------------------------- the method


def loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg: AdadepthConfig):
  """SILog(S, P_S) + SILog(S, P_U) + ld_weight * L_d(S), after U's step (BN eval mode)."""
  del cfg
  ms = state.method_state
  sg = jax.lax.stop_gradient
  ring = ring_restart(ms["frames"], frame.starts_recording)
  branch, loss_u, gnorm_u, u_ok = sg(branch_step(
      ms["u"], consts.batch_stats, frame, ring["items"][0], ring["count"] > 0, rng, model, mcfg))

  def depth_of(variables):
    return model.depth(variables, frame.image[None], False)[0]       # (H, W)

  student = depth_of(variables_of(trainable, consts))
  ref = sg(depth_of(variables_of(state.source, consts)))
  ema = sg(depth_of(variables_of(ms["teacher"], consts)))
  unsup = sg(depth_of({"params": branch.params["depth"], "batch_stats": consts.batch_stats}))
  k = ms["depth_scale"]
  labels = pseudo_labels(k * ref, k * ema, k * unsup, mcfg)
  l_sup, n_sup = silog(k * student, labels.sup, mcfg)
  l_unsup, n_unsup = silog(k * student, labels.unsup, mcfg)
  own = l_sup + l_unsup
  l_d, n = depth_refining_term(student, frame, mcfg.ld)
  total = own + ms["ld_weight"] * l_d
  pixels = student.size
  logs = {"loss_adadepth": own, "loss_sup": l_sup, "loss_unsup": l_unsup, "loss_u": loss_u,
          "u_grad_norm": gnorm_u, "u_updated": u_ok.astype(student.dtype),
          "u_scale": labels.scale, "keep_sup": n_sup / pixels, "keep_unsup": n_unsup / pixels,
          "loss_d": l_d, "n_instances": n}
  return total, sg(Aux(student, logs, {"u": branch, "frames": ring_push(ring, frame.image)}))


def depth_scale(config: AdadepthConfig, resources: dict) -> float:
  """The factor to metres: `config.depth_scale`, else the weights' (`resources[METRIC_FACTOR]`,
  given by `run.run_sequence`), else 1."""
  if config.depth_scale is not None:
    return config.depth_scale
  factor = resources.get(METRIC_FACTOR)
  return 1.0 if factor is None else factor


def build(config: AdadepthConfig = AdadepthConfig()) -> Method:
  """Ada-Depth with `config` bound. method_state = {"teacher": E (the trainable leaves' EMA),
  "u": `Branch`, "frames": a one-image ring, "ld_weight": ()}; Adam(config.lr) for S."""
  from pitta_jax.adapt.engine import optax_update, select

  def init(model, parts, cfg, resources):
    del cfg
    check(POSE in resources, "adadepth needs resources['pose'], the weights' pose network")
    check(INPUT_SIZE in resources, "adadepth needs resources['input_size'], the frames' (H, W)")
    check(model.spec.output == "sigmoid_disparity",
          f"adadepth's MonoDepth2 branch needs sigmoid disparities; {model.spec.name} gives "
          f"{model.spec.output}")
    check((config.sfm.min_depth, config.sfm.max_depth) == tuple(model.spec.depth_range),
          f"adadepth: sfm min/max depth {config.sfm.min_depth}, {config.sfm.max_depth} must be "
          f"{model.spec.name}'s depth range {tuple(model.spec.depth_range)}")
    copy = lambda tree: jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), tree)
    pose = resources[POSE]
    params = {"depth": copy(trainable_lib.merge(parts.trainable, parts.frozen, {})["params"]),
              "pose": copy(pose.variables["params"])}
    branch = Branch(params, optax.adam(config.lr).init(params),
                    copy({k: v for k, v in pose.variables.items() if k != "params"}),
                    pose.module)
    teacher = copy(parts.trainable)
    dtype = tree_dtype(teacher)
    h, w = resources[INPUT_SIZE]
    return {"teacher": teacher, "u": branch,
            "frames": ring_init(jnp.zeros((h, w, 3), dtype), 1),
            "ld_weight": jnp.asarray(config.ld_weight, dtype),
            "depth_scale": jnp.asarray(depth_scale(config, resources), dtype)}

  def update(state, grads, loss_value, aux, rng, tx, cfg):
    """S's Adam step (non-finite guard), U's step unless S's was rejected, E's EMA, the ring."""
    del rng
    state, skipped, unorm = optax_update(state, grads, loss_value, tx, cfg)
    ms = state.method_state
    a = config.ema_decay
    teacher = jax.tree_util.tree_map(lambda e, s: a * e + (1.0 - a) * s, ms["teacher"],
                                     state.trainable)
    branch = select(skipped, ms["u"], aux.carry["u"])
    ms = {**ms, "teacher": teacher, "u": branch, "frames": aux.carry["frames"]}
    return state.replace(method_state=ms), skipped, unorm

  return Method("adadepth", config, init=init, loss=loss, update=update,
                optimizer=lambda cfg: optax.adam(config.lr),
                requires=(("bn_stats", "running", "runs BatchNorm in eval mode"),
                          ("steps_per_frame", 1, "updates once per frame")),
                # upstream trains every parameter of S (`Adapt.__init__`: the encoder's and the
                # decoder's parameters in one Adam)
                setting=(("selector", "all"),),
                needs=("pose", "intrinsics", "previous_frame"), report_after_update=True,
                metres=True)
