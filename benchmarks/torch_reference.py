"""PyTorch steps as a performance-minded PyTorch user writes them: the timing references.

PITTA (`TorchPitta`), same configuration as the JAX engine's default (docs/method.md):
MonoDepth2 ResNet-18 with upstream's modules (`tests/torch_monodepth2.py`), batch 1, train-mode
BatchNorm with the frame's batch statistics and the running statistics untouched (TENT's
`configure_model`: `track_running_stats = False`, running buffers dropped), only the encoder BN
gamma/beta adapted by Adam (lr 1e-4), one step per frame, loss eqs. 5-10:

- instance masks M_j from the panoptic id map (binary g_j = 1), eqs. 3-4;
- pseudo labels D~'_j by a median filter with the border-shrinking window (eq. 7): `F.unfold`
  of the NaN-padded masked depths and `nanmedian` over each window, all N maps in one call.
  `nanmedian` returns the lower middle value; eq. 7 wants the mean of the two middle values when
  the window count c is even, which happens only within s // 2 pixels of the border, so there
  (a few thousand windows) the upper middle value, -nanmedian(-w), is averaged in;
- L_d = 1/N sum_j sum |D~_j - D~'_j| (eq. 8), literally over the N instances, batched;
- Laplacian edge maps with clamped (replicated) borders on the channel-mean image and the depth,
  L_e = sum |dI - dD| (eqs. 5, 6, 9); L = L_d + lambda L_e (eq. 10).

Optimisers: `fused=True` (`FUSED_OPTIMIZERS`). On CPU tensors PyTorch's Adam and SGD default to
their per-tensor for-loop; the fused CPU kernels (PyTorch >= 2.4) update each tensor in one pass.
On 28.6 M parameters (two MonoDepth2 depth networks' worth, 2 vCPUs of an Intel Xeon, PyTorch
2.13): Adam 106 ms per step as the for-loop, 77 with `foreach=True`, 22 fused; SGD (Nesterov,
weight decay) on 23.6 M: 40, 45 and 13 ms. `fused=False` gives the for-loop (step.py
`--compare-torch-optimizers`).

Options a PyTorch user reaches for: `memory_format=torch.channels_last` (oneDNN's preferred
layout on CPU) and `compile=True` (`torch.compile` with inductor of the depth + loss function,
forward and backward; the optimiser step stays eager). Predict-then-adapt as in the engine: the
returned depth is the one the loss was computed on.

The baselines' steps, in the method's own setting (`pitta_jax.methods.method_setting`), same
loss as the JAX method, written as their upstream code does it:
- `TorchNone`: eval mode, `torch.no_grad()` forward;
- `TorchActmad` (jmiemirza/ActMAD): BN eval mode, forward hooks on the 20 encoder BNs, a
  `deque(maxlen=K)` of previous frames' detached activations, L1 of the per-location mean and
  variance against the source statistics, + L_d; SGD (Nesterov, weight decay) on every encoder
  conv and BN parameter;
- `TorchCotta` (qinenergy/cotta): student and EMA teacher (`deepcopy`), N augmented views
  (upstream's loop of per-view transforms, `tests/torch_tta.t_augment`) through the teacher as
  one batch, their mean as the pseudo label (or the method's per-pixel gate), L1 + L_d; Adam on
  every parameter, EMA, stochastic restore.
"""

from __future__ import annotations

import collections
import copy
import math
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import torch_monodepth2 as tm  # noqa: E402  (upstream layer structure)

MIN_DEPTH, MAX_DEPTH = 0.1, 100.0
FUSED_OPTIMIZERS = True  # the references' default: PyTorch's fused CPU optimiser kernels
DYNAMIC_COCO_IDS = (1, 2, 3, 4, 6, 7, 8)  # person, bicycle, car, motorcycle, bus, train, truck


def disp_to_depth(disp: torch.Tensor) -> torch.Tensor:
  """MonoDepth2's sigmoid disparity -> depth (paper Sec. 3, MonoDepth2)."""
  min_disp, max_disp = 1.0 / MAX_DEPTH, 1.0 / MIN_DEPTH
  return 1.0 / (min_disp + (max_disp - min_disp) * disp)


