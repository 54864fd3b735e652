"""PITTA's loss (eqs. 3-10) and its gradients: JAX against PyTorch autograd, written natively.

Reference: eqs. 3-10 as a PyTorch user writes them, with native ops and their own derivative
conventions: `Tensor.abs()` (derivative 0 at 0), an `F.unfold` + `torch.sort` median filter
with the border-shrinking window (NaN padding excluded, mean of the two middle values),
masks by comparison, a replicate-padded Laplacian (`F.pad(mode="replicate")`). Nothing in it is
adjusted to agree with our code.

The fixtures are chosen so that ties dominate, where the subgradient conventions matter: a
smooth curved depth whose pixels mostly equal their own window median (|D~ - D~'| = 0 exactly)
and an image with flat regions (Laplacian exactly 0). Checked:
- dL/dD of the public `pitta_jax.losses.pitta_loss`: float64 JAX vs float64 PyTorch at 1e-6,
  float32 JAX vs float64 PyTorch within 1e-3 of the largest component with the same sign in
  every component;
- dL/d(encoder BN gamma, beta) of a converted MonoDepth2 at 640x192 in train-mode BN: float64
  JAX vs float64 PyTorch at 1e-6; float32 JAX vs float64 PyTorch no further than twice PyTorch's
  own float32 gradient (or 2e-3 of the leaf's largest component; batch-1 BN backward in float32
  is ill-conditioned, see test_monodepth2_parity) and with the same sign wherever float32
  PyTorch agrees in sign. PyTorch's CPU kernels sum BN's per-channel statistics in float64; with
  one-stage float32 sums JAX was 2.5e-3 (one thread) to 1.3e-2 (two threads) off here, PyTorch
  7.9e-4 (`models.layers.BatchNorm` sums rows first).
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

S, LAM = 5, 0.2


# ---------------------------------------------------------------------- the PyTorch reference


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
  return (p[2:, 1:-1] + p[:-2, 1:-1] + p[1:-1, 2:] + p[1:-1, :-2] - 4 * x).abs()


def t_pitta_loss(image: torch.Tensor, depth: torch.Tensor, panoptic: np.ndarray, dynamic_ids):
  """Eqs. 3-10: image (H, W, 3), depth (H, W), binary masks."""
  l_d = 0.0
  for seg_id in dynamic_ids:
    mask = torch.from_numpy(panoptic == seg_id).to(depth.dtype)   # M_j (eq. 3, g_j = 1)
    masked = depth * mask                                         # eq. 4
    pseudo = t_median_filter(masked.detach(), S)                  # eq. 7, a constant
    l_d = l_d + (masked - pseudo).abs().sum()                     # eq. 8
  l_d = l_d / len(dynamic_ids)
  l_e = (t_laplacian_edges(image.mean(-1)) - t_laplacian_edges(depth)).abs().sum()  # eq. 9
  return l_d + LAM * l_e, l_d, l_e                                # eq. 10


# ---------------------------------------------------------------------- tie-heavy fixtures


def _panoptic(h: int, w: int) -> tuple[np.ndarray, list[int]]:
  """Three dynamic instances (two touching) on a static background segment 7."""
  panoptic = np.full((h, w), 7, np.int32)
  panoptic[h // 2:h - 4, w // 12:w // 2 - w // 10] = 11
  panoptic[h // 2:h - 4, w // 2 - w // 10:w // 2 + w // 8] = 12   # touches instance 11
  panoptic[h // 4:h - 4, 3 * w // 4:3 * w // 4 + 6] = 13
  return panoptic, [11, 12, 13]


def _flat_image(h: int, w: int) -> np.ndarray:
  """Piecewise-constant image: flat regions (Laplacian exactly 0) with a few edges."""
  image = np.full((h, w, 3), 0.5, np.float32)
  image[: h // 3] = (0.75, 0.75, 0.875)                # sky
  image[h // 2:, : w // 3] = (0.25, 0.25, 0.25)        # road
  image[h // 3: h // 2, w // 2:] = (0.625, 0.5, 0.375)  # facade
  return image


@pytest.fixture(scope="module")
def depth_case():
  """A smooth, curved depth (dyadic values, exact in float32 and float64)."""
  h, w = 48, 80
  yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
  depth = 8.0 + 0.125 * xx + 0.0625 * yy + 2.0 ** -9 * (xx - 30.0) ** 2 + 2.0 ** -8 * (yy - 20.0) ** 2
  panoptic, ids = _panoptic(h, w)
  return _flat_image(h, w), depth.astype(np.float32), panoptic, ids


def _tie_fraction(depth: np.ndarray, panoptic: np.ndarray, ids) -> float:
  d = torch.from_numpy(depth.astype(np.float64))
  ties = total = 0
  for i in ids:
    m = torch.from_numpy(panoptic == i).double()
    inside = m.bool()
    ties += int(((d * m - t_median_filter(d * m, S)) == 0)[inside].sum())
    total += int(inside.sum())
  return ties / total


def _torch_depth_grad(image, depth, panoptic, ids):
  d = torch.from_numpy(depth).double().requires_grad_(True)
  total, _, _ = t_pitta_loss(torch.from_numpy(image).double(), d, panoptic, ids)
  total.backward()
  return float(total.detach()), d.grad.numpy()


def _jax_depth_grad(image, depth, panoptic, ids, dtype):
  fn = jax.jit(jax.value_and_grad(
      lambda d: losses.pitta_loss(image.astype(dtype), d, panoptic, jnp.asarray(ids), s=S,
                                  lam=LAM).total))
  value, grad = fn(jnp.asarray(depth, dtype))
  return float(value), np.asarray(grad, np.float64)


def test_depth_gradient_matches_torch_autograd_at_ties(depth_case):
  image, depth, panoptic, ids = depth_case
  ties = _tie_fraction(depth, panoptic, ids)
  print(f"instance pixels equal to their own pseudo label: {ties:.0%}")
  assert ties > 0.5  # the fixture must exercise |0|
  t_val, t_grad = _torch_depth_grad(image, depth, panoptic, ids)
  scale = np.max(np.abs(t_grad))
  with jax.enable_x64(True):
    j64_val, j64 = _jax_depth_grad(image, depth, panoptic, ids, jnp.float64)
  j32_val, j32 = _jax_depth_grad(image, depth, panoptic, ids, jnp.float32)
  d64 = np.max(np.abs(j64 - t_grad)) / scale
  d32 = np.max(np.abs(j32 - t_grad)) / scale
  flips = int(np.sum(np.sign(j32) != np.sign(t_grad)))
  print(f"dL/dD vs float64 torch, max diff / max |grad|: float64 {d64:.1e}, float32 {d32:.1e}; "
        f"float32 sign disagreements {flips} of {t_grad.size}; "
        f"loss {t_val:.4f} (jax64 {j64_val:.4f}, jax32 {j32_val:.4f})")
  np.testing.assert_allclose(j64_val, t_val, rtol=1e-6)
  assert d64 < 1e-6
  assert d32 < 1e-3
  assert flips == 0


# ---------------------------------------------------------------------- converted MonoDepth2


def test_edge_loss_gradient_matches_torch_at_zero_edges_and_equal_edges():
  """dL_e/dD (eq. 9) where both of its |.| are at 0: a flat, saturated depth block and ramps
  (depth Laplacian exactly 0) and rows where the image equals the depth (dI = dD exactly).
  PyTorch's `Tensor.abs()` has derivative 0 there; a |.| with another convention at 0 (e.g.
  +1, as `jnp.abs`'s) changes most components. float64 on both sides."""
  h, w = 12, 16
  depth = np.full((h, w), 20.0)
  depth[:, :4] = 100.0                                      # saturated far region: flat
  depth[6:, 8:] += np.arange(w - 8)[None, :] * 0.5          # a ramp: Laplacian 0 inside it
  image = np.full((h, w, 3), 0.5)
  image[:, 12:] = 0.75                                      # flat regions and one edge
  image[:3] = depth[:3, :, None]                            # rows 0-2: dI = dD exactly
  d = torch.from_numpy(depth).requires_grad_(True)
  l_e = (t_laplacian_edges(torch.from_numpy(image).mean(-1)) - t_laplacian_edges(d)).abs().sum()
  l_e.backward()
  with torch.no_grad():
    d_depth = t_laplacian_edges(d)
    d_image = t_laplacian_edges(torch.from_numpy(image).mean(-1))
  zero_lap, equal = float((d_depth == 0).double().mean()), float((d_depth == d_image).double().mean())
  assert zero_lap > 0.5 and equal > 0.2, (zero_lap, equal)
  with jax.enable_x64(True):
    value, grad = jax.value_and_grad(
        lambda x: losses.edge_guided_loss(jnp.asarray(image), x))(jnp.asarray(depth))
  print(f"Laplacian 0 at {zero_lap:.0%} of pixels, dI = dD at {equal:.0%}; L_e jax "
        f"{float(value):.6f} torch {float(l_e.detach()):.6f}")
  np.testing.assert_allclose(float(value), float(l_e.detach()), rtol=1e-12)
  np.testing.assert_allclose(np.asarray(grad), d.grad.numpy(), rtol=0, atol=1e-12)


