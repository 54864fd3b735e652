"""Independent PyTorch references of the baselines ActMAD and CoTTA on MonoDepth2 (torch_monodepth2).

Written the way their official code does it, with native ops, not shaped after our JAX code:
- ActMAD (jmiemirza/ActMAD, methods/actmad_kitti.py + utils/utils.py SaveOutput): forward hooks
  on the BatchNorm2d modules, `torch.mean/var(dim=0)` of the hooked outputs, `nn.L1Loss()` per
  layer summed, model in train mode with its BN modules in eval mode, `torch.optim.SGD(lr,
  momentum, weight_decay, nesterov=True)`. Our online variant's batch = the current frame + a
  `collections.deque(maxlen=K)` of previous frames' detached hooked outputs; with a single
  sample the variance is taken as 0. Source statistics both ways: upstream's `AverageMeter` of
  per-batch statistics (`upstream_source_stats`) and the whole set's (`pooled_source_stats`,
  our definition).
Where our variant departs from upstream (online batch, BN eval mode in CoTTA, no hue), the
reference follows the variant, as methods/*.py document it.
- CoTTA (qinenergy/cotta, cifar/cotta.py + my_transforms.py): `deepcopy` teacher (the anchor
  only gates, see `CoTTA`), N augmented views with torchvision's tensor formulas (brightness/contrast/saturation blends,
  gamma with the 1e-8 clamp, edge padding, a 5x5 Gaussian blur, centre crop, flip, noise, clip) from
  explicitly given draws, `torch.optim.Adam`, `ema = a * ema + (1 - a) * p` over
  `parameters()`, restore `p = src * mask + p * (1 - mask)` with given masks.
- PITTA's L_d (eq. 8) on the adapted depth, with the median filter of test_pitta_torch.
"""

from __future__ import annotations

import collections
import copy

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from test_pitta_torch import t_median_filter


def flax_path(torch_name: str) -> str:
  """Encoder parameter name -> Flax leaf path: `encoder.layer2.0.downsample.1.weight` ->
  `layer2_0/downsample_bn/scale`, `encoder.conv1.weight` -> `conv1/kernel`."""
  parts = torch_name.split(".")[1:]
  leaf = parts.pop()
  name = ".".join(parts).replace("downsample.0", "downsample_conv").replace(
      "downsample.1", "downsample_bn")
  parts = name.split(".")
  if parts[0].startswith("layer"):
    parts = [f"{parts[0]}_{parts[1]}"] + parts[2:]
  kind = "kernel" if "conv" in parts[-1] else ("scale" if leaf == "weight" else "bias")
  return "/".join(parts + [kind])


def encoder_params(enc) -> dict[str, np.ndarray]:
  """The encoder's parameters (fc excluded) keyed by Flax leaf path, conv kernels as HWIO."""
  out = {}
  for name, p in enc.named_parameters():
    if name.startswith("encoder.fc"):
      continue
    key = flax_path(name)
    a = p.detach().double().numpy()
    out[key] = a.transpose(2, 3, 1, 0) if a.ndim == 4 else a
  return out


def disp_to_depth(disp, min_depth=0.1, max_depth=100.0):
  return 1.0 / (1 / max_depth + (1 / min_depth - 1 / max_depth) * disp)


def depth_refining(depth: torch.Tensor, panoptic: np.ndarray, ids, s: int) -> torch.Tensor:
  """Eq. 8 with binary masks: (1/N) sum_j sum |D M_j - median_s(D M_j)| (labels detached)."""
  total = 0.0
  for seg_id in ids:
    masked = depth * torch.from_numpy(panoptic == seg_id).to(depth.dtype)
    total = total + (masked - t_median_filter(masked.detach(), s)).abs().sum()
  return total / len(ids)


def _image(x: np.ndarray) -> torch.Tensor:
  return torch.from_numpy(np.asarray(x, np.float64)).permute(2, 0, 1)[None]


# ----------------------------------------------------------------------------------- ActMAD


def _bn_modules(enc):
  return [(n, m) for n, m in enc.named_modules() if isinstance(m, nn.BatchNorm2d)]


def _hooked_forward(enc, dec, x):
  """Scale-0 disparity and a clone of every BN output (as upstream SaveOutput: the blocks'
  in-place ReLU would overwrite it)."""
  saved = {}
  hooks = [m.register_forward_hook(lambda mod, i, o, n=n: saved.__setitem__(n, o.clone()))
           for n, m in _bn_modules(enc)]
  disp = dec(enc(x))[("disp", 0)]
  for h in hooks:
    h.remove()
  return disp, saved


