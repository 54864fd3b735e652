"""An independent PyTorch MonoViT, the reference for the converter parity tests.

Written from upstream zxcqlf/MonoViT (`networks/mpvit.py` `mpvit_small`, `networks/hr_decoder.py`
`DepthDecoder`, `networks/hr_layers.py`, `networks/nets.py` `DeepNet`) with exactly upstream's
state_dict key names, so the files it saves have the released layout:

* encoder.pth: the MPViT state dict (`stem.0.conv.weight`, `patch_embed_stages.0.patch_embeds.0
  .patch_conv.dwconv.weight`, `mhca_stages.2.mhca_blks.1.MHCA_layers.3.factoratt_crpe.qkv.weight`,
  ...) plus MonoDepth2's `height`, `width`, `use_stereo`. The shared `cpe`/`crpe` of each
  MHCAEncoder are registered under every owner, so their tensors appear several times
  (`mhca_blks.1.cpe.proj.weight` = `mhca_blks.1.MHCA_layers.0.cpe.proj.weight` = ...).
* depth.pth: the decoder state dict, every module twice: `convs.<name>.*` (ModuleDict) and
  `decoder.<k>.*` (ModuleList of the same modules in insertion order).
* the high-resolution releases: one `DeepNet` state dict saved from `nn.DataParallel`,
  `module.encoder.*` + `module.decoder.*`.

mmcv, timm and einops are not installed here: BatchNorm2d stands for mmcv's `build_norm_layer(
dict(type="BN"))`, drop path and the rearranges are written out.
"""

from __future__ import annotations

import re

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


class DropPath(nn.Module):
  """Stochastic depth per sample (timm's), active in train mode only."""

  def __init__(self, p=0.0):
    super().__init__()
    self.p = p

  def forward(self, x):
    if self.p == 0.0 or not self.training:
      return x
    keep = x.new_empty((x.shape[0],) + (1,) * (x.ndim - 1)).bernoulli_(1 - self.p)
    return x * keep / (1 - self.p)


class Mlp(nn.Module):
  def __init__(self, in_features, hidden_features):
    super().__init__()
    self.fc1 = nn.Linear(in_features, hidden_features)
    self.act = nn.GELU()
    self.fc2 = nn.Linear(hidden_features, in_features)
    self.drop = nn.Dropout(0.0)

  def forward(self, x):
    return self.drop(self.fc2(self.drop(self.act(self.fc1(x)))))


class Conv2d_BN(nn.Module):
  def __init__(self, in_ch, out_ch, kernel_size=1, stride=1, pad=0, act_layer=None):
    super().__init__()
    self.conv = nn.Conv2d(in_ch, out_ch, kernel_size, stride, pad, bias=False)
    self.bn = nn.BatchNorm2d(out_ch)
    self.act_layer = act_layer() if act_layer is not None else nn.Identity()

  def forward(self, x):
    return self.act_layer(self.bn(self.conv(x)))


class DWConv2d_BN(nn.Module):
  def __init__(self, in_ch, out_ch, kernel_size=1, stride=1, act_layer=nn.Hardswish):
    super().__init__()
    self.dwconv = nn.Conv2d(in_ch, out_ch, kernel_size, stride, (kernel_size - 1) // 2,
                            groups=out_ch, bias=False)
    self.pwconv = nn.Conv2d(out_ch, out_ch, 1, 1, 0, bias=False)
    self.bn = nn.BatchNorm2d(out_ch)
    self.act = act_layer() if act_layer is not None else nn.Identity()

  def forward(self, x):
    return self.act(self.bn(self.pwconv(self.dwconv(x))))


class DWCPatchEmbed(nn.Module):
  def __init__(self, in_chans, embed_dim, patch_size, stride):
    super().__init__()
    self.patch_conv = DWConv2d_BN(in_chans, embed_dim, patch_size, stride, nn.Hardswish)

  def forward(self, x):
    return self.patch_conv(x)


class Patch_Embed_stage(nn.Module):
  def __init__(self, embed_dim, num_path=4, isPool=False):
    super().__init__()
    self.patch_embeds = nn.ModuleList([
        DWCPatchEmbed(embed_dim, embed_dim, 3, 2 if isPool and idx == 0 else 1)
        for idx in range(num_path)])

  def forward(self, x):
    outs = []
    for pe in self.patch_embeds:
      x = pe(x)
      outs.append(x)
    return outs


