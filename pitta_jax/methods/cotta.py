"""CoTTA (Wang et al., CVPR 2022) for depth, as a baseline of the paper, with PITTA's L_d added.

Upstream (`cifar/cotta.py`, `forward_and_adapt`): a student (the adapted network), a mean
teacher (EMA of the student, decay `mt`) and a frozen anchor (the source). The teacher's
prediction averaged over N = 32 augmented views is the pseudo label where the anchor is not
confident, else the teacher's plain prediction; the student is trained towards it; then the
teacher moves (EMA) and each trainable element is restored to the source with probability p.

For depth (our choices, the paper gives none):
- prediction = the network's scale-0 disparity (`model.outputs(...)[0]`, (H, W));
- the gate: upstream takes the augmented mean where the anchor is not confident (the
  classification code when the batch's mean max-probability is below `ap`, 0.92 on CIFAR-10;
  the dense code per pixel, where the anchor's class probability is below 0.69, a 5% quantile
  of the source domain), so under a domain shift the augmented mean is the label from the first
  frame on. A depth network has no class probability. `gate="always"` (default) takes the
  augmented mean everywhere; `gate="spread"` is a per-pixel stand-in for the dense rule: the
  augmented mean where the views disagree, their relative spread std / mean (unbiased std, as
  `torch.std`) above `threshold`, else the teacher's single view. (A gate on the anchor's
  disagreement with the teacher, which these steps used before, cannot fire: the teacher
  starts as the anchor and its EMA at 0.999 barely leaves it, so the method was a mean teacher
  without its augmentation.);
- loss: L1 (mean over pixels) between the student's disparity and the pseudo label
  (stop-gradient), in place of the soft cross-entropy, + ld_weight * L_d (eq. 8) on the
  student's depth (paper Sec. 4.1);
- augmentations: upstream's photometric ones (`get_tta_transforms`, non-soft ranges): colour
  jitter (brightness, contrast, saturation, gamma in a random order per view; hue is not
  implemented), 5x5 Gaussian blur (on the edge-padded image, as upstream's pad-blur-crop),
  horizontal flip with p 0.5 (the prediction is flipped back),
  Gaussian noise, clipping to [0, 1]; no affine warp (a warped disparity map would need warping
  back and its border filled). The N views (with gate 'spread' also the plain image) go
  through the teacher as one batch;
- the evaluated depth is the depth of the pseudo label (what upstream's forward returns); with
  `AdaptConfig.steps_per_frame` > 1 that of the last inner step, drawn after the steps before it
  (`Method.report_last_step`: upstream's `steps` loop returns its last pass's output).

BatchNorm is in eval mode (running statistics) for all three networks, so a view's prediction
does not depend on the other views: the method requires `AdaptConfig.bn_stats == "running"`.
(Upstream's classification CoTTA sets `track_running_stats=False` before copying the teacher
and the anchor, so all three normalise with the statistics of the test batch, each augmented
view with its own; with one frame per step, batch statistics would be those of one image.)
The restore target (upstream's anchor, the source) is the engine's `state.source` (the
trainable leaves at the start); the teacher is in the method state. Which leaves adapt is
`AdaptConfig.selector` (upstream adapts every weight and bias: `--selector all`). With
`reset_every`, the engine resets the student and its optimiser and the teacher is copied from
the source again, as upstream's `reset()` does (the anchor is the source throughout).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from pitta_jax import nonsmooth, prng
from pitta_jax import trainable as trainable_lib
from pitta_jax.configs import check, check_types, is_number, finite, option
from pitta_jax.dtypes import tree_dtype
from pitta_jax.methods.base import Aux, Method, variables_of
from pitta_jax.methods.depth_refining import DepthRefiningConfig, depth_refining_term

JITTERS = ("brightness", "contrast", "saturation", "gamma")  # the order index of AugParams
GATES = ("always", "spread")  # CottaConfig.gate
# the most augmented views taken (32x upstream's 32): the views are one batch of the teacher's
# forward, and far more than this only ends in an allocation failure (10^12 overflowed an index)
MAX_AUGMENT = 1024


@dataclasses.dataclass(frozen=True)
class CottaConfig:
  """CoTTA's knobs (upstream cifar/cotta.py, get_tta_transforms non-soft) and the paper's L_d."""
  n_augment: int = option(32, f"N augmented teacher views, 1..{MAX_AUGMENT} (upstream: 32)")
  gate: str = option("always", "where the pseudo label is the augmented mean: 'always' (upstream "
                               "under a domain shift, where the anchor is not confident) or "
                               "'spread' (per pixel, where the views' std / mean > threshold)")
  threshold: float = option(0.1, "gate='spread': the views' relative spread above which a pixel "
                                 "takes the augmented mean")
  ema_decay: float = option(0.999, "teacher EMA decay (upstream: 0.999 on CIFAR and ImageNet-C)")
  restore_p: float = option(0.01, "probability of restoring each trainable element to the source "
                                  "per step (upstream: 0.01 on CIFAR-10, 0.001 in its ImageNet-C "
                                  "code)")
  lr: float = option(1e-4 / 12, "Adam learning rate (CoTTA's rule for dense prediction)")
  brightness: float = option(0.4, "brightness factor uniform in [1 - b, 1 + b] (upstream)")
  contrast: float = option(0.3, "contrast factor uniform in [1 - c, 1 + c] (upstream)")
  saturation: float = option(0.5, "saturation factor uniform in [1 - s, 1 + s] (upstream)")
  gamma: float = option(0.3, "gamma uniform in [1 - g, 1 + g] (upstream)")
  blur_sigma_min: float = option(0.001, "5x5 Gaussian blur sigma, lower end (upstream)")
  blur_sigma_max: float = option(0.5, "5x5 Gaussian blur sigma, upper end (upstream)")
  flip_p: float = option(0.5, "probability of a horizontal flip per view")
  noise_std: float = option(0.005, "Gaussian noise standard deviation")
  ld_weight: float = option(1.0, "weight of PITTA's L_d (eq. 8) added to the loss (paper Sec. 4.1)")
  ld: DepthRefiningConfig = DepthRefiningConfig()

  def __post_init__(self):
    check_types(self)
    check(1 <= self.n_augment <= MAX_AUGMENT,
          f"n_augment must be in 1..{MAX_AUGMENT}, got {self.n_augment}")
    check(self.gate in GATES, f"gate must be one of {', '.join(GATES)}, got {self.gate!r}")
    check(self.gate != "spread" or self.n_augment >= 2,
          f"gate='spread' needs n_augment >= 2 (the views' spread), got {self.n_augment}")
    finite(self.threshold, "threshold", 0.0)
    check(0.0 <= self.ema_decay <= 1.0, f"ema_decay must be in [0, 1], got {self.ema_decay}")
    check(0.0 <= self.restore_p <= 1.0, f"restore_p must be in [0, 1], got {self.restore_p}")
    finite(self.lr, "lr", 0.0)
    for name in ("brightness", "contrast", "saturation", "gamma"):
      value = getattr(self, name)
      check(is_number(value) and 0.0 <= value < 1.0,
            f"{name} must be in [0, 1), got {value!r}")
    finite(self.blur_sigma_min, "blur_sigma_min", 0.0)
    finite(self.blur_sigma_max, "blur_sigma_max", 0.0)  # an inf draws inf (or NaN) sigmas
    # the fields' names, so that the command's error names both flags
    check(0.0 < self.blur_sigma_min <= self.blur_sigma_max,
          f"need 0 < blur_sigma_min <= blur_sigma_max, got {self.blur_sigma_min}, "
          f"{self.blur_sigma_max}")
    check(0.0 <= self.flip_p <= 1.0, f"flip_p must be in [0, 1], got {self.flip_p}")
    finite(self.noise_std, "noise_std", 0.0)
    finite(self.ld_weight, "ld_weight", 0.0)


class AugParams(NamedTuple):
  """The random draws of N views (explicit, so a test can pass the same ones to PyTorch)."""
  order: jax.Array    # (N, 4) int32, a permutation of JITTERS per view
  factors: jax.Array  # (N, 4) brightness, contrast, saturation, gamma factors
  sigma: jax.Array    # (N,) blur sigma
  flip: jax.Array     # (N,) bool
  noise: jax.Array    # (N, H, W, 3) the additive noise (already times noise_std)


def sample_augment(rng: jax.Array, n: int, height: int, width: int, config: CottaConfig,
                   dtype=jnp.float32) -> AugParams:
  """N views' parameters, uniform in the configured ranges (as torchvision's `uniform_`); drawn
  through `prng.unrolled` (the same numbers as jax.random's threefry, faster on CPU)."""
  k_order, k_fac, k_sig, k_flip, k_noise = jax.random.split(prng.unrolled(rng), 5)
  order = jax.vmap(lambda k: jax.random.permutation(k, len(JITTERS)))(jax.random.split(k_order, n))
  spread = jnp.asarray([config.brightness, config.contrast, config.saturation, config.gamma], dtype)
  factors = jax.random.uniform(k_fac, (n, 4), dtype, 1.0 - spread, 1.0 + spread)
  sigma = jax.random.uniform(k_sig, (n,), dtype, config.blur_sigma_min, config.blur_sigma_max)
  flip = jax.random.bernoulli(k_flip, config.flip_p, (n,))
  noise = config.noise_std * jax.random.normal(k_noise, (n, height, width, 3), dtype)
  return AugParams(order.astype(jnp.int32), factors, sigma, flip, noise)


def _gray(x: jax.Array) -> jax.Array:
  """(H, W, 3) -> (H, W, 1), torchvision's rgb_to_grayscale weights."""
  return (0.2989 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2])[..., None]


