"""An independent PyTorch Depth Anything V2 as upstream builds it, the reference for the
`official` checkpoint format (transformers' `DepthAnythingForDepthEstimation` is the reference
for the `hf` format).

Written from DepthAnything/Depth-Anything-V2 (`depth_anything_v2/dpt.py`, `dinov2.py`,
`dinov2_layers/*`, `util/blocks.py`) with exactly its state_dict names: `pretrained.*`
(DinoVisionTransformer: `patch_embed.proj`, `cls_token`, `pos_embed`, `mask_token`,
`blocks.i.{norm1, attn.qkv, attn.proj, ls1.gamma, norm2, mlp.fc1, mlp.fc2, ls2.gamma}`, `norm`)
and `depth_head.*` (`projects.i`, `resize_layers.{0,1,3}`, `scratch.layer{i}_rn`,
`scratch.refinenet{i}.{resConfUnit1, resConfUnit2}.conv{1,2}`, `.out_conv`,
`scratch.output_conv1`, `scratch.output_conv2.{0,2}`). transformers has no module with
upstream's position-embedding resize (`scale_factor` with the 0.1 offset), hence this file.
Sizes are parameters so that the tests can shrink the ViT; the defaults are ViT-S.

`randomize_` draws O(1)-activation weights; `hf_state_from_official` renames (and splits qkv
of) them into transformers' names: the tests draw one set of weights and write both formats.
"""

from __future__ import annotations

import math
import re

import torch
import torch.nn as nn
import torch.nn.functional as F


class PatchEmbed(nn.Module):
  def __init__(self, patch, dim):
    super().__init__()
    self.proj = nn.Conv2d(3, dim, kernel_size=patch, stride=patch)

  def forward(self, x):
    return self.proj(x).flatten(2).transpose(1, 2)  # (B, N, C)


class Attention(nn.Module):
  def __init__(self, dim, heads):
    super().__init__()
    self.heads = heads
    self.scale = (dim // heads) ** -0.5
    self.qkv = nn.Linear(dim, 3 * dim)
    self.proj = nn.Linear(dim, dim)

  def forward(self, x):
    b, n, c = x.shape
    qkv = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
    q, k, v = qkv[0] * self.scale, qkv[1], qkv[2]
    attn = (q @ k.transpose(-2, -1)).softmax(dim=-1)
    return self.proj((attn @ v).transpose(1, 2).reshape(b, n, c))


class Mlp(nn.Module):
  def __init__(self, dim, hidden):
    super().__init__()
    self.fc1 = nn.Linear(dim, hidden)
    self.act = nn.GELU()
    self.fc2 = nn.Linear(hidden, dim)

  def forward(self, x):
    return self.fc2(self.act(self.fc1(x)))


class LayerScale(nn.Module):
  def __init__(self, dim, init_values=1.0):
    super().__init__()
    self.gamma = nn.Parameter(init_values * torch.ones(dim))

  def forward(self, x):
    return x * self.gamma


class Block(nn.Module):
  def __init__(self, dim, heads, mlp_ratio):
    super().__init__()
    self.norm1 = nn.LayerNorm(dim, eps=1e-6)
    self.attn = Attention(dim, heads)
    self.ls1 = LayerScale(dim)
    self.norm2 = nn.LayerNorm(dim, eps=1e-6)
    self.mlp = Mlp(dim, int(dim * mlp_ratio))
    self.ls2 = LayerScale(dim)

  def forward(self, x):
    x = x + self.ls1(self.attn(self.norm1(x)))
    return x + self.ls2(self.mlp(self.norm2(x)))


class DinoVisionTransformer(nn.Module):
  def __init__(self, img_size=518, patch_size=14, embed_dim=384, depth=12, num_heads=6,
               mlp_ratio=4.0, interpolate_offset=0.1):
    super().__init__()
    self.patch_size = patch_size
    self.interpolate_offset = interpolate_offset
    self.patch_embed = PatchEmbed(patch_size, embed_dim)
    n = (img_size // patch_size) ** 2
    self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
    self.pos_embed = nn.Parameter(torch.zeros(1, n + 1, embed_dim))
    self.blocks = nn.ModuleList([Block(embed_dim, num_heads, mlp_ratio) for _ in range(depth)])
    self.norm = nn.LayerNorm(embed_dim, eps=1e-6)
    self.head = nn.Identity()
    self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))

  def interpolate_pos_encoding(self, x, w, h):
    # as upstream: `w` is the image height (dim 2), `h` the width
    npatch, n = x.shape[1] - 1, self.pos_embed.shape[1] - 1
    if npatch == n and w == h:
      return self.pos_embed
    pos = self.pos_embed.float()
    cls_pos, patch_pos = pos[:, 0], pos[:, 1:]
    dim = x.shape[-1]
    w0 = w // self.patch_size + self.interpolate_offset
    h0 = h // self.patch_size + self.interpolate_offset
    sqrt_n = math.sqrt(n)
    patch_pos = F.interpolate(
        patch_pos.reshape(1, int(sqrt_n), int(sqrt_n), dim).permute(0, 3, 1, 2),
        scale_factor=(float(w0) / sqrt_n, float(h0) / sqrt_n), mode="bicubic", antialias=False)
    assert int(w0) == patch_pos.shape[-2] and int(h0) == patch_pos.shape[-1]
    patch_pos = patch_pos.permute(0, 2, 3, 1).view(1, -1, dim)
    return torch.cat((cls_pos.unsqueeze(0), patch_pos), dim=1).to(x.dtype)

  def get_intermediate_layers(self, x, n):
    _, _, w, h = x.shape
    x = self.patch_embed(x)
    x = torch.cat((self.cls_token.expand(x.shape[0], -1, -1), x), dim=1)
    x = x + self.interpolate_pos_encoding(x, w, h)
    outputs = []
    for i, blk in enumerate(self.blocks):
      x = blk(x)
      if i in n:
        outputs.append(x)
    outputs = [self.norm(o) for o in outputs]
    return tuple((o[:, 1:], o[:, 0]) for o in outputs)