class ConvPosEnc(nn.Module):
  def __init__(self, dim, k=3):
    super().__init__()
    self.proj = nn.Conv2d(dim, dim, k, 1, k // 2, groups=dim)

  def forward(self, x, size):
    b, n, c = x.shape
    feat = x.transpose(1, 2).reshape(b, c, *size)
    return (self.proj(feat) + feat).flatten(2).transpose(1, 2)


class ConvRelPosEnc(nn.Module):
  def __init__(self, Ch, h, window):
    super().__init__()
    self.window = window
    self.conv_list = nn.ModuleList()
    self.head_splits = []
    for win, split in window.items():
      pad = win // 2
      self.conv_list.append(nn.Conv2d(split * Ch, split * Ch, (win, win), padding=(pad, pad),
                                      groups=split * Ch))
      self.head_splits.append(split)
    self.channel_splits = [s * Ch for s in self.head_splits]

  def forward(self, q, v, size):
    b, h, n, ch = q.shape
    hh, ww = size
    v_img = v.permute(0, 1, 3, 2).reshape(b, h * ch, hh, ww)  # B h (H W) Ch -> B (h Ch) H W
    parts = torch.split(v_img, self.channel_splits, dim=1)
    conv_v = torch.cat([conv(x) for conv, x in zip(self.conv_list, parts)], dim=1)
    conv_v = conv_v.reshape(b, h, ch, n).permute(0, 1, 3, 2)  # -> B h (H W) Ch
    return q * conv_v


class FactorAtt_ConvRelPosEnc(nn.Module):
  def __init__(self, dim, num_heads=8, qkv_bias=False, shared_crpe=None):
    super().__init__()
    self.num_heads = num_heads
    self.scale = (dim // num_heads) ** -0.5
    self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
    self.attn_drop = nn.Dropout(0.0)
    self.proj = nn.Linear(dim, dim)
    self.proj_drop = nn.Dropout(0.0)
    self.crpe = shared_crpe

  def forward(self, x, size):
    b, n, c = x.shape
    qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
    q, k, v = qkv[0], qkv[1], qkv[2]  # (B, h, N, Ch)
    k_softmax = k.softmax(dim=2)
    kv = torch.einsum("bhnk,bhnv->bhkv", k_softmax, v)
    factor_att = torch.einsum("bhnk,bhkv->bhnv", q, kv)
    crpe = self.crpe(q, v, size=size)
    x = self.scale * factor_att + crpe
    x = x.transpose(1, 2).reshape(b, n, c)
    return self.proj_drop(self.proj(x))


class MHCABlock(nn.Module):
  def __init__(self, dim, num_heads, mlp_ratio=3, drop_path=0.0, qkv_bias=True, shared_cpe=None,
               shared_crpe=None):
    super().__init__()
    self.cpe = shared_cpe
    self.crpe = shared_crpe
    self.factoratt_crpe = FactorAtt_ConvRelPosEnc(dim, num_heads, qkv_bias, shared_crpe)
    self.mlp = Mlp(dim, dim * mlp_ratio)
    self.drop_path = DropPath(drop_path) if drop_path > 0.0 else nn.Identity()
    self.norm1 = nn.LayerNorm(dim, eps=1e-6)
    self.norm2 = nn.LayerNorm(dim, eps=1e-6)

  def forward(self, x, size):
    if self.cpe is not None:
      x = self.cpe(x, size)
    x = x + self.drop_path(self.factoratt_crpe(self.norm1(x), size))
    return x + self.drop_path(self.mlp(self.norm2(x)))


class MHCAEncoder(nn.Module):
  def __init__(self, dim, num_layers=1, num_heads=8, mlp_ratio=3, drop_path_list=(),
               crpe_window=None):
    super().__init__()
    crpe_window = crpe_window or {3: 2, 5: 3, 7: 3}
    self.num_layers = num_layers
    self.cpe = ConvPosEnc(dim, k=3)
    self.crpe = ConvRelPosEnc(Ch=dim // num_heads, h=num_heads, window=crpe_window)
    self.MHCA_layers = nn.ModuleList([
        MHCABlock(dim, num_heads, mlp_ratio, drop_path_list[i], shared_cpe=self.cpe,
                  shared_crpe=self.crpe) for i in range(num_layers)])

  def forward(self, x, size):
    hh, ww = size
    for layer in self.MHCA_layers:
      x = layer(x, (hh, ww))
    return x.reshape(x.shape[0], hh, ww, -1).permute(0, 3, 1, 2)


class ResBlock(nn.Module):
  def __init__(self, in_features, out_features=None, act_layer=nn.Hardswish):
    super().__init__()
    out_features = out_features or in_features
    self.conv1 = Conv2d_BN(in_features, in_features, act_layer=act_layer)
    self.dwconv = nn.Conv2d(in_features, in_features, 3, 1, 1, bias=False, groups=in_features)
    self.norm = nn.BatchNorm2d(in_features)
    self.act = act_layer()
    self.conv2 = Conv2d_BN(in_features, out_features)

  def forward(self, x):
    feat = self.act(self.norm(self.dwconv(self.conv1(x))))
    return x + self.conv2(feat)


class MHCA_stage(nn.Module):
  def __init__(self, embed_dim, out_embed_dim, num_layers, num_heads, mlp_ratio, num_path,
               drop_path_list):
    super().__init__()
    self.mhca_blks = nn.ModuleList([
        MHCAEncoder(embed_dim, num_layers, num_heads, mlp_ratio, drop_path_list)
        for _ in range(num_path)])
    self.InvRes = ResBlock(embed_dim, embed_dim)
    self.aggregate = Conv2d_BN(embed_dim * (num_path + 1), out_embed_dim, act_layer=nn.Hardswish)

  def forward(self, inputs):
    outs = [self.InvRes(inputs[0])]
    for x, enc in zip(inputs, self.mhca_blks):
      _, _, hh, ww = x.shape
      outs.append(enc(x.flatten(2).transpose(1, 2), size=(hh, ww)))
    return self.aggregate(torch.cat(outs, dim=1)), outs


class MPViT(nn.Module):
  def __init__(self, num_stages=4, num_layers=(1, 1, 1, 1), mlp_ratios=(8, 8, 4, 4),
               num_path=(4, 4, 4, 4), embed_dims=(64, 128, 256, 512), num_heads=(8, 8, 8, 8),
               drop_path_rate=0.2):
    super().__init__()
    self.num_stages = num_stages
    rates = torch.linspace(0, drop_path_rate, sum(num_layers)).tolist()
    dpr, cur = [], 0
    for n in num_layers:
      dpr.append(rates[cur:cur + n])
      cur += n
    self.stem = nn.Sequential(
        Conv2d_BN(3, embed_dims[0] // 2, 3, 2, 1, act_layer=nn.Hardswish),
        Conv2d_BN(embed_dims[0] // 2, embed_dims[0], 3, 1, 1, act_layer=nn.Hardswish))
    self.patch_embed_stages = nn.ModuleList([
        Patch_Embed_stage(embed_dims[i], num_path[i], isPool=True) for i in range(num_stages)])
    self.mhca_stages = nn.ModuleList([
        MHCA_stage(embed_dims[i], embed_dims[i + 1] if i + 1 != num_stages else embed_dims[i],
                   num_layers[i], num_heads[i], mlp_ratios[i], num_path[i], dpr[i])
        for i in range(num_stages)])

  def forward(self, x):
    x = self.stem(x)
    outs = [x]
    for i in range(self.num_stages):
      x, _ = self.mhca_stages[i](self.patch_embed_stages[i](x))
      outs.append(x)
    return outs


def mpvit_small(**kwargs):
  return MPViT(num_stages=4, num_path=[2, 3, 3, 3], num_layers=[1, 3, 6, 3],
               embed_dims=[64, 128, 216, 288], mlp_ratios=[4, 4, 4, 4], num_heads=[8, 8, 8, 8],
               **kwargs)


# ---------------------------------------------------------------- hr_layers.py / hr_decoder.py


def upsample(x):
  return F.interpolate(x, scale_factor=2, mode="nearest")


class Conv3x3(nn.Module):
  def __init__(self, in_channels, out_channels):
    super().__init__()
    self.pad = nn.ReflectionPad2d(1)
    self.conv = nn.Conv2d(int(in_channels), int(out_channels), 3)

  def forward(self, x):
    return self.conv(self.pad(x))


class ConvBlock(nn.Module):
  def __init__(self, in_channels, out_channels):
    super().__init__()
    self.conv = Conv3x3(in_channels, out_channels)
    self.nonlin = nn.ELU(inplace=True)

  def forward(self, x):
    return self.nonlin(self.conv(x))


class Conv1x1(nn.Module):
  def __init__(self, in_channels, out_channels):
    super().__init__()
    self.conv = nn.Conv2d(in_channels, out_channels, 1, stride=1, bias=False)

  def forward(self, x):
    return self.conv(x)


class ChannelAttention(nn.Module):
  def __init__(self, in_planes, ratio=16):
    super().__init__()
    self.avg_pool = nn.AdaptiveAvgPool2d(1)
    self.fc = nn.Sequential(nn.Linear(in_planes, in_planes // ratio, bias=False),
                            nn.ReLU(inplace=True),
                            nn.Linear(in_planes // ratio, in_planes, bias=False))
    self.sigmoid = nn.Sigmoid()

  def forward(self, x):
    b, c, _, _ = x.size()
    w = self.fc(self.avg_pool(x).view(b, c)).view(b, c, 1, 1)
    return self.sigmoid(w).expand_as(x) * x


class Attention_Module(nn.Module):
  def __init__(self, high_feature_channel, output_channel=None):
    super().__init__()
    out_channel = output_channel if output_channel is not None else high_feature_channel
    self.ca = ChannelAttention(high_feature_channel)
    self.conv_se = nn.Conv2d(high_feature_channel, out_channel, 3, 1, 1)
    self.relu = nn.ReLU(inplace=True)

  def forward(self, x):
    return self.relu(self.conv_se(self.ca(x)))


class fSEModule(nn.Module):
  def __init__(self, high_feature_channel, low_feature_channels, output_channel=None):
    super().__init__()
    in_channel = high_feature_channel + low_feature_channels
    out_channel = output_channel if output_channel is not None else high_feature_channel
    self.avg_pool = nn.AdaptiveAvgPool2d(1)
    self.fc = nn.Sequential(nn.Linear(in_channel, in_channel // 16, bias=False),
                            nn.ReLU(inplace=True),
                            nn.Linear(in_channel // 16, in_channel, bias=False))
    self.sigmoid = nn.Sigmoid()
    self.conv_se = nn.Conv2d(in_channel, out_channel, 1, 1)
    self.relu = nn.ReLU(inplace=True)

  def forward(self, high_features, low_features):
    features = torch.cat([upsample(high_features)] + low_features, 1)
    b, c, _, _ = features.size()
    y = self.sigmoid(self.fc(self.avg_pool(features).view(b, c)).view(b, c, 1, 1))
    return self.relu(self.conv_se(features * y.expand_as(features)))


class DepthDecoder(nn.Module):
  def __init__(self, ch_enc=(64, 128, 216, 288, 288), num_ch_enc=(64, 64, 128, 256, 512),
               num_output_channels=1):
    super().__init__()
    self.num_ch_enc = num_ch_enc
    self.ch_enc = ch_enc
    self.num_ch_dec = [16, 32, 64, 128, 256]
    self.convs = nn.ModuleDict()
    for i in (4, 3, 2, 1):
      self.convs[f"f{i}"] = Attention_Module(ch_enc[i], num_ch_enc[i])
    self.all_position = ["01", "11", "21", "31", "02", "12", "22", "03", "13", "04"]
    self.attention_position = ["31", "22", "13", "04"]
    self.non_attention_position = ["01", "11", "21", "02", "12", "03"]
    for j in range(5):
      for i in range(5 - j):
        ch_in = num_ch_enc[i] / 2 if (i == 0 and j != 0) else num_ch_enc[i]
        ch_out = ch_in / 2
        self.convs[f"X_{i}{j}_Conv_0"] = ConvBlock(ch_in, ch_out)
        if i == 0 and j == 4:
          self.convs[f"X_{i}{j}_Conv_1"] = ConvBlock(ch_out, self.num_ch_dec[i])
    for index in self.attention_position:
      row, col = int(index[0]), int(index[1])
      self.convs[f"X_{index}_attention"] = fSEModule(
          num_ch_enc[row + 1] // 2, num_ch_enc[row] + self.num_ch_dec[row + 1] * (col - 1))
    for index in self.non_attention_position:
      row, col = int(index[0]), int(index[1])
      if col == 1:
        self.convs[f"X_{row + 1}{col - 1}_Conv_1"] = ConvBlock(
            num_ch_enc[row + 1] // 2 + num_ch_enc[row], self.num_ch_dec[row + 1])
      else:
        self.convs[f"X_{index}_downsample"] = Conv1x1(
            num_ch_enc[row + 1] // 2 + num_ch_enc[row] + self.num_ch_dec[row + 1] * (col - 1),
            self.num_ch_dec[row + 1] * 2)
        self.convs[f"X_{row + 1}{col - 1}_Conv_1"] = ConvBlock(self.num_ch_dec[row + 1] * 2,
                                                               self.num_ch_dec[row + 1])
    for i in range(4):
      self.convs[f"dispconv{i}"] = Conv3x3(self.num_ch_dec[i], num_output_channels)
    self.decoder = nn.ModuleList(list(self.convs.values()))
    self.sigmoid = nn.Sigmoid()

  def nestConv(self, conv, high_feature, low_features):
    feats = torch.cat([upsample(conv[0](high_feature))] + low_features, 1)
    if len(conv) == 3:
      feats = conv[2](feats)
    return conv[1](feats)

  def forward(self, input_features):
    features = {f"X_{i}0": self.convs[f"f{i}"](input_features[i]) for i in (4, 3, 2, 1)}
    features["X_00"] = input_features[0]
    for index in self.all_position:
      row, col = int(index[0]), int(index[1])
      low = [features[f"X_{row}{i}"] for i in range(col)]
      high = features[f"X_{row + 1}{col - 1}"]
      if index in self.attention_position:
        features["X_" + index] = self.convs[f"X_{index}_attention"](
            self.convs[f"X_{row + 1}{col - 1}_Conv_0"](high), low)
      else:
        conv = [self.convs[f"X_{row + 1}{col - 1}_Conv_0"],
                self.convs[f"X_{row + 1}{col - 1}_Conv_1"]]
        if col != 1:
          conv.append(self.convs[f"X_{index}_downsample"])
        features["X_" + index] = self.nestConv(conv, high, low)
    x = self.convs["X_04_Conv_1"](upsample(self.convs["X_04_Conv_0"](features["X_04"])))
    return {("disp", 0): self.sigmoid(self.convs["dispconv0"](x)),
            ("disp", 1): self.sigmoid(self.convs["dispconv1"](features["X_04"])),
            ("disp", 2): self.sigmoid(self.convs["dispconv2"](features["X_13"])),
            ("disp", 3): self.sigmoid(self.convs["dispconv3"](features["X_22"]))}


class DeepNet(nn.Module):
  """`networks/nets.py` DeepNet('mpvitnet'): the module the high-resolution releases save
  (`encoder`, `decoder`; given ones replace upstream's mpvit_small() and DepthDecoder())."""

  def __init__(self, encoder=None, decoder=None):
    super().__init__()
    self.encoder = encoder if encoder is not None else mpvit_small()
    self.decoder = decoder if decoder is not None else DepthDecoder()

  def forward(self, x):
    return self.decoder(self.encoder(x))


# ---------------------------------------------------------------- test helpers


def randomize_(module: nn.Module, seed: int, gain: float = 1.0) -> None:
  """Random weights, random BN running statistics, non-trivial norm affines.

  Scaled so that activations stay O(1) through the network (kernels and Linear weights
  N(0, gain^2 / fan_in), norm gammas U[0.3, 0.8], biases and betas 0.1 N(0, 1)) and the sigmoid
  disparities neither saturate nor stay flat, as with trained weights (the decoder's ReLU/ELU
  chain needs gain ~ sqrt(2), He's, to keep its variance). NumPy draws: torch's generator is
  several times slower for MPViT's 22M values.
  """
  rng = np.random.default_rng(seed)

  def fill(t, values):
    t.copy_(torch.from_numpy(values.astype(np.float32)).reshape(t.shape))

  with torch.no_grad():
    for name, p in module.named_parameters():  # shared modules appear once here
      if p.ndim > 1:
        fill(p, rng.standard_normal(p.shape, np.float32) * (gain / p[0].numel() ** 0.5))
      elif name.endswith("weight"):  # BN / LN gamma
        fill(p, 0.3 + 0.5 * rng.random(p.shape, np.float32))
      else:
        fill(p, 0.1 * rng.standard_normal(p.shape, np.float32))
    for mod in module.modules():
      if isinstance(mod, nn.BatchNorm2d):
        fill(mod.running_mean, 0.2 * rng.standard_normal(mod.running_mean.shape, np.float32))
        fill(mod.running_var, 0.5 + rng.random(mod.running_var.shape, np.float32))
        mod.num_batches_tracked.fill_(7)


def bn_train_(module: nn.Module) -> nn.Module:
  """Eval mode except every BatchNorm in train mode (batch statistics, running-stat updates):
  PITTA's `use_batch_stats`, without upstream's stochastic depth."""
  module.eval()
  for m in module.modules():
    if isinstance(m, nn.BatchNorm2d):
      m.train()
  return module


def flax_path(torch_module_name: str) -> str:
  """Encoder module name -> the Flax module path: `a.3.b` -> `a_3/b`, `patch_conv` dropped."""
  name = torch_module_name.replace(".patch_conv", "")
  return re.sub(r"\.(\d+)", r"_\1", name).replace(".", "/")


def norm_grads(encoder: MPViT) -> dict:
  """Gradients of every encoder BN and LN gamma/beta, keyed by Flax leaf path
  (`stem_0/bn/scale`)."""
  grads = {}
  for name, m in encoder.named_modules():
    if isinstance(m, (nn.BatchNorm2d, nn.LayerNorm)):
      key = flax_path(name)
      grads[key + "/scale"] = m.weight.grad.double().numpy()
      grads[key + "/bias"] = m.bias.grad.double().numpy()
  return grads