def _jitter(x: jax.Array, which: jax.Array, factors: jax.Array) -> jax.Array:
  """One of torchvision's adjust_{brightness, contrast, saturation, gamma} (float image)."""
  def blend(other, f):
    return jnp.clip(f * x + (1.0 - f) * other, 0.0, 1.0)
  branches = (
      lambda: blend(jnp.zeros_like(x), factors[0]),
      lambda: blend(jnp.mean(_gray(x)), factors[1]),
      lambda: blend(_gray(x), factors[2]),
      # upstream clamps to [1e-8, 1] before the power (NaN gradients otherwise)
      lambda: jnp.clip(jnp.clip(x, 1e-8, 1.0) ** factors[3], 0.0, 1.0))
  return jax.lax.switch(which, branches)


def _blur(x: jax.Array, sigma: jax.Array) -> jax.Array:
  """torchvision's gaussian_blur, kernel 5, separable, on the edge-padded image: upstream pads
  by half the image size (`transforms.Pad(padding_mode="edge")`) before its affine warp and
  blur and centre-crops after them, so without the warp the blur's border sees replicated
  edge pixels. x (H, W, 3)."""
  taps = jnp.arange(-2.0, 3.0, dtype=x.dtype)
  k = jnp.exp(-0.5 * (taps / sigma) ** 2)
  k = k / jnp.sum(k)
  p = jnp.pad(x, ((2, 2), (2, 2), (0, 0)), mode="edge")
  h, w = x.shape[:2]
  rows = sum(k[i] * p[i:i + h] for i in range(5))            # (H, W + 4, 3)
  return sum(k[i] * rows[:, i:i + w] for i in range(5))


