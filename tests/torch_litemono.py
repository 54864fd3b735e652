"""An independent PyTorch Lite-Mono, the reference for the converter parity tests.

Written from noahzn/Lite-Mono's `networks/depth_encoder.py` / `depth_decoder.py` / `layers.py`
with exactly upstream's state_dict key names: the encoder's `downsample_layers.0.{0,1,2}`
(`conv.weight`, `bn_gelu.bn.*`), `stem2.0.conv.weight`, `downsample_layers.{1,2}.0.conv.weight`,
`stages.i.j.*` (DilatedConv: `ddwconv.conv`, `bn1`, the unused `norm`, `pwconv1/2`, `gamma`;
LGFI: `pos_embd.token_projection` in stage 0, `norm_xca`, `gamma_xca`, `xca.{temperature,qkv,
proj}`, `norm`, `pwconv1/2`, `gamma`); the decoder's `decoder = nn.ModuleList(convs.values())`
(upconvs (2,0), (2,1), (1,0), (1,1), (0,0), (0,1) as `decoder.0..5.conv.conv.*`, dispconvs for
scales 0..2 as `decoder.6..8.conv.*`). timm is not installed here, and drop path is an identity
at inference, so the blocks have no DropPath (build with drop_path_rate=0 upstream to compare
train-mode BN). One deviation for the float64 gradient tests: the Fourier position map (computed
in float32, as upstream) is cast to the projection's dtype before the 1x1 conv.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

DIMS_DEPTHS = {"lite-mono": ([48, 80, 128], [4, 4, 10]),
               "lite-mono-small": ([48, 80, 128], [4, 4, 7]),
               "lite-mono-tiny": ([32, 64, 128], [4, 4, 7]),
               "lite-mono-8m": ([64, 128, 224], [4, 4, 10])}


def dilation_table(model, height, width):
  deep = model in ("lite-mono", "lite-mono-8m")
  if (height, width) == (192, 640) or model == "lite-mono-8m":
    last = [1, 2, 3, 1, 2, 3, 2, 4, 6] if deep else [1, 2, 3, 2, 4, 6]
    return [[1, 2, 3], [1, 2, 3], last]
  assert (height, width) == (320, 1024)
  last = [1, 2, 5, 1, 2, 5, 2, 4, 10] if deep else [1, 2, 5, 2, 4, 10]
  return [[1, 2, 5], [1, 2, 5], last]


class PositionalEncodingFourier(nn.Module):
  def __init__(self, hidden_dim=32, dim=768, temperature=10000):
    super().__init__()
    self.token_projection = nn.Conv2d(hidden_dim * 2, dim, kernel_size=1)
    self.hidden_dim, self.temperature = hidden_dim, temperature

  def forward(self, B, H, W):
    ones = torch.ones(B, H, W)
    y = ones.cumsum(1, dtype=torch.float32)
    x = ones.cumsum(2, dtype=torch.float32)
    y = y / (y[:, -1:, :] + 1e-6) * (2 * math.pi)
    x = x / (x[:, :, -1:] + 1e-6) * (2 * math.pi)
    k = torch.arange(self.hidden_dim, dtype=torch.float32)
    k = self.temperature ** (2 * (k // 2) / self.hidden_dim)
    px, py = x[..., None] / k, y[..., None] / k
    px = torch.stack((px[..., 0::2].sin(), px[..., 1::2].cos()), dim=4).flatten(3)
    py = torch.stack((py[..., 0::2].sin(), py[..., 1::2].cos()), dim=4).flatten(3)
    pos = torch.cat((py, px), dim=3).permute(0, 3, 1, 2)
    return self.token_projection(pos.to(self.token_projection.weight.dtype))


class XCA(nn.Module):
  def __init__(self, dim, num_heads=8, qkv_bias=False):
    super().__init__()
    self.num_heads = num_heads
    self.temperature = nn.Parameter(torch.ones(num_heads, 1, 1))
    self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
    self.proj = nn.Linear(dim, dim)

  def forward(self, x):
    B, N, C = x.shape
    qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, C // self.num_heads).permute(2, 0, 3, 1, 4)
    q, k, v = (t.transpose(-2, -1) for t in qkv)  # (B, heads, d, N)
    q, k = F.normalize(q, dim=-1), F.normalize(k, dim=-1)
    attn = ((q @ k.transpose(-2, -1)) * self.temperature).softmax(dim=-1)
    return self.proj((attn @ v).permute(0, 3, 1, 2).reshape(B, N, C))


class LayerNorm(nn.Module):
  """Upstream's LayerNorm (only its channels_last form is used by Lite-Mono)."""

  def __init__(self, n, eps=1e-6):
    super().__init__()
    self.weight = nn.Parameter(torch.ones(n))
    self.bias = nn.Parameter(torch.zeros(n))
    self.eps, self.shape = eps, (n,)

  def forward(self, x):
    return F.layer_norm(x, self.shape, self.weight, self.bias, self.eps)