class ResidualConvUnit(nn.Module):
  def __init__(self, features):
    super().__init__()
    self.conv1 = nn.Conv2d(features, features, 3, 1, 1, bias=True)
    self.conv2 = nn.Conv2d(features, features, 3, 1, 1, bias=True)
    self.activation = nn.ReLU(False)

  def forward(self, x):
    out = self.conv2(self.activation(self.conv1(self.activation(x))))
    return out + x


class FeatureFusionBlock(nn.Module):
  def __init__(self, features):
    super().__init__()
    self.out_conv = nn.Conv2d(features, features, 1, 1, 0, bias=True)
    self.resConfUnit1 = ResidualConvUnit(features)
    self.resConfUnit2 = ResidualConvUnit(features)

  def forward(self, *xs, size=None):
    output = xs[0]
    if len(xs) == 2:
      output = output + self.resConfUnit1(xs[1])
    output = self.resConfUnit2(output)
    modifier = {"scale_factor": 2} if size is None else {"size": size}
    output = F.interpolate(output, **modifier, mode="bilinear", align_corners=True)
    return self.out_conv(output)


class DPTHead(nn.Module):
  def __init__(self, in_channels, features, out_channels, head_features=32, metric=False):
    super().__init__()
    self.projects = nn.ModuleList([nn.Conv2d(in_channels, c, 1, 1, 0) for c in out_channels])
    self.resize_layers = nn.ModuleList([
        nn.ConvTranspose2d(out_channels[0], out_channels[0], 4, 4, 0),
        nn.ConvTranspose2d(out_channels[1], out_channels[1], 2, 2, 0),
        nn.Identity(),
        nn.Conv2d(out_channels[3], out_channels[3], 3, 2, 1)])
    self.scratch = nn.Module()
    for i, c in enumerate(out_channels):
      setattr(self.scratch, f"layer{i + 1}_rn", nn.Conv2d(c, features, 3, 1, 1, bias=False))
    self.scratch.stem_transpose = None
    for i in range(1, 5):
      setattr(self.scratch, f"refinenet{i}", FeatureFusionBlock(features))
    self.scratch.output_conv1 = nn.Conv2d(features, features // 2, 3, 1, 1)
    last = [nn.Sigmoid()] if metric else [nn.ReLU(True), nn.Identity()]  # metric_depth/dpt.py
    self.scratch.output_conv2 = nn.Sequential(
        nn.Conv2d(features // 2, head_features, 3, 1, 1), nn.ReLU(True),
        nn.Conv2d(head_features, 1, 1, 1, 0), *last)

  def forward(self, out_features, patch_h, patch_w):
    out = []
    for i, (x, _) in enumerate(out_features):
      x = x.permute(0, 2, 1).reshape(x.shape[0], x.shape[-1], patch_h, patch_w)
      out.append(self.resize_layers[i](self.projects[i](x)))
    s = self.scratch
    l1, l2 = s.layer1_rn(out[0]), s.layer2_rn(out[1])
    l3, l4 = s.layer3_rn(out[2]), s.layer4_rn(out[3])
    path = s.refinenet4(l4, size=l3.shape[2:])
    path = s.refinenet3(path, l3, size=l2.shape[2:])
    path = s.refinenet2(path, l2, size=l1.shape[2:])
    path = s.refinenet1(path, l1)
    out = s.output_conv1(path)
    out = F.interpolate(out, (int(patch_h * 14), int(patch_w * 14)), mode="bilinear",
                        align_corners=True)
    return s.output_conv2(out)


class DepthAnythingV2(nn.Module):
  """Upstream `DepthAnythingV2(encoder, features, out_channels)` with the ViT size as arguments;
  with `max_depth`, upstream's metric model (`metric_depth/depth_anything_v2/dpt.py`)."""

  def __init__(self, embed_dim=384, depth=12, num_heads=6, layer_idx=(2, 5, 8, 11), features=64,
               out_channels=(48, 96, 192, 384), head_features=32, img_size=518, max_depth=None):
    super().__init__()
    self.layer_idx = list(layer_idx)
    self.max_depth = max_depth
    self.pretrained = DinoVisionTransformer(img_size, 14, embed_dim, depth, num_heads)
    self.depth_head = DPTHead(embed_dim, features, list(out_channels), head_features,
                              metric=max_depth is not None)

  def forward(self, x):
    """x: (B, 3, H, W) ImageNet-normalised -> (B, H, W) relative inverse depth (metric: depth
    in metres)."""
    patch_h, patch_w = x.shape[-2] // 14, x.shape[-1] // 14
    features = self.pretrained.get_intermediate_layers(x, self.layer_idx)
    if self.max_depth is not None:
      return (self.depth_head(features, patch_h, patch_w) * self.max_depth).squeeze(1)
    return F.relu(self.depth_head(features, patch_h, patch_w)).squeeze(1)


def randomize_(model: DepthAnythingV2, seed: int) -> DepthAnythingV2:
  """Random weights whose activations stay O(1): kernels ~ N(0, 1 / fan_in), LayerNorm gamma
  ~ 1 + 0.2 N, LayerScale ~ U[0.5, 1.5], tokens and position embeddings ~ 0.5 N, biases and
  beta ~ 0.1 N; the last bias is shifted by +1 so that most outputs pass the final ReLU."""
  g = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for name, p in model.named_parameters():
      n = torch.randn(p.shape, generator=g)
      if re.search(r"norm\d?\.weight$", name):
        p.copy_(1 + 0.2 * n)
      elif re.search(r"\.ls\d\.gamma$", name):
        p.copy_(0.5 + torch.rand(p.shape, generator=g))
      elif name.endswith(("pos_embed", "cls_token", "mask_token")):
        p.copy_(0.5 * n)
      elif re.search(r"resize_layers\.[01]\.weight$", name):  # ConvTranspose2d (in, out, k, k)
        p.copy_(n / p.shape[0] ** 0.5)
      elif p.ndim >= 2:
        p.copy_(n / math.prod(p.shape[1:]) ** 0.5)
      else:
        p.copy_(0.1 * n)
    model.depth_head.scratch.output_conv2[2].bias.add_(1.0)
  return model.eval()


def hf_state_from_official(state: dict, depth: int) -> dict:
  """Upstream state dict -> transformers `DepthAnythingForDepthEstimation` names as transformers
  >= 5 holds them (attention.q_proj/k_proj/v_proj/o_proj; qkv split by rows in q, k, v order)."""
  out = {"backbone.embeddings.cls_token": state["pretrained.cls_token"],
         "backbone.embeddings.mask_token": state["pretrained.mask_token"],
         "backbone.embeddings.position_embeddings": state["pretrained.pos_embed"]}
  pairs = [("backbone.embeddings.patch_embeddings.projection", "pretrained.patch_embed.proj"),
           ("backbone.layernorm", "pretrained.norm"),
           ("head.conv1", "depth_head.scratch.output_conv1"),
           ("head.conv2", "depth_head.scratch.output_conv2.0"),
           ("head.conv3", "depth_head.scratch.output_conv2.2")]
  for i in range(depth):
    s, t = f"pretrained.blocks.{i}", f"backbone.encoder.layer.{i}"
    pairs += [(f"{t}.attention.o_proj", f"{s}.attn.proj")]
    pairs += [(f"{t}.{n}", f"{s}.{n}") for n in ("norm1", "norm2", "mlp.fc1", "mlp.fc2")]
    for p in ("weight", "bias"):
      for n, part in zip("qkv", state[f"{s}.attn.qkv.{p}"].chunk(3)):
        out[f"{t}.attention.{n}_proj.{p}"] = part
    for u in (1, 2):
      out[f"{t}.layer_scale{u}.lambda1"] = state[f"{s}.ls{u}.gamma"]
  for i in range(4):
    r = f"neck.reassemble_stage.layers.{i}"
    pairs += [(f"{r}.projection", f"depth_head.projects.{i}")]
    if i != 2:
      pairs += [(f"{r}.resize", f"depth_head.resize_layers.{i}")]
    out[f"neck.convs.{i}.weight"] = state[f"depth_head.scratch.layer{i + 1}_rn.weight"]
    s, t = f"depth_head.scratch.refinenet{i + 1}", f"neck.fusion_stage.layers.{3 - i}"
    pairs += [(f"{t}.projection", f"{s}.out_conv")]
    pairs += [(f"{t}.residual_layer{u}.convolution{c}", f"{s}.resConfUnit{u}.conv{c}")
              for u in (1, 2) for c in (1, 2)]
  for hf_name, name in pairs:
    for p in ("weight", "bias"):
      out[f"{hf_name}.{p}"] = state[f"{name}.{p}"]
  return {k: v.contiguous() for k, v in out.items()}