def jitter_view(image: jax.Array, order: jax.Array, factors: jax.Array) -> jax.Array:
  """One view's colour jitter: clip `image` (H, W, 3) to [0, 1], then the four adjustments in
  the view's `order` (4,) with its `factors` (4,)."""
  x = jnp.clip(image, 0.0, 1.0)
  for step in range(len(JITTERS)):
    x = _jitter(x, order[step], factors)
  return x


def augment_views(image: jax.Array, params: AugParams) -> jax.Array:
  """The N augmented views (N, H, W, 3) of `image` (H, W, 3) in upstream's order: clip, colour
  jitter (random order), blur, flip, noise, clip.

  The jitter runs one view at a time (`lax.map`), so each step computes only the adjustment its
  view draws; batched (`vmap`), `lax.switch` becomes a select over all four adjustments of every
  view, and 32 views of 640x192 took 2.8x as long (most of it the gamma's power, computed four
  times per view instead of once). Blur, flip and noise are batched."""
  jittered = jax.lax.map(lambda p: jitter_view(image, *p), (params.order, params.factors))

  def finish(x, sigma, flip, noise):
    x = _blur(x, sigma)
    x = jnp.where(flip, x[:, ::-1], x)
    return jnp.clip(x + noise, 0.0, 1.0)
  return jax.vmap(finish)(jittered, params.sigma, params.flip, params.noise)


def teacher_predictions(model, variables, image: jax.Array, params: AugParams, plain: bool
                        ) -> tuple[jax.Array | None, jax.Array]:
  """The teacher's disparity of `image` (H, W) if `plain` (else None), and its N augmented views'
  disparities (N, H, W), each flipped back, from one batched forward of the images (BN eval
  mode: the views do not see each other)."""
  views = augment_views(image, params)
  batch = jnp.concatenate([image[None], views]) if plain else views
  disp = model.outputs(variables, batch, False)[0][..., 0]
  single, disp = (disp[0], disp[1:]) if plain else (None, disp)             # (H, W), (N, H, W)
  return single, jnp.where(params.flip[:, None, None], disp[:, :, ::-1], disp)


def pseudo_label(single: jax.Array | None, views: jax.Array, mcfg: CottaConfig
                 ) -> tuple[jax.Array, jax.Array]:
  """(pseudo label (H, W), gate (H, W) bool: where it is the views' mean) from the teacher's
  single view (H, W) (None for gate 'always') and its augmented views (N, H, W)."""
  averaged = jnp.mean(views, axis=0)
  if mcfg.gate == "always":
    return averaged, jnp.ones(averaged.shape, bool)
  gate = jnp.std(views, axis=0, ddof=1) / averaged > mcfg.threshold
  return jnp.where(gate, averaged, single), gate


