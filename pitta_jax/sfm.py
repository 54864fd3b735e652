"""MonoDepth2's self-supervised (structure-from-motion) loss kit, as pure jittable functions.

Upstream: nianticlabs/monodepth2 `layers.py` (`SSIM`, `BackprojectDepth`, `Project3D`,
`get_smooth_loss`, `transformation_from_parameters`) and `trainer.py`
(`generate_images_pred`, `compute_reprojection_loss`, `compute_losses`) with upstream's
defaults: full-resolution multi-scale (disparities upsampled to the input size, not
`--v1_multiscale`), per-pixel minimum over source frames (not `--avg_reprojection`),
auto-masking on (not `--disable_automasking`), SSIM on. Needed by the pose-based baselines
(CoMoDa, ...); PITTA itself is pose-agnostic (paper eq. 2).

Conventions: images NHWC float in [0, 1], depth / disparity (B, H, W), intrinsics K and inv_K
(B, 4, 4) for the full-resolution image, camera motions T (B, 4, 4) mapping target-camera points
to source-camera points (upstream's `outputs[("cam_T_cam", 0, frame_id)]`;
`transformation_from_parameters` from `pitta_jax.models.pose` builds them from the pose net's
axis-angle and translation).

`warp` is `F.grid_sample(image, coords, mode="bilinear", padding_mode="border",
align_corners=...)`. MonoDepth2, CoMoDa and Ada-Depth all call `F.grid_sample(...,
padding_mode="border")` without `align_corners`, so which convention they sample with depends
on the PyTorch they ran on: MonoDepth2's training code predates PyTorch 1.3, whose default was
align_corners=True (the convention of `Project3D`'s normalisation by W - 1, H - 1); CoMoDa
(PyTorch 1.3.0) and Ada-Depth (1.7.1) ran after the default became False, which samples x * W /
(W - 1) - 0.5 for `Project3D`'s pixel x (half a pixel off at the borders, not the identity for a
static camera). `SfmLossConfig.align_corners` is False, what the two baselines' adaptation code
computed; True gives MonoDepth2's training convention. The gradients follow torch's grid sampler: bilinear weights from floor(x) (so on a pixel centre the
coordinate derivative is the forward difference), and border clipping passes the coordinate
gradient only strictly inside (0, size - 1) (torch treats the borders as out of bounds).
The derivatives of |x| and clamp are PyTorch's (`pitta_jax.nonsmooth`); the per-pixel minimum
sends the gradient to the first minimum, as `torch.min(dim=1)`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax import prng
from pitta_jax.configs import check, check_types, finite, option
from pitta_jax.models.depth_decoder import MAX_DEPTH, MIN_DEPTH, disp_to_depth
from pitta_jax.models.interpolate import resize_bilinear
from pitta_jax.models.pose import transformation_from_parameters
from pitta_jax.nonsmooth import absolute, clamp

Array = jax.Array

# Fixed constants of upstream's formulas (not options upstream either).
SSIM_C1 = 0.01 ** 2          # layers.SSIM
SSIM_C2 = 0.03 ** 2
SSIM_WEIGHT = 0.85           # trainer.compute_reprojection_loss: 0.85 SSIM + 0.15 L1
PROJECT_EPS = 1e-7           # layers.Project3D
MEAN_DISP_EPS = 1e-7         # trainer.compute_losses: disp / (mean_disp + 1e-7)
TIE_NOISE = 1e-5             # trainer.compute_losses: randn * 0.00001 on the identity loss


@dataclasses.dataclass(frozen=True)
class SfmLossConfig:
  """MonoDepth2's photometric loss options (upstream `options.py` defaults)."""
  min_depth: float = option(MIN_DEPTH, "depth of disparity 1 (MonoDepth2 --min_depth)")
  max_depth: float = option(MAX_DEPTH, "depth of disparity 0 (MonoDepth2 --max_depth)")
  scales: tuple[int, ...] = option((0, 1, 2, 3), "decoder scales in the loss (MonoDepth2 --scales)")
  smoothness: float = option(1e-3, "edge-aware smoothness weight (--disparity_smoothness)")
  automask: bool = option(True, "identity-reprojection auto-masking (not --disable_automasking)")
  align_corners: bool = option(False, "the warp's grid_sample convention: False = what CoMoDa's "
                                      "and Ada-Depth's code compute (PyTorch >= 1.3 default), "
                                      "True = MonoDepth2's training (PyTorch < 1.3)")

  def __post_init__(self):
    check_types(self)
    finite(self.min_depth, "min_depth", 0.0)
    check(self.min_depth > 0, f"min_depth must be > 0, got {self.min_depth!r}")
    finite(self.max_depth, "max_depth", 0.0)
    check(self.max_depth > self.min_depth,
          f"max_depth must exceed min_depth, got {self.max_depth!r} <= {self.min_depth!r}")
    check(isinstance(self.scales, tuple) and len(self.scales) > 0
          and all(isinstance(s, int) and s >= 0 for s in self.scales)
          and len(set(self.scales)) == len(self.scales),
          f"scales must be a non-empty tuple of distinct ints >= 0, got {self.scales!r}")
    finite(self.smoothness, "smoothness", 0.0)
    check(isinstance(self.automask, bool), f"automask must be a bool, got {self.automask!r}")
    check(isinstance(self.align_corners, bool),
          f"align_corners must be a bool, got {self.align_corners!r}")


