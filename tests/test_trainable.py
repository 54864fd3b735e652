"""Which leaves each selector adapts on ResNet-18 MonoDepth2 (paper Sec. 4.1 and Table 5).

References are hand-counted from the ResNet-18 architecture: 20 BN layers with
64 + 4*64 + (4*128 + 128) + (4*256 + 256) + (4*512 + 512) = 4,800 channels -> 9,600 gamma/beta
values; 20 conv layers (stem, 16 block convs, 3 downsample convs).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax.traverse_util import flatten_dict

from pitta_jax import trainable
from pitta_jax.models.depth_decoder import DepthNet


@pytest.fixture(scope="module")
def variables():
  """Zeros with the variables' shapes (selection depends on names and shapes only; no init
  compile needed)."""
  shapes = jax.eval_shape(DepthNet(18).init, jax.random.PRNGKey(0), jnp.zeros((1, 64, 64, 3)))
  return jax.tree_util.tree_map(lambda s: np.zeros(s.shape, s.dtype), shapes)


def _n_values(tree):
  return sum(v.size for v in jax.tree_util.tree_leaves(tree))


def test_encoder_bn_is_default_and_picks_all_20_bn_layers(variables):
  parts = trainable.split(variables)
  flat = flatten_dict(parts.trainable, sep="/")
  assert len(flat) == 40 and _n_values(parts.trainable) == 9600
  assert all(k.startswith("encoder/") and k.endswith(("/scale", "/bias")) for k in flat)
  assert "encoder/layer2_0/downsample_bn/scale" in flat and "encoder/bn1/bias" in flat
  assert not any("decoder" in k for k in flat)


def test_all_selects_every_parameter(variables):
  parts = trainable.split(variables, trainable.Selector("all"))
  assert _n_values(parts.trainable) == _n_values(variables["params"]) == 14_329_236  # 11,176,512 ResNet-18 (no fc) + 3,152,724 decoder
  assert parts.frozen == {}


def test_fraction_follows_forward_order(variables):
  sel = trainable.parse_selector("fraction(cnn=20, bn=50)")
  paths = trainable.selected_paths(variables, sel)
  convs = [p for p in paths if p.endswith("/kernel")]
  # last 4 of 20 convs; in a block PyTorch runs conv1, conv2, then the downsample branch
  assert convs == ["encoder/layer4_0/conv2/kernel", "encoder/layer4_0/downsample_conv/kernel",
                   "encoder/layer4_1/conv1/kernel", "encoder/layer4_1/conv2/kernel"]
  bns = sorted({p.rsplit("/", 1)[0] for p in paths if not p.endswith("/kernel")})
  assert len(bns) == 10 and bns[0] == "encoder/layer3_0/bn1"  # last 10 of 20 BN layers
  parts = trainable.split(variables, sel)
  bn_values = sum(v.size for k, v in flatten_dict(parts.trainable, sep="/").items()
                  if not k.endswith("kernel"))
  assert bn_values == 2 * (5 * 256 + 5 * 512)
  assert trainable.parse_selector("cnn20_bn50") == sel


def test_split_merge_round_trip(variables):
  parts = trainable.split(variables, trainable.parse_selector("cnn40_bn60"))
  merged = trainable.merge(*parts)
  for a, b in zip(jax.tree_util.tree_leaves(merged), jax.tree_util.tree_leaves(variables)):
    assert a is b
  assert jax.tree_util.tree_structure(merged) == jax.tree_util.tree_structure(variables)


def test_optimizer_sees_only_trainable(variables):
  """Adam state is allocated for the 9,600 adapted values only; the frozen tree never changes."""
  parts = trainable.split(variables)
  opt = optax.adam(1e-4)
  state = opt.init(parts.trainable)
  assert _n_values(state) == 2 * 9600 + 1  # mu, nu, count


def test_bad_selectors_fail_clearly():
  with pytest.raises(ValueError, match="cannot parse selector"):
    trainable.parse_selector("bn_only")
  with pytest.raises(ValueError, match="percentage"):
    trainable.Selector("fraction", cnn=120, bn=0)
  with pytest.raises(ValueError, match="no BatchNorm"):
    trainable.selected_paths({"params": {"decoder": {"w": {"kernel": np.zeros(1)}}}},
                             trainable.Selector())
