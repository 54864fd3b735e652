"""The model registry, `Network`, and weights directories (`load_weights` validation).

References: MonoDepth2's disp_to_depth written out here; hand-counted ResNet-18 layers (20 BN);
each bad weights directory must give one WeightsError naming the file.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pitta_jax.checkpoint import WeightsError, load_weights, save_weights
from pitta_jax.models.depth_decoder import DepthNet
from pitta_jax.models.random_init import random_monodepth2_variables
from pitta_jax.models.registry import MODELS, get_spec, network

H, W = 64, 96


@pytest.fixture(scope="module")
def variables():
  return random_monodepth2_variables(0)


@pytest.fixture(scope="module")
def weights_dir(tmp_path_factory, variables):
  root = tmp_path_factory.mktemp("w") / "r18"
  save_weights(root, "monodepth2", {"num_layers": 18, "height": H, "width": W}, variables)
  return root


def test_registry_lists_monodepth2_and_rejects_unknown_names():
  assert "monodepth2" in MODELS and get_spec("monodepth2").output == "sigmoid_disparity"
  with pytest.raises(ValueError, match="unknown model 'resnet'.*monodepth2"):
    get_spec("resnet")


def test_network_depth_is_monodepth2_disp_to_depth(variables):
  net = network("monodepth2", {"num_layers": 18})
  x = jnp.asarray(np.random.default_rng(0).uniform(size=(1, H, W, 3)), jnp.float32)
  disp = np.asarray(DepthNet(18).apply(variables, x, train=False)[0][..., 0], np.float64)
  want = 1.0 / (1.0 / 100.0 + (1.0 / 0.1 - 1.0 / 100.0) * disp)  # MonoDepth2, min 0.1, max 100
  np.testing.assert_allclose(np.asarray(net.depth(variables, x, False)), want, rtol=1e-5)


def test_capture_returns_every_encoder_batchnorm_output(variables):
  net = network("monodepth2", {"num_layers": 18})
  x = jnp.zeros((1, H, W, 3), jnp.float32)
  _, acts = net.capture(variables, x, False, r"encoder/(bn1|.*/(bn\d|downsample_bn))")
  assert len(acts) == 20  # ResNet-18: stem + 16 block BNs + 3 downsample BNs
  assert list(acts)[0] == "encoder/bn1" and acts["encoder/bn1"].shape == (1, H // 2, W // 2, 64)


def test_forward_order_starts_at_the_stem():
  order = network("monodepth2", {"num_layers": 18}).forward_order()
  assert order[:3] == ["encoder/conv1", "encoder/bn1", "encoder/layer1_0/conv1"]
  assert order.index("encoder/layer2_0/conv2") < order.index("encoder/layer2_0/downsample_conv")


def test_load_weights_round_trip(weights_dir, variables):
  w = load_weights(weights_dir)
  assert w.spec.name == "monodepth2" and (w.height, w.width) == (H, W)
  for a, b in zip(jax.tree_util.tree_leaves(w.depth), jax.tree_util.tree_leaves(variables)):
    np.testing.assert_array_equal(a, np.asarray(b, np.float32))


def _edit_json(root, **changes):
  meta = json.loads((root / "model.json").read_text())
  meta.update(changes)
  (root / "model.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("change,match", [
    ({"height": "64"}, "height must be a positive integer"),
    ({"height": 70}, "multiples of 32"),
    ({"architecture": "resnet"}, "architecture 'resnet' is not one of"),
    ({"num_layers": 34}, "does not match the network in model.json"),
    ({"architecture": ["monodepth2"]}, re.escape("architecture ['monodepth2'] is not one of")),
    ({"has_pose": "no"}, "has_pose must be true or false, got 'no'"),
    ({"use_stereo": 1}, "use_stereo must be true or false, got 1"),
    ({"architecture": "monovit", "num_layers": [1, 3, 6, 3], "num_heads": [0, 0, 0, 0]},
     "cannot build the network it describes .ZeroDivisionError"),
    # the text "18" printed as 18 ("must be one of [18, 34, 50], got 18"), and the pose
    # network's depth was checked only once its tree loaded
    ({"num_layers": 18.0}, re.escape("num_layers must be one of [18, 34, 50], got 18.0")),
    ({"has_pose": True, "pose_num_layers": "18"},
     re.escape("pose_num_layers must be one of [18, 34, 50], got '18'")),
])
def test_bad_model_json_is_one_error_naming_the_file(weights_dir, tmp_path, change, match):
  import shutil
  root = tmp_path / "w"
  shutil.copytree(weights_dir, root)
  _edit_json(root, **change)
  with pytest.raises(WeightsError, match=re.escape(str(root)) + ".*" + match):
    load_weights(root)


def test_not_an_object_corrupt_or_nonfinite_weights(weights_dir, tmp_path, variables):
  import shutil
  root = tmp_path / "list"
  shutil.copytree(weights_dir, root)
  (root / "model.json").write_text("[1, 2]")
  with pytest.raises(WeightsError, match="expected a JSON object"):
    load_weights(root)
  bad = jax.tree_util.tree_map(np.array, variables)
  bad["params"]["encoder"]["bn1"]["scale"][0] = np.nan
  save_weights(tmp_path / "nan", "monodepth2", {"num_layers": 18, "height": H, "width": W}, bad)
  with pytest.raises(WeightsError, match="encoder/bn1/scale holds non-finite"):
    load_weights(tmp_path / "nan")
  corrupt = tmp_path / "corrupt"
  shutil.copytree(weights_dir, corrupt)
  for f in (corrupt / "depth").rglob("*"):
    if f.is_file():
      f.write_bytes(b"garbage")
  with pytest.raises(WeightsError, match="cannot read the checkpoint"):
    load_weights(corrupt)


def test_a_truncated_data_file_is_one_line_without_tracebacks(weights_dir, tmp_path):
  """Orbax's asynchronous restore reports a truncated value, but the reads still in flight
  print tracebacks from tensorstore's threads; the weights are checked synchronously first."""
  import shutil
  import subprocess
  import sys
  bad = tmp_path / "truncated"
  shutil.copytree(weights_dir, bad)
  data = sorted(f for f in (bad / "depth").rglob("*") if f.is_file() and "/d/" in str(f))
  for f in data:  # every data file: reads fail in several of orbax's concurrent restores
    f.write_bytes(f.read_bytes()[:10])
  proc = subprocess.run([sys.executable, "-c", "import sys; from pitta_jax.checkpoint import "
                         "load_weights; load_weights(sys.argv[1])", str(bad)],
                        capture_output=True, text=True)
  assert proc.returncode == 1 and "WeightsError" in proc.stderr
  assert proc.stderr.count("Traceback") == 1 and "Event loop is closed" not in proc.stderr


