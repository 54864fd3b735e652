"""ActMAD (Mirza et al., CVPR 2023) as a baseline of the paper, with PITTA's L_d added (Sec. 4.1).

ActMAD aligns the test-time activation statistics of chosen BatchNorm layers with the source
statistics: for each layer l, the mean and the (unbiased) variance over the batch axis *per
location* (h, w, c), and

    L_actmad = sum_l [ mean_hwc |mu_l - mu_l^src| + mean_hwc |var_l - var_l^src| ]

(upstream `methods/actmad_kitti.py`: `nn.L1Loss(reduction="mean")` per layer on
`SaveOutput.get_out_mean/var`, i.e. `torch.mean/var(dim=0)` of the BN outputs, summed over
layers; BN layers in eval mode, all parameters trained with SGD, lr, momentum 0.9, Nesterov,
weight decay 5e-4). Here the layers are all 20 BatchNorms of the ResNet-18 encoder
(`ActmadConfig.layers`), and the total loss is L_actmad + ld_weight * L_d (eq. 8) on the depth of
the same forward pass.

Online, batch 1 has no variance, so the batch is the current frame (with gradient) plus the
last K frames' activations (a FIFO in the method state, stop-gradient; `base.ring_*`). On the
very first frame (n = 1) the variance is 0 (divisor max(n - 1, 1)), so only the mean term moves
the parameters. The ring holds the activations of each frame as computed before its update,
and keeps them across a recording's start (`StepInput.starts_recording`): the ring stands in for
a batch, whose images upstream draws independently, not for a frame's neighbours.
`AdaptConfig.reset_every` empties it with the weights put back (as at the start).

BatchNorm runs in eval mode (running statistics) as upstream: the method requires
`AdaptConfig.bn_stats == "running"` and fails at init otherwise. The frame's depth is evaluated
after its update (`report_after_update`): upstream adapts on the whole test set and tests it
afterwards, which is not online; testing each frame after its own update is the nearest online
reading (docs/method.md). The frame joins the ring once, so one update per frame is required
(`steps_per_frame == 1`).

Which parameters adapt (our choice): every encoder conv kernel and BN scale/bias
(`--selector 'fraction(cnn=100,bn=100)'`, the method's setting), never the decoder. Upstream's
SGD takes all of `model.parameters()` and moves whatever gets a gradient: ActMAD's own loss
reaches only the encoder, so without L_d (`ld_weight=0`) the two are the same; with L_d, the
paper's addition computed on the decoder's output, upstream's optimiser would also step the
decoder. We keep ActMAD's reach so that L_d changes its loss, not the set of weights it adapts;
`--selector all` gives the other reading (the decoder then also decays with weight_decay where
L_d is 0). Source statistics come in `resources["actmad_source_stats"]`
({layer path: (mean (h, w, c), var (h, w, c))}), computed once by `source_statistics`.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, Iterable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from pitta_jax import nonsmooth
from pitta_jax.configs import check, check_types, finite, option
from pitta_jax.methods.base import (Aux, Method, ring_init, ring_push, ring_restart,
                                    ring_valid, variables_of)
from pitta_jax.methods.depth_refining import DepthRefiningConfig, depth_refining_term

RESOURCE = "actmad_source_stats"
ENCODER_BN = r"encoder/(.*/)?(bn\d*|downsample_bn)"  # the 20 BatchNorms of a ResNet-18 encoder


@dataclasses.dataclass(frozen=True)
class ActmadConfig:
  """ActMAD's knobs (upstream methods/actmad_kitti.py) and the paper's added L_d."""
  layers: str = option(ENCODER_BN, "regular expression over module paths: the BatchNorm layers "
                                   "whose outputs are aligned (default: every encoder BN)")
  ring_size: int = option(8, "K: previous frames' activations kept for the batch statistics "
                             "(batch 1 has no variance)")
  lr: float = option(1e-4, "SGD learning rate (upstream's KITTI setting)")
  momentum: float = option(0.9, "SGD momentum (upstream)")
  nesterov: bool = option(True, "Nesterov momentum (upstream)")
  weight_decay: float = option(5e-4, "L2 weight decay added to the gradient, as torch SGD (upstream)")
  ld_weight: float = option(1.0, "weight of PITTA's L_d (eq. 8) added to the loss (paper Sec. 4.1)")
  ld: DepthRefiningConfig = DepthRefiningConfig()

  def __post_init__(self):
    check_types(self)
    try:
      re.compile(self.layers)
    except re.error as e:
      raise ValueError(f"layers {self.layers!r}: not a regular expression ({e})") from None
    check(self.ring_size >= 1, f"ring_size must be >= 1, got {self.ring_size}")
    finite(self.lr, "lr", 0.0)
    finite(self.momentum, "momentum", 0.0)
    check(self.momentum < 1.0, f"momentum must be < 1, got {self.momentum}")
    finite(self.weight_decay, "weight_decay", 0.0)
    finite(self.ld_weight, "ld_weight", 0.0)


def optimizer(config: ActmadConfig) -> optax.GradientTransformation:
  """torch.optim.SGD(lr, momentum, weight_decay, nesterov): decay added to the gradient first."""
  return optax.chain(optax.add_decayed_weights(config.weight_decay),
                     optax.sgd(config.lr, momentum=config.momentum or None,
                               nesterov=config.nesterov))


def _bn_hint(model, variables) -> str:
  """The network's encoder BatchNorm layers (`trainable.encoder_layers`), for an error about a
  `layers` regex that matches none: the default names MonoDepth2's (`bn1`, `downsample_bn`),
  while a network of one's own built on `flax.linen.BatchNorm` has `BatchNorm_0`, ...; empty
  when the encoder has none."""
  from pitta_jax.trainable import encoder_layers
  encoder = getattr(getattr(model, "spec", None), "encoder", "encoder")
  paths = encoder_layers(variables, "bn", encoder)
  if not paths:
    return ""
  more = f", ... ({len(paths)} in all)" if len(paths) > 4 else ""
  return f"; the encoder's BatchNorm layers are {', '.join(paths[:4])}{more}"


def source_statistics(model, variables, images: Iterable[Any], layers: str = ENCODER_BN
                      ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
  """Per-location mean and unbiased variance of each matched layer's output over source images.

  model: a `registry.Network`; variables: its Flax variables; images: an iterable of batches
  (B, H, W, 3) in [0, 1], all of one size (the size adaptation runs at). BN in eval mode.
  Returns {path: (mean (h, w, c), var (h, w, c))}, accumulated in float64 with Chan's parallel
  update, i.e. the statistics of the whole set. (Upstream averages per-batch means and per-batch
  variances with an AverageMeter, each batch weighing the same: that equals these for the mean
  when every batch has the same size, and for the variance only up to the between-batch spread
  and the per-batch N - 1.)
  """
  capture = jax.jit(lambda v, x: model.capture(v, x, False, layers)[1])
  count, means, m2s = 0, {}, {}
  for batch in images:
    acts = {k: np.asarray(a, np.float64) for k, a in capture(variables, jnp.asarray(batch)).items()}
    check(len(acts) > 0, f"layers {layers!r} (--actmad.layers) matches no module of the "
                         f"network whose output is one feature map{_bn_hint(model, variables)}")
    b = next(iter(acts.values())).shape[0]
    for k, a in acts.items():
      mean_b, m2_b = a.mean(0), ((a - a.mean(0)) ** 2).sum(0)
      if k not in means:
        means[k], m2s[k] = mean_b, m2_b
        continue
      delta = mean_b - means[k]
      means[k] = means[k] + delta * b / (count + b)
      m2s[k] = m2s[k] + m2_b + delta ** 2 * count * b / (count + b)
    count += b
  check(count >= 2, f"source statistics need at least 2 images (unbiased variance), got {count}")
  check(len(means) > 0, f"no module matches {layers!r}")
  dtype = np.asarray(jax.tree_util.tree_leaves(variables)[0]).dtype
  return {k: (means[k].astype(dtype), (m2s[k] / (count - 1)).astype(dtype)) for k in means}


def batch_moments(current: jax.Array, ring: dict[str, jax.Array]) -> tuple[jax.Array, jax.Array]:
  """Mean and unbiased variance over {current} + the ring's valid entries, per location.

  current: (h, w, c) (differentiable); ring: `ring_init` of (h, w, c) items (constants).
  Divisor max(n - 1, 1): with no previous frame the variance is 0.

  The sums over the K ring slots are written slot by slot (elementwise adds; so is the
  gradient's sum over the broadcast mean): XLA:CPU hands a reduction over the leading axis of
  a (K, h, w, c) array to YNNPACK's reduce, which ran these few passes over memory so slowly
  that they took most of the step (640x192, K = 8, 2 vCPUs: 1031 -> 392 ms/frame).
  """
  w = ring_valid(ring).astype(current.dtype)                             # (K,)
  past = jax.lax.stop_gradient(ring["items"])
  slots = range(past.shape[0])
  n = 1.0 + jnp.sum(w)
  mean = (current + sum(w[i] * past[i] for i in slots)) / n
  ss = (current - mean) ** 2 + sum(w[i] * (past[i] - mean) ** 2 for i in slots)
  return mean, ss / jnp.maximum(n - 1.0, 1.0)


def loss(trainable, *, state, consts, frame, rng, model, cfg, mcfg: ActmadConfig):
  """L_actmad (over the frame + ring) + ld_weight * L_d of the frame's depth (BN eval mode)."""
  del rng, cfg
  ms = state.method_state
  out, acts = model.capture(variables_of(trainable, consts), frame.image[None], False, mcfg.layers)
  depth = model.spec.to_depth(out[0][0, ..., 0])                          # (H, W)
  l_mean = l_var = jnp.zeros((), depth.dtype)
  for path, (src_mean, src_var) in ms["source"].items():
    mean, var = batch_moments(acts[path][0], ms["rings"][path])
    l_mean = l_mean + jnp.mean(nonsmooth.absolute(mean - src_mean))
    l_var = l_var + jnp.mean(nonsmooth.absolute(var - src_var))
  l_d, n = depth_refining_term(depth, frame, mcfg.ld)
  own = l_mean + l_var
  total = own + ms["ld_weight"] * l_d
  logs = {"loss_actmad": own, "loss_mean": l_mean, "loss_var": l_var, "loss_d": l_d,
          "n_instances": n}
  carry = {p: acts[p][0] for p in ms["source"]}
  return total, jax.lax.stop_gradient(Aux(depth, logs, carry))


def build(config: ActmadConfig = ActmadConfig()) -> Method:
  """ActMAD with `config` bound. method_state = {"source": {path: (mean, var)}, "rings": {path:
  ring of (h, w, c)}, "ld_weight": ()} (ld_weight in the state: one compile serves a sweep)."""
  from pitta_jax.adapt.engine import all_finite, optax_update

  def init(model, parts, cfg, resources):
    del model, parts
    check(cfg.bn_stats == "running",
          "actmad runs BatchNorm in eval mode: use bn_stats='running' (--bn-stats running)")
    check(RESOURCE in resources, f"actmad needs resources[{RESOURCE!r}] "
                                 "(methods.actmad.source_statistics of source images)")
    # private copies: the runner donates the carry, which must not alias the caller's arrays
    source = {k: (jnp.array(m, copy=True), jnp.array(v, copy=True))
              for k, (m, v) in resources[RESOURCE].items()}
    return {"source": source,
            "rings": {k: ring_init(m, config.ring_size) for k, (m, _) in source.items()},
            "ld_weight": jnp.asarray(config.ld_weight, next(iter(source.values()))[0].dtype)}

  def update(state, grads, loss_value, aux, rng, tx, cfg):
    del rng
    state, skipped, unorm = optax_update(state, grads, loss_value, tx, cfg)
    ms = state.method_state
    ok = all_finite(aux.carry)  # a non-finite frame must not poison the ring
    rings = {k: jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b),
                                       ring_push(r, aux.carry[k]), r)
             for k, r in ms["rings"].items()}
    return state.replace(method_state={**ms, "rings": rings}), skipped, unorm

  def reset(method_state, source):
    """`AdaptConfig.reset_every`: the ring is emptied with the weights put back, as at the
    start; its activations came from the weights that the reset discards."""
    del source
    return {**method_state, "rings": {k: ring_restart(r, jnp.array(True))
                                      for k, r in method_state["rings"].items()}}

  def prepare(model, variables, source):
    return {RESOURCE: source_statistics(model, variables, source.batches(), config.layers)}

  return Method("actmad", config, init=init, loss=loss, update=update, reset=reset,
                optimizer=lambda cfg: optimizer(config), prepare=prepare,
                requires=(("bn_stats", "running", "runs BatchNorm in eval mode"),
                          ("steps_per_frame", 1, "adds each frame to its ring once")),
                # upstream tests after adapting (the nearest online reading: after the update)
                report_after_update=True,
                setting=(("selector", "fraction(cnn=100,bn=100)"),))
