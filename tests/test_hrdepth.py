"""Parity of the Flax HR-Depth + `weights_convert.hrdepth` with a PyTorch HR-Depth.

Reference: MonoDepth2's PyTorch encoder (`tests/torch_monodepth2.py`) + `tests/torch_hrdepth.py`
(upstream's decoder, its `convs` ModuleDict also registered as the `decoder` ModuleList), random
weights and BN statistics, saved as upstream's `encoder.pth` (with `height`, `width`,
`use_stereo`) and `depth.pth` (every decoder tensor under both names), converted without torch
and compared output by output at 96x64. Tolerances: 1e-4 max abs on disparities (float32), 1e-9
relative on float64 gradients (rounding: measured 3.5e-14).
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np
import pytest
import torch

import torch_hrdepth as th
import torch_monodepth2 as tm
from pitta_jax.models.hrdepth import SPEC, HRDepthNet
from test_sgdepth import encoder_bn_grads
from weights_convert import hrdepth as conv
from weights_convert.pth import CheckpointError

torch.set_num_threads(2)
H, W = 64, 96
TRAIN_SIZE = (320, 1024)  # written into encoder.pth: the converter must take it from there
METADATA = ("height", "width", "use_stereo")


def _image(seed, batch=1, h=H, w=W):
  return np.random.default_rng(seed).uniform(0, 1, (batch, h, w, 3)).astype(np.float32)


def _load_torch(root):
  """Fresh torch modules from the saved files (train mode mutates running statistics)."""
  enc, dec = tm.ResnetEncoder(18), th.HRDepthDecoder(tm.num_ch_enc(18))
  enc.load_state_dict({k: v for k, v in torch.load(root / "encoder.pth").items()
                       if k not in METADATA})
  dec.load_state_dict(torch.load(root / "depth.pth"))
  return enc, dec


def _torch_disps(enc, dec, x):
  out = dec(enc(torch.from_numpy(x).permute(0, 3, 1, 2)))
  return [out[("disparity", f"Scale{s}")].permute(0, 2, 3, 1) for s in range(4)]


@pytest.fixture(scope="module")
def released(tmp_path_factory):
  root = tmp_path_factory.mktemp("hrdepth")
  enc, dec = tm.ResnetEncoder(18), th.HRDepthDecoder(tm.num_ch_enc(18))
  tm.randomize_(enc, 0)
  tm.randomize_(dec, 1)
  enc_state = dict(enc.state_dict())
  enc_state.update(height=TRAIN_SIZE[0], width=TRAIN_SIZE[1], use_stereo=True)
  # torch's pre-1.6 serialisation, as the released files (PyTorch 1.5); in it the two names of a
  # decoder tensor share one storage
  torch.save(enc_state, root / "encoder.pth", _use_new_zipfile_serialization=False)
  torch.save(dec.state_dict(), root / "depth.pth", _use_new_zipfile_serialization=False)
  config, variables = conv.convert_hrdepth(root / "encoder.pth", root / "depth.pth")
  return {"root": root, "torch": (enc.eval(), dec.eval()), "config": config,
          "variables": variables}


@pytest.fixture(scope="module")
def fns():
  net = HRDepthNet(18)
  return (jax.jit(lambda v, x: net.apply(v, x, train=False)),
          jax.jit(lambda v, x: net.apply(v, x, train=True, mutable=["batch_stats"])))


def test_layout_and_config(released):
  """depth.pth stores each layer twice (convs.* and decoder.*), incl. the never-called
  X_0j_Conv_0; the config takes the training size from encoder.pth."""
  keys = list(torch.load(released["root"] / "depth.pth"))
  assert "convs.X_00_Conv_0.conv.conv.weight" in keys and "decoder.0.conv.conv.weight" in keys
  assert len(keys) == 2 * len({k for k in keys if k.startswith("convs.")})
  assert conv.upstream_layers() == list(released["torch"][1].convs.keys())
  assert released["config"] == {"num_layers": 18, "height": 320, "width": 1024}
  json.dumps(released["config"])
  assert isinstance(SPEC.build(released["config"]), HRDepthNet)


def test_eval_mode_disparities_match_torch(released, fns):
  x = _image(1)
  with torch.no_grad():
    ref = [r.numpy() for r in _torch_disps(*released["torch"], x)]
  out = fns[0](released["variables"], x)
  for s in range(4):
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref[s])))
    print(f"hrdepth eval {W}x{H} scale {s}: max abs diff {diff:.2e}")
    assert out[s].shape == ref[s].shape == (1, H >> s, W >> s, 1)
    assert diff < 1e-4


def test_train_mode_bn_matches_torch(released, fns):
  enc, dec = _load_torch(released["root"])
  enc.train(), dec.train()
  x = _image(2, batch=2)
  with torch.no_grad():
    ref = [r.numpy() for r in _torch_disps(enc, dec, x)]
  out, new_vars = fns[1](released["variables"], x)
  for s in range(4):
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref[s])))
    print(f"hrdepth train-BN {W}x{H} scale {s}: max abs diff {diff:.2e}")
    assert diff < 1e-4
  bn = enc.encoder.layer4[0].downsample[1]
  got = new_vars["batch_stats"]["encoder"]["layer4_0"]["downsample_bn"]
  d_mean = float(np.max(np.abs(np.asarray(got["mean"]) - bn.running_mean.numpy())))
  d_var = float(np.max(np.abs(np.asarray(got["var"]) - bn.running_var.numpy())
                       / bn.running_var.numpy()))
  print(f"hrdepth running mean max abs diff {d_mean:.2e}, var max rel diff {d_var:.2e}")
  assert d_mean < 1e-4 and d_var < 1e-4


def test_encoder_bn_gradient_matches_torch_float64(released):
  """d(sum_s mean(w_s * disp_s)) / d(encoder BN gamma, beta), train-mode BN, float64 both sides."""
  h, w = 64, 64
  x = _image(3, batch=2, h=h, w=w)
  rng = np.random.default_rng(4)
  weights = [rng.normal(size=(2, h >> s, w >> s, 1)) for s in range(4)]
  enc, dec = _load_torch(released["root"])
  enc, dec = enc.double().train(), dec.double().train()
  out = _torch_disps(enc, dec, x.astype(np.float64))
  loss_t = sum((d * torch.from_numpy(wt)).mean() for d, wt in zip(out, weights))
  loss_t.backward()
  ref = tm.bn_grads(enc)
  with jax.enable_x64(True):
    loss_j, got = encoder_bn_grads(HRDepthNet(18), released["variables"], x, weights)
  assert set(got) == set(ref) and len(ref) == 40
  rel = max(float(np.max(np.abs(got[k] - ref[k])) / np.max(np.abs(ref[k]))) for k in ref)
  print(f"hrdepth loss float64 jax {loss_j:.12f} torch {loss_t.item():.12f}; encoder BN "
        f"gamma/beta grads worst max-relative diff over 40 leaves: {rel:.2e}")
  np.testing.assert_allclose(loss_j, loss_t.item(), rtol=1e-10)
  assert rel < 1e-9


def test_run_writes_a_weights_directory(released, tmp_path):
  from pitta_jax.checkpoint import load_tree
  root = released["root"]
  parser = argparse.ArgumentParser()
  conv.add_arguments(parser)
  out = conv.run(parser.parse_args(["--encoder", str(root / "encoder.pth"),
                                    "--depth", str(root / "depth.pth"), "--out", str(tmp_path / "w")]))
  meta = json.loads((out / "model.json").read_text())
  assert meta["architecture"] == "hrdepth"
  assert (meta["num_layers"], meta["height"], meta["width"]) == (18, 320, 1024)
  loaded = load_tree(out / "depth")
  for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(released["variables"])):
    np.testing.assert_array_equal(a, b)


def test_input_size_rule(released):
  with pytest.raises(ValueError, match="multiples of 32"):
    HRDepthNet().apply(released["variables"], np.zeros((1, 64, 100, 3), np.float32))


def _convert_with(tmp_path, released, name, state):
  torch.save(state, tmp_path / name)
  return conv.convert_hrdepth(released["root"] / "encoder.pth", tmp_path / name)


def test_unexpected_missing_and_misshapen_keys_are_named(released, tmp_path):
  state = torch.load(released["root"] / "depth.pth")
  with pytest.raises(CheckpointError, match=r"1 unexpected keys: convs.X_13_attention.fc.1.weight"):
    _convert_with(tmp_path, released, "extra.pth",
                  dict(state, **{"convs.X_13_attention.fc.1.weight": torch.zeros(1)}))
  # X_12_downsample is decoder.25: drop both copies
  missing = {k: v for k, v in state.items()
             if k not in ("convs.X_12_downsample.conv.weight", "decoder.25.conv.weight")}
  with pytest.raises(CheckpointError, match=r"1 missing keys: convs.X_12_downsample.conv.weight"):
    _convert_with(tmp_path, released, "missing.pth", missing)
  wrong = torch.zeros(1, 33, 3, 3)
  with pytest.raises(CheckpointError,
                     match=r"convs.dispConvScale1.conv.weight has shape \(1, 33, 3, 3\)"):
    _convert_with(tmp_path, released, "wrong.pth", dict(state, **{
        "convs.dispConvScale1.conv.weight": wrong, "decoder.30.conv.weight": wrong}))
  enc_state = torch.load(released["root"] / "encoder.pth")
  del enc_state["width"]
  torch.save(enc_state, tmp_path / "encoder.pth")
  with pytest.raises(CheckpointError, match=r"encoder.pth: no 'width' entry"):
    conv.convert_hrdepth(tmp_path / "encoder.pth", released["root"] / "depth.pth")
  # Lite-HR-Depth's encoder (upstream mobilenetV3_encoder: `encoder.features.<i>.*`) is named
  torch.save({"encoder.features.0.0.weight": torch.zeros(16, 3, 3, 3), "height": 384,
              "width": 1280}, tmp_path / "lite_encoder.pth")
  with pytest.raises(CheckpointError, match=r"lite_encoder.pth: a MobileNetV3 encoder "
                                            r"\(Lite-HR-Depth\); only HR-Depth with a ResNet-18/34 encoder"):
    conv.convert_hrdepth(tmp_path / "lite_encoder.pth", released["root"] / "depth.pth")


def test_twins_must_agree(released, tmp_path):
  """A `decoder.<i>` copy that differs from, or lacks, its `convs.<name>` twin is an error, also
  for the never-called X_0j_Conv_0 layers."""
  state = torch.load(released["root"] / "depth.pth")
  changed = dict(state, **{"decoder.16.fc.0.weight": state["decoder.16.fc.0.weight"] + 1})
  with pytest.raises(CheckpointError,
                     match=r"decoder.16.fc.0.weight differs from its twin convs.X_31_attention.fc.0.weight"):
    _convert_with(tmp_path, released, "changed.pth", changed)
  lone = {k: v for k, v in state.items() if k != "decoder.5.conv.conv.bias"}
  with pytest.raises(CheckpointError,
                     match=r"convs.X_01_Conv_0.conv.conv.bias without its twin decoder.5.conv.conv.bias"):
    _convert_with(tmp_path, released, "lone.pth", lone)
  # the never-called layers may be absent altogether (both copies)
  unused = ("X_00_Conv_0", "X_01_Conv_0", "X_02_Conv_0", "X_03_Conv_0")
  idx = [conv.upstream_layers().index(n) for n in unused]
  pruned = {k: v for k, v in state.items()
            if not any(k.startswith(f"convs.{n}.") for n in unused)
            and not any(k.startswith(f"decoder.{i}.") for i in idx)}
  _, variables = _convert_with(tmp_path, released, "pruned.pth", pruned)
  for a, b in zip(jax.tree_util.tree_leaves(variables), jax.tree_util.tree_leaves(released["variables"])):
    np.testing.assert_array_equal(a, b)


def test_a_resnet50_encoder_is_named_as_unsupported(released, tmp_path):
  """HR-Depth's decoder widths fit ResNet-18/34 only: a Bottleneck ResNet-50 encoder.pth (its
  torchvision names: `layer1.0.conv3`, six `layer3` blocks) is refused by name before any key
  table is applied, not reported as a pile of missing and unexpected keys."""
  state = {"encoder.conv1.weight": torch.zeros(64, 3, 7, 7),
           "encoder.layer1.0.conv3.weight": torch.zeros(256, 64, 1, 1),
           **{f"encoder.layer3.{b}.conv1.weight": torch.zeros(1) for b in range(6)},
           "height": 320, "width": 1024, "use_stereo": False}
  torch.save(state, tmp_path / "r50.pth")
  with pytest.raises(CheckpointError, match=r"^\S*r50\.pth: a ResNet-50 encoder; HR-Depth's "
                                            r"decoder fits ResNet-18/34$"):
    conv.convert_hrdepth(tmp_path / "r50.pth", released["root"] / "depth.pth")


def test_only_the_never_called_layers_params_are_ignorable(released, tmp_path):
  """Only the four never-called X_0j_Conv_0 layers' own ConvBlock parameters may be left unused:
  a stray key beside them in the X_0 column (here under X_04_attention, a layer the forward
  uses) is an unexpected key, named."""
  state = torch.load(released["root"] / "depth.pth")
  with pytest.raises(CheckpointError, match=r"1 unexpected keys: convs\.X_04_attention\.fc\.1\."
                                            r"weight"):
    _convert_with(tmp_path, released, "stray.pth",
                  dict(state, **{"convs.X_04_attention.fc.1.weight": torch.zeros(1)}))