def pooled_source_stats(enc, dec, images: np.ndarray) -> dict:
  """{bn name: (mean, var)} of the whole set of images (N, H, W, 3): `torch.mean` / `torch.var`
  over all their hooked outputs stacked, eval mode, each (C, h, w). This is our definition
  (`actmad.source_statistics`); upstream's is `upstream_source_stats`."""
  enc.eval(), dec.eval()
  with torch.no_grad():
    outs = [_hooked_forward(enc, dec, _image(im))[1] for im in images]
  return {n: (torch.vstack([o[n] for o in outs]).mean(0), torch.vstack([o[n] for o in outs]).var(0))
          for n in outs[0]}


def upstream_source_stats(enc, dec, batches: list[np.ndarray]) -> tuple[dict, list[dict]]:
  """ActMAD's own clean statistics (methods/actmad_kitti.py with utils' `SaveOutput` and
  `AverageMeter`): per loader batch (B, H, W, 3) the hooked outputs' `torch.mean(dim=0)` and
  `torch.var(dim=0)`, averaged over batches, each batch counting once. Returns
  ({bn name: (mean, var)}, the per-batch {bn name: (mean, var)})."""
  enc.eval(), dec.eval()
  per_batch = []
  with torch.no_grad():
    for batch in batches:
      x = torch.cat([_image(im) for im in batch])
      outs = _hooked_forward(enc, dec, x)[1]
      per_batch.append({n: (o.mean(dim=0), o.var(dim=0)) for n, o in outs.items()})
  meters = {n: tuple(sum(b[n][i] for b in per_batch) / len(per_batch) for i in range(2))
            for n in per_batch[0]}
  return meters, per_batch


class ActMAD:
  def __init__(self, enc, dec, stats, lr, ring_size, ld_weight, s, trainable, momentum=0.9,
               weight_decay=5e-4):
    """trainable: the Flax leaf paths (`flax_path`) of the encoder parameters to adapt."""
    self.enc, self.dec, self.stats = enc, dec, stats
    self.ld_weight, self.s = ld_weight, s
    params = [p for n, p in enc.named_parameters()
              if not n.startswith("encoder.fc") and flax_path(n) in trainable]
    self.opt = torch.optim.SGD(params, lr=lr, momentum=momentum, weight_decay=weight_decay,
                               nesterov=True)
    self.fifo = collections.deque(maxlen=ring_size)
    self.l1 = nn.L1Loss(reduction="mean")

  def step(self, image, panoptic, ids):
    """One frame; returns (total, actmad loss, L_d) as floats."""
    self.enc.train(), self.dec.train()
    for _, m in _bn_modules(self.enc):
      m.eval()
    self.opt.zero_grad()
    disp, acts = _hooked_forward(self.enc, self.dec, _image(image))
    loss_mean = loss_var = 0.0
    for name, (src_mean, src_var) in self.stats.items():
      batch = torch.vstack([acts[name]] + [old[name] for old in self.fifo])
      mean = batch.mean(0)
      var = batch.var(0) if batch.shape[0] > 1 else torch.zeros_like(mean)
      loss_mean = loss_mean + self.l1(mean, src_mean)
      loss_var = loss_var + self.l1(var, src_var)
    own = loss_mean + loss_var
    l_d = depth_refining(disp_to_depth(disp[0, 0]), panoptic, ids, self.s)
    total = own + self.ld_weight * l_d
    total.backward()
    self.opt.step()
    self.fifo.append({n: a.detach() for n, a in acts.items()})
    return float(total.detach()), float(own.detach()), float(l_d.detach())

  @torch.no_grad()
  def depth(self, image) -> np.ndarray:
    """The frame's depth (H, W) as upstream tests after `optimizer.step()` (eval mode)."""
    self.enc.eval(), self.dec.eval()
    return disp_to_depth(self.dec(self.enc(_image(image)))[("disp", 0)][0, 0]).numpy()


# ----------------------------------------------------------------------------------- CoTTA


