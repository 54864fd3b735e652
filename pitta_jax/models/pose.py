"""MonoDepth2's pose network (`networks/pose_decoder.py`, `layers.py`), NHWC.

`PoseNet` = a `ResnetEncoder(num_input_images=2)` named "encoder" over two stacked frames and a
`PoseDecoder` named "decoder": 1x1 squeeze to 256 + ReLU, two 3x3 convs (256, ReLU), a 1x1 conv
to 6 * num_frames_to_predict_for, spatial mean, x 0.01 -> axis-angle (3) + translation (3).
Needed by the CoMoDa baseline; PITTA itself is pose-agnostic (paper eq. 2).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import flax.linen as nn

from pitta_jax.models.layers import Conv, ModuleDef, conv
from pitta_jax.models.resnet import ResnetEncoder
from pitta_jax.nonsmooth import norm


class PoseDecoder(nn.Module):
  """`PoseDecoder(num_ch_enc, num_input_features=1, num_frames_to_predict_for=2, stride=1)`."""
  num_input_features: int = 1
  num_frames_to_predict_for: int = 2
  stride: int = 1
  conv: ModuleDef = Conv

  @nn.compact
  def __call__(self, features_per_input: list[list[jax.Array]]) -> tuple[jax.Array, jax.Array]:
    """features_per_input: for each input feature set, the encoder's 5 maps.

    Returns (axisangle, translation), each (B, num_frames_to_predict_for, 1, 3).
    """
    squeeze = conv(256, 1, use_bias=True, name="squeeze", module=self.conv)
    x = jnp.concatenate([nn.relu(squeeze(f[-1])) for f in features_per_input], axis=-1)
    x = nn.relu(conv(256, 3, self.stride, 1, use_bias=True, name="pose_0", module=self.conv)(x))
    x = nn.relu(conv(256, 3, self.stride, 1, use_bias=True, name="pose_1", module=self.conv)(x))
    x = conv(6 * self.num_frames_to_predict_for, 1, use_bias=True, name="pose_2", module=self.conv)(x)
    x = 0.01 * jnp.mean(x, axis=(1, 2)).reshape(-1, self.num_frames_to_predict_for, 1, 6)
    return x[..., :3], x[..., 3:]


class PoseNet(nn.Module):
  """MonoDepth2's separate-ResNet pose network ("pose_model_type == separate_resnet")."""
  num_layers: int = 18
  num_frames_to_predict_for: int = 2
  conv: ModuleDef = Conv

  @nn.compact
  def __call__(self, frame_pair: jax.Array, train: bool = False) -> tuple[jax.Array, jax.Array]:
    """frame_pair: (B, H, W, 6), two RGB frames in [0, 1] stacked along channels."""
    features = ResnetEncoder(self.num_layers, 2, self.conv, name="encoder")(frame_pair, train)
    return PoseDecoder(1, self.num_frames_to_predict_for, conv=self.conv,
                       name="decoder")([features])


def rot_from_axisangle(vec: jax.Array) -> jax.Array:
  """(B, 1, 3) axis-angle -> (B, 4, 4) homogeneous rotation (Rodrigues), as MonoDepth2."""
  angle = norm(vec, axis=2, keepdims=True)  # (B, 1, 1); torch's derivative at rest (0, not NaN)
  axis = vec / (angle + 1e-7)
  ca, sa = jnp.cos(angle), jnp.sin(angle)
  c = 1.0 - ca
  x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]  # (B, 1)
  ca, sa, c = ca[..., 0], sa[..., 0], c[..., 0]
  rows = [
      [x * x * c + ca, x * y * c - z * sa, z * x * c + y * sa],
      [x * y * c + z * sa, y * y * c + ca, y * z * c - x * sa],
      [z * x * c - y * sa, y * z * c + x * sa, z * z * c + ca],
  ]
  rot3 = jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)[:, 0]  # (B, 3, 3)
  batch = vec.shape[0]
  out = jnp.zeros((batch, 4, 4), vec.dtype).at[:, :3, :3].set(rot3)
  return out.at[:, 3, 3].set(1.0)


def translation_matrix(t: jax.Array) -> jax.Array:
  """(B, 1, 3) or (B, 3) translation -> (B, 4, 4)."""
  t = t.reshape(t.shape[0], 3)
  eye = jnp.broadcast_to(jnp.eye(4, dtype=t.dtype), (t.shape[0], 4, 4))
  return eye.at[:, :3, 3].set(t)


def transformation_from_parameters(axisangle: jax.Array, translation: jax.Array,
                                   invert: bool = False) -> jax.Array:
  """MonoDepth2's `transformation_from_parameters`: (B, 1, 3) x 2 -> (B, 4, 4) camera motion.

  invert=False: M = T @ R; invert=True: M = R^T @ (-t translation).
  """
  rot = rot_from_axisangle(axisangle)
  t = translation
  if invert:
    rot = jnp.swapaxes(rot, 1, 2)
    t = -t
  trans = translation_matrix(t)
  return rot @ trans if invert else trans @ rot