def check_scales(scales: Sequence[int], n_outputs: int, name: str = "sfm.scales") -> None:
  """ValueError (one line) unless the network's `n_outputs` disparity maps (scales 0 ..
  n_outputs - 1) include every scale of the loss (`SfmLossConfig.scales`); checked when the
  step is traced, before any frame. name: the config field's path (a method's
  `comoda.sfm.scales`: its command-line flag is `--` + name)."""
  check(max(scales) < n_outputs, f"{name} {tuple(scales)}: the network gives scales 0.."
                                 f"{n_outputs - 1} only (--{name})")


# ----------------------------------------------------------------------------- photometric


def _avg_pool3(x: Array) -> Array:
  """3x3 average pool, stride 1, no padding, on (B, H, W, C): `nn.AvgPool2d(3, 1)`."""
  total = jax.lax.reduce_window(x, 0.0, jax.lax.add, (1, 3, 3, 1),
                                (1, 1, 1, 1), "VALID")
  return total / 9.0


def ssim_loss(x: Array, y: Array) -> Array:
  """MonoDepth2's `SSIM` module: per-pixel (1 - SSIM) / 2 clamped to [0, 1].

  x, y: (B, H, W, C) images; returns (B, H, W, C). Statistics are 3x3 means over
  reflection-padded inputs (`nn.ReflectionPad2d(1)` + `nn.AvgPool2d(3, 1)`); H and W must be
  at least 2, as PyTorch's reflection padding by 1 requires (ValueError otherwise).
  """
  if min(x.shape[1:3]) < 2:
    raise ValueError(f"ssim_loss needs (B, H, W, C) images with H, W >= 2 (reflection padding by "
                     f"1, nn.ReflectionPad2d(1)), got shape {x.shape}")
  pad = ((0, 0), (1, 1), (1, 1), (0, 0))
  x = jnp.pad(x, pad, mode="reflect")
  y = jnp.pad(y, pad, mode="reflect")
  mu_x, mu_y = _avg_pool3(x), _avg_pool3(y)
  sigma_x = _avg_pool3(x ** 2) - mu_x ** 2
  sigma_y = _avg_pool3(y ** 2) - mu_y ** 2
  sigma_xy = _avg_pool3(x * y) - mu_x * mu_y
  n = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
  d = (mu_x ** 2 + mu_y ** 2 + SSIM_C1) * (sigma_x + sigma_y + SSIM_C2)
  return clamp((1 - n / d) / 2, 0.0, 1.0)


def reprojection_loss(pred: Array, target: Array) -> Array:
  """`trainer.compute_reprojection_loss`: 0.85 SSIM + 0.15 L1, channel means.

  pred, target: (B, H, W, 3); returns (B, H, W).
  """
  l1 = jnp.mean(absolute(target - pred), axis=-1)
  ssim = jnp.mean(ssim_loss(pred, target), axis=-1)
  return SSIM_WEIGHT * ssim + (1 - SSIM_WEIGHT) * l1