def test_edge_loss_gradient_matches_torch_jitted_float32():
  """The same ties in float32 with the image an argument of the jitted gradient, as a step
  compiles it: I_bar is torch's channel mean bit for bit, so dI = dD stays an exact tie (with
  jnp.mean, XLA's reciprocal product left residuals of 1e-7 there and gradients of +-1 to +-4
  per pixel against PyTorch's 0)."""
  rng = np.random.default_rng(5)
  h, w = 12, 16
  depth = (rng.integers(4, 400, (h, w)) * 0.25).astype(np.float32)  # exact in float32
  image = (rng.integers(0, 256, (h, w, 3)) / 255.0).astype(np.float32)
  image[:5] = depth[:5, :, None]                                   # rows 0-4: dI = dD exactly
  image[8:, 6:] = depth[8:, 6:, None] * np.float32(0.5)
  image[8:, 6:, 0] += np.float32(0.25)
  image[8:, 6:, 2] -= np.float32(0.25)                             # I_bar = D / 2 there
  d = torch.from_numpy(depth.copy()).requires_grad_(True)
  i_bar = torch.from_numpy(image.copy()).mean(-1)
  l_e = (t_laplacian_edges(i_bar) - t_laplacian_edges(d)).abs().sum()
  l_e.backward()
  with torch.no_grad():
    ties = float((t_laplacian_edges(d) == t_laplacian_edges(i_bar)).double().mean())
  assert ties > 0.25, ties
  value, grad = jax.jit(jax.value_and_grad(losses.edge_guided_loss, argnums=1))(
      jnp.asarray(image), jnp.asarray(depth))
  np.testing.assert_allclose(float(value), float(l_e.detach()), rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(grad), d.grad.numpy())  # sign patterns: exact