class BNGELU(nn.Module):
  def __init__(self, n):
    super().__init__()
    self.bn = nn.BatchNorm2d(n, eps=1e-5)
    self.act = nn.GELU()

  def forward(self, x):
    return self.act(self.bn(x))


class Conv(nn.Module):
  def __init__(self, nIn, nOut, kSize, stride, padding=0, bn_act=False):
    super().__init__()
    self.bn_act = bn_act
    self.conv = nn.Conv2d(nIn, nOut, kSize, stride, padding, bias=False)
    if bn_act:
      self.bn_gelu = BNGELU(nOut)

  def forward(self, x):
    x = self.conv(x)
    return self.bn_gelu(x) if self.bn_act else x


class CDilated(nn.Module):
  def __init__(self, nIn, nOut, kSize, d=1, groups=1):
    super().__init__()
    self.conv = nn.Conv2d(nIn, nOut, kSize, padding=(kSize - 1) // 2 * d, bias=False,
                          dilation=d, groups=groups)

  def forward(self, x):
    return self.conv(x)


class DilatedConv(nn.Module):
  def __init__(self, dim, k, dilation=1, expan_ratio=6):
    super().__init__()
    self.ddwconv = CDilated(dim, dim, k, d=dilation, groups=dim)
    self.bn1 = nn.BatchNorm2d(dim)
    self.norm = LayerNorm(dim)  # registered upstream, never called
    self.pwconv1 = nn.Linear(dim, expan_ratio * dim)
    self.act = nn.GELU()
    self.pwconv2 = nn.Linear(expan_ratio * dim, dim)
    self.gamma = nn.Parameter(1e-6 * torch.ones(dim))

  def forward(self, x):
    y = self.bn1(self.ddwconv(x)).permute(0, 2, 3, 1)
    y = self.gamma * self.pwconv2(self.act(self.pwconv1(y)))
    return x + y.permute(0, 3, 1, 2)


class LGFI(nn.Module):
  def __init__(self, dim, expan_ratio=6, use_pos_emb=True, num_heads=6, qkv_bias=True):
    super().__init__()
    self.pos_embd = PositionalEncodingFourier(dim=dim) if use_pos_emb else None
    self.norm_xca = LayerNorm(dim)
    self.gamma_xca = nn.Parameter(1e-6 * torch.ones(dim))
    self.xca = XCA(dim, num_heads=num_heads, qkv_bias=qkv_bias)
    self.norm = LayerNorm(dim)
    self.pwconv1 = nn.Linear(dim, expan_ratio * dim)
    self.act = nn.GELU()
    self.pwconv2 = nn.Linear(expan_ratio * dim, dim)
    self.gamma = nn.Parameter(1e-6 * torch.ones(dim))

  def forward(self, x):
    inp = x
    B, C, H, W = x.shape
    x = x.reshape(B, C, H * W).permute(0, 2, 1)
    if self.pos_embd is not None:
      x = x + self.pos_embd(B, H, W).reshape(B, -1, x.shape[1]).permute(0, 2, 1)
    x = x + self.gamma_xca * self.xca(self.norm_xca(x))
    x = x.reshape(B, H, W, C)
    x = self.gamma * self.pwconv2(self.act(self.pwconv1(self.norm(x))))
    return inp + x.permute(0, 3, 1, 2)