def restore_masks(rng: jax.Array, tree, p: float):
  """Bernoulli(p) masks shaped like `tree`'s leaves (True = restore to the source).

  One draw for all leaves' elements, cut into the leaves' shapes: a draw per leaf (as upstream's
  `torch.rand(p.shape)` loop) gives XLA one random-bits program per leaf, and MonoDepth2's 88
  leaves took 24 s to compile instead of 3 s. The masks' law is the same (i.i.d. elements).
  The draw goes through `prng.unrolled` (jax.random's numbers, faster on CPU)."""
  leaves, treedef = jax.tree_util.tree_flatten(tree)
  draw = jax.random.bernoulli(prng.unrolled(rng), p, (sum(x.size for x in leaves),))
  masks, start = [], 0
  for x in leaves:
    masks.append(draw[start:start + x.size].reshape(x.shape))
    start += x.size
  return jax.tree_util.tree_unflatten(treedef, masks)


def _disp(model, variables, image):
  return model.outputs(variables, image[None], False)[0][0, ..., 0]


def loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg: CottaConfig):
  """L1(student disparity, gated teacher pseudo label) + ld_weight * L_d(student depth)."""
  del cfg
  ms = state.method_state
  sg = jax.lax.stop_gradient
  student = _disp(model, variables_of(trainable, consts), frame.image)      # (H, W)
  teacher_vars = trainable_lib.merge(ms["teacher"], consts.frozen, consts.batch_stats)
  h, w = frame.image.shape[:2]
  params = sample_augment(rng, mcfg.n_augment, h, w, mcfg, frame.image.dtype)
  single, views = sg(teacher_predictions(model, teacher_vars, frame.image, params,
                                         plain=mcfg.gate != "always"))
  pseudo, gate = pseudo_label(single, views, mcfg)
  own = jnp.mean(nonsmooth.absolute(student - pseudo))
  l_d, n = depth_refining_term(model.spec.to_depth(student), frame, mcfg.ld)
  total = own + ms["ld_weight"] * l_d
  logs = {"loss_cotta": own, "loss_d": l_d, "n_instances": n,
          "gate_fraction": jnp.mean(gate.astype(student.dtype))}
  return total, sg(Aux(model.spec.to_depth(pseudo), logs))


def build(config: CottaConfig = CottaConfig()) -> Method:
  """CoTTA with `config` bound. method_state = {"teacher": the EMA of the trainable leaves,
  "ld_weight": ()}; Adam(config.lr) replaces AdaptConfig's optimiser."""
  from pitta_jax.adapt.engine import optax_update

  def init(model, parts, cfg, resources):
    del model, resources
    check(cfg.bn_stats == "running",
          "cotta runs BatchNorm in eval mode: use bn_stats='running' (--bn-stats running)")
    teacher = jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), parts.trainable)
    dtype = tree_dtype(teacher)
    return {"teacher": teacher, "ld_weight": jnp.asarray(config.ld_weight, dtype)}

  def update(state, grads, loss_value, aux, rng, tx, cfg):
    """Adam step (with the non-finite guard), teacher EMA, stochastic restore (upstream order).

    Leaf by leaf. The same update on the raveled vector (`pitta_jax.flat_optim`, as CoMoDa's)
    compiled in fewer kernels (640x192, 2 vCPU Intel, 2026-12-05: 2004 -> 1453, XLA's compile
    26.0-26.1 -> 22.2-22.8 s) but its concatenations and splits of the student, teacher, source
    and gradient made the step 4% slower (4051 vs 3896 ms/frame, medians of 4 interleaved)."""
    del aux
    state, skipped, unorm = optax_update(state, grads, loss_value, tx, cfg)
    a = config.ema_decay
    teacher = jax.tree_util.tree_map(lambda t, s: a * t + (1.0 - a) * s,
                                     state.method_state["teacher"], state.trainable)
    masks = restore_masks(rng, state.trainable, config.restore_p)
    restored = jax.tree_util.tree_map(jnp.where, masks, state.source, state.trainable)
    state = state.replace(trainable=restored,
                          method_state={**state.method_state, "teacher": teacher})
    return state, skipped, unorm

  def reset(method_state, source):
    """Upstream's `reset()`: the teacher starts again from the (restored) source weights."""
    return {**method_state, "teacher": source}

  return Method("cotta", config, init=init, loss=loss, update=update, reset=reset,
                # upstream's forward returns its last `steps` pass's teacher output
                report_last_step=True,
                optimizer=lambda cfg: optax.adam(config.lr),
                requires=(("bn_stats", "running", "runs BatchNorm in eval mode"),),
                setting=(("selector", "all"),))