def smooth_loss(disp: Array, image: Array) -> Array:
  """`layers.get_smooth_loss`: edge-aware first-order smoothness, a scalar.

  disp: (B, H, W), the caller's (mean-normalised) disparity; image: (B, H, W, C) of the same
  size. mean(|d_x disp| exp(-mean_c |d_x I|)) + the same along y.
  """
  gd_x = absolute(disp[:, :, :-1] - disp[:, :, 1:])
  gd_y = absolute(disp[:, :-1, :] - disp[:, 1:, :])
  gi_x = jnp.mean(absolute(image[:, :, :-1] - image[:, :, 1:]), axis=-1)
  gi_y = jnp.mean(absolute(image[:, :-1, :] - image[:, 1:, :]), axis=-1)
  return jnp.mean(gd_x * jnp.exp(-gi_x)) + jnp.mean(gd_y * jnp.exp(-gi_y))


# ----------------------------------------------------------------------------- geometry


def backproject(depth: Array, inv_K: Array) -> Array:
  """`layers.BackprojectDepth`: depth (B, H, W), inv_K (B, 4, 4) -> (B, 4, H*W) points.

  Pixel (row r, column c) is the homogeneous (x = c, y = r, 1), flattened row-major; the
  camera point is depth * inv_K[:3, :3] @ pixel, with a fourth coordinate 1.
  """
  b, h, w = depth.shape
  ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
  pix = np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)], 0).astype(depth.dtype)  # (3, HW)
  cam = jnp.matmul(inv_K[:, :3, :3], jnp.asarray(pix), precision=jax.lax.Precision.HIGHEST)
  cam = depth.reshape(b, 1, h * w) * cam
  return jnp.concatenate([cam, jnp.ones((b, 1, h * w), depth.dtype)], axis=1)


def project(points: Array, K: Array, T: Array, height: int, width: int) -> Array:
  """`layers.Project3D`: (B, 4, H*W) points -> (B, H, W, 2) grid_sample coordinates.

  K, T: (B, 4, 4); height, width: the image size the points were backprojected from (upstream
  fixes it in the module's constructor).

  P = (K @ T)[:3]; pixel = P X / (z + 1e-7); normalised to [-1, 1] by (W - 1), (H - 1)
  (align_corners=True), x (column) first.
  """
  hp = jax.lax.Precision.HIGHEST
  P = jnp.matmul(K, T, precision=hp)[:, :3, :]
  cam = jnp.matmul(P, points, precision=hp)                       # (B, 3, HW)
  pix = cam[:, :2, :] / (cam[:, 2:3, :] + PROJECT_EPS)
  pix = jnp.transpose(pix.reshape(points.shape[0], 2, height, width), (0, 2, 3, 1))
  pix = pix / jnp.asarray([width - 1, height - 1], pix.dtype)
  return (pix - 0.5) * 2


def _border_clip(x: Array, size: int) -> Array:
  """Clip to [0, size - 1]; the gradient passes only strictly inside, as torch's sampler."""
  inside = (x > 0) & (x < size - 1)
  return jnp.where(inside, x, jax.lax.stop_gradient(jnp.clip(x, 0, size - 1)))


def _unnormalize(x: Array, size: int, align_corners: bool) -> Array:
  """grid_sample's [-1, 1] -> pixel index, written as torch's CPU sampler computes it."""
  if align_corners:  # -1 and 1 are the centres of the first and last pixels
    return (x + 1) * ((size - 1) / 2)
  return x * (size / 2) + (size / 2 - 0.5)  # -1 and 1 are the outer edges of those pixels


