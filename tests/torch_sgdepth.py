"""An independent PyTorch SGDepth, the reference for `tests/test_sgdepth.py`.

Written from ifnspaml/SGDepth's `models/` with exactly upstream's state_dict key names: the
whole multi-task `SGDepth` (`common.encoder.encoder.*` torchvision ResNet with `fc = None`,
`common.decoder.blocks.step_k.conv.*`, `depth.decoder.blocks.step_k.conv.*`,
`depth.multires.convs.s.*`, `seg.*`, `pose.encoder.encoder.*`, `pose.decoder.{squeeze, conv_1,
conv_2, conv_3}.*`). The ResNet comes from `torch_monodepth2` (torchvision is not installed);
the input normalisation is upstream's data-loader step, `imagenet_normalize`.
"""

from __future__ import annotations

import torch
import torch.nn as nn

import torch_monodepth2 as tm

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def imagenet_normalize(x: torch.Tensor) -> torch.Tensor:
  """torchvision `Normalize(mean, std)` on an NCHW batch: (x - mean) / std per channel."""
  mean = torch.tensor(IMAGENET_MEAN, dtype=x.dtype).view(1, 3, 1, 1)
  std = torch.tensor(IMAGENET_STD, dtype=x.dtype).view(1, 3, 1, 1)
  return (x - mean) / std


class ResnetEncoder(nn.Module):
  """SGDepth's encoder: a torchvision ResNet without classifier, no normalisation inside."""

  def __init__(self, num_layers: int, num_input_images: int = 1):
    super().__init__()
    block, layers = tm.SPECS[num_layers]
    self.encoder = tm.ResNet(block, layers, num_input_images)
    self.encoder.fc = None  # upstream drops the classifier: no fc.* keys in the state dict
    self.num_ch_enc = tuple(tm.num_ch_enc(num_layers))

  def forward(self, x):
    e = self.encoder
    l0 = e.relu(e.bn1(e.conv1(x)))
    l1 = e.layer1(e.maxpool(l0))
    l2 = e.layer2(l1)
    l3 = e.layer3(l2)
    return l0, l1, l2, l3, e.layer4(l3)


class PreConvBlock(nn.Module):
  """Reflection pad + 3x3 conv + ELU on tuple element `pos` (pos - 1 for pos > 0), stored at pos."""

  def __init__(self, pos, n_in, n_out):
    super().__init__()
    self.pos = pos
    self.pad = nn.ReflectionPad2d(1)
    self.conv = nn.Conv2d(n_in, n_out, 3)
    self.nl = nn.ELU()

  def forward(self, *x):
    src = x[self.pos] if self.pos == 0 else x[self.pos - 1]
    return x[:self.pos] + (self.nl(self.conv(self.pad(src))),) + x[self.pos + 1:]


class UpSkipBlock(nn.Module):
  """Nearest x2 of element pos - 1, concat with skip element pos (none at pos 5), pad, conv, ELU."""

  def __init__(self, pos, ch_in, ch_skip, ch_out):
    super().__init__()
    self.pos = pos
    self.up = nn.Upsample(scale_factor=2)
    self.pad = nn.ReflectionPad2d(1)
    self.conv = nn.Conv2d(ch_in + ch_skip, ch_out, 3)
    self.nl = nn.ELU()

  def forward(self, *x):
    new = self.up(x[self.pos - 1])
    if self.pos != 5:
      new = torch.cat((new, x[self.pos]), 1)
    return x[:self.pos - 1] + (self.nl(self.conv(self.pad(new))),) + x[self.pos:]


class PartialDecoder(nn.Module):
  """Decoder steps start .. end-1 as `blocks.step_k` (even: PreConvBlock, odd: UpSkipBlock)."""

  def __init__(self, chs_dec, chs_enc, start=0, end=None):
    super().__init__()
    self.chs_dec, self.chs_enc = tuple(chs_dec), tuple(chs_enc)
    self.start = start
    self.end = 2 * len(chs_dec) if end is None else end
    self.blocks = nn.ModuleDict()
    for step in range(self.start, self.end):
      stage, pos = step // 2, (step + 1) // 2
      if step % 2 == 0:
        n_in = self.chs_dec[stage - 1] if stage > 0 else self.chs_enc[0]
        self.blocks[f"step_{step}"] = PreConvBlock(pos, n_in, self.chs_dec[stage])
      else:
        skip = self.chs_enc[stage + 1] if stage + 1 < len(self.chs_enc) else 0
        self.blocks[f"step_{step}"] = UpSkipBlock(pos, self.chs_dec[stage], skip,
                                                  self.chs_dec[stage])

  def forward(self, *x):
    for step in range(self.start, self.end):
      x = self.blocks[f"step_{step}"](*x)
    return x