JIT_INIT_SCRIPT = """
import flax.linen as nn, jax, jax.numpy as jnp, numpy as np
from pitta_jax.models.random_init import jit_init

class Net(nn.Module):
  @nn.compact
  def __call__(self, x):                                     # (1, 8, 12, 3)
    x = nn.Conv(8, (3, 3))(x)                                # lecun_normal: truncated normal
    x = nn.BatchNorm(use_running_average=False)(x)
    x = nn.Conv(4, (3, 3), kernel_init=nn.initializers.variance_scaling(
        2.0, "fan_out", "normal"), bias_init=nn.initializers.normal(0.1))(x)
    return nn.Dense(3, kernel_init=nn.initializers.he_uniform(),
                    bias_init=nn.initializers.uniform(0.2))(x)

x = jnp.zeros((1, 8, 12, 3), jnp.float32)
default_init = jax.jit(Net().init)  # one compile for both keys (jit_init compiles per call)
for key in (jax.random.PRNGKey(0), jax.random.fold_in(jax.random.PRNGKey(0), 1)):
  ours, default = jit_init(Net(), key, x), default_init(key, x)
  assert jax.tree_util.tree_structure(ours) == jax.tree_util.tree_structure(default)
  for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(default)):
    assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
print("bitwise")
"""