def warp(image: Array, coords: Array, align_corners: bool = True) -> Array:
  """Bilinear sampling, `F.grid_sample(image, coords, padding_mode="border", align_corners=...)`.

  image: (B, H, W, C); coords: (B, Ho, Wo, 2), x = column first, in [-1, 1] (align_corners:
  -1 and 1 are the centres of the first and last pixels, else their outer edges); beyond the
  first and last pixel centres the border value. Returns (B, Ho, Wo, C).
  Written with gathers so that both gradients (image: scatter-add of the bilinear weights;
  coords: through the weights, floor held constant) are torch's.
  """
  b, h, w, c = image.shape
  ix = _border_clip(_unnormalize(coords[..., 0], w, align_corners), w)
  iy = _border_clip(_unnormalize(coords[..., 1], h, align_corners), h)
  x0 = jax.lax.stop_gradient(jnp.floor(ix))
  y0 = jax.lax.stop_gradient(jnp.floor(iy))
  x1, y1 = x0 + 1, y0 + 1
  flat = image.reshape(b, h * w, c)

  def corner(xc, yc, weight):
    valid = (xc >= 0) & (xc <= w - 1) & (yc >= 0) & (yc <= h - 1)
    idx = (jnp.clip(yc, 0, h - 1) * w + jnp.clip(xc, 0, w - 1)).astype(jnp.int32)
    vals = jnp.take_along_axis(flat, idx.reshape(b, -1, 1), axis=1).reshape(*idx.shape, c)
    return jnp.where(valid[..., None], weight[..., None] * vals, 0.0)

  return (corner(x0, y0, (x1 - ix) * (y1 - iy)) + corner(x1, y0, (ix - x0) * (y1 - iy))
          + corner(x0, y1, (x1 - ix) * (iy - y0)) + corner(x1, y1, (ix - x0) * (iy - y0)))


# ----------------------------------------------------------------------------- the loss


class SfmAux(NamedTuple):
  """Per-scale by-products of `monodepth2_loss` (index i is cfg.scales[i])."""
  per_scale: Array         # (S,) loss of each scale (photometric + weighted smoothness)
  reprojection: Array      # (S, B, H, W) the per-pixel minimum reprojection, before weights
  identity_selection: Array  # (S, B, H, W) 1 where a warped source won (upstream's name)


