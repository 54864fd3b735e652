"""An independent PyTorch MonoDepth2 loss, the reference for tests/test_sfm.py.

Written from MonoDepth2's `layers.py` (`SSIM`, `BackprojectDepth`, `Project3D`,
`get_smooth_loss`, `transformation_from_parameters`) and `trainer.py` (`generate_images_pred`,
`compute_reprojection_loss`, `compute_losses`) the way upstream writes them: NCHW tensors,
`nn.ReflectionPad2d` + `nn.AvgPool2d`, `F.interpolate`, `F.grid_sample(padding_mode="border")`
(upstream passes no align_corners: PyTorch's default since 1.3, False, is what CoMoDa's and
Ada-Depth's adaptation code ran with; `align_corners=True` gives MonoDepth2's pre-1.3 training),
`torch.min(dim=1)`. Upstream's
defaults: not v1_multiscale, not avg_reprojection, auto-masking on, SSIM on. The only change:
the tie-break noise (torch.randn upstream) is passed in so both sides use the same draw, and the
scale-s colour image (a data-loader resize upstream) is `F.avg_pool2d(target, 2**s)`.
For the tests' float32 comparisons a call also keeps (detached, not part of the loss) the sampling
coordinates and the |target - warped| residuals: where float32 rounding decides a kink of the
loss (a floor or border of the sampler, the sign of an L1 residual), the float64 values locate it.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


class SSIM(nn.Module):
  def __init__(self):
    super().__init__()
    self.mu_x_pool = nn.AvgPool2d(3, 1)
    self.mu_y_pool = nn.AvgPool2d(3, 1)
    self.sig_x_pool = nn.AvgPool2d(3, 1)
    self.sig_y_pool = nn.AvgPool2d(3, 1)
    self.sig_xy_pool = nn.AvgPool2d(3, 1)
    self.refl = nn.ReflectionPad2d(1)
    self.C1 = 0.01 ** 2
    self.C2 = 0.03 ** 2

  def forward(self, x, y):
    x = self.refl(x)
    y = self.refl(y)
    mu_x = self.mu_x_pool(x)
    mu_y = self.mu_y_pool(y)
    sigma_x = self.sig_x_pool(x ** 2) - mu_x ** 2
    sigma_y = self.sig_y_pool(y ** 2) - mu_y ** 2
    sigma_xy = self.sig_xy_pool(x * y) - mu_x * mu_y
    ssim_n = (2 * mu_x * mu_y + self.C1) * (2 * sigma_xy + self.C2)
    ssim_d = (mu_x ** 2 + mu_y ** 2 + self.C1) * (sigma_x + sigma_y + self.C2)
    return torch.clamp((1 - ssim_n / ssim_d) / 2, 0, 1)


class BackprojectDepth(nn.Module):
  def __init__(self, batch_size, height, width, dtype=torch.float32):
    super().__init__()
    self.batch_size, self.height, self.width = batch_size, height, width
    meshgrid = np.meshgrid(range(width), range(height), indexing="xy")
    id_coords = torch.from_numpy(np.stack(meshgrid, axis=0).astype(np.float64)).to(dtype)
    self.ones = torch.ones(batch_size, 1, height * width, dtype=dtype)
    pix = torch.stack([id_coords[0].view(-1), id_coords[1].view(-1)], 0).unsqueeze(0)
    self.pix_coords = torch.cat([pix.repeat(batch_size, 1, 1), self.ones], 1)

  def forward(self, depth, inv_K):
    cam_points = torch.matmul(inv_K[:, :3, :3], self.pix_coords)
    cam_points = depth.view(self.batch_size, 1, -1) * cam_points
    return torch.cat([cam_points, self.ones], 1)


class Project3D(nn.Module):
  def __init__(self, batch_size, height, width, eps=1e-7):
    super().__init__()
    self.batch_size, self.height, self.width, self.eps = batch_size, height, width, eps

  def forward(self, points, K, T):
    P = torch.matmul(K, T)[:, :3, :]
    cam_points = torch.matmul(P, points)
    pix_coords = cam_points[:, :2, :] / (cam_points[:, 2, :].unsqueeze(1) + self.eps)
    pix_coords = pix_coords.view(self.batch_size, 2, self.height, self.width)
    pix_coords = pix_coords.permute(0, 2, 3, 1)
    pix_coords = pix_coords.clone()
    pix_coords[..., 0] /= self.width - 1
    pix_coords[..., 1] /= self.height - 1
    return (pix_coords - 0.5) * 2


def get_smooth_loss(disp, img):
  """disp (B, 1, H, W), img (B, 3, H, W)."""
  grad_disp_x = torch.abs(disp[:, :, :, :-1] - disp[:, :, :, 1:])
  grad_disp_y = torch.abs(disp[:, :, :-1, :] - disp[:, :, 1:, :])
  grad_img_x = torch.mean(torch.abs(img[:, :, :, :-1] - img[:, :, :, 1:]), 1, keepdim=True)
  grad_img_y = torch.mean(torch.abs(img[:, :, :-1, :] - img[:, :, 1:, :]), 1, keepdim=True)
  grad_disp_x = grad_disp_x * torch.exp(-grad_img_x)
  grad_disp_y = grad_disp_y * torch.exp(-grad_img_y)
  return grad_disp_x.mean() + grad_disp_y.mean()


def rot_from_axisangle(vec):
  angle = torch.norm(vec, 2, 2, True)
  axis = vec / (angle + 1e-7)
  ca, sa = torch.cos(angle), torch.sin(angle)
  C = 1 - ca
  x, y, z = axis[..., 0].unsqueeze(1), axis[..., 1].unsqueeze(1), axis[..., 2].unsqueeze(1)
  xs, ys, zs = x * sa, y * sa, z * sa
  xC, yC, zC = x * C, y * C, z * C
  xyC, yzC, zxC = x * yC, y * zC, z * xC
  rot = torch.zeros((vec.shape[0], 4, 4), dtype=vec.dtype)
  rot[:, 0, 0] = torch.squeeze(x * xC + ca)
  rot[:, 0, 1] = torch.squeeze(xyC - zs)
  rot[:, 0, 2] = torch.squeeze(zxC + ys)
  rot[:, 1, 0] = torch.squeeze(xyC + zs)
  rot[:, 1, 1] = torch.squeeze(y * yC + ca)
  rot[:, 1, 2] = torch.squeeze(yzC - xs)
  rot[:, 2, 0] = torch.squeeze(zxC - ys)
  rot[:, 2, 1] = torch.squeeze(yzC + xs)
  rot[:, 2, 2] = torch.squeeze(z * zC + ca)
  rot[:, 3, 3] = 1
  return rot


def get_translation_matrix(translation_vector):
  T = torch.zeros(translation_vector.shape[0], 4, 4, dtype=translation_vector.dtype)
  t = translation_vector.contiguous().view(-1, 3, 1)
  T[:, 0, 0] = 1
  T[:, 1, 1] = 1
  T[:, 2, 2] = 1
  T[:, 3, 3] = 1
  T[:, :3, 3, None] = t
  return T


def transformation_from_parameters(axisangle, translation, invert=False):
  R = rot_from_axisangle(axisangle)
  t = translation.clone()
  if invert:
    R = R.transpose(1, 2)
    t = t * -1
  T = get_translation_matrix(t)
  return torch.matmul(R, T) if invert else torch.matmul(T, R)


def disp_to_depth(disp, min_depth, max_depth):
  min_disp, max_disp = 1 / max_depth, 1 / min_depth
  scaled_disp = min_disp + (max_disp - min_disp) * disp
  return scaled_disp, 1 / scaled_disp


class Monodepth2Loss:
  """`generate_images_pred` + `compute_losses` for frame_ids [0, 1..N], one batch of size B."""

  def __init__(self, batch_size, height, width, scales=(0, 1, 2, 3), min_depth=0.1,
               max_depth=100.0, disparity_smoothness=1e-3, disable_automasking=False,
               dtype=torch.float32, align_corners=None):
    self.scales, self.height, self.width = scales, height, width
    self.disable_automasking = disable_automasking
    # None: upstream's call, no align_corners argument (PyTorch's default)
    self.grid_kwargs = {} if align_corners is None else {"align_corners": align_corners}
    self.align_corners = bool(align_corners)
    self.min_depth, self.max_depth = min_depth, max_depth
    self.disparity_smoothness = disparity_smoothness
    self.ssim = SSIM()
    self.backproject_depth = BackprojectDepth(batch_size, height, width, dtype)
    self.project_3d = Project3D(batch_size, height, width)

  def compute_reprojection_loss(self, pred, target):
    abs_diff = torch.abs(target - pred)
    l1_loss = abs_diff.mean(1, True)
    ssim_loss = self.ssim(pred, target).mean(1, True)
    return 0.85 * ssim_loss + 0.15 * l1_loss

  def __call__(self, target, sources, disps, K, inv_K, poses, noise, pixel_weights=None,
               colors=None):
    """target (B, 3, H, W); sources: list of (B, 3, H, W); disps: list of (B, 1, h_s, w_s);
    poses: list of (B, 4, 4); noise: (S, B, N, H, W) standard normal (unused when
    disable_automasking).
    colors: the target at each scale (default F.avg_pool2d).
    Returns (loss, per-scale losses (S,), identity selection (S, B, H, W) or None, the candidates
    of the per-pixel minimum (S, B, 2N or N, H, W)). Kept on the object: `pixel_coords`
    (S, N, B, H, W, 2), the sampled (x, y) in source pixels, and `residuals` (S, N, B, 3, H, W),
    target minus each warped source."""
    total_loss, per_scale, selections, candidates = 0, [], [], []
    coords, residuals = [], []
    for k, scale in enumerate(self.scales):
      disp = F.interpolate(disps[k], [self.height, self.width], mode="bilinear",
                           align_corners=False)
      _, depth = disp_to_depth(disp, self.min_depth, self.max_depth)
      preds = []
      for i, source in enumerate(sources):
        cam_points = self.backproject_depth(depth, inv_K)
        pix_coords = self.project_3d(cam_points, K, poses[i])
        with warnings.catch_warnings():  # PyTorch's notice that the default is False
          warnings.filterwarnings("ignore", "Default grid_sample", UserWarning)
          preds.append(F.grid_sample(source, pix_coords, padding_mode="border",
                                     **self.grid_kwargs))
        size = pix_coords.new_tensor([self.width, self.height])
        coords.append((pix_coords.detach() + 1) / 2 * (size - 1) if self.align_corners else
                      ((pix_coords.detach() + 1) * size - 1) / 2)
        residuals.append((target - preds[-1]).detach())
      loss = 0
      reprojection_losses = torch.cat(
          [self.compute_reprojection_loss(p, target) for p in preds], 1)
      if not self.disable_automasking:
        identity_reprojection_loss = torch.cat(
            [self.compute_reprojection_loss(s, target) for s in sources], 1)
        identity_reprojection_loss = identity_reprojection_loss + noise[k] * 0.00001
        combined = torch.cat((identity_reprojection_loss, reprojection_losses), dim=1)
      else:
        combined = reprojection_losses
      candidates.append(combined.detach())
      if combined.shape[1] == 1:
        to_optimise, idxs = combined[:, 0], None
      else:
        to_optimise, idxs = torch.min(combined, dim=1)
      if not self.disable_automasking:
        selections.append((idxs > identity_reprojection_loss.shape[1] - 1).float())
      if pixel_weights is not None:
        to_optimise = to_optimise * pixel_weights
      loss += to_optimise.mean()
      disp_s = disps[k]
      if colors is not None:       # upstream's inputs[("color", 0, scale)]
        color = colors[k]
      else:
        color = F.avg_pool2d(target, 2 ** scale) if scale > 0 else target
      mean_disp = disp_s.mean(2, True).mean(3, True)
      norm_disp = disp_s / (mean_disp + 1e-7)
      loss += self.disparity_smoothness * get_smooth_loss(norm_disp, color) / (2 ** scale)
      total_loss += loss
      per_scale.append(loss)
    selections = torch.stack(selections) if selections else None
    n = len(sources)
    self.pixel_coords = torch.stack(coords).reshape(len(self.scales), n, *coords[0].shape)
    self.residuals = torch.stack(residuals).reshape(len(self.scales), n, *residuals[0].shape)
    return (total_loss / len(self.scales), torch.stack(per_scale), selections,
            torch.stack(candidates))