class MultiRes(nn.Module):
  """One padded 3x3 conv head per decoder output; `convs.0` is the highest resolution."""

  def __init__(self, dec_chs, out_chs, pp=None):
    super().__init__()
    self.pad = nn.ReflectionPad2d(1)
    self.convs = nn.ModuleList(nn.Conv2d(c, out_chs, 3) for c in dec_chs[::-1])
    self.pp = pp if pp is not None else (lambda t: t)

  def forward(self, *x):
    return tuple(self.pp(conv(self.pad(t))) for conv, t in zip(self.convs[::-1], x))


class ScaleGrad(torch.autograd.Function):
  """Identity forward, gradient times `scale` backward."""

  @staticmethod
  def forward(ctx, scale, x):
    ctx.scale = scale
    return x.view_as(x)

  @staticmethod
  def backward(ctx, grad):
    return None, ctx.scale * grad


class ScaledSplit(nn.Module):
  """One copy of the inputs per grad weight, each scaling the gradient it sends back."""

  def __init__(self, *grad_weights):
    super().__init__()
    self.grad_weights = grad_weights

  def forward(self, *inputs):
    return tuple(tuple(ScaleGrad.apply(w, t) for t in inputs) for w in self.grad_weights)


class SGDepthCommon(nn.Module):
  def __init__(self, num_layers, split_pos, grad_scales):
    super().__init__()
    self.encoder = ResnetEncoder(num_layers)
    self.shape_enc = tuple(reversed(self.encoder.num_ch_enc))
    self.shape_dec = (256, 128, 64, 32, 16)
    self.decoder = PartialDecoder(self.shape_dec, self.shape_enc, 0, split_pos)
    self.split = ScaledSplit(*grad_scales)

  def forward(self, x):
    x = tuple(reversed(self.encoder(x)))  # lowest resolution first
    return self.split(*self.decoder(*x))


class SGDepthDepth(nn.Module):
  def __init__(self, common, resolutions):
    super().__init__()
    self.resolutions = resolutions
    self.decoder = PartialDecoder(common.decoder.chs_dec, common.decoder.chs_enc,
                                  common.decoder.end)
    self.multires = MultiRes(self.decoder.chs_dec[-resolutions:], 1, nn.Sigmoid())

  def forward(self, *x):
    return self.multires(*self.decoder(*x)[-self.resolutions:])


class SGDepthSeg(nn.Module):
  def __init__(self, common, num_classes=20):
    super().__init__()
    self.decoder = PartialDecoder(common.decoder.chs_dec, common.decoder.chs_enc,
                                  common.decoder.end)
    self.multires = MultiRes(self.decoder.chs_dec[-1:], num_classes)

  def forward(self, *x):
    return self.multires(*self.decoder(*x)[-1:])[-1]


class PoseDecoder(nn.Module):
  """SGDepth's pose decoder: squeeze, two 3x3 convs, 1x1 to 6, spatial mean (no x0.01)."""

  def __init__(self, input_channels):
    super().__init__()
    self.nl = nn.ReLU()
    self.squeeze = nn.Conv2d(input_channels, 256, 1)
    self.conv_1 = nn.Conv2d(256, 256, 3, 1, 1)
    self.conv_2 = nn.Conv2d(256, 256, 3, 1, 1)
    self.conv_3 = nn.Conv2d(256, 6, 1)

  def forward(self, x):
    x = self.nl(self.conv_2(self.nl(self.conv_1(self.nl(self.squeeze(x))))))
    x = self.conv_3(x).mean((3, 2)).view(-1, 1, 1, 6)
    return x[..., :3], x[..., 3:]


class SGDepthPose(nn.Module):
  def __init__(self, num_layers):
    super().__init__()
    self.encoder = ResnetEncoder(num_layers, num_input_images=2)
    self.decoder = PoseDecoder(self.encoder.num_ch_enc[-1])

  def forward(self, x):
    return self.decoder(self.encoder(x)[-1])


class SGDepth(nn.Module):
  """Upstream's `SGDepth` module tree (its batch-dict `forward` replaced by `depth_outputs`).

  split_pos: upstream's --model-split-pos (0..4; 1 released), translated to decoder steps as
  upstream does (max(2 p - 1, 0)). grad_scale_depth: the ScaledSplit weight of the depth branch.
  """

  def __init__(self, split_pos=1, num_layers=18, grad_scale_depth=0.95, grad_scale_seg=0.05,
               resolutions_depth=4, num_layers_pose=18):
    super().__init__()
    steps = max(2 * split_pos - 1, 0)
    self.common = SGDepthCommon(num_layers, steps, (grad_scale_depth, grad_scale_seg))
    self.depth = SGDepthDepth(self.common, resolutions_depth)
    self.seg = SGDepthSeg(self.common)
    self.pose = SGDepthPose(num_layers_pose)

  def depth_outputs(self, images):
    """images: NCHW RGB in [0, 1] -> disparities, full resolution first (upstream's
    outputs['disp', s] for s = 0, 1, ...)."""
    x_depth, _ = self.common(imagenet_normalize(images))
    return list(reversed(self.depth(*x_depth)))