def t_augment(img: torch.Tensor, order, factors, sigma, flip, noise) -> torch.Tensor:
  """One view of img (1, 3, H, W): clip, jitter in `order` (0 brightness, 1 contrast,
  2 saturation, 3 gamma), blur, flip, noise, clip. noise: a (1, 3, H, W) tensor (upstream's
  `torch.randn` draw) or an (H, W, 3) array (the JAX run's draws, added in float64)."""
  x = img.clamp(0.0, 1.0)
  gray = lambda t: (0.2989 * t[:, 0] + 0.587 * t[:, 1] + 0.114 * t[:, 2]).unsqueeze(1)
  for j in order:
    f = float(factors[j])
    if j == 0:
      x = (f * x).clamp(0, 1)
    elif j == 1:
      x = (f * x + (1 - f) * gray(x).mean(dim=(-3, -2, -1), keepdim=True)).clamp(0, 1)
    elif j == 2:
      x = (f * x + (1 - f) * gray(x)).clamp(0, 1)
    else:
      x = (x.clamp(1e-8, 1.0) ** f).clamp(0, 1)
  t = torch.linspace(-2, 2, 5, dtype=x.dtype)
  k1 = torch.exp(-0.5 * (t / float(sigma)) ** 2)
  k1 = k1 / k1.sum()
  kernel = (k1[:, None] * k1[None, :]).expand(3, 1, 5, 5)
  # upstream: transforms.Pad(n / 2, padding_mode="edge"), (RandomAffine: not for depth),
  # GaussianBlur(5) (torchvision: reflect padding, conv), CenterCrop(n)
  pad = 4
  x = F.pad(x, (pad, pad, pad, pad), mode="replicate")
  x = F.conv2d(F.pad(x, (2, 2, 2, 2), mode="reflect"), kernel, groups=3)
  x = x[..., pad:-pad, pad:-pad]
  if flip:
    x = x.flip(-1)
  if not isinstance(noise, torch.Tensor):
    noise = torch.from_numpy(np.array(noise, np.float64)).permute(2, 0, 1)[None]
  return (x + noise).clamp(0, 1)


class CoTTA:
  """threshold None: the pseudo label is the views' mean (upstream under a shift, where the
  anchor is not confident); else per pixel where the views' `std / mean` exceeds it.
  every_param: Adam and the restore over every weight and bias of the encoder and the decoder,
  as upstream's `collect_params` and `restore` (its ResNet `fc` left out: no forward pass uses
  it); else over the encoder's BatchNorm parameters."""
  def __init__(self, enc, dec, lr, ema, threshold, ld_weight, s, every_param=False):
    self.model = nn.ModuleDict({"enc": enc, "dec": dec})
    self.ema_model = copy.deepcopy(self.model)
    for p in self.ema_model.parameters():
      p.detach_()
    self.source = copy.deepcopy(self.model.state_dict())
    if every_param:
      self.trainable = {n: p for n, p in self.model.named_parameters()
                        if not n.startswith("enc.encoder.fc.")}
    else:
      self.trainable = {f"enc.{mn}.{pn}": p for mn, m in enc.named_modules()
                        if isinstance(m, nn.BatchNorm2d) for pn, p in m.named_parameters()}
    self.opt = torch.optim.Adam(self.trainable.values(), lr=lr)
    self.ema, self.threshold, self.ld_weight, self.s = ema, threshold, ld_weight, s

  def disp(self, model, x):
    return model["dec"](model["enc"](x))[("disp", 0)][:, 0]

  @torch.no_grad()
  def views(self, x, aug):
    """The teacher's disparities of the N augmented views of x (1, 3, H, W), flipped back."""
    self.ema_model.eval()
    views = torch.cat([t_augment(x, aug["order"][i], aug["factors"][i], aug["sigma"][i],
                                 aug["flip"][i], aug["noise"][i])
                       for i in range(len(aug["sigma"]))])
    outs = self.disp(self.ema_model, views)
    return torch.stack([o.flip(-1) if f else o for o, f in zip(outs, aug["flip"])])

  def step(self, image, panoptic, ids, aug, masks):
    """aug: dict of numpy draws (order, factors, sigma, flip, noise); masks: {name: bool array}
    of the restore. Returns (total, own loss, L_d, pseudo label, gate fraction)."""
    self.model.eval(), self.ema_model.eval()
    x = _image(image)
    student = self.disp(self.model, x)[0]
    with torch.no_grad():
      teacher = self.disp(self.ema_model, x)[0]
      outs = self.views(x, aug)
      if self.threshold is None:
        gate = torch.ones_like(teacher, dtype=torch.bool)
      else:
        gate = outs.std(0) / outs.mean(0) > self.threshold
      pseudo = torch.where(gate, outs.mean(0), teacher)
    own = F.l1_loss(student, pseudo)
    l_d = depth_refining(disp_to_depth(student), panoptic, ids, self.s)
    total = own + self.ld_weight * l_d
    total.backward()
    self.opt.step()
    self.opt.zero_grad()
    total, own, l_d = total.detach(), own.detach(), l_d.detach()
    with torch.no_grad():
      for t, p in zip(self.ema_model.parameters(), self.model.parameters()):
        t.data[:] = self.ema * t.data[:] + (1 - self.ema) * p.data[:]
      for n, p in self.trainable.items():
        m = torch.from_numpy(np.array(masks[n])).to(p.dtype)
        p.data = self.source[n] * m + p * (1.0 - m)
    return float(total), float(own), float(l_d), pseudo.numpy(), float(gate.double().mean())