def even_count_pixels(h: int, w: int, s: int) -> torch.Tensor:
  """Flat indices of the pixels whose border-shrunk s x s window holds an even count."""
  r = s // 2
  i, j = torch.arange(h), torch.arange(w)
  rows = (i + r).clamp(max=h - 1) - (i - r).clamp(min=0) + 1  # (H,)
  cols = (j + r).clamp(max=w - 1) - (j - r).clamp(min=0) + 1  # (W,)
  return ((rows[:, None] * cols[None, :]) % 2 == 0).flatten().nonzero().flatten()


def median_filter(x: torch.Tensor, s: int = 5) -> torch.Tensor:
  """Eq. 7 on a batch of maps: x (B, H, W) -> (B, H, W), window shrinking at the border."""
  b, h, w = x.shape
  r = s // 2
  padded = F.pad(x[:, None], (r, r, r, r), value=math.nan)  # out-of-image slots are ignored
  windows = F.unfold(padded, s)  # (B, s*s, H*W)
  med = windows.nanmedian(1).values  # (B, H*W), the lower middle value
  even = even_count_pixels(h, w, s)
  if even.numel():  # eq. 7: mean of the two middle values for even counts
    upper = -(-windows[:, :, even]).nanmedian(1).values
    med[:, even] = (med[:, even] + upper) / 2
  return med.view(b, h, w)