def test_jit_init_draws_bitwise_what_the_default_compile_draws():
  """`jit_init` compiles an init at optimisation level 1 on the CPU: the threefry bits and the
  initialisers' float transforms (truncated normal, normal, uniform, BN constants) must come out
  as under `jax.jit(module.init)` at XLA's default level, or `train-source` would not reproduce
  a seed. In a subprocess without XLA_FLAGS: the suite compiles its own programs with other
  code-generation flags (tests/conftest.py), and XLA's defaults are what a user gets."""
  env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
  env["JAX_PLATFORMS"] = "cpu"
  proc = subprocess.run([sys.executable, "-c", JIT_INIT_SCRIPT], env=env, capture_output=True,
                        text=True, timeout=300)
  assert proc.returncode == 0 and proc.stdout.strip() == "bitwise", proc.stderr[-4000:]


def test_networks_refuse_integer_and_channels_first_images():
  """An 8-bit image made the normalisation constants 8-bit too ((x - 0) / 0: every depth NaN,
  silently); an NCHW batch was reported as an unsupported input size ('96x3')."""
  from pitta_jax.models.registry import network
  net = network("monodepth2", {"num_layers": 18})
  with pytest.raises(TypeError, match="images must be floating RGB in \\[0, 1\\], got uint8"):
    net.depth({}, np.zeros((1, 64, 96, 3), np.uint8), False)
  with pytest.raises(ValueError, match=r"\(B, H, W, 3\) NHWC batch, got shape \(1, 3, 64, 96\) "
                                       r"\(NCHW\? move the channels last\)"):
    net.outputs({}, np.zeros((1, 3, 64, 96), np.float32), False)
  with pytest.raises(ValueError, match=r"got shape \(64, 96, 3\)"):
    net.capture({}, np.zeros((64, 96, 3), np.float32), False, "encoder/.*")



def test_an_array_of_the_wrong_shape_is_named(variables, tmp_path):
  """A weights file whose array names all fit but one array has another shape (a damaged or
  hand-edited file): one error naming the file, the array and both shapes."""
  import copy
  bad = copy.deepcopy(jax.tree_util.tree_map(np.asarray, variables))
  bad["params"]["encoder"]["bn1"]["scale"] = bad["params"]["encoder"]["bn1"]["scale"][:32]
  save_weights(tmp_path / "w", "monodepth2", {"num_layers": 18, "height": H, "width": W}, bad)
  with pytest.raises(WeightsError, match=r"encoder/bn1/scale has shape \(32,\), the network in "
                                         r"model\.json expects \(64,\)"):
    load_weights(tmp_path / "w")


def test_model_json_without_a_size_is_the_released_size_and_a_boolean_size_is_refused(
    weights_dir, tmp_path):
  """A model.json without height/width describes MonoDepth2's released mono_640x192 weights
  (H 192, W 640); JSON `true` is no height, although Python's bool is an int."""
  import shutil
  root = tmp_path / "w"
  shutil.copytree(weights_dir, root)
  meta = json.loads((root / "model.json").read_text())
  del meta["height"], meta["width"]
  (root / "model.json").write_text(json.dumps(meta))
  w = load_weights(root)
  assert (w.height, w.width) == (192, 640)
  _edit_json(root, height=True)
  with pytest.raises(WeightsError, match=re.escape(str(root)) + r".*height must be a positive "
                                         r"integer, got True"):
    load_weights(root)


