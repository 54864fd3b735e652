"""CoMoDa (Kuznietsov et al., WACV 2021) as a baseline of the paper, with PITTA's L_d added (Sec. 4.1).

CoMoDa keeps training the self-supervised network online (official code Yevkuzn/CoMoDA,
`CoMoDA.py`): per frame one Adam step (lr 1e-4) of the depth network (encoder + decoder) and
the pose network (encoder + decoder) on MonoDepth2's loss (`pitta_jax.sfm.monodepth2_loss`:
0.85 SSIM + 0.15 L1 reprojection, per-pixel minimum over the source frames and the auto-mask's
identity losses, edge-aware smoothness, 4 scales), with

- BatchNorm in eval mode and its scale/bias frozen (`set_adapt`); every other weight of both
  networks adapts (selector `no_bn`, required). `set_adapt` freezes parameters whose name
  contains "bn", which misses the ResNet's `downsample.1` BatchNorms; here every BatchNorm is
  frozen, as the method intends;
- the test sample's per-pixel minimum reprojection map multiplied by a mask of possibly moving
  objects (`compute_losses`: after the minimum, before the mean). Here the mask is
  1 - [pixel on a dynamic instance]: every dynamic segment of the frame (L_d's classes, eq. 3,
  from the panoptic input; not capped at L_d's `max_instances`; upstream: YOLOv5 masks);
- experience replay: each step's batch is the test sample and `replay` source-domain samples
  (`--batch_size 4` = 1 + 3) with all-ones masks, in one forward pass (BN in eval mode: the
  samples do not interact). The samples are windows of consecutive frames of
  `SourceData.sequences` (the clear streets on the synthetic benchmark, `--replay-root` on real
  data; `replay_set`), at most `replay_size` of them, evenly spaced; each step draws `replay` of
  them with the step's key (upstream cycles through a pre-shuffled list of KITTI samples);
- the identity losses' tie-break noise: one draw per step shared by the scales (as upstream).

Deviations (ours; docs/method.md):
- no GPS: the velocity loss (upstream `--translation_weight` 0.005) is off and updates are not
  gated on the speed (`--min_translation` 0.2);
- pose: MonoDepth2's released pairs pose network, one pair per source frame (MonoDepth2's
  `predict_poses`: (t-1, t) inverted, (t, t+1) as it is), where upstream feeds all three frames
  to a 3-frame pose encoder;
- disparity -> depth by `disp_to_depth(0.1, 100)`, as the MonoDepth2 weights were trained
  (upstream warps with 1 / disp);
- `latency` 0 (default, causal): the update at frame t uses (t-1 -> t); `latency` 1: the update
  at frame t uses (t-2, t -> t-1), upstream's frame_ids (0, -1, 1) one frame late. The replay
  samples take the same window (one batch, one window shape): with latency 0 they are pairs,
  one warped source and one identity loss in the minimum, where upstream replays triplets (its
  frame_ids for every sample), as latency 1 does here. The evaluated depth is frame t's: with
  latency 0 before frame t's update (predict-then-adapt), with latency 1 after it, as upstream,
  whose depth of frame t comes from the network already updated on the window (t-2, t-1, t)
  (`Method.report_after_update`);
- the first frame (latency 0), the first two (latency 1), and a frame whose K is unknown make
  no update (loss 0; parameters and both Adam states untouched), as upstream starts at the
  second frame of a video; so does each recording's first frame (first two) where recordings
  follow each other in one stream (`StepInput.starts_recording`): no frame pair spans two.

Total loss: L_comoda + ld_weight * L_d (eq. 8) on the depth of the adapted test frame (the
current frame, or with latency 1 the previous one), with the same instance masks.

The engine differentiates w.r.t. the depth network (`state.trainable`); the pose network and
its Adam state (`PoseState`), the last 1 + latency frames (`base.ring_*`) and the replay set are
method state. `loss` computes both networks' gradients in one backward pass and gives the engine
a value with the depth gradient attached (`_attach_gradient`); the pose gradient reaches
`update` in `Aux.carry`. `update` steps both networks under one non-finite guard (engine
`optax_update`'s semantics) on raveled parameter vectors (`pitta_jax.flat_optim`). A new
sequence starts from the source weights (the engine's `init_state`) with fresh Adam states
(upstream's `adapt()` reloads the weights per sequence but keeps one optimiser, and the replay
iterator, over all sequences); `AdaptConfig.reset_every` resets the depth network and its
optimiser only.

The warp samples with PyTorch's align_corners=False, what upstream's `F.grid_sample` call
computed on the PyTorch 1.3.0 it pins (`SfmLossConfig.align_corners`). The smoothness term's
colour images at scales 1-3 are block means of the frame (upstream's data loader resizes with
PIL's antialiasing filter): the edge weights exp(-|grad I|) differ slightly, the photometric
term not at all.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from pitta_jax import prng
from pitta_jax import trainable as trainable_lib
from pitta_jax.configs import check, check_types, finite, option
from pitta_jax.dtypes import tree_dtype
from pitta_jax.flat_optim import flat, flat_step
from pitta_jax.methods.base import (POSE, Aux, Method, ring_init, ring_push, ring_restart,
                                    ring_valid, variables_of)
from pitta_jax.methods.depth_refining import (DepthRefiningConfig, depth_refining_term,
                                              dynamic_pixels)
from pitta_jax.models.pose import transformation_from_parameters
from pitta_jax.sfm import SfmLossConfig, check_scales, monodepth2_loss

Tree = Any
REPLAY_IMAGES = "comoda_replay_images"  # resources: (R, F, H, W, 3) windows of source frames
REPLAY_K = "comoda_replay_K"            # resources: (R, 3, 3) K of each window's centre frame
SELECTOR = "no_bn"


@dataclasses.dataclass(frozen=True)
class ComodaConfig:
  """CoMoDa's knobs (official code/options.py, CoMoDA.py) and the paper's added L_d."""
  lr: float = option(1e-4, "Adam learning rate of the depth and pose networks (CoMoDA "
                           "--learning_rate)")
  replay: int = option(3, "source samples replayed per step besides the test sample (CoMoDA "
                          "--batch_size 4 = 1 + 3)")
  replay_size: int = option(64, "most source windows kept on the device, evenly spaced over the "
                                "source sequences (ours; CoMoDA reads its replay list from disk)")
  latency: int = option(0, "0: update at frame t on (t-1 -> t) (ours, causal); 1: on "
                           "(t-2, t -> t-1), one frame late as CoMoDA's frame_ids 0 -1 1")
  sfm: SfmLossConfig = SfmLossConfig()
  ld_weight: float = option(1.0, "weight of PITTA's L_d (eq. 8) added to the loss (paper Sec. 4.1)")
  ld: DepthRefiningConfig = DepthRefiningConfig()
  # the moving-object mask needs the dynamic instances with or without L_d
  # (`depth_refining.instance_uses`: what a frame without instances means)
  INSTANCE_USE: ClassVar[str] = "CoMoDa's loss masks no moving object"

  def __post_init__(self):
    check_types(self)
    finite(self.lr, "lr", 0.0)
    check(self.replay >= 0, f"replay must be >= 0, got {self.replay}")
    check(self.replay_size >= 1, f"replay_size must be >= 1, got {self.replay_size}")
    check(self.latency in (0, 1), f"latency must be 0 or 1, got {self.latency}")
    finite(self.ld_weight, "ld_weight", 0.0)

  @property
  def offsets(self) -> tuple[int, ...]:
    """The source frames relative to the adapted frame (upstream's frame_ids[1:])."""
    return (-1,) if self.latency == 0 else (-1, 1)

  @property
  def window(self) -> int:
    """Frames per sample: (t-1, t) or (t-1, t, t+1); the adapted frame is index 1."""
    return 1 + len(self.offsets)


@struct.dataclass
class PoseState:
  """The adapted pose network in the method state: its module (static) and variables split
  like the depth network's (BN scale/bias frozen), with its own Adam state."""
  module: Any = struct.field(pytree_node=False)
  trainable: Tree = None
  frozen: Tree = None
  batch_stats: Tree = None
  opt_state: Tree = None

  def variables(self, trainable: Tree) -> Tree:
    return trainable_lib.merge(trainable, self.frozen, self.batch_stats)


class Sample(NamedTuple):
  """One step's training batch (B = 1 + replay): the test sample first."""
  target: jax.Array    # (B, H, W, 3) the adapted frames
  sources: jax.Array   # (B, N, H, W, 3) their neighbours, in `offsets` order
  K: jax.Array         # (B, 3, 3)
  weights: jax.Array   # (B, H, W) 1 - moving-object mask (replay: 1)
  centre: Any          # StepInput of the adapted test frame (its instances give L_d)
  active: jax.Array    # () bool: the test frame has its neighbours and a K


def _adam(config: ComodaConfig) -> optax.GradientTransformation:
  """torch.optim.Adam(lr) (official CoMoDA.py, one optimiser over both networks: element-wise,
  so one per network is the same)."""
  return optax.adam(config.lr)


def optimizer(config: ComodaConfig) -> optax.GradientTransformation:
  """The depth network's optimiser as the engine sees it (its state, init and reset): Adam on the
  raveled tree (`flat_optim`); `update` steps it on the raveled vector directly."""
  return flat(_adam(config))


# ----------------------------------------------------------------------------- replay set


def replay_set(source, config: ComodaConfig) -> dict[str, np.ndarray]:
  """The replay windows of `source.sequences` as arrays (host side, once before the run).

  Windows of `config.window` consecutive frames whose centre frame has K; at most
  `replay_size`, evenly spaced over all windows (deterministic). Returns {REPLAY_IMAGES:
  (R, F, H, W, 3) float32, REPLAY_K: (R, 3, 3) float32}; with `replay` 0, R = 0 (the arrays
  still give the frame size). ValueError (one line, naming the flag) when there is no window.
  """
  f = config.window
  windows = [seq[i:i + f] for seq in source.sequences for i in range(len(seq) - f + 1)
             if seq[i + 1].intrinsics is not None]
  if config.replay > 0:
    check(len(windows) > 0, f"comoda replays {f} consecutive source frames with intrinsics: "
                            "give --replay-root DIR (KITTI layout) or use the synthetic benchmark")
    pick = np.unique(np.round(np.linspace(0, len(windows) - 1,
                                          min(config.replay_size, len(windows)))).astype(int))
    images = np.stack([[fr.image for fr in windows[i]] for i in pick]).astype(np.float32)
    K = np.stack([windows[i][1].intrinsics for i in pick]).astype(np.float32)
    return {REPLAY_IMAGES: images, REPLAY_K: K}
  frames = [fr.image for seq in source.sequences for fr in seq] or list(source.images)
  check(len(frames) > 0, "comoda needs the frame size from source data: give --replay-root DIR "
                         "or --source-images PATH")
  h, w = np.shape(frames[0])[:2]
  return {REPLAY_IMAGES: np.zeros((0, f, h, w, 3), np.float32),
          REPLAY_K: np.zeros((0, 3, 3), np.float32)}


def step_draws(rng: jax.Array, n_replay_set: int, config: ComodaConfig, height: int, width: int,
               dtype=jnp.float32) -> tuple[jax.Array, jax.Array]:
  """The step's random draws from its key: which replay windows (replay,) int32 (without
  repetition when the set is large enough), and the identity tie-break noise
  (S, B, N, H, W), one standard-normal draw shared by the S scales (official compute_losses)."""
  k_idx, k_noise = jax.random.split(rng)
  n = config.replay
  if n:
    idx = jax.random.choice(k_idx, n_replay_set, (n,), replace=n_replay_set < n)
  else:
    idx = jnp.zeros((0,), jnp.int32)
  shape = (1, 1 + n, len(config.offsets), height, width)
  noise = jax.random.normal(prng.unrolled(k_noise), shape, dtype)  # = jax.random's, faster
  return idx.astype(jnp.int32), jnp.broadcast_to(noise, (len(config.sfm.scales),) + shape[1:])


# ----------------------------------------------------------------------------- the step


def _frame_ring(image_shape: tuple[int, int], max_segments: int, size: int, dtype
                ) -> dict[str, dict[str, jax.Array]]:
  """Rings (`base.ring_init`) of the last `size` frames, one per StepInput field."""
  from pitta_jax.adapt.engine import StepInput
  h, w = image_shape
  example = StepInput(
      image=jnp.zeros((h, w, 3), dtype), panoptic=jnp.zeros((h, w), jnp.int32),
      seg_ids=jnp.zeros((max_segments,), jnp.int32),
      seg_classes=jnp.zeros((max_segments,), jnp.int32),
      seg_valid=jnp.zeros((max_segments,), bool), valid=jnp.zeros((), bool),
      intrinsics=jnp.zeros((3, 3), dtype), has_intrinsics=jnp.zeros((), bool),
      starts_recording=jnp.zeros((), bool))
  return {name: ring_init(x, size) for name, x in example._asdict().items()}


def _rings_before(rings: dict, frame) -> dict:
  """The rings as `frame` sees them: empty when it starts a new recording."""
  return {name: ring_restart(r, frame.starts_recording) for name, r in rings.items()}


def _ring_frame(rings: dict, k: int, frame):
  """The frame k steps back (k = 0: the last one) as a StepInput, and whether it exists;
  a missing frame is replaced by `frame` so that every computation stays finite."""
  valid = ring_valid(rings["image"])[k]
  fields = {name: jnp.where(valid, r["items"][k].astype(getattr(frame, name).dtype),
                            getattr(frame, name))
            for name, r in rings.items()}
  return type(frame)(**fields), valid


def _intrinsics4(K: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(B, 3, 3) -> K, inv_K (B, 4, 4) as MonoDepth2's data loader makes them."""
  b = K.shape[0]
  K4 = jnp.broadcast_to(jnp.eye(4, dtype=K.dtype), (b, 4, 4)).at[:, :3, :3].set(K)
  return K4, jnp.linalg.inv(K4)


def build_sample(frame, ms: dict, idx: jax.Array, config: ComodaConfig) -> Sample:
  """The step's batch: the test sample (current frame, or with latency 1 the previous one)
  and the replay windows `idx`. Missing neighbours and an unknown K are replaced by finite
  stand-ins (the current frame, the identity) and the sample is marked inactive."""
  rings = _rings_before(ms["ring"], frame)
  dtype = rings["image"]["items"].dtype
  if config.latency == 0:
    centre, active = frame, ring_valid(rings["image"])[0]
    prev, _ = _ring_frame(rings, 0, frame)
    neighbours = [prev.image]
  else:
    centre, active = _ring_frame(rings, 0, frame)
    prev, has_prev = _ring_frame(rings, 1, frame)
    active = active & has_prev
    neighbours = [prev.image, frame.image]
  active = active & centre.has_intrinsics
  K = jnp.where(centre.has_intrinsics, centre.intrinsics, jnp.eye(3, dtype=centre.intrinsics.dtype))
  moving = dynamic_pixels(centre, config.ld)                              # (H, W)
  h, w = moving.shape
  images = ms["replay_images"][idx]                                       # (R, F, H, W, 3)
  target = jnp.concatenate([centre.image[None].astype(dtype), images[:, 1]])
  test_sources = jnp.stack(neighbours).astype(dtype)[None]               # (1, N, H, W, 3)
  replay_sources = jnp.concatenate([images[:, :1], images[:, 2:]], axis=1)
  sources = jnp.concatenate([test_sources, replay_sources])
  Ks = jnp.concatenate([K[None].astype(dtype), ms["replay_K"][idx]])
  weights = jnp.concatenate([(~moving).astype(dtype)[None],
                             jnp.ones((idx.shape[0], h, w), dtype)])
  return Sample(target, sources, Ks, weights, centre, active)


def camera_motions(pose: PoseState, pose_trainable: Tree, target: jax.Array,
                   sources: jax.Array, offsets: tuple[int, ...]) -> jax.Array:
  """Target -> source camera motions (B, N, 4, 4) from the pairs pose network (MonoDepth2's
  `predict_poses`): the pair (source, target) inverted for a past frame, (target, source) for a
  future one. All pairs go through one batched forward (BN eval mode: independent)."""
  b = sources.shape[0]
  pairs = [jnp.concatenate([sources[:, i], target] if off < 0 else [target, sources[:, i]], -1)
           for i, off in enumerate(offsets)]
  axisangle, translation = pose.module.apply(pose.variables(pose_trainable),
                                             jnp.concatenate(pairs), False)   # (N*B, 2, 1, 3)
  motions = [transformation_from_parameters(axisangle[i * b:(i + 1) * b, 0],
                                            translation[i * b:(i + 1) * b, 0], invert=off < 0)
             for i, off in enumerate(offsets)]
  return jnp.stack(motions, axis=1)


def _attach_gradient(value: jax.Array, params: Tree, grads: Tree) -> jax.Array:
  """`value` (the same number) whose gradient w.r.t. `params` is `grads`: value +
  <params - sg(params), sg(grads)>, where the inner product is exactly 0 for finite grads."""
  sg = jax.lax.stop_gradient
  dots = jax.tree_util.tree_map(lambda p, g: jnp.sum((p - sg(p)) * sg(g)), params, grads)
  return sg(value) + sum(jax.tree_util.tree_leaves(dots))


def loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg: ComodaConfig):
  """L_comoda (MonoDepth2's loss over the test sample and the replay samples) + ld_weight *
  L_d of the adapted test frame's depth; 0 on an inactive frame (no neighbours or no K)."""
  del cfg
  sg = jax.lax.stop_gradient
  ms = state.method_state
  pose: PoseState = ms["pose"]
  dtype = ms["ring"]["image"]["items"].dtype
  h, w = frame.image.shape[:2]
  idx, noise = step_draws(rng, ms["replay_images"].shape[0], mcfg, h, w, dtype)
  batch = build_sample(frame, ms, idx, mcfg)
  scales = mcfg.sfm.scales

  def objective(depth_trainable, pose_trainable):
    outs = model.outputs(variables_of(depth_trainable, consts), batch.target, False)
    check_scales(scales, len(outs), "comoda.sfm.scales")
    disps = [outs[s][..., 0] for s in scales]
    poses = camera_motions(pose, pose_trainable, batch.target, batch.sources, mcfg.offsets)
    K4, inv_K4 = _intrinsics4(batch.K)
    own, _ = monodepth2_loss(batch.target, batch.sources, disps, K4, inv_K4, poses,
                             cfg=mcfg.sfm, noise=noise, pixel_weights=batch.weights)
    l_d, n = depth_refining_term(model.spec.to_depth(outs[0][0, ..., 0]), batch.centre, mcfg.ld)
    on = batch.active.astype(dtype)
    own, l_d = own * on, l_d * on
    # the test sample's depth (H, W): frame t's with latency 0; with latency 1 the engine
    # reports frame t's after the update instead (report_after_update)
    evaluated = model.spec.to_depth(outs[0][0, ..., 0])
    return own + ms["ld_weight"] * l_d, (own, l_d, n, evaluated)

  (total, (own, l_d, n, depth)), (g_depth, g_pose) = jax.value_and_grad(
      objective, argnums=(0, 1), has_aux=True)(sg(trainable), pose.trainable)
  logs = {"loss_comoda": own, "loss_d": l_d, "n_instances": n}
  carry = {"pose_grads": g_pose, "active": batch.active, "frame": frame}
  return _attach_gradient(total, trainable, g_depth), sg(Aux(depth, logs, carry))


def build(config: ComodaConfig = ComodaConfig()) -> Method:
  """CoMoDa with `config` bound. method_state = {"pose": PoseState, "ring": the last 1 + latency
  frames, "replay_images", "replay_K", "ld_weight": ()} (ld_weight in the state: one compile
  serves a sweep)."""
  from pitta_jax.adapt.engine import select

  def init(model, parts, cfg, resources):
    # bn_stats, selector and steps_per_frame: `requires`, checked by the engine before init
    check(POSE in resources, "comoda needs the weights' pose network (resources['pose'])")
    check(REPLAY_IMAGES in resources, "comoda needs its replay set (resources from "
                                      "methods.comoda.replay_set / Method.prepare)")
    check(model.spec.output == "sigmoid_disparity"
          and tuple(model.spec.depth_range) == (config.sfm.min_depth, config.sfm.max_depth),
          f"comoda: the {model.spec.name} network's disparity range {model.spec.depth_range} "
          f"differs from --comoda.sfm.min-depth/max-depth "
          f"({config.sfm.min_depth}, {config.sfm.max_depth})")
    dtype = tree_dtype(parts.trainable)
    # private copies: the runner donates the carry, which must not alias the caller's arrays
    images = jnp.array(resources[REPLAY_IMAGES], dtype, copy=True)
    check(config.replay == 0 or images.shape[0] > 0, "comoda: the replay set is empty")
    check(images.shape[1] == config.window,
          f"comoda: replay windows of {images.shape[1]} frames, latency {config.latency} "
          f"needs {config.window}")
    net = resources[POSE]
    as_dtype = lambda t: jax.tree_util.tree_map(lambda x: jnp.array(x, dtype, copy=True), t)
    psplit = trainable_lib.split(net.variables, trainable_lib.parse_selector(SELECTOR))
    ptr = as_dtype(psplit.trainable)
    pose = PoseState(net.module, ptr, as_dtype(psplit.frozen), as_dtype(psplit.batch_stats),
                     optimizer(config).init(ptr))
    return {"pose": pose,
            "ring": _frame_ring(images.shape[2:4], cfg.max_segments, 1 + config.latency, dtype),
            "replay_images": images,
            "replay_K": jnp.array(resources[REPLAY_K], dtype, copy=True),
            "ld_weight": jnp.asarray(config.ld_weight, dtype)}

  def update(state, grads, loss_value, aux, rng, tx, cfg):
    """Adam on both networks under one non-finite guard (engine.optax_update's: the loss, a
    gradient, new parameters or a new optimiser state not finite -> neither network moves,
    n_skipped counts it); nothing moves on an inactive frame; the frame joins the ring."""
    del rng, tx  # tx is `optimizer(config)`, stepped here on the raveled trees
    ms = state.method_state
    pose: PoseState = ms["pose"]
    c = aux.carry
    d = flat_step(_adam(config), state.trainable, grads, state.opt_state)
    p = flat_step(_adam(config), pose.trainable, c["pose_grads"], pose.opt_state)
    ok = jnp.isfinite(loss_value) & d.finite & p.finite if cfg.skip_nonfinite else jnp.array(True)
    move, skipped = c["active"] & ok, c["active"] & ~ok
    pose = pose.replace(trainable=p.unravel(jnp.where(move, p.new, p.old)),
                        opt_state=select(move, p.opt_state, pose.opt_state))
    ring = {name: ring_push(r, getattr(c["frame"], name))
            for name, r in _rings_before(ms["ring"], c["frame"]).items()}
    state = state.replace(
        trainable=d.unravel(jnp.where(move, d.new, d.old)),
        opt_state=select(move, d.opt_state, state.opt_state),
        n_skipped=state.n_skipped + skipped.astype(jnp.int32),
        method_state={**ms, "pose": pose, "ring": ring})
    return state, skipped, jnp.where(move, jnp.sqrt(jnp.sum(d.update * d.update)), 0.0)

  def prepare(model, variables, source):
    del model, variables
    return replay_set(source, config)

  return Method("comoda", config, init=init, loss=loss, update=update,
                optimizer=lambda cfg: optimizer(config), prepare=prepare,
                requires=(("bn_stats", "running", "runs BatchNorm in eval mode"),
                          ("selector", SELECTOR, "adapts every weight except BatchNorm "
                                                 "scale/bias"),
                          ("steps_per_frame", 1, "makes one step per frame")),
                needs=("pose", "intrinsics", "previous_frame"),
                report_after_update=config.latency == 1)
