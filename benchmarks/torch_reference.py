"""A PyTorch eager PITTA step, written as a PyTorch user would: the timing reference.

Same configuration as the JAX engine's default (docs/method.md): MonoDepth2 ResNet-18 with
upstream's layer structure (`tests/torch_monodepth2.py`), batch 1, train-mode BatchNorm with the
frame's batch statistics and the running statistics untouched (TENT's `configure_model`:
`track_running_stats = False`, running buffers dropped), only the encoder BN gamma/beta adapted
by Adam (lr 1e-4), one step per frame, loss eqs. 5-10:

- instance masks M_j from the panoptic id map (binary g_j = 1), eqs. 3-4;
- pseudo labels D~'_j by a median filter with the border-shrinking window (eq. 7): unfold of the
  +inf-padded masked depths, a sort over each window, then per pixel the mean of the sorted values
  at ranks (c-1)//2 and c//2, c = the pixel's window count (`torch.median` would return the
  lower middle value for even counts, which is not eq. 7's rule);
- L_d = 1/N sum_j sum |D~_j - D~'_j| (eq. 8), literally over the N instances, batched;
- Laplacian edge maps with clamped (replicated) borders on the channel-mean image and the depth,
  L_e = sum |dI - dD| (eqs. 5, 6, 9); L = L_d + lambda L_e (eq. 10).

Predict-then-adapt as in the engine: the returned depth is the one the loss was computed on.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import torch_monodepth2 as tm  # noqa: E402  (upstream layer structure)

MIN_DEPTH, MAX_DEPTH = 0.1, 100.0
DYNAMIC_COCO_IDS = (1, 2, 3, 4, 6, 7, 8)  # person, bicycle, car, motorcycle, bus, train, truck


def disp_to_depth(disp: torch.Tensor) -> torch.Tensor:
  """MonoDepth2's sigmoid disparity -> depth (paper Sec. 3, MonoDepth2)."""
  min_disp, max_disp = 1.0 / MAX_DEPTH, 1.0 / MIN_DEPTH
  return 1.0 / (min_disp + (max_disp - min_disp) * disp)


def median_filter(x: torch.Tensor, s: int = 5) -> torch.Tensor:
  """Eq. 7 on a batch of maps: x (B, H, W) -> (B, H, W), window shrinking at the border."""
  b, h, w = x.shape
  r = s // 2
  padded = F.pad(x[:, None], (r, r, r, r), value=math.inf)  # out-of-image slots sort last
  # (B, H*W, s*s), contiguous: sorting along the last axis is ~1.5x faster than along axis 1
  windows = F.unfold(padded, s).transpose(1, 2).contiguous()
  ordered = windows.sort(dim=-1).values
  ones = F.pad(x.new_ones(1, 1, h, w), (r, r, r, r))
  count = F.unfold(ones, s).sum(1).long()[0]  # (H*W,) pixels in each window
  lower = ordered.gather(-1, ((count - 1) // 2)[None, :, None].expand(b, -1, 1))
  upper = ordered.gather(-1, (count // 2)[None, :, None].expand(b, -1, 1))
  return ((lower + upper) / 2).view(b, h, w)  # even count: mean of the two middle values


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


def pitta_loss(image: torch.Tensor, depth: torch.Tensor, masks: torch.Tensor, s: int = 5,
               lam: float = 0.2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
  """Eq. 10: image (3, H, W), depth (H, W), masks (N, H, W) -> (L, L_d, L_e)."""
  n = masks.shape[0]
  if n:
    masked = depth[None] * masks  # D~_j, eq. 4
    pseudo = median_filter(masked.detach(), s)  # D~'_j, eq. 7, constants
    l_d = (masked - pseudo).abs().sum() / n  # eq. 8
  else:
    l_d = depth.new_zeros(())
  l_e = (laplacian_edges(image.mean(0)) - laplacian_edges(depth)).abs().sum()  # eq. 9
  total = l_e if math.isinf(lam) else l_d + lam * l_e
  return total, l_d, l_e


class TorchPitta:
  """MonoDepth2 + Adam on the encoder's BN affine parameters, one `step` per frame."""

  def __init__(self, encoder: nn.Module, decoder: nn.Module, lr: float = 1e-4, lam: float = 0.2,
               window: int = 5):
    self.encoder, self.decoder, self.lam, self.window = encoder, decoder, lam, window
    params = self.configure_model()
    self.optimizer = torch.optim.Adam(params, lr=lr)

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

  def step(self, image: torch.Tensor, panoptic: torch.Tensor, segments: list[tuple[int, int]]
           ) -> tuple[torch.Tensor, float]:
    """One frame: depth and loss before the update, then one Adam step. -> (depth, L)."""
    masks = instance_masks(panoptic, segments)
    depth = self.depth(image)
    loss, _, _ = pitta_loss(image[0], depth, masks, self.window, self.lam)
    self.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    self.optimizer.step()
    return depth.detach(), loss.item()


def build(seed: int = 0, num_layers: int = 18) -> tuple[nn.Module, nn.Module]:
  """Random-weight MonoDepth2 encoder and depth decoder (`torch_monodepth2.randomize_`)."""
  encoder = tm.ResnetEncoder(num_layers)
  decoder = tm.DepthDecoder(tm.num_ch_enc(num_layers))
  tm.randomize_(encoder, seed)
  tm.randomize_(decoder, seed + 1)
  return encoder, decoder


__all__ = ["TorchPitta", "build", "median_filter", "laplacian_edges", "instance_masks",
           "pitta_loss", "disp_to_depth"]