class AvgPool(nn.Module):
  def __init__(self, ratio):
    super().__init__()
    self.pool = nn.ModuleList([nn.AvgPool2d(3, stride=2, padding=1) for _ in range(ratio)])

  def forward(self, x):
    for p in self.pool:
      x = p(x)
    return x


class LiteMono(nn.Module):
  def __init__(self, model="lite-mono", height=192, width=640, heads=(8, 8, 8),
               use_pos_embd_xca=(True, False, False), expan_ratio=6):
    super().__init__()
    dims, self.depth = DIMS_DEPTHS[model]
    self.num_ch_enc = list(dims)
    dil = dilation_table(model, height, width)
    self.downsample_layers = nn.ModuleList()
    self.downsample_layers.append(nn.Sequential(
        Conv(3, dims[0], 3, 2, 1, bn_act=True), Conv(dims[0], dims[0], 3, 1, 1, bn_act=True),
        Conv(dims[0], dims[0], 3, 1, 1, bn_act=True)))
    self.stem2 = nn.Sequential(Conv(dims[0] + 3, dims[0], 3, 2, 1))
    self.input_downsample = nn.ModuleList([AvgPool(i) for i in range(1, 5)])
    for i in range(2):
      self.downsample_layers.append(nn.Sequential(Conv(dims[i] * 2 + 3, dims[i + 1], 3, 2, 1)))
    self.stages = nn.ModuleList()
    for i in range(3):
      blocks = [DilatedConv(dims[i], 3, dil[i][j], expan_ratio) for j in range(self.depth[i] - 1)]
      blocks.append(LGFI(dims[i], expan_ratio, use_pos_embd_xca[i], heads[i]))
      self.stages.append(nn.Sequential(*blocks))

  def forward(self, x):
    x = (x - 0.45) / 0.225
    x_down = [pool(x) for pool in self.input_downsample]
    x = self.downsample_layers[0](x)
    x = self.stem2(torch.cat((x, x_down[0]), dim=1))
    features, tmp = [], [x]
    x = self.stages[0](x)
    tmp.append(x)
    features.append(x)
    for i in (1, 2):
      tmp.append(x_down[i])
      x = self.downsample_layers[i](torch.cat(tmp, dim=1))
      tmp = [x]
      x = self.stages[i](x)
      tmp.append(x)
      features.append(x)
    return features


class Conv3x3(nn.Module):
  def __init__(self, cin, cout):
    super().__init__()
    self.pad = nn.ReflectionPad2d(1)
    self.conv = nn.Conv2d(int(cin), int(cout), 3)

  def forward(self, x):
    return self.conv(self.pad(x))


class ConvBlock(nn.Module):
  def __init__(self, cin, cout):
    super().__init__()
    self.conv = Conv3x3(cin, cout)
    self.nonlin = nn.ELU(inplace=True)

  def forward(self, x):
    return self.nonlin(self.conv(x))


def upsample(x):
  return F.interpolate(x, scale_factor=2, mode="bilinear")


