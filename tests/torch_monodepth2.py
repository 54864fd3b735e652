"""An independent PyTorch MonoDepth2, the reference for the converter parity tests.

Written from MonoDepth2's published architecture with exactly upstream's state_dict key names:
the encoder wraps a torchvision-layout ResNet as `encoder.*` (`encoder.conv1.weight`,
`encoder.layer1.0.bn1.running_mean`, ..., `encoder.fc.*`); the depth decoder stores its convs in
`decoder = nn.ModuleList(convs.values())` (upconvs (4,0), (4,1), (3,0), ... (0,1) as
`decoder.0..9.conv.conv.*`, dispconvs for scales 0..3 as `decoder.10..13.conv.*`); the pose
decoder as `net.0..3`. torchvision is not installed here, so the ResNet is written out.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


class BasicBlock(nn.Module):
  expansion = 1

  def __init__(self, inplanes, planes, stride=1, downsample=None):
    super().__init__()
    self.conv1 = nn.Conv2d(inplanes, planes, 3, stride, 1, bias=False)
    self.bn1 = nn.BatchNorm2d(planes)
    self.relu = nn.ReLU(inplace=True)
    self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
    self.bn2 = nn.BatchNorm2d(planes)
    self.downsample = downsample

  def forward(self, x):
    identity = x
    out = self.relu(self.bn1(self.conv1(x)))
    out = self.bn2(self.conv2(out))
    if self.downsample is not None:
      identity = self.downsample(x)
    return self.relu(out + identity)


class Bottleneck(nn.Module):
  expansion = 4

  def __init__(self, inplanes, planes, stride=1, downsample=None):
    super().__init__()
    self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
    self.bn1 = nn.BatchNorm2d(planes)
    self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)
    self.bn2 = nn.BatchNorm2d(planes)
    self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
    self.bn3 = nn.BatchNorm2d(planes * 4)
    self.relu = nn.ReLU(inplace=True)
    self.downsample = downsample

  def forward(self, x):
    identity = x
    out = self.relu(self.bn1(self.conv1(x)))
    out = self.relu(self.bn2(self.conv2(out)))
    out = self.bn3(self.conv3(out))
    if self.downsample is not None:
      identity = self.downsample(x)
    return self.relu(out + identity)


class ResNet(nn.Module):
  """torchvision's ResNet layout (names conv1, bn1, layer1..4, fc)."""

  def __init__(self, block, layers, num_input_images=1):
    super().__init__()
    self.inplanes = 64
    self.conv1 = nn.Conv2d(3 * num_input_images, 64, 7, 2, 3, bias=False)
    self.bn1 = nn.BatchNorm2d(64)
    self.relu = nn.ReLU(inplace=True)
    self.maxpool = nn.MaxPool2d(3, 2, 1)
    self.layer1 = self._make_layer(block, 64, layers[0])
    self.layer2 = self._make_layer(block, 128, layers[1], 2)
    self.layer3 = self._make_layer(block, 256, layers[2], 2)
    self.layer4 = self._make_layer(block, 512, layers[3], 2)
    self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
    self.fc = nn.Linear(512 * block.expansion, 1000)

  def _make_layer(self, block, planes, blocks, stride=1):
    downsample = None
    if stride != 1 or self.inplanes != planes * block.expansion:
      downsample = nn.Sequential(
          nn.Conv2d(self.inplanes, planes * block.expansion, 1, stride, bias=False),
          nn.BatchNorm2d(planes * block.expansion))
    layers = [block(self.inplanes, planes, stride, downsample)]
    self.inplanes = planes * block.expansion
    layers += [block(self.inplanes, planes) for _ in range(1, blocks)]
    return nn.Sequential(*layers)


SPECS = {18: (BasicBlock, [2, 2, 2, 2]), 34: (BasicBlock, [3, 4, 6, 3]),
         50: (Bottleneck, [3, 4, 6, 3])}


class ResnetEncoder(nn.Module):
  def __init__(self, num_layers=18, num_input_images=1):
    super().__init__()
    block, layers = SPECS[num_layers]
    self.encoder = ResNet(block, layers, num_input_images)

  def forward(self, input_image):
    e = self.encoder
    x = (input_image - 0.45) / 0.225
    features = [e.relu(e.bn1(e.conv1(x)))]
    features.append(e.layer1(e.maxpool(features[-1])))
    features.append(e.layer2(features[-1]))
    features.append(e.layer3(features[-1]))
    features.append(e.layer4(features[-1]))
    return features


class Conv3x3(nn.Module):
  def __init__(self, in_ch, out_ch):
    super().__init__()
    self.pad = nn.ReflectionPad2d(1)
    self.conv = nn.Conv2d(int(in_ch), int(out_ch), 3)

  def forward(self, x):
    return self.conv(self.pad(x))


