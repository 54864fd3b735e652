"""PITTA's loss (eq. 10) and its gradient w.r.t. the encoder BN parameters: JAX vs PyTorch.

Reference: a straightforward PyTorch implementation of eqs. 3-10 written here (unfold-based
median filter with the border-shrinking window, masks by comparison, replicate-padded
Laplacian), run on the PyTorch MonoDepth2 of `tests/torch_monodepth2.py` in train-mode BN; JAX
runs the public `pitta_jax.losses.pitta_loss` on the converted weights. Both take
d|u|/du = +1 at u = 0 (a pixel that is its own window median gives u = 0 exactly; torch.abs
would give 0 there), so the subgradients are the same.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from flax.traverse_util import flatten_dict

import torch_monodepth2 as tm
from pitta_jax import losses, trainable
from pitta_jax.models.depth_decoder import DepthNet, disp_to_depth
from weights_convert.monodepth2 import convert_monodepth2

H, W, S, LAM = 64, 96, 5, 0.2


def t_abs(u):
  return torch.where(u >= 0, u, -u)  # subgradient +1 at 0, as jnp.abs


def t_median_filter(x: torch.Tensor, s: int) -> torch.Tensor:
  """Eq. 7: window shrinking at the border (NaN padding excluded), mean of two middles."""
  r = s // 2
  padded = F.pad(x[None, None], (r, r, r, r), value=float("nan"))
  windows = F.unfold(padded, s)[0]                       # (s*s, H*W)
  count = (~torch.isnan(windows)).sum(0)                 # valid values per window
  ordered = torch.sort(windows, dim=0).values            # NaN sorts last
  lo = ordered.gather(0, ((count - 1) // 2)[None])[0]
  hi = ordered.gather(0, (count // 2)[None])[0]
  return ((lo + hi) / 2).reshape(x.shape)


def t_laplacian_edges(x: torch.Tensor) -> torch.Tensor:
  """Eqs. 5-6 with U = V = 1: |4-neighbour sum - 4 x| with clamped (replicated) indices."""
  p = F.pad(x[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
  return t_abs(p[2:, 1:-1] + p[:-2, 1:-1] + p[1:-1, 2:] + p[1:-1, :-2] - 4 * x)


def t_pitta_loss(image: torch.Tensor, depth: torch.Tensor, panoptic: np.ndarray, dynamic_ids):
  """Eqs. 3-10: image (H, W, 3), depth (H, W), binary masks."""
  l_d = 0.0
  for seg_id in dynamic_ids:
    mask = torch.from_numpy(panoptic == seg_id).to(depth.dtype)   # M_j (eq. 3, g_j = 1)
    masked = depth * mask                                         # eq. 4
    pseudo = t_median_filter(masked.detach(), S)                  # eq. 7, a constant
    l_d = l_d + t_abs(masked - pseudo).sum()                      # eq. 8
  l_d = l_d / len(dynamic_ids)
  l_e = t_abs(t_laplacian_edges(image.mean(-1)) - t_laplacian_edges(depth)).sum()  # eq. 9
  return l_d + LAM * l_e, l_d, l_e                                # eq. 10


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
  root = tmp_path_factory.mktemp("mono")
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  tm.randomize_(enc, 21), tm.randomize_(dec, 22)
  torch.save({**enc.state_dict(), "height": H, "width": W}, root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  _, variables, _ = convert_monodepth2(root / "encoder.pth", root / "depth.pth")
  rng = np.random.default_rng(0)
  yy, xx = np.mgrid[0:H, 0:W]
  image = np.clip(0.5 + 0.3 * np.sin(xx / 6.0)[..., None] * np.array([1.0, 0.7, 0.4])
                  + 0.05 * rng.normal(size=(H, W, 3)), 0, 1).astype(np.float32)
  panoptic = np.full((H, W), 7, np.int32)
  panoptic[30:52, 8:40] = 11
  panoptic[30:52, 40:62] = 12   # touches instance 11
  panoptic[18:52, 70:76] = 13
  return enc, dec, variables, image, panoptic, [11, 12, 13]


def _torch_side(enc, dec, image, panoptic, ids, dtype):
  enc, dec = enc.to(dtype).train(), dec.to(dtype).train()
  enc.zero_grad(), dec.zero_grad()
  x = torch.from_numpy(image).to(dtype)
  disp = dec(enc(x.permute(2, 0, 1)[None]))[("disp", 0)][0, 0]
  depth = 1.0 / (1 / 100 + (1 / 0.1 - 1 / 100) * disp)
  total, l_d, l_e = t_pitta_loss(x, depth, panoptic, ids)
  total.backward()
  return float(total), float(l_d), float(l_e), tm.bn_grads(enc)


def _jax_side(variables, image, panoptic, ids, dtype, with_grad=True):
  cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), t)
  parts = trainable.split(cast(variables))
  net = DepthNet(18)
  dyn = jnp.asarray(ids, jnp.int32)

  @jax.jit
  def value_and_grad(tr, frozen, stats, image, panoptic):
    def loss_fn(tr):
      disp = net.apply(trainable.merge(tr, frozen, stats), image[None], train=True)[0]
      out = losses.pitta_loss(image, disp_to_depth(disp[0, ..., 0]), panoptic, dyn, s=S, lam=LAM)
      return out.total, out
    if not with_grad:  # forward only: a cheaper compile
      return loss_fn(tr), {"encoder": {}}
    return jax.value_and_grad(loss_fn, has_aux=True)(tr)

  (total, parts_out), grads = value_and_grad(parts.trainable, parts.frozen, parts.batch_stats,
                                             cast(image), jnp.asarray(panoptic))
  flat = flatten_dict(grads["encoder"], sep="/")
  return (float(total), float(parts_out.l_d), float(parts_out.l_e),
          {k: np.asarray(v, np.float64) for k, v in flat.items()})


def test_pitta_loss_and_bn_gradient_match_torch(setup):
  enc, dec, variables, image, panoptic, ids = setup
  # float32: the loss value (what runs in practice)
  t32 = _torch_side(enc, dec, image, panoptic, ids, torch.float32)
  j32 = _jax_side(variables, image, panoptic, ids, jnp.float32, with_grad=False)
  rel = [abs(a - b) / abs(b) for a, b in zip(j32[:3], t32[:3])]
  print(f"float32 L, L_d, L_e: jax {j32[0]:.4f} {j32[1]:.4f} {j32[2]:.4f} torch {t32[0]:.4f} "
        f"{t32[1]:.4f} {t32[2]:.4f}; rel diffs {rel[0]:.1e} {rel[1]:.1e} {rel[2]:.1e}")
  assert max(rel) < 1e-4
  # float64: the gradient w.r.t. the 40 encoder BN gamma/beta leaves (in float32 a batch-1 BN
  # backward cancels too much to compare at 1e-3, see test_monodepth2_parity)
  t64 = _torch_side(enc, dec, image, panoptic, ids, torch.float64)
  with jax.enable_x64(True):
    j64 = _jax_side(variables, image, panoptic, ids, jnp.float64)
  assert set(j64[3]) == set(t64[3]) and len(t64[3]) == 40
  worst = max(float(np.max(np.abs(j64[3][k] - t64[3][k])) / np.max(np.abs(t64[3][k])))
              for k in t64[3])
  print(f"float64 loss rel diff {abs(j64[0] - t64[0]) / abs(t64[0]):.1e}; BN gradient worst "
        f"max-relative diff over 40 leaves {worst:.1e}")
  np.testing.assert_allclose(j64[0], t64[0], rtol=1e-6)  # the losses compute in float32
  assert worst < 1e-3