class DepthDecoder(nn.Module):
  def __init__(self, num_ch_enc, scales=range(3)):
    super().__init__()
    self.scales = list(scales)
    enc = list(num_ch_enc)
    dec = [c // 2 for c in enc]
    self.convs = {}
    for i in range(2, -1, -1):
      self.convs[("upconv", i, 0)] = ConvBlock(enc[-1] if i == 2 else dec[i + 1], dec[i])
      self.convs[("upconv", i, 1)] = ConvBlock(dec[i] + (enc[i - 1] if i > 0 else 0), dec[i])
    for s in self.scales:
      self.convs[("dispconv", s)] = Conv3x3(dec[s], 1)
    self.decoder = nn.ModuleList(list(self.convs.values()))

  def forward(self, features):
    out = {}
    x = features[-1]
    for i in range(2, -1, -1):
      x = [upsample(self.convs[("upconv", i, 0)](x))]
      if i > 0:
        x.append(features[i - 1])
      x = self.convs[("upconv", i, 1)](torch.cat(x, 1))
      if i in self.scales:
        out[("disp", i)] = torch.sigmoid(upsample(self.convs[("dispconv", i)](x)))
    return out


def randomize_(module: nn.Module, seed: int) -> None:
  """Random weights and non-trivial BN statistics, scaled so activations stay O(1).

  Kernels ~ N(0, 1 / fan_in); BN and LN gamma ~ U[0.3, 0.8] resp. U[0.6, 1.4]; the layer scales
  `gamma`/`gamma_xca` ~ U[0.2, 0.5] (upstream's 1e-6 init would make every block an identity and
  the test blind to it); XCA temperatures ~ U[0.5, 1.5]; biases and betas ~ 0.1 N(0, 1); running
  means ~ 0.2 N(0, 1), variances ~ U[0.5, 1.5]. Unused LayerNorms get random values too.
  """
  g = torch.Generator().manual_seed(seed)
  uniform = lambda shape, lo, hi: lo + (hi - lo) * torch.rand(shape, generator=g)
  with torch.no_grad():
    for name, p in module.named_parameters():
      leaf = name.rsplit(".", 1)[-1]
      if p.ndim > 1 and leaf == "weight":
        p.copy_(torch.randn(p.shape, generator=g) * (1.0 / p[0].numel()) ** 0.5)
      elif leaf == "temperature":
        p.copy_(uniform(p.shape, 0.5, 1.5))
      elif leaf in ("gamma", "gamma_xca"):
        p.copy_(uniform(p.shape, 0.2, 0.5))
      elif leaf == "weight" and ".norm" in f".{name}":
        p.copy_(uniform(p.shape, 0.6, 1.4))
      elif leaf == "weight":  # BN gamma
        p.copy_(uniform(p.shape, 0.3, 0.8))
      else:
        p.copy_(0.1 * torch.randn(p.shape, generator=g))
    for mod in module.modules():
      if isinstance(mod, nn.BatchNorm2d):
        mod.running_mean.copy_(0.2 * torch.randn(mod.running_mean.shape, generator=g))
        mod.running_var.copy_(uniform(mod.running_var.shape, 0.5, 1.5))
        mod.num_batches_tracked.fill_(7)


def flax_path(torch_module_name: str) -> str:
  """`stages.2.9.norm_xca` -> `stages_2_9/norm_xca`, `downsample_layers.0.1.bn_gelu.bn` ->
  `downsample_layers_0_1/bn` (the Flax names of the encoder's normalisation layers)."""
  parts = torch_module_name.replace(".bn_gelu.bn", ".bn").split(".")
  return f"{parts[0]}_{parts[1]}_{parts[2]}/" + "/".join(parts[3:])


def norm_grads(encoder: LiteMono) -> dict:
  """Encoder BN and (used) LN gamma/beta gradients keyed by Flax leaf path (`.../scale`,
  `.../bias`)."""
  grads = {}
  for name, mod in encoder.named_modules():
    if isinstance(mod, (nn.BatchNorm2d, LayerNorm)) and mod.weight.grad is not None:
      key = flax_path(name)
      grads[key + "/scale"] = mod.weight.grad.double().numpy()
      grads[key + "/bias"] = mod.bias.grad.double().numpy()
  return grads