def test_weights_the_loader_would_refuse_are_not_written(variables, tmp_path):
  """save_weights checks the input size before writing anything (no directory is left); a tree
  with an array the network does not have is refused on loading, named."""
  with pytest.raises(ValueError, match=r"input size 100x64 .* multiples of 32"):
    save_weights(tmp_path / "odd", "monodepth2", {"num_layers": 18, "height": 64, "width": 100},
                 variables)
  assert not (tmp_path / "odd").exists()
  extra = jax.tree_util.tree_map(np.asarray, variables)
  extra = {**extra, "params": {**extra["params"], "extra": {"kernel": np.zeros((1, 1), np.float32)}}}
  save_weights(tmp_path / "extra", "monodepth2", {"num_layers": 18, "height": H, "width": W}, extra)
  with pytest.raises(WeightsError, match=r"0 missing, 1 unexpected arrays, e\.g\. "
                                         r"\['params/extra/kernel'\]"):
    load_weights(tmp_path / "extra")


def test_input_size_rule_on_each_side_and_its_bound():
  """Both sides must be multiples of size_multiple (32 for MonoDepth2); the largest side taken is
  MAX_SIDE = 16384 pixels itself, on either side."""
  from pitta_jax.models.spec import MAX_SIDE
  spec = get_spec("monodepth2")
  with pytest.raises(ValueError, match=r"input size 100x64 \(WxH\) .* multiples of 32"):
    spec.check_size(64, 100)
  assert MAX_SIDE == 16384
  spec.check_size(32, 16384)
  spec.check_size(16384, 32)
  for h, w in ((32, 16384 + 32), (16384 + 32, 32)):
    with pytest.raises(ValueError, match=r"more than 16384 pixels on a side"):
      spec.check_size(h, w)


def test_a_network_of_ones_own_must_return_its_maps_as_the_spec_says():
  """ModelSpec's contract: `module.apply` returns a tuple of (B, H, W, 1) maps, full resolution
  first. `Network.depth` reads `outputs[0][..., 0]`, so a module returning one bare (B, H, W, 1)
  array gave image 0's map as the depth of the whole batch, (H, W), and one returning (B, H, W)
  maps the first column of each image, (B, H): no error, wrong depths. Reference: the
  contract-abiding module's depth, disp_to_depth of its own map, per image."""
  import flax.linen as nn
  from pitta_jax.models.registry import Network
  from pitta_jax.models.spec import ModelSpec

  class Net(nn.Module):
    form: str

    @nn.compact
    def __call__(self, images, train=False):
      disp = nn.sigmoid(nn.Conv(1, (3, 3), name="head")(images))     # (B, H, W, 1)
      return {"bare": disp, "no_channel": (disp[..., 0],), "list": [disp, disp[:, ::2, ::2]],
              "low_first": (disp[:, ::2, ::2], disp), "empty": ()}[self.form]

  images = np.random.default_rng(0).random((2, 8, 16, 3)).astype(np.float32)
  variables = Net("list").init(jax.random.PRNGKey(0), images)
  spec = ModelSpec("mine", build=lambda config: Net("list"), output="sigmoid_disparity",
                   size_multiple=8, default_size=(8, 16))
  disp = np.asarray(Net("list").apply(variables, images)[0])[..., 0]  # (2, 8, 16)
  want = 1 / (1 / 100 + (1 / 0.1 - 1 / 100) * disp.astype(np.float64))
  got = Network(spec, Net("list")).depth(variables, images, False)
  assert got.shape == (2, 8, 16)
  np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)
  for form, what in (("bare", r"one array of shape \(2, 8, 16, 1\), not a tuple"),
                     ("no_channel", r"a first map of shape \(2, 8, 16\)"),
                     ("low_first", r"a first map of shape \(2, 4, 8, 1\)"),
                     ("empty", r"tuple \(\)")):
    net = Network(spec, Net(form))
    for call in (lambda: net.depth(variables, images, False),
                 lambda: jax.jit(net.outputs, static_argnums=2)(variables, images, False),
                 lambda: net.capture(variables, images, False, "head")):
      with pytest.raises(ValueError, match=r"network mine: module.apply must return a tuple of "
                                           r"\(B, H, W, 1\) maps, the full-resolution one "
                                           rf"\(2, 8, 16, 1\) first .*got {what}"):
        call()