@pytest.fixture(scope="module")
def network_case(tmp_path_factory):
  h, w = 192, 640
  root = tmp_path_factory.mktemp("mono")
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  tm.randomize_(enc, 21), tm.randomize_(dec, 22)
  torch.save({**enc.state_dict(), "height": h, "width": w}, root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  _, variables, _ = convert_monodepth2(root / "encoder.pth", root / "depth.pth")
  yy, xx = np.mgrid[0:h, 0:w]
  image = _flat_image(h, w)
  image = np.clip(image + 0.2 * np.sin(xx / 40.0)[..., None] * (yy > h // 2)[..., None], 0, 1)
  panoptic, ids = _panoptic(h, w)
  return enc, dec, variables, image.astype(np.float32), panoptic, ids


def _torch_side(enc, dec, image, panoptic, ids, dtype):
  enc, dec = enc.to(dtype).train(), dec.to(dtype).train()
  enc.zero_grad(), dec.zero_grad()
  x = torch.from_numpy(image).to(dtype)
  disp = dec(enc(x.permute(2, 0, 1)[None]))[("disp", 0)][0, 0]
  depth = 1.0 / (1 / 100 + (1 / 0.1 - 1 / 100) * disp)           # MonoDepth2's disp_to_depth
  total, l_d, l_e = t_pitta_loss(x, depth, panoptic, ids)
  total.backward()
  ties = _tie_fraction(depth.detach().double().numpy(), panoptic, ids)
  return total.item(), l_d.item(), l_e.item(), tm.bn_grads(enc), ties


def _jax_side(variables, image, panoptic, ids, dtype):
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
    return jax.value_and_grad(loss_fn, has_aux=True)(tr)

  (total, parts_out), grads = value_and_grad(parts.trainable, parts.frozen, parts.batch_stats,
                                             cast(image), jnp.asarray(panoptic))
  flat = flatten_dict(grads["encoder"], sep="/")
  return (float(total), float(parts_out.l_d), float(parts_out.l_e),
          {k: np.asarray(v, np.float64) for k, v in flat.items()})


def _worst(a: dict, b: dict) -> float:
  """Worst over leaves of max |a - b| / max |b| (1e-3 of the largest component = 1e-3)."""
  return max(float(np.max(np.abs(a[k] - b[k])) / np.max(np.abs(b[k]))) for k in b)


def test_pitta_loss_and_bn_gradient_match_torch_at_640x192(network_case):
  enc, dec, variables, image, panoptic, ids = network_case
  t64 = _torch_side(enc, dec, image, panoptic, ids, torch.float64)
  t32 = _torch_side(enc, dec, image, panoptic, ids, torch.float32)
  with jax.enable_x64(True):
    j64 = _jax_side(variables, image, panoptic, ids, jnp.float64)
  j32 = _jax_side(variables, image, panoptic, ids, jnp.float32)
  print(f"instance pixels equal to their own pseudo label: {t64[4]:.0%}")
  # the loss value in float32 (what runs in practice)
  rel = [abs(a - b) / abs(b) for a, b in zip(j32[:3], t64[:3])]
  print(f"float32 L, L_d, L_e: jax {j32[0]:.4f} {j32[1]:.4f} {j32[2]:.4f} torch64 {t64[0]:.4f} "
        f"{t64[1]:.4f} {t64[2]:.4f}; rel diffs {rel[0]:.1e} {rel[1]:.1e} {rel[2]:.1e}")
  assert max(rel) < 1e-4
  # float64: the gradient w.r.t. the 40 encoder BN gamma/beta leaves
  assert set(j64[3]) == set(t64[3]) and len(t64[3]) == 40
  w64 = _worst(j64[3], t64[3])
  np.testing.assert_allclose(j64[0], t64[0], rtol=1e-6)
  # float32: within float32 noise of the float64 truth (PyTorch's own float32 gradient is
  # ~1e-3 off it here), and the same sign in every component above that noise (1% of its leaf's
  # largest component)
  w32, wt32 = _worst(j32[3], t64[3]), _worst(t32[3], t64[3])
  big = {k: np.abs(t64[3][k]) > 1e-2 * np.max(np.abs(t64[3][k])) for k in t64[3]}
  flips = sum(int(np.sum((np.sign(j32[3][k]) != np.sign(t64[3][k])) & big[k])) for k in t64[3])
  n_big = sum(int(v.sum()) for v in big.values())
  print(f"BN gradient vs float64 torch, worst max-diff / max over 40 leaves: jax64 {w64:.1e}, "
        f"jax32 {w32:.1e}, torch32 {wt32:.1e}; jax32 sign disagreements {flips} of {n_big} "
        f"components above 1% of their leaf's largest")
  assert w64 < 1e-6
  assert w32 < max(2 * wt32, 2e-3)
  assert flips == 0