def laplacian_edges(x: torch.Tensor) -> torch.Tensor:
  """|4-neighbour Laplacian| with clamped indices, eqs. 5-6 (U = V = 1): (H, W) -> (H, W)."""
  p = F.pad(x[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
  lap = (p[2:, 1:-1] + p[:-2, 1:-1]) + (p[1:-1, 2:] + p[1:-1, :-2]) - 4 * x
  return lap.abs()


def instance_masks(panoptic: torch.Tensor, segments: list[tuple[int, int]]) -> torch.Tensor:
  """Binary masks M_j of the dynamic instances (eq. 3): (N, H, W) float32."""
  ids = [seg_id for seg_id, cat in segments if cat in DYNAMIC_COCO_IDS]
  if not ids:
    return panoptic.new_zeros((0,) + tuple(panoptic.shape), dtype=torch.float32)
  return (panoptic[None] == torch.tensor(ids)[:, None, None]).float()


def depth_refining(depth: torch.Tensor, masks: torch.Tensor, s: int = 5) -> torch.Tensor:
  """L_d, eq. 8: depth (H, W), masks (N, H, W) -> 1/N sum_j sum |D M_j - sg(median(D M_j))|."""
  n = masks.shape[0]
  if not n:
    return depth.new_zeros(())
  masked = depth[None] * masks  # D~_j, eq. 4
  pseudo = median_filter(masked.detach(), s)  # D~'_j, eq. 7, constants
  return (masked - pseudo).abs().sum() / n


def pitta_loss(image: torch.Tensor, depth: torch.Tensor, masks: torch.Tensor, s: int = 5,
               lam: float = 0.2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
  """Eq. 10: image (3, H, W), depth (H, W), masks (N, H, W) -> (L, L_d, L_e)."""
  l_d = depth_refining(depth, masks, s)
  l_e = (laplacian_edges(image.mean(0)) - laplacian_edges(depth)).abs().sum()  # eq. 9
  total = l_e if math.isinf(lam) else l_d + lam * l_e
  return total, l_d, l_e


def to_input(image: np.ndarray, memory_format=torch.contiguous_format) -> torch.Tensor:
  """(H, W, 3) float32 -> (1, 3, H, W) in `memory_format`."""
  return torch.from_numpy(image).permute(2, 0, 1)[None].contiguous(memory_format=memory_format)


class TorchPitta:
  """MonoDepth2 + Adam on the encoder's BN affine parameters, one `step` per frame.

  memory_format: torch.contiguous_format (NCHW, as upstream) or torch.channels_last.
  compile: `torch.compile` the depth + loss function (inductor), forward and backward.
  """

  def __init__(self, encoder: nn.Module, decoder: nn.Module, lr: float = 1e-4, lam: float = 0.2,
               window: int = 5, memory_format=torch.contiguous_format, compile: bool = False,
               fused: bool = FUSED_OPTIMIZERS):
    self.encoder, self.decoder, self.lam, self.window = encoder, decoder, lam, window
    self.memory_format = memory_format
    encoder.to(memory_format=memory_format)
    decoder.to(memory_format=memory_format)
    params = self.configure_model()
    self.optimizer = torch.optim.Adam(params, lr=lr, fused=fused)
    self.loss_fn = torch.compile(self._loss) if compile else self._loss

  def configure_model(self) -> list[nn.Parameter]:
    """TENT-style: train mode, batch statistics only, grads for encoder BN gamma/beta only."""
    self.encoder.train()
    self.decoder.train()
    for p in list(self.encoder.parameters()) + list(self.decoder.parameters()):
      p.requires_grad_(False)
    params = []
    for m in self.encoder.modules():
      if isinstance(m, nn.BatchNorm2d):
        m.track_running_stats = False
        m.running_mean, m.running_var = None, None
        m.weight.requires_grad_(True)
        m.bias.requires_grad_(True)
        params += [m.weight, m.bias]
    return params

  def depth(self, image: torch.Tensor) -> torch.Tensor:
    """image (1, 3, H, W) in [0, 1] -> depth (H, W) (scale 0, batch statistics)."""
    disp = self.decoder(self.encoder(image))[("disp", 0)]
    return disp_to_depth(disp)[0, 0]

  def _loss(self, image: torch.Tensor, masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    depth = self.depth(image)
    return pitta_loss(image[0], depth, masks, self.window, self.lam)[0], depth

  def step(self, image: torch.Tensor, panoptic: torch.Tensor, segments: list[tuple[int, int]]
           ) -> tuple[torch.Tensor, float]:
    """One frame: depth and loss before the update, then one Adam step. -> (depth, L)."""
    masks = instance_masks(panoptic, segments)
    loss, depth = self.loss_fn(image, masks)
    self.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    self.optimizer.step()
    return depth.detach(), loss.item()


class TorchNone:
  """No adaptation: eval-mode BN (running statistics), one no-grad forward per frame.

  memory_format and compile as `TorchPitta`'s (compile: `torch.compile` of the forward)."""

  def __init__(self, encoder: nn.Module, decoder: nn.Module,
               memory_format=torch.contiguous_format, compile: bool = False):
    self.encoder, self.decoder = encoder.eval(), decoder.eval()
    encoder.to(memory_format=memory_format)
    decoder.to(memory_format=memory_format)
    self.forward = torch.compile(self._forward) if compile else self._forward

  def _forward(self, image: torch.Tensor) -> torch.Tensor:
    return disp_to_depth(self.decoder(self.encoder(image))[("disp", 0)])[0, 0]

  def step(self, image, panoptic, segments) -> tuple[torch.Tensor, float]:
    with torch.no_grad():
      return self.forward(image), 0.0


def encoder_bns(encoder: nn.Module) -> list[tuple[str, nn.Module]]:
  """The encoder's BatchNorm2d modules (ActMAD's hooked layers), in forward order."""
  return [(n, m) for n, m in encoder.named_modules() if isinstance(m, nn.BatchNorm2d)]


class TorchActmad:
  """ActMAD + L_d: hooks on the encoder BNs, SGD on every encoder parameter (fc excluded); the
  reported depth is the frame's after the step (as upstream evaluates).

  source_stats: {bn module name: (mean, var)}, each (C, h, w) float32; config: the JAX method's
  `ActmadConfig` (the same knobs on both sides).
  """

  def __init__(self, encoder, decoder, source_stats, config, fused: bool = FUSED_OPTIMIZERS):
    self.encoder, self.decoder, self.stats = encoder, decoder, source_stats
    self.ld_weight, self.window = config.ld_weight, config.ld.window
    encoder.train(), decoder.train()
    for _, m in encoder_bns(encoder):
      m.eval()
    for p in decoder.parameters():
      p.requires_grad_(False)
    params = [p for n, p in encoder.named_parameters() if not n.startswith("encoder.fc")]
    self.optimizer = torch.optim.SGD(params, lr=config.lr, momentum=config.momentum,
                                     weight_decay=config.weight_decay, nesterov=config.nesterov,
                                     fused=fused)
    self.ring = collections.deque(maxlen=config.ring_size)
    self.saved: dict[str, torch.Tensor] = {}
    for name, m in encoder_bns(encoder):  # upstream's SaveOutput hook
      m.register_forward_hook(lambda mod, i, o, n=name: self.saved.__setitem__(n, o.clone()))

  def step(self, image, panoptic, segments) -> tuple[torch.Tensor, float]:
    self.optimizer.zero_grad(set_to_none=True)
    disp = self.decoder(self.encoder(image))[("disp", 0)]
    depth = disp_to_depth(disp)[0, 0]
    loss = 0.0
    for name, (src_mean, src_var) in self.stats.items():
      batch = torch.cat([self.saved[name]] + [old[name] for old in self.ring])
      mean = batch.mean(0)
      var = batch.var(0) if batch.shape[0] > 1 else torch.zeros_like(mean)
      loss = loss + F.l1_loss(mean, src_mean) + F.l1_loss(var, src_var)
    loss = loss + self.ld_weight * depth_refining(depth, instance_masks(panoptic, segments),
                                                  self.window)
    loss.backward()
    self.optimizer.step()
    self.ring.append({n: a.detach() for n, a in self.saved.items()})
    with torch.no_grad():  # upstream tests after optimizer.step(): the reported depth
      after = disp_to_depth(self.decoder(self.encoder(image))[("disp", 0)])[0, 0]
    return after, loss.item()


class TorchCotta:
  """CoTTA + L_d: student, EMA teacher, the source as the restore target; Adam on every
  parameter; BN eval mode. config: the JAX method's `CottaConfig`."""

  def __init__(self, encoder, decoder, config, seed=0, fused: bool = FUSED_OPTIMIZERS):
    self.model = nn.ModuleDict({"enc": encoder, "dec": decoder}).eval()
    self.teacher = copy.deepcopy(self.model)
    for p in self.teacher.parameters():
      p.requires_grad_(False)
    self.source = {n: p.detach().clone() for n, p in self.model.named_parameters()}
    self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr, fused=fused)
    self.cfg = config
    self.rng = np.random.default_rng(seed)
    self.noise_rng = torch.Generator().manual_seed(seed)

  @staticmethod
  def disp(model, x):
    return model["dec"](model["enc"](x))[("disp", 0)][:, 0]

  def views(self, x: torch.Tensor) -> tuple[torch.Tensor, list[bool]]:
    """N augmented views (upstream: one transform call per view), (N, 3, H, W), and which of
    them are flipped. The noise is upstream's `GaussianNoise`: `torch.randn`, float32."""
    from torch_tta import t_augment
    c = self.cfg
    h, w = x.shape[-2:]
    spread = np.array([c.brightness, c.contrast, c.saturation, c.gamma])
    out, flips = [], []
    for _ in range(c.n_augment):
      factors = self.rng.uniform(1 - spread, 1 + spread)
      flips.append(bool(self.rng.random() < c.flip_p))
      out.append(t_augment(x, self.rng.permutation(4), factors,
                           self.rng.uniform(c.blur_sigma_min, c.blur_sigma_max), flips[-1],
                           c.noise_std * torch.randn((1, 3, h, w), generator=self.noise_rng)))
    return torch.cat(out).float(), flips

  def step(self, image, panoptic, segments) -> tuple[torch.Tensor, float]:
    c = self.cfg
    student = self.disp(self.model, image)[0]
    with torch.no_grad():
      views, flips = self.views(image)
      spread = c.gate == "spread"
      out = self.disp(self.teacher, torch.cat([image, views]) if spread else views)
      outs = torch.stack([o.flip(-1) if f else o for o, f in zip(out[int(spread):], flips)])
      pseudo = outs.mean(0)
      if spread:
        pseudo = torch.where(outs.std(0) / pseudo > c.threshold, pseudo, out[0])
    loss = F.l1_loss(student, pseudo) + c.ld_weight * depth_refining(
        disp_to_depth(student), instance_masks(panoptic, segments), c.ld.window)
    self.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    self.optimizer.step()
    with torch.no_grad():
      for t, p in zip(self.teacher.parameters(), self.model.parameters()):
        t.mul_(c.ema_decay).add_(p, alpha=1 - c.ema_decay)
      for n, p in self.model.named_parameters():
        m = torch.rand(p.shape) < c.restore_p
        p.copy_(torch.where(m, self.source[n], p))
    return disp_to_depth(pseudo), loss.item()


def _frozen_bn_params(modules) -> list[nn.Parameter]:
  """CoMoDa's `set_adapt`: every module in eval mode, BN scale/bias frozen; the rest trainable."""
  params = []
  for m in modules:
    m.eval()
    for mod in m.modules():
      if isinstance(mod, nn.BatchNorm2d):
        mod.weight.requires_grad_(False)
        mod.bias.requires_grad_(False)
    params += [p for p in m.parameters() if p.requires_grad]
  return params


def _camera(K: np.ndarray, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
  """(3, 3) K -> (batch, 4, 4) K and its inverse, as MonoDepth2's data loaders give them."""
  K4 = torch.eye(4)
  K4[:3, :3] = torch.from_numpy(np.asarray(K, np.float32))
  return K4.expand(batch, 4, 4).contiguous(), torch.linalg.inv(K4).expand(batch, 4, 4).contiguous()


class _SfmBranch:
  """A depth + pose network pair trained by MonoDepth2's loss on (previous -> current) pairs
  (`tests/torch_sfm.Monodepth2Loss`, upstream's generate_images_pred + compute_losses)."""

  def __init__(self, encoder, decoder, pose_encoder, pose_decoder, K, batch, height, width):
    from torch_sfm import Monodepth2Loss
    self.enc, self.dec, self.penc, self.pdec = encoder, decoder, pose_encoder, pose_decoder
    self.K, self.inv_K = _camera(K, batch)
    self.loss = Monodepth2Loss(batch, height, width)

  def __call__(self, target, source, pixel_weights=None):
    """target, source (B, 3, H, W) -> (loss, the target's disparities per scale)."""
    from torch_sfm import transformation_from_parameters
    outputs = self.dec(self.enc(target))
    disps = [outputs[("disp", s)] for s in range(4)]
    axisangle, translation = self.pdec([self.penc(torch.cat([source, target], 1))])
    pose = transformation_from_parameters(axisangle[:, 0], translation[:, 0], invert=True)
    b, _, h, w = target.shape
    noise = torch.randn(4, b, 1, h, w)  # the identity losses' tie-break
    loss = self.loss(target, [source], disps, self.K, self.inv_K, [pose], noise,
                     pixel_weights=pixel_weights)[0]
    return loss, disps


class TorchComoda:
  """CoMoDa + L_d (Yevkuzn/CoMoDA's adapt loop): depth and pose networks, BN eval mode and
  frozen, Adam on everything else; batch = the test pair (t-1 -> t) with the moving-object mask
  + `replay` source pairs with all-ones masks; the first frame makes no update.

  replay_pairs: (R, 2, 3, H, W) consecutive source frames (previous, current); config: the JAX
  method's `ComodaConfig`."""

  def __init__(self, encoder, decoder, pose_encoder, pose_decoder, K, replay_pairs, config,
               seed=0, fused: bool = FUSED_OPTIMIZERS):
    h, w = replay_pairs.shape[-2:]
    self.optimizer = torch.optim.Adam(
        _frozen_bn_params((encoder, decoder, pose_encoder, pose_decoder)), config.lr, fused=fused)
    self.branch = _SfmBranch(encoder, decoder, pose_encoder, pose_decoder, K, 1 + config.replay,
                             h, w)
    self.replay_pairs, self.replay = replay_pairs, config.replay
    self.ld_weight, self.window = config.ld_weight, config.ld.window
    self.rng = np.random.default_rng(seed)
    self.previous = None

  def step(self, image, panoptic, segments) -> tuple[torch.Tensor, float]:
    masks = instance_masks(panoptic, segments)
    if self.previous is None:
      self.previous = image
      with torch.no_grad():
        return disp_to_depth(self.branch.dec(self.branch.enc(image))[("disp", 0)])[0, 0], 0.0
    idx = torch.from_numpy(self.rng.choice(len(self.replay_pairs), self.replay, replace=False))
    target = torch.cat([image, self.replay_pairs[idx, 1]])
    source = torch.cat([self.previous, self.replay_pairs[idx, 0]])
    weights = torch.ones(target.shape[0], *target.shape[-2:])
    if masks.shape[0]:
      weights[0] = 1 - masks.amax(0)
    own, disps = self.branch(target, source, weights)
    depth = disp_to_depth(disps[0][0, 0])
    loss = own + self.ld_weight * depth_refining(depth, masks, self.window)
    self.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    self.optimizer.step()
    self.previous = image
    return depth.detach(), loss.item()


class TorchAdadepth:
  """Ada-Depth + L_d (Malefikus/ada-depth's `Adapt.process_batch`, batch 1, frame ids (0, -1)):
  the self-supervised branch U (its own depth + pose networks) takes one MonoDepth2 step, then
  the student S one SILog step on the pseudo-labels filtered by the frozen source R and the EMA
  teacher E (`augment_pseudo`), + L_d; E follows S; the reported depth is S's after its step."""

  def __init__(self, encoder, decoder, pose_encoder, pose_decoder, K, height, width, config,
               depth_scale: float = 1.0, fused: bool = FUSED_OPTIMIZERS):
    """depth_scale: the factor from the network's depth to metres, the JAX step's
    (`methods.adadepth.depth_scale`: `config.depth_scale`, else the weights', else 1)."""
    self.s = {"encoder": encoder, "depth": decoder}
    self.ref = copy.deepcopy(self.s)
    self.ema = copy.deepcopy(self.s)
    self.u = {"encoder": copy.deepcopy(encoder), "depth": copy.deepcopy(decoder)}
    for m in (*self.s.values(), *self.ref.values(), *self.ema.values(), *self.u.values(),
              pose_encoder, pose_decoder):
      m.eval()
    self.cfg, self.scale = config, depth_scale
    self.opt_s = torch.optim.Adam([p for m in self.s.values() for p in m.parameters()], config.lr,
                                  fused=fused)
    self.opt_u = torch.optim.Adam([p for m in (*self.u.values(), pose_encoder, pose_decoder)
                                   for p in m.parameters()], config.lr, fused=fused)
    self.branch = _SfmBranch(self.u["encoder"], self.u["depth"], pose_encoder, pose_decoder, K,
                             1, height, width)
    self.previous = None

  @staticmethod
  def depth(models, x):
    return disp_to_depth(models["depth"](models["encoder"](x))[("disp", 0)])

  def pseudo(self, ref, unsup, ema):
    """upstream augment_pseudo on metre depths (1, 1, H, W) -> (P_S, P_U)."""
    c = self.cfg
    mask0 = ema > c.min_depth
    mask0[:, :, :int(c.top_fraction * ema.shape[2]), :] = False
    scale = torch.median(ema[mask0]) / torch.median(unsup[mask0])
    keep_u = ((ema - unsup * scale) ** 2 / ema) < c.threshold
    p_u = (keep_u.float() * unsup * scale).clamp(c.min_depth, c.max_depth)
    keep_s = (((ref - ema) ** 2 / ref) < c.threshold) * mask0
    return (keep_s.float() * ema).clamp(c.min_depth, c.max_depth), p_u

  def silog(self, depth, label):
    c = self.cfg
    valid = label > c.label_min
    g = torch.log(depth[valid]) - torch.log(label[valid])
    return torch.sqrt((g ** 2).mean() - c.variance_focus * g.mean() ** 2) * c.silog_factor

  def step(self, image, panoptic, segments) -> tuple[torch.Tensor, float]:
    if self.previous is None:
      self.previous = image
      with torch.no_grad():
        return self.depth(self.s, image)[0, 0], 0.0
    loss_u, _ = self.branch(image, self.previous)
    self.opt_u.zero_grad(set_to_none=True)
    loss_u.backward()
    self.opt_u.step()
    c = self.cfg
    depth = self.depth(self.s, image)
    with torch.no_grad():
      p_s, p_u = self.pseudo(self.scale * self.depth(self.ref, image),
                             self.scale * self.depth(self.u, image),
                             self.scale * self.depth(self.ema, image))
    loss = (self.silog(self.scale * depth, p_s) + self.silog(self.scale * depth, p_u)
            + c.ld_weight * depth_refining(depth[0, 0], instance_masks(panoptic, segments),
                                           c.ld.window))
    self.opt_s.zero_grad(set_to_none=True)
    loss.backward()
    self.opt_s.step()
    with torch.no_grad():
      for key in ("encoder", "depth"):
        for e, p in zip(self.ema[key].parameters(), self.s[key].parameters()):
          e.mul_(c.ema_decay).add_(p, alpha=1 - c.ema_decay)
      after = self.depth(self.s, image)[0, 0]
    self.previous = image
    return after, loss.item()


def jax_bn_path(torch_name: str) -> str:
  """An encoder BN module name -> the JAX module path: `encoder.layer2.0.downsample.1` ->
  `encoder/layer2_0/downsample_bn`, `encoder.bn1` -> `encoder/bn1`."""
  parts = torch_name.replace("downsample.1", "downsample_bn").split(".")[1:]
  if parts[0].startswith("layer"):
    parts = [f"{parts[0]}_{parts[1]}"] + parts[2:]
  return "/".join(["encoder"] + parts)


# method name -> a factory of its PyTorch step, called as make(enc, dec, config, **keywords):
# config is the JAX side's method config (the knobs come from it, not from literals here); the
# keywords are lr (AdaptConfig.lr, PITTA's), memory_format, compile, source_stats, pose, K,
# replay_pairs, height, width: each factory takes what it uses
TORCH_STEPS = {
    "pitta": lambda enc, dec, config, lr=None, memory_format=torch.contiguous_format,
    compile=False, fused=FUSED_OPTIMIZERS, **_: TorchPitta(
        enc, dec, lr=lr, lam=config.lam, window=config.ld.window, memory_format=memory_format,
        compile=compile, fused=fused),
    "none": lambda enc, dec, config, memory_format=torch.contiguous_format, compile=False, **_:
    TorchNone(enc, dec, memory_format, compile),
    "actmad": lambda enc, dec, config, source_stats=None, fused=FUSED_OPTIMIZERS, **_:
    TorchActmad(enc, dec, source_stats, config, fused=fused),
    "cotta": lambda enc, dec, config, fused=FUSED_OPTIMIZERS, **_: TorchCotta(
        enc, dec, config, fused=fused),
    "comoda": lambda enc, dec, config, pose=None, K=None, replay_pairs=None,
    fused=FUSED_OPTIMIZERS, **_: TorchComoda(enc, dec, *pose, K, replay_pairs, config,
                                             fused=fused),
    "adadepth": lambda enc, dec, config, pose=None, K=None, height=None, width=None,
    depth_scale=1.0, fused=FUSED_OPTIMIZERS, **_: TorchAdadepth(
        enc, dec, *pose, K, height, width, config, depth_scale, fused=fused),
}

# the methods whose PyTorch step also needs a pose network, K and (CoMoDa) source pairs
NEEDS_POSE = ("comoda", "adadepth")


def build_pose(seed: int = 2, num_layers: int = 18) -> tuple[nn.Module, nn.Module]:
  """Random-weight MonoDepth2 pairs pose network: a 2-image ResNet encoder and its decoder."""
  encoder = tm.ResnetEncoder(num_layers, num_input_images=2)
  decoder = tm.PoseDecoder(tm.num_ch_enc(num_layers))
  tm.randomize_(encoder, seed)
  tm.randomize_(decoder, seed + 1)
  return encoder, decoder


def build(seed: int = 0, num_layers: int = 18) -> tuple[nn.Module, nn.Module]:
  """Random-weight MonoDepth2 encoder and depth decoder (`torch_monodepth2.randomize_`)."""
  encoder = tm.ResnetEncoder(num_layers)
  decoder = tm.DepthDecoder(tm.num_ch_enc(num_layers))
  tm.randomize_(encoder, seed)
  tm.randomize_(decoder, seed + 1)
  return encoder, decoder


__all__ = ["TorchPitta", "TorchNone", "TorchActmad", "TorchCotta", "TorchComoda", "TorchAdadepth",
           "TORCH_STEPS", "NEEDS_POSE", "build", "build_pose",
           "jax_bn_path", "median_filter",
           "laplacian_edges", "instance_masks", "pitta_loss", "depth_refining", "disp_to_depth",
           "even_count_pixels", "to_input", "encoder_bns"]
