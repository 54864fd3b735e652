"""MonoDepth2's loss kit (`pitta_jax.sfm`) against an independent PyTorch MonoDepth2 loss.

Reference: tests/torch_sfm.py, written from MonoDepth2's layers.py / trainer.py with native
torch ops (nn.ReflectionPad2d + nn.AvgPool2d, F.grid_sample(padding_mode="border"; both
align_corners), F.interpolate, torch.min(dim=1), torch.abs, torch.clamp). Each function's
value and its gradient (of a random linear functional of the output, so every output element
counts) are compared in float32 and float64; the measured differences are printed (-s).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
import torch.nn.functional as F

import torch_sfm as ts
from pitta_jax import sfm

B, H, W, N = 2, 32, 64, 2
TORCH_DTYPE = {np.float32: torch.float32, np.float64: torch.float64}


def _t(x, dtype, grad=False):
  t = torch.from_numpy(np.asarray(x, dtype))
  return t.requires_grad_(grad)


def _nchw(x):
  return x.permute(0, 3, 1, 2)


def _close(name, got, want, rtol, atol):
  got, want = np.asarray(got), np.asarray(want)
  err = float(np.max(np.abs(got - want))) if got.size else 0.0
  print(f"{name}: max |diff| {err:.3g} (max |ref| {float(np.max(np.abs(want))):.3g})")
  np.testing.assert_allclose(got, want, rtol=rtol, atol=atol, err_msg=name)


def _tol(dtype):
  return (2e-5, 2e-6) if dtype == np.float32 else (1e-10, 1e-12)


def _images(seed, shape=(B, H, W, 3)):
  """Smooth-ish random images in [0, 1] (noise plus a gradient, so SSIM is not degenerate)."""
  r = np.random.default_rng(seed)
  ramp = np.linspace(0, 1, shape[2])[None, None, :, None]
  return np.clip(0.6 * r.random(shape) + 0.4 * ramp, 0, 1)


def _x64(dtype):
  return jax.enable_x64(dtype == np.float64)


# ---------------------------------------------------------------------- photometric pieces


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ssim_and_reprojection(dtype):
  """ssim_loss (B, H, W, 3) and reprojection_loss (B, H, W): values and d/d(pred, target)."""
  x, y = _images(0), _images(1)
  y[:, :4, :4] = x[:, :4, :4]            # identical patches: SSIM 1, the clamp's lower bound
  r = np.random.default_rng(2)
  cs, cr = r.standard_normal((B, H, W, 3)), r.standard_normal((B, H, W))
  with _x64(dtype):
    xj, yj = jnp.asarray(x, dtype), jnp.asarray(y, dtype)
    def both(a, b):
      ssim_map, rep_map = sfm.ssim_loss(a, b), sfm.reprojection_loss(a, b)
      return (jnp.sum(ssim_map * cs.astype(dtype)), jnp.sum(rep_map * cr.astype(dtype))), (
          ssim_map, rep_map)
    jac = jax.jit(jax.jacrev(both, argnums=(0, 1), has_aux=True))
    ((gsx, gsy), (grx, gry)), (ssim_map, rep_map) = jac(xj, yj)

  xt, yt = _t(x, dtype, True), _t(y, dtype, True)
  ssim_t = ts.SSIM()(_nchw(xt), _nchw(yt)).permute(0, 2, 3, 1)
  (ssim_t * _t(cs, dtype)).sum().backward()
  rtol, atol = _tol(dtype)
  _close("ssim value", ssim_map, ssim_t.detach(), rtol, atol)
  _close("ssim d/dx", gsx, xt.grad, rtol, atol * 10)
  _close("ssim d/dy", gsy, yt.grad, rtol, atol * 10)

  xt, yt = _t(x, dtype, True), _t(y, dtype, True)
  loss = ts.Monodepth2Loss(B, H, W, dtype=TORCH_DTYPE[dtype])
  rep_t = loss.compute_reprojection_loss(_nchw(xt), _nchw(yt))[:, 0]
  (rep_t * _t(cr, dtype)).sum().backward()
  _close("reprojection value", rep_map, rep_t.detach(), rtol, atol)
  _close("reprojection d/dpred", grx, xt.grad, rtol, atol * 10)
  _close("reprojection d/dtarget", gry, yt.grad, rtol, atol * 10)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_smooth_loss(dtype):
  """get_smooth_loss on a mean-normalised disparity with flat runs (|d disp| = 0 ties)."""
  r = np.random.default_rng(3)
  disp = np.round(r.random((B, H, W)) * 4) / 4 + 0.1     # many equal neighbours
  image = _images(4)
  with _x64(dtype):
    fn = jax.jit(jax.value_and_grad(sfm.smooth_loss, argnums=(0, 1)))
    val, (gd, gi) = fn(jnp.asarray(disp, dtype), jnp.asarray(image, dtype))
  dt, it = _t(disp, dtype, True), _t(image, dtype, True)
  want = ts.get_smooth_loss(dt[:, None], _nchw(it))
  want.backward()
  rtol, atol = _tol(dtype)
  _close("smooth value", val, want.detach(), rtol, atol)
  _close("smooth d/ddisp", gd, dt.grad, rtol, atol)
  _close("smooth d/dimage", gi, it.grad, rtol, atol)


# ---------------------------------------------------------------------- geometry


def _intrinsics(h, w):
  K = np.array([[0.58 * w, 0, 0.5 * w, 0], [0, 1.92 * h, 0.5 * h, 0], [0, 0, 1, 0],
                [0, 0, 0, 1]])
  K = np.repeat(K[None], B, 0)
  return K, np.linalg.inv(K)


def _pose_params(seed):
  r = np.random.default_rng(seed)
  return 0.02 * r.standard_normal((B, N, 1, 3)), 0.1 * r.standard_normal((B, N, 1, 3))


def test_transformation_from_parameters_is_monodepth2s():
  """The re-exported pose.transformation_from_parameters equals the torch reference (float64)."""
  aa, tr = _pose_params(5)
  for invert in (False, True):
    with jax.enable_x64(True):
      got = sfm.transformation_from_parameters(jnp.asarray(aa[:, 0]), jnp.asarray(tr[:, 0]),
                                               invert)
    want = ts.transformation_from_parameters(_t(aa[:, 0], np.float64), _t(tr[:, 0], np.float64),
                                             invert)
    _close(f"T (invert={invert})", got, want, 1e-12, 1e-14)


def test_the_pose_gradient_at_rest_is_torchs():
  """At an axis-angle of exactly 0 (a pose net at rest, a zero-initialised head) MonoDepth2's
  torch.norm gives the rotation a zero derivative; jnp.linalg.norm gave NaN, which made a
  CoMoDa or Ada-Depth step non-finite (skipped). Away from 0 the gradients agree as well."""
  r = np.random.default_rng(3)
  tr = 0.1 * r.standard_normal((2, 1, 3))
  weights = r.standard_normal((2, 4, 4))
  for aa in (np.zeros((2, 1, 3)), 0.02 * r.standard_normal((2, 1, 3))):
    with jax.enable_x64(True):
      got = jax.grad(lambda a: jnp.sum(sfm.transformation_from_parameters(
          a, jnp.asarray(tr)) * weights))(jnp.asarray(aa))
    a = torch.tensor(aa, requires_grad=True)
    (ts.transformation_from_parameters(a, _t(tr, np.float64)) * torch.tensor(weights)).sum(
        ).backward()
    assert np.all(np.isfinite(np.asarray(got)))
    np.testing.assert_allclose(np.asarray(got), a.grad.numpy(), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_backproject_project(dtype):
  """BackprojectDepth + Project3D: coordinates and their gradient w.r.t. depth and T."""
  r = np.random.default_rng(6)
  depth = 1 + 20 * r.random((B, H, W))
  K, inv_K = _intrinsics(H, W)
  aa, tr = _pose_params(7)
  T = ts.transformation_from_parameters(_t(aa[:, 0], np.float64),
                                        _t(tr[:, 0], np.float64)).numpy()
  c = r.standard_normal((B, H, W, 2))
  with _x64(dtype):
    def g(d, t):
      pts = sfm.backproject(d, jnp.asarray(inv_K, dtype))
      coords = sfm.project(pts, jnp.asarray(K, dtype), t, H, W)
      return jnp.sum(coords * c.astype(dtype)), (pts, coords)
    (gd, gt), (pts, coords) = jax.jit(jax.grad(g, argnums=(0, 1), has_aux=True))(
        jnp.asarray(depth, dtype), jnp.asarray(T, dtype))
  dt, Tt = _t(depth, dtype, True), _t(T, dtype, True)
  pts_t = ts.BackprojectDepth(B, H, W, TORCH_DTYPE[dtype])(dt, _t(inv_K, dtype))
  coords_t = ts.Project3D(B, H, W)(pts_t, _t(K, dtype), Tt)
  (coords_t * _t(c, dtype)).sum().backward()
  rtol, atol = _tol(dtype)
  _close("backproject", pts, pts_t.detach(), rtol, atol * 10)
  _close("project", coords, coords_t.detach(), rtol, atol)
  _close("project d/ddepth", gd, dt.grad, rtol, atol)
  _close("project d/dT", gt, Tt.grad, rtol * 5, atol * 100)


# ---------------------------------------------------------------------- warp


def _warp_case(kind, align_corners):
  """Image 9x17 (H - 1, W - 1 powers of two: align_corners' pixel-centre coordinates are exact
  in float32), 8x16 without align_corners (H, W powers of two, for the same reason)."""
  r = np.random.default_rng(8)
  h, w = (9, 17) if align_corners else (8, 16)
  image = r.random((B, h, w, 3))
  if kind == "random":       # well beyond [-1, 1] on every side: border padding
    coords = r.uniform(-1.4, 1.4, (B, 12, 20, 2))
  else:                      # exactly on pixel centres, the first/last included, and outside
    cols, rows = np.arange(-2, w + 2), np.arange(-1, h + 1)   # beyond both borders
    if align_corners:
      xs, ys = cols / ((w - 1) / 2) - 1, rows / ((h - 1) / 2) - 1
    else:
      xs, ys = (2 * cols + 1) / w - 1, (2 * rows + 1) / h - 1
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    coords = np.repeat(np.stack([gx, gy], -1)[None], B, 0)
  return image, coords


@pytest.mark.parametrize("align_corners", [True, False])
@pytest.mark.parametrize("kind", ["random", "centres"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_warp(kind, dtype, align_corners):
  """warp vs F.grid_sample(border, align_corners): value, d/dimage, d/dcoords."""
  image, coords = _warp_case(kind, align_corners)
  c = np.random.default_rng(9).standard_normal(coords.shape[:3] + (3,))
  with _x64(dtype):
    def f(i, g):
      out = sfm.warp(i, g, align_corners)
      return jnp.sum(out * c.astype(dtype)), out
    (gi, gc), out = jax.jit(jax.grad(f, argnums=(0, 1), has_aux=True))(
        jnp.asarray(image, dtype), jnp.asarray(coords, dtype))
  it, ct = _t(image, dtype, True), _t(coords, dtype, True)
  want = F.grid_sample(_nchw(it), ct, mode="bilinear", padding_mode="border",
                       align_corners=align_corners).permute(0, 2, 3, 1)
  (want * _t(c, dtype)).sum().backward()
  rtol, atol = _tol(dtype)
  _close(f"warp {kind} value", out, want.detach(), rtol, atol)
  _close(f"warp {kind} d/dimage", gi, it.grad, rtol, atol * 10)
  _close(f"warp {kind} d/dcoords", gc, ct.grad, rtol, atol * 10)
  if kind == "centres":      # on a centre the sample is the pixel itself
    h, w = image.shape[1:3]
    np.testing.assert_array_equal(np.asarray(out)[:, 1:h + 1, 2:w + 2], image.astype(dtype))


# ---------------------------------------------------------------------- the full loss


@pytest.fixture(scope="module")
def loss_case():
  r = np.random.default_rng(10)
  target = _images(11)
  sources = np.stack([np.clip(np.roll(target, 1 + i, axis=2) + 0.05 * r.standard_normal(
      target.shape), 0, 1) for i in range(N)], 1)                      # (B, N, H, W, 3)
  disps = [0.05 + 0.3 * r.random((B, H // 2 ** s, W // 2 ** s)) for s in range(4)]
  K, inv_K = _intrinsics(H, W)
  aa, tr = _pose_params(12)
  noise = r.standard_normal((4, B, N, H, W))
  weights = (r.random((B, H, W)) > 0.3).astype(np.float64)
  return dict(target=target, sources=sources, disps=disps, K=K, inv_K=inv_K, aa=aa, tr=tr,
              noise=noise, weights=weights)


@pytest.fixture(scope="module")
def jax_loss():
  """One compiled value-and-gradient of the loss per case and dtype, shared by the loss tests."""
  compiled = {}

  def run(case, dtype, weights):
    with _x64(dtype):
      if (id(case), dtype) not in compiled:
        def f(disps, aa, tr, weights):
          poses = jnp.stack([sfm.transformation_from_parameters(aa[:, i], tr[:, i])
                             for i in range(N)], 1)
          return sfm.monodepth2_loss(
              jnp.asarray(case["target"], dtype), jnp.asarray(case["sources"], dtype), disps,
              jnp.asarray(case["K"], dtype), jnp.asarray(case["inv_K"], dtype), poses,
              cfg=sfm.SfmLossConfig(), noise=jnp.asarray(case["noise"], dtype),
              pixel_weights=weights)
        compiled[id(case), dtype] = jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2),
                                                               has_aux=True))
      (val, aux), grads = compiled[id(case), dtype](
          [jnp.asarray(d, dtype) for d in case["disps"]], jnp.asarray(case["aa"], dtype),
          jnp.asarray(case["tr"], dtype), jnp.asarray(weights, dtype))
      return np.asarray(val), jax.tree.map(np.asarray, aux), jax.tree.map(np.asarray, grads)

  return run


def _torch_loss(case, dtype, weights):
  disps = [_t(d[:, None], dtype, True) for d in case["disps"]]
  aa, tr = _t(case["aa"], dtype, True), _t(case["tr"], dtype, True)
  poses = [ts.transformation_from_parameters(aa[:, i], tr[:, i]) for i in range(N)]
  loss = ts.Monodepth2Loss(B, H, W, dtype=TORCH_DTYPE[dtype])
  val, per_scale, sel, candidates = loss(
      _nchw(_t(case["target"], dtype)), [_nchw(_t(case["sources"][:, i], dtype)) for i in range(N)],
      disps, _t(case["K"], dtype), _t(case["inv_K"], dtype), poses, _t(case["noise"], dtype),
      _t(weights, dtype))
  val.backward()
  return dict(val=val.detach().numpy(), per_scale=per_scale.detach().numpy(), sel=sel.numpy(),
              candidates=candidates.numpy(), gdisp=[d.grad[:, 0].numpy() for d in disps],
              gaa=aa.grad.numpy(), gtr=tr.grad.numpy(), coords=loss.pixel_coords.numpy(),
              residuals=loss.residuals.numpy())


def _compare_loss(got, want, rtol, atol, gtol):
  val, aux, (gdisp, gaa, gtr) = got
  _close("loss", val, want["val"], rtol, atol)
  _close("per-scale", aux.per_scale, want["per_scale"], rtol, atol)
  for s in range(4):
    scale = np.max(np.abs(want["gdisp"][s]))
    _close(f"d/ddisp scale {s} (/ max)", gdisp[s] / scale, want["gdisp"][s] / scale, 0, gtol)
  scale = max(np.max(np.abs(want["gaa"])), np.max(np.abs(want["gtr"])))
  _close("d/daxisangle (/ max)", gaa / scale, want["gaa"] / scale, 0, gtol)
  _close("d/dtranslation (/ max)", gtr / scale, want["gtr"] / scale, 0, gtol)


@pytest.fixture(scope="module")
def torch_float64(loss_case):
  """The float64 reference with pixel weights 1 (shared: its candidates locate near ties)."""
  return _torch_loss(loss_case, np.float64, np.ones((B, H, W)))


def test_monodepth2_loss_float64(loss_case, jax_loss, torch_float64):
  """Full loss (2 sources, 4 scales, auto-masking), float64: value, per-scale terms, identity
  selection (exactly), d/d(disparity at each scale), d/d(axis-angle, translation) of both
  poses. (Pixel weights: 1 here, a random 0/1 mask in the float32 test.)"""
  got = jax_loss(loss_case, np.float64, np.ones((B, H, W)))
  want = torch_float64
  print(f"warped source wins at {want['sel'].mean():.3f} of the pixels")
  assert 0.05 < want["sel"].mean() < 0.95, "the identity and the warped losses must both win"
  np.testing.assert_array_equal(got[1].identity_selection, want["sel"])
  _compare_loss(got, want, 1e-10, 1e-12, 1e-9)


def test_monodepth2_loss_exact_ties_float64(loss_case, jax_loss):
  """The per-pixel minimum at exact ties, as `torch.min(dim)` takes it: the first candidate wins
  and gets the whole gradient. Source 1 is source 0 with source 0's pose, so the two warped
  candidates are equal bit for bit wherever they are computed; PyTorch then sends their
  gradient to source 0's pose only (source 1's pose gradient is exactly 0), and so must we.
  (A rule that split ties, or took the last, would put gradient on source 1's pose.)"""
  sources, aa, tr = (loss_case[k].copy() for k in ("sources", "aa", "tr"))
  sources[:, 1], aa[:, 1], tr[:, 1] = sources[:, 0], aa[:, 0], tr[:, 0]
  case = {**loss_case, "sources": sources, "aa": aa, "tr": tr}
  want = _torch_loss(case, np.float64, np.ones((B, H, W)))
  cand = want["candidates"]                                           # (S, B, 2N, H, W)
  np.testing.assert_array_equal(cand[:, :, N], cand[:, :, N + 1])     # the warped pair ties
  print(f"warped (tied) source wins at {want['sel'].mean():.3f} of the pixels")
  assert 0.05 < want["sel"].mean() < 0.95
  assert np.all(want["gaa"][:, 1] == 0) and np.all(want["gtr"][:, 1] == 0)
  assert np.max(np.abs(want["gaa"][:, 0])) > 0 and np.max(np.abs(want["gtr"][:, 0])) > 0
  got = jax_loss(case, np.float64, np.ones((B, H, W)))
  np.testing.assert_array_equal(got[1].identity_selection, want["sel"])
  _compare_loss(got, want, 1e-10, 1e-12, 1e-9)
  assert np.all(got[2][1][:, 1] == 0) and np.all(got[2][2][:, 1] == 0)


def _float32_kinks(ref: dict, margin: float = 1e-5) -> dict[str, np.ndarray]:
  """(B, H, W) masks of the pixels whose loss has a kink that float32 rounding can decide,
  located in the float64 reference `ref` (pixel weights 1) by a margin far above float32's
  rounding of these quantities (~1e-7) and far below their spread:
  - "tie": the per-pixel minimum's two best candidates within `margin` (which one wins);
  - "l1": a warped source's channel within `margin` of the target (the sign of |target - pred|);
  - "grid": a sampled coordinate within `margin` of an integer (the sampler's floor, or a border,
    where the coordinate gradient jumps), spread to the 3x3 neighbours whose SSIM statistics
    contain the sample."""
  cand = np.sort(ref["candidates"], axis=2)                            # (S, B, 2N, H, W)
  tie = np.any(cand[:, :, 1] - cand[:, :, 0] < margin, axis=0)
  l1 = np.any(np.abs(ref["residuals"]) < margin, axis=(0, 1, 3))       # (S, N, B, 3, H, W)
  c = ref["coords"]                                                    # (S, N, B, H, W, 2)
  on_grid = np.pad(np.any(np.abs(c - np.round(c)) < margin, axis=(0, 1, 5)), ((0, 0), (1, 1), (1, 1)))
  grid = np.zeros_like(tie)
  for dy in range(3):
    for dx in range(3):
      grid |= on_grid[:, dy:dy + H, dx:dx + W]
  return {"tie": tie, "l1": l1, "grid": grid}


def test_monodepth2_loss_float32(loss_case, jax_loss, torch_float64):
  """The same in float32 with a random 0/1 pixel-weight mask (CoMoDa's use). Where a kink of the
  loss lies within float32 rounding of the evaluation point (`_float32_kinks`: a near tie of the
  per-pixel minimum, an L1 residual near 0, a sample near a grid line), which side is taken
  depends on the order of float32 operations, so the gradient there is not defined to float32
  precision: such pixels are weighted 0 as well, on both sides; the rest must agree (selection
  exactly, gradients tightly)."""
  kinks = _float32_kinks(torch_float64)
  print("excluded: " + ", ".join(f"{k} {int(m.sum())}" for k, m in kinks.items())
        + f" of {B * H * W} pixels")
  excluded = kinks["tie"] | kinks["l1"] | kinks["grid"]
  assert excluded.mean() < 0.01
  weights = loss_case["weights"] * ~excluded
  got = jax_loss(loss_case, np.float32, weights)
  want = _torch_loss(loss_case, np.float32, weights)
  keep = weights.astype(bool)[None].repeat(4, 0)
  np.testing.assert_array_equal(got[1].identity_selection[keep], want["sel"][keep])
  _compare_loss(got, want, 1e-5, 1e-7, 1e-4)


def test_monodepth2_loss_no_automask_scaled_targets(loss_case):
  """float64, cfg.automask=False (upstream --disable_automasking), scales (0, 2), the scale-2
  colour image given explicitly (an antialiased F.interpolate, as a data loader would resize):
  value and gradients vs the reference with disable_automasking and the same colours."""
  case, scales = loss_case, (0, 2)
  target_t = _nchw(_t(case["target"], np.float64))
  colors = [target_t, F.interpolate(target_t, (H // 4, W // 4), mode="bilinear",
                                    align_corners=False, antialias=True)]
  disps_t = [_t(case["disps"][s][:, None], np.float64, True) for s in scales]
  aa, tr = _t(case["aa"], np.float64, True), _t(case["tr"], np.float64, True)
  poses_t = [ts.transformation_from_parameters(aa[:, i], tr[:, i]) for i in range(N)]
  ref = ts.Monodepth2Loss(B, H, W, scales=scales, disable_automasking=True,
                          dtype=torch.float64)
  want, want_per_scale, _, _ = ref(
      target_t, [_nchw(_t(case["sources"][:, i], np.float64)) for i in range(N)], disps_t,
      _t(case["K"], np.float64), _t(case["inv_K"], np.float64), poses_t, None, None, colors)
  want.backward()
  with jax.enable_x64(True):
    cfg = sfm.SfmLossConfig(scales=scales, automask=False)
    def f(disps, aa, tr):
      poses = jnp.stack([sfm.transformation_from_parameters(aa[:, i], tr[:, i])
                         for i in range(N)], 1)
      return sfm.monodepth2_loss(
          jnp.asarray(case["target"]), jnp.asarray(case["sources"]), disps,
          jnp.asarray(case["K"]), jnp.asarray(case["inv_K"]), poses, cfg=cfg,
          scaled_targets=[jnp.asarray(c.permute(0, 2, 3, 1).numpy()) for c in colors])
    (val, aux), (gd, gaa, gtr) = jax.jit(jax.value_and_grad(f, (0, 1, 2), has_aux=True))(
        [jnp.asarray(case["disps"][s]) for s in scales], jnp.asarray(case["aa"]),
        jnp.asarray(case["tr"]))
    gd, gaa, gtr = [np.asarray(g) for g in gd], np.asarray(gaa), np.asarray(gtr)
  _close("loss (no automask)", val, want.detach(), 1e-10, 1e-12)
  _close("per-scale (no automask)", aux.per_scale, want_per_scale.detach(), 1e-10, 1e-12)
  assert np.all(np.asarray(aux.identity_selection) == 1)
  for k in range(2):
    scale = disps_t[k].grad.abs().max().item()
    _close(f"d/ddisp scale {scales[k]} (/ max)", gd[k] / scale, disps_t[k].grad[:, 0] / scale,
           0, 1e-9)
  scale = max(aa.grad.abs().max().item(), tr.grad.abs().max().item())
  _close("d/daxisangle (/ max)", gaa / scale, aa.grad / scale, 0, 1e-9)
  _close("d/dtranslation (/ max)", gtr / scale, tr.grad / scale, 0, 1e-9)


def test_loss_rng_and_config():
  """With rng instead of noise the loss runs (tie-break drawn), and the config validates."""
  cfg = sfm.SfmLossConfig(scales=(0,))
  r = np.random.default_rng(13)
  target = jnp.asarray(_images(14, (1, 16, 32, 3)), jnp.float32)
  sources = jnp.asarray(r.random((1, 1, 16, 32, 3)), jnp.float32)
  K, inv_K = _intrinsics(16, 32)
  poses = jnp.broadcast_to(jnp.eye(4), (1, 1, 4, 4))
  fn = jax.jit(lambda t, src, d, k, ik, p, key: sfm.monodepth2_loss(
      t, src, [d], k, ik, p, cfg=cfg, rng=key))
  loss, aux = fn(target, sources, jnp.full((1, 16, 32), 0.3), jnp.asarray(K[:1], jnp.float32),
                 jnp.asarray(inv_K[:1], jnp.float32), poses, jax.random.key(0))
  assert np.isfinite(loss) and aux.reprojection.shape == (1, 1, 16, 32)
  for bad in (dict(min_depth=0.0), dict(max_depth=0.05), dict(scales=()), dict(scales=(0, 0)),
              dict(smoothness=-1.0), dict(automask=1)):
    with pytest.raises(ValueError):
      sfm.SfmLossConfig(**bad)


def test_a_target_not_divisible_by_the_coarsest_scale_is_named():
  """H and W must be divisible by 2**max(scales) for the block means of the target at each
  scale: a 6x8 target at scales 0-2 was a bare reshape TypeError."""
  cfg = sfm.SfmLossConfig(scales=(0, 1, 2), automask=False)
  b, h, w = 1, 6, 8
  disps = [jnp.full((b, h // 2 ** s, w // 2 ** s), 0.5) for s in cfg.scales]
  eye = jnp.eye(4)[None]
  with pytest.raises(ValueError, match=r"8x6 must be divisible by 2\*\*2 = 4"):
    sfm.monodepth2_loss(jnp.zeros((b, h, w, 3)), jnp.zeros((b, 1, h, w, 3)), disps, eye, eye,
                        eye[:, None], cfg=cfg)


@pytest.mark.parametrize("shape", [(1, 1, 5, 3), (1, 4, 1, 3)])
def test_ssim_refuses_an_axis_that_reflection_padding_cannot_pad(shape):
  """MonoDepth2's SSIM pads by reflection (nn.ReflectionPad2d(1)), which PyTorch refuses on an
  axis of one pixel; ssim_loss gave a (1 - SSIM) / 2 map of such an image (jnp.pad's 'reflect'
  repeats the single pixel) where upstream has none."""
  x = np.random.default_rng(0).random(shape).astype(np.float32)
  with pytest.raises(RuntimeError, match="Padding size should be less than"):
    torch.nn.ReflectionPad2d(1)(torch.from_numpy(x).permute(0, 3, 1, 2))
  with pytest.raises(ValueError, match="ssim_loss"):
    sfm.ssim_loss(x, x)
  with pytest.raises(ValueError, match="ssim_loss"):
    sfm.reprojection_loss(x, x)


def test_a_scale_the_network_lacks_is_named_with_its_flag():
  """A loss scale beyond the network's outputs is refused in one line naming the method's
  field and its flag (`--comoda.sfm.scales`): it said only "sfm.scales", no flag."""
  from pitta_jax.sfm import check_scales
  check_scales((0, 1, 2, 3), 4, "comoda.sfm.scales")  # scales 0..3 of 4 maps: accepted
  with pytest.raises(ValueError, match=r"^comoda\.sfm\.scales \(0, 7\): the network gives "
                                       r"scales 0\.\.3 only \(--comoda\.sfm\.scales\)$"):
    check_scales((0, 7), 4, "comoda.sfm.scales")
