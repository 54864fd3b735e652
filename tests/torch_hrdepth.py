"""An independent PyTorch HR-Depth decoder, the reference for `tests/test_hrdepth.py`.

Written from shawLyu/HR-Depth's `networks/HR_Depth_Decoder.py` and `layers.py` (ResNet encoder
case, `mobile_encoder=False`) with upstream's state_dict layout: the layers in an `nn.ModuleDict`
`convs` (keys `X_ij_Conv_k`, `X_ij_attention`, `X_ij_downsample`, `dispConvScale{s}`, inserted in
upstream's order) that is also registered as `decoder = nn.ModuleList(convs.values())`, so
`state_dict()` holds every tensor twice. The encoder is MonoDepth2's (`torch_monodepth2`).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from torch_monodepth2 import ConvBlock, Conv3x3  # upstream's layers.py has the same two


def upsample(x):
  return F.interpolate(x, scale_factor=2, mode="nearest")


class Conv1x1(nn.Module):
  def __init__(self, in_channels, out_channels):
    super().__init__()
    self.conv = nn.Conv2d(in_channels, out_channels, 1, stride=1, bias=False)

  def forward(self, x):
    return self.conv(x)


class fSEModule(nn.Module):
  """Feature-fusion squeeze-excitation: upsampled high + low features, SE weights, 1x1 conv."""

  def __init__(self, high_feature_channel, low_feature_channels, output_channel=None):
    super().__init__()
    channel = high_feature_channel + low_feature_channels
    out_channel = high_feature_channel if output_channel is None else output_channel
    self.avg_pool = nn.AdaptiveAvgPool2d(1)
    self.fc = nn.Sequential(nn.Linear(channel, channel // 16, bias=False), nn.ReLU(inplace=True),
                            nn.Linear(channel // 16, channel, bias=False))
    self.sigmoid = nn.Sigmoid()
    self.conv_se = nn.Conv2d(channel, out_channel, kernel_size=1, stride=1)
    self.relu = nn.ReLU(inplace=True)

  def forward(self, high_features, low_features):
    x = torch.cat([upsample(high_features)] + list(low_features), 1)
    b, c = x.shape[:2]
    y = self.sigmoid(self.fc(self.avg_pool(x).view(b, c)).view(b, c, 1, 1))
    return self.relu(self.conv_se(x * y.expand_as(x)))


class HRDepthDecoder(nn.Module):
  def __init__(self, num_ch_enc, scales=range(4), num_output_channels=1):
    super().__init__()
    self.num_ch_enc = num_ch_enc
    self.num_ch_dec = np.array([16, 32, 64, 128, 256])
    self.all_position = ["01", "11", "21", "31", "02", "12", "22", "03", "13", "04"]
    self.attention_position = ["31", "22", "13", "04"]
    self.non_attention_position = ["01", "11", "21", "02", "12", "03"]
    enc, dec = num_ch_enc, self.num_ch_dec

    self.convs = nn.ModuleDict()
    for j in range(5):
      for i in range(5 - j):
        n_in = enc[i] / 2 if (i == 0 and j != 0) else enc[i]
        self.convs[f"X_{i}{j}_Conv_0"] = ConvBlock(n_in, n_in / 2)
        if i == 0 and j == 4:
          self.convs[f"X_{i}{j}_Conv_1"] = ConvBlock(n_in / 2, dec[i])
    for index in self.attention_position:
      row, col = int(index[0]), int(index[1])
      self.convs[f"X_{index}_attention"] = fSEModule(
          enc[row + 1] // 2, enc[row] + dec[row + 1] * (col - 1))
    for index in self.non_attention_position:
      row, col = int(index[0]), int(index[1])
      if col == 1:
        self.convs[f"X_{row + 1}{col - 1}_Conv_1"] = ConvBlock(
            enc[row + 1] // 2 + enc[row], dec[row + 1])
      else:
        self.convs[f"X_{index}_downsample"] = Conv1x1(
            enc[row + 1] // 2 + enc[row] + dec[row + 1] * (col - 1), dec[row + 1] * 2)
        self.convs[f"X_{row + 1}{col - 1}_Conv_1"] = ConvBlock(dec[row + 1] * 2, dec[row + 1])
    for i in range(4):
      self.convs[f"dispConvScale{i}"] = Conv3x3(dec[i], num_output_channels)
    self.decoder = nn.ModuleList(list(self.convs.values()))
    self.sigmoid = nn.Sigmoid()

  def nestConv(self, conv, high_feature, low_features):
    x = torch.cat([upsample(conv[0](high_feature))] + list(low_features), 1)
    if len(conv) == 3:
      x = conv[2](x)
    return conv[1](x)

  def forward(self, input_features):
    features = {f"X_{i}0": input_features[i] for i in range(5)}
    for index in self.all_position:
      row, col = int(index[0]), int(index[1])
      low = [features[f"X_{row}{i}"] for i in range(col)]
      below = f"X_{row + 1}{col - 1}"
      if index in self.attention_position:
        features[f"X_{index}"] = self.convs[f"X_{index}_attention"](
            self.convs[f"{below}_Conv_0"](features[below]), low)
      else:
        conv = [self.convs[f"{below}_Conv_0"], self.convs[f"{below}_Conv_1"]]
        if col != 1:
          conv.append(self.convs[f"X_{index}_downsample"])
        features[f"X_{index}"] = self.nestConv(conv, features[below], low)
    x = self.convs["X_04_Conv_1"](upsample(self.convs["X_04_Conv_0"](features["X_04"])))
    return {
        ("disparity", "Scale0"): self.sigmoid(self.convs["dispConvScale0"](x)),
        ("disparity", "Scale1"): self.sigmoid(self.convs["dispConvScale1"](features["X_04"])),
        ("disparity", "Scale2"): self.sigmoid(self.convs["dispConvScale2"](features["X_13"])),
        ("disparity", "Scale3"): self.sigmoid(self.convs["dispConvScale3"](features["X_22"])),
    }