def _downscale(image: Array, factor: int) -> Array:
  """Mean over factor x factor blocks (`F.avg_pool2d(x, factor)`), (B, H, W, C)."""
  if factor == 1:
    return image
  b, h, w, c = image.shape
  return image.reshape(b, h // factor, factor, w // factor, factor, c).mean(axis=(2, 4))


def _first_min(x: Array) -> tuple[Array, Array]:
  """Minimum over axis 2 and its first index, the gradient to that index (`torch.min(dim=1)`
  on each scale's (B, candidates, H, W))."""
  idx = jnp.argmin(x, axis=2)
  return jnp.take_along_axis(x, idx[:, :, None], axis=2)[:, :, 0], idx


def monodepth2_loss(target: Array, sources: Array, disps: Sequence[Array], K: Array,
                    inv_K: Array, poses: Array, *, cfg: SfmLossConfig,
                    rng: Array | None = None, noise: Array | None = None,
                    pixel_weights: Array | None = None,
                    scaled_targets: Sequence[Array] | None = None) -> tuple[Array, SfmAux]:
  """MonoDepth2's training loss (`trainer.generate_images_pred` + `compute_losses`).

  target: (B, H, W, 3) frame 0; sources: (B, N, H, W, 3) the N source frames (upstream's
  frame_ids[1:], in order); disps: one (B, H / 2**s, W / 2**s) sigmoid disparity per s in
  cfg.scales; K, inv_K: (B, 4, 4) full-resolution intrinsics; poses: (B, N, 4, 4) target ->
  source camera motions.
  Per scale s: the disparity is upsampled bilinearly (align_corners=False) to (H, W), turned into
  depth by `disp_to_depth(min_depth, max_depth)`, each source is warped into the target view, and
  the per-pixel reprojection loss is the minimum over sources and (with cfg.automask) over the
  unwarped sources' identity losses plus 1e-5 * noise (the tie-break); the photometric term is
  mean(min * pixel_weights). The smoothness term is
  cfg.smoothness / 2**s * smooth_loss(disp_s / mean(disp_s), target at scale s). The loss is the
  mean of the per-scale sums.
  rng / noise: the tie-break's standard-normal draw, (S, B, N, H, W); `noise` if given, else
  drawn from `rng` (required with cfg.automask). pixel_weights: (B, H, W) multiplies the minimum
  reprojection map before its mean, e.g. CoMoDa's mask of moving objects; None = 1.
  scaled_targets: the target at each scale (upstream's ("color", 0, s), resized by its data
  loader); None = `_downscale` (block means; H and W must be divisible by 2**max(scales)).
  Returns (loss (), SfmAux).
  """
  b, h, w, _ = target.shape
  n = sources.shape[1]
  n_scales = len(cfg.scales)
  check(len(disps) == n_scales, f"need one disparity per scale {cfg.scales}, got {len(disps)}")
  if scaled_targets is None:
    block = 2 ** max(cfg.scales)
    check(h % block == 0 and w % block == 0,
          f"the target's {w}x{h} must be divisible by 2**{max(cfg.scales)} = {block} for its "
          f"block means at every scale (or give scaled_targets)")
  if cfg.automask and noise is None:
    check(rng is not None, "monodepth2_loss with automask needs rng or noise")
    noise = jax.random.normal(prng.unrolled(rng), (n_scales, b, n, h, w), target.dtype)

  # All scales and sources go through one batched backprojection, warp and reprojection loss
  # (the same arithmetic as upstream's loops, a fraction of the program to compile).
  full = []
  for s, disp in zip(cfg.scales, disps):
    check(disp.shape == (b, h // 2 ** s, w // 2 ** s),
          f"disparity at scale {s} must be {(b, h // 2 ** s, w // 2 ** s)}, got {disp.shape}")
    full.append(resize_bilinear(disp[..., None], (h, w), align_corners=False)[..., 0])
  depth = disp_to_depth(jnp.concatenate(full), cfg.min_depth, cfg.max_depth)  # (S*B, H, W)
  points = backproject(depth, jnp.tile(inv_K, (n_scales, 1, 1)))
  coords = jnp.stack([project(points, jnp.tile(K, (n_scales, 1, 1)),
                              jnp.tile(poses[:, i], (n_scales, 1, 1)), h, w)
                      for i in range(n)], axis=1)                     # (S*B, N, H, W, 2)
  src = jnp.tile(sources, (n_scales, 1, 1, 1, 1))                     # (S*B, N, H, W, 3)
  warped = warp(src.reshape(-1, h, w, 3), coords.reshape(-1, h, w, 2), cfg.align_corners)
  preds = jnp.concatenate([sources.reshape(-1, h, w, 3), warped]) if cfg.automask else warped
  reps = reprojection_loss(preds, jnp.repeat(jnp.tile(target, (preds.shape[0] // (b * n), 1, 1, 1)),
                                             n, axis=0))
  reps = reps.reshape(-1, b, n, h, w)                 # ([identity,] scale 0, ..., B, N, H, W)
  combined = reps[-n_scales:]                                           # (S, B, N, H, W)
  if cfg.automask:
    combined = jnp.concatenate([reps[0] + noise * TIE_NOISE, combined], axis=2)
  best, idx = _first_min(combined)                                      # (S, B, H, W)
  selections = (idx > (n - 1 if cfg.automask else -1)).astype(target.dtype)
  weighted = best if pixel_weights is None else best * pixel_weights
  photometric = jnp.mean(weighted, axis=(1, 2, 3))                      # (S,)

  per_scale = []
  for k, (s, disp) in enumerate(zip(cfg.scales, disps)):
    norm_disp = disp / (jnp.mean(disp, axis=(1, 2), keepdims=True) + MEAN_DISP_EPS)
    color = _downscale(target, 2 ** s) if scaled_targets is None else scaled_targets[k]
    per_scale.append(photometric[k] + cfg.smoothness * smooth_loss(norm_disp, color) / (2 ** s))
  per_scale = jnp.stack(per_scale)
  aux = SfmAux(per_scale, jax.lax.stop_gradient(best), selections)
  return jnp.mean(per_scale), aux


__all__ = ["SfmLossConfig", "SfmAux", "check_scales", "ssim_loss", "reprojection_loss", "smooth_loss",
           "backproject", "project", "warp", "monodepth2_loss", "transformation_from_parameters",
           "disp_to_depth"]