class ConvBlock(nn.Module):
  def __init__(self, in_ch, out_ch):
    super().__init__()
    self.conv = Conv3x3(in_ch, out_ch)
    self.nonlin = nn.ELU(inplace=True)

  def forward(self, x):
    return self.nonlin(self.conv(x))


class DepthDecoder(nn.Module):
  def __init__(self, num_ch_enc, scales=range(4)):
    super().__init__()
    self.scales = list(scales)
    ch_dec = [16, 32, 64, 128, 256]
    self.convs = {}
    for i in range(4, -1, -1):
      self.convs[("upconv", i, 0)] = ConvBlock(num_ch_enc[-1] if i == 4 else ch_dec[i + 1],
                                               ch_dec[i])
      self.convs[("upconv", i, 1)] = ConvBlock(ch_dec[i] + (num_ch_enc[i - 1] if i > 0 else 0),
                                               ch_dec[i])
    for s in self.scales:
      self.convs[("dispconv", s)] = Conv3x3(ch_dec[s], 1)
    self.decoder = nn.ModuleList(list(self.convs.values()))

  def forward(self, features):
    outputs = {}
    x = features[-1]
    for i in range(4, -1, -1):
      x = self.convs[("upconv", i, 0)](x)
      x = [F.interpolate(x, scale_factor=2, mode="nearest")]
      if i > 0:
        x += [features[i - 1]]
      x = self.convs[("upconv", i, 1)](torch.cat(x, 1))
      if i in self.scales:
        outputs[("disp", i)] = torch.sigmoid(self.convs[("dispconv", i)](x))
    return outputs


class PoseDecoder(nn.Module):
  def __init__(self, num_ch_enc, num_input_features=1, num_frames_to_predict_for=2):
    super().__init__()
    self.nf = num_frames_to_predict_for
    self.convs = {
        "squeeze": nn.Conv2d(num_ch_enc[-1], 256, 1),
        ("pose", 0): nn.Conv2d(num_input_features * 256, 256, 3, 1, 1),
        ("pose", 1): nn.Conv2d(256, 256, 3, 1, 1),
        ("pose", 2): nn.Conv2d(256, 6 * num_frames_to_predict_for, 1),
    }
    self.net = nn.ModuleList(list(self.convs.values()))

  def forward(self, input_features):
    cat = torch.cat([F.relu(self.convs["squeeze"](f[-1])) for f in input_features], 1)
    out = cat
    for i in range(3):
      out = self.convs[("pose", i)](out)
      if i != 2:
        out = F.relu(out)
    out = 0.01 * out.mean(3).mean(2).view(-1, self.nf, 1, 6)
    return out[..., :3], out[..., 3:]


def num_ch_enc(num_layers):
  return [64, 64, 128, 256, 512] if num_layers < 50 else [64, 256, 512, 1024, 2048]


def randomize_(module: nn.Module, seed: int) -> None:
  """Random weights and non-trivial BN statistics (so parity checks every term).

  Scaled so that activations stay O(1) through the network and the sigmoid disparities do not
  saturate, as with trained weights; otherwise a parity test would compare mostly 0s and 1s.
  """
  g = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for name, p in module.named_parameters():
      fan_in = p[0].numel() if p.ndim > 1 else 1
      if p.ndim > 1:
        p.copy_(torch.randn(p.shape, generator=g) * (1.0 / fan_in) ** 0.5)
      elif name.endswith("weight"):  # BN gamma
        p.copy_(0.3 + 0.5 * torch.rand(p.shape, generator=g))
      else:  # biases and BN beta
        p.copy_(0.1 * torch.randn(p.shape, generator=g))
    for mod in module.modules():
      if isinstance(mod, nn.BatchNorm2d):
        mod.running_mean.copy_(0.2 * torch.randn(mod.running_mean.shape, generator=g))
        mod.running_var.copy_(0.5 + torch.rand(mod.running_var.shape, generator=g))
        mod.num_batches_tracked.fill_(7)


def bn_grads(encoder: "ResnetEncoder") -> dict:
  """Encoder BN gamma/beta gradients keyed by the Flax leaf path (`layer3_1/bn2/scale`, ...):
  torch `layer3.1.bn2` -> `layer3_1/bn2`, `downsample.1` -> `downsample_bn`."""
  grads = {}
  for name, module in encoder.encoder.named_modules():
    if isinstance(module, nn.BatchNorm2d):
      parts = name.replace("downsample.1", "downsample_bn").split(".")
      if parts[0].startswith("layer"):
        parts = [f"{parts[0]}_{parts[1]}"] + parts[2:]
      key = "/".join(parts)
      grads[key + "/scale"] = module.weight.grad.double().numpy()
      grads[key + "/bias"] = module.bias.grad.double().numpy()
  return grads
