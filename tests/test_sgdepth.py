"""Parity of the Flax SGDepth depth network + `weights_convert.sgdepth` with a PyTorch SGDepth.

Reference: `tests/torch_sgdepth.py`, upstream's multi-task module tree with upstream's state_dict
names, random weights and BN statistics, saved with `torch.save(model.state_dict())` as upstream's
`model.pth`, converted without torch and compared output by output at 96x64 (the network needs
multiples of 32). Tolerances: 1e-4 max abs on disparities (float32), 1e-9 relative on float64
gradients (rounding: measured 3e-14).
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from flax.traverse_util import flatten_dict, unflatten_dict

import torch_monodepth2 as tm
import torch_sgdepth as ts
from pitta_jax.models.sgdepth import SPEC, SGDepthNet
from weights_convert import sgdepth as conv
from weights_convert.pth import CheckpointError

torch.set_num_threads(2)
H, W = 64, 96


def _save(root, split_pos=1, resolutions=4, seed=0, grad_scale_depth=1.0, legacy=False):
  """A random upstream SGDepth saved as upstream saves it; returns (module, model.pth path).

  legacy: torch's pre-1.6 serialisation, which the released files (PyTorch 1.1) use.
  """
  model = ts.SGDepth(split_pos=split_pos, resolutions_depth=resolutions,
                     grad_scale_depth=grad_scale_depth)
  tm.randomize_(model, seed)
  root.mkdir(parents=True, exist_ok=True)
  path = root / "model.pth"
  torch.save(model.state_dict(), path, _use_new_zipfile_serialization=not legacy)
  return model.eval(), path


def _image(seed, batch=1, h=H, w=W):
  return np.random.default_rng(seed).uniform(0, 1, (batch, h, w, 3)).astype(np.float32)


def _torch_disps(model, x):
  with torch.no_grad():
    out = model.depth_outputs(torch.from_numpy(x).permute(0, 3, 1, 2))
  return [d.permute(0, 2, 3, 1).numpy() for d in out]


@pytest.fixture(scope="module")
def released(tmp_path_factory):
  """The released layout: split position 1, 4 depth resolutions, ResNet-18, legacy format."""
  model, path = _save(tmp_path_factory.mktemp("sgdepth"), legacy=True)
  config, variables = conv.convert_sgdepth(path)
  return {"torch": model, "path": path, "config": config, "variables": variables}


@pytest.fixture(scope="module")
def fns():
  net = SGDepthNet(18, 4)
  return (jax.jit(lambda v, x: net.apply(v, x, train=False)),
          jax.jit(lambda v, x: net.apply(v, x, train=True, mutable=["batch_stats"])))


def test_config_and_keys(released):
  """model.pth holds seg.* and pose.* (declared ignorable) and no fc.*; the config is complete."""
  keys = list(torch.load(released["path"]))
  assert any(k.startswith("seg.") for k in keys) and any(k.startswith("pose.") for k in keys)
  assert not any(".fc." in k for k in keys)
  assert released["config"] == {"num_layers": 18, "num_scales": 4, "height": 192, "width": 640}
  assert isinstance(SPEC.build(released["config"]), SGDepthNet)
  json.dumps(released["config"])


def test_eval_mode_disparities_match_torch(released, fns):
  x = _image(1)
  ref = _torch_disps(released["torch"], x)
  out = fns[0](released["variables"], x)
  assert len(out) == 4
  for s in range(4):
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref[s])))
    print(f"sgdepth eval {W}x{H} scale {s}: max abs diff {diff:.2e}")
    assert out[s].shape == ref[s].shape == (1, H >> s, W >> s, 1)
    assert diff < 1e-4


def test_train_mode_bn_matches_torch(released, fns):
  """Batch statistics to normalise; the running estimates after one momentum-0.1 update."""
  model = ts.SGDepth(grad_scale_depth=1.0)
  model.load_state_dict(torch.load(released["path"]))
  model.train()
  x = _image(2, batch=2)
  ref = _torch_disps(model, x)
  out, new_vars = fns[1](released["variables"], x)
  for s in range(4):
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref[s])))
    print(f"sgdepth train-BN {W}x{H} scale {s}: max abs diff {diff:.2e}")
    assert diff < 1e-4
  bn = model.common.encoder.encoder.layer3[1].bn2
  got = new_vars["batch_stats"]["encoder"]["layer3_1"]["bn2"]
  d_mean = float(np.max(np.abs(np.asarray(got["mean"]) - bn.running_mean.numpy())))
  d_var = float(np.max(np.abs(np.asarray(got["var"]) - bn.running_var.numpy())
                       / bn.running_var.numpy()))
  print(f"sgdepth running mean max abs diff {d_mean:.2e}, var max rel diff {d_var:.2e}")
  assert d_mean < 1e-4 and d_var < 1e-4


def test_encoder_bn_gradient_matches_torch_float64(released):
  """d(sum_s mean(w_s * disp_s)) / d(encoder BN gamma, beta), train-mode BN, float64 both sides.

  The torch model's depth ScaledSplit weight is 1 (upstream trains with 0.9-0.95 and evaluates
  with 0; a constant factor on the shared part's gradient, not part of the depth function).
  """
  h, w = 64, 64
  x = _image(3, batch=2, h=h, w=w)
  rng = np.random.default_rng(4)
  weights = [rng.normal(size=(2, h >> s, w >> s, 1)) for s in range(4)]

  model = ts.SGDepth(grad_scale_depth=1.0)
  model.load_state_dict(torch.load(released["path"]))
  model = model.double().train()
  out = model.depth_outputs(torch.from_numpy(x).double().permute(0, 3, 1, 2))
  loss_t = sum((d.permute(0, 2, 3, 1) * torch.from_numpy(w)).mean() for d, w in zip(out, weights))
  loss_t.backward()
  ref = tm.bn_grads(model.common.encoder)

  with jax.enable_x64(True):
    loss_j, got = encoder_bn_grads(SGDepthNet(18, 4), released["variables"], x, weights)
  assert set(got) == set(ref) and len(ref) == 40
  rel = max(float(np.max(np.abs(got[k] - ref[k])) / np.max(np.abs(ref[k]))) for k in ref)
  print(f"sgdepth loss float64 jax {loss_j:.12f} torch {loss_t.item():.12f}; encoder BN "
        f"gamma/beta grads worst max-relative diff over 40 leaves: {rel:.2e}")
  np.testing.assert_allclose(loss_j, loss_t.item(), rtol=1e-10)
  assert rel < 1e-9


def encoder_bn_grads(net, variables, x, weights):
  """float64 loss sum_s mean(w_s * disp_s) and its gradient w.r.t. the encoder's BN scale/bias
  (train-mode BN), keyed `layer1_0/bn1/scale`...; call under `jax.enable_x64(True)`.

  Only the BN leaves are differentiated (the rest enter as a second argument), which keeps the
  compiled program to what the check needs.
  """
  flat = {k: jnp.asarray(a, jnp.float64) for k, a in flatten_dict(variables["params"], sep="/").items()}
  is_bn = lambda k: k.startswith("encoder/") and k.rsplit("/", 1)[1] in ("scale", "bias")
  bn = {k: a for k, a in flat.items() if is_bn(k)}
  rest = {k: a for k, a in flat.items() if not is_bn(k)}
  stats = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), variables["batch_stats"])

  def loss_fn(bn, rest, x):
    params = unflatten_dict({**bn, **rest}, sep="/")
    disps = net.apply({"params": params, "batch_stats": stats}, x, train=True)
    return sum(jnp.mean(d * w) for d, w in zip(disps, weights))

  loss, grads = jax.jit(jax.value_and_grad(loss_fn))(
      bn, rest, jnp.asarray(x, jnp.float64))
  return float(loss), {k[len("encoder/"):]: np.asarray(g) for k, g in grads.items()}


def test_other_split_position(tmp_path, fns):
  """A model trained with --model-split-pos 2: 3 decoder steps in common.decoder, 7 in depth."""
  model, path = _save(tmp_path, split_pos=2, seed=5)
  assert conv.infer_split(torch.load(path), str(path)) == 3
  config, variables = conv.convert_sgdepth(path, height=96, width=320)
  assert config == {"num_layers": 18, "num_scales": 4, "height": 96, "width": 320}
  x = _image(6)
  out, ref = fns[0](variables, x), _torch_disps(model, x)
  diff = max(float(np.max(np.abs(np.asarray(o) - r))) for o, r in zip(out, ref))
  print(f"sgdepth split 2, eval: max abs diff {diff:.2e}")
  assert diff < 1e-4


def test_fewer_depth_resolutions(tmp_path):
  """--model-depth-resolutions 1: one head (depth.multires.convs.0, full resolution)."""
  _, path = _save(tmp_path, resolutions=1, seed=6)
  config, variables = conv.convert_sgdepth(path)
  assert config["num_scales"] == 1
  heads = [k for k in variables["params"]["decoder"] if k.startswith("dispconv")]
  assert heads == ["dispconv_0"]


def test_run_writes_a_weights_directory(released, tmp_path):
  from pitta_jax.checkpoint import load_tree
  parser = argparse.ArgumentParser()
  conv.add_arguments(parser)
  out = conv.run(parser.parse_args(["--model", str(released["path"]), "--out", str(tmp_path / "w")]))
  meta = json.loads((out / "model.json").read_text())
  assert meta["architecture"] == "sgdepth" and meta["num_layers"] == 18
  assert (meta["height"], meta["width"]) == (192, 640)
  loaded = load_tree(out / "depth")
  for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(released["variables"])):
    np.testing.assert_array_equal(a, b)


def test_input_size_rule(released):
  with pytest.raises(ValueError, match="multiples of 32"):
    SGDepthNet().apply(released["variables"], np.zeros((1, 100, 96, 3), np.float32))


def test_unexpected_missing_and_misshapen_keys_are_named(released, tmp_path):
  state = torch.load(released["path"])
  bad = dict(state, **{"depth.decoder.blocks.step_1.extra": torch.zeros(1)})
  torch.save(bad, tmp_path / "extra.pth")
  with pytest.raises(CheckpointError, match=r"1 unexpected keys: depth.decoder.blocks.step_1.extra"):
    conv.convert_sgdepth(tmp_path / "extra.pth")
  bad = {k: v for k, v in state.items() if k != "depth.multires.convs.2.bias"}
  torch.save(bad, tmp_path / "missing.pth")
  with pytest.raises(CheckpointError, match=r"1 missing keys: depth.multires.convs.2.bias"):
    conv.convert_sgdepth(tmp_path / "missing.pth")
  bad = dict(state, **{"common.decoder.blocks.step_0.conv.weight": torch.zeros(256, 512, 1, 1)})
  torch.save(bad, tmp_path / "wrong.pth")
  with pytest.raises(CheckpointError,
                     match=r"common.decoder.blocks.step_0.conv.weight has shape \(256, 512, 1, 1\)"):
    conv.convert_sgdepth(tmp_path / "wrong.pth")


def test_a_file_of_another_network_is_named(released, tmp_path):
  """MonoDepth2's encoder.pth (as upstream's trainer saves it: the ResnetEncoder's state_dict and
  the training size) given to the SGDepth converter, and SGDepth's model.pth given as MonoDepth2's
  encoder: each message names what the file looks like and the converter that reads it (the
  first said 'is it a decoder?' of a file holding encoder keys)."""
  from weights_convert.monodepth2 import convert_monodepth2
  from weights_convert.strict import check_keys
  encoder = tm.ResnetEncoder(18)
  md2 = tmp_path / "encoder.pth"
  torch.save({**encoder.state_dict(), "height": 192, "width": 640, "use_stereo": False}, md2)
  with pytest.raises(CheckpointError, match=rf"^{md2}: not an SGDepth model\.pth \(no "
                     r"common\.encoder\.encoder\.\* keys\); its keys look like a ResNet "
                     r"encoder\.pth \(`pitta-jax convert monodepth2 --encoder`\)$"):
    conv.convert_sgdepth(md2)
  with pytest.raises(CheckpointError, match=r"holds no ResNet encoder .*: its keys look like "
                     r"SGDepth's model\.pth \(`pitta-jax convert sgdepth`\)$"):
    convert_monodepth2(released["path"], md2)
  # a key list is cut after 8 names per kind, and the file's look is named
  present = [f"convs.X_0{i}_Conv_0.conv.conv.weight" for i in range(10)]
  with pytest.raises(CheckpointError) as info:
    check_keys("depth.pth", present, ["decoder.0.conv.conv.weight"], lambda k: False)
  assert str(info.value) == (
      "depth.pth: 10 unexpected keys: " + ", ".join(present[:8]) + ", ... and 2 more; 1 missing "
      "keys: decoder.0.conv.conv.weight (1 keys expected); its keys look like an HR-Depth or "
      "MonoViT depth.pth (`pitta-jax convert hrdepth` / `monovit`)")


def test_a_stereo_release_without_pose_files_says_so(tmp_path):
  """MonoDepth2's stereo_640x192 ships no pose network: the README's command with its pose flags
  says to leave them out (was: pose_encoder.pth: no such file)."""
  from weights_convert.monodepth2 import convert_monodepth2
  encoder = tmp_path / "encoder.pth"
  torch.save({**tm.ResnetEncoder(18).state_dict(), "height": 192, "width": 640,
              "use_stereo": True}, encoder)
  with pytest.raises(CheckpointError, match=r"pose_encoder\.pth: no such file; a stereo-trained "
                     r"release .* leave out --pose-encoder and --pose"):
    convert_monodepth2(encoder, tmp_path / "depth.pth", tmp_path / "pose_encoder.pth",
                       tmp_path / "pose.pth")


def test_more_than_four_disparity_heads_are_refused(released, tmp_path):
  """Upstream's depth resolutions are 1..4 (MonoDepth2's four scales): a fifth head
  `depth.multires.convs.4` is refused, named, rather than converted into a network with
  a scale the decoder does not have."""
  state = torch.load(released["path"])
  fifth = {k.replace("convs.3.", "convs.4."): v for k, v in state.items()
           if k.startswith("depth.multires.convs.3.")}
  torch.save({**state, **fifth}, tmp_path / "five.pth")
  with pytest.raises(CheckpointError, match=r"five\.pth: depth\.multires\.convs holds heads "
                                            r"\[0, 1, 2, 3, 4\], expected 0\.\.n-1 with n in 1\.\.4"):
    conv.convert_sgdepth(tmp_path / "five.pth")


def test_decoder_steps_must_split_once_and_stray_keys_are_named(released, tmp_path):
  """The ten PartialDecoder steps are common.decoder 0..k-1 then depth.decoder k..9: a file
  without the depth branch's last step is named as not SGDepth's layout (rather than listed as
  missing keys), and a stray key under that last step is an unexpected key like any other."""
  state = torch.load(released["path"])
  torch.save({k: v for k, v in state.items()
              if not k.startswith("depth.decoder.blocks.step_9.")}, tmp_path / "nine.pth")
  with pytest.raises(CheckpointError, match=r"nine\.pth: decoder steps common\.decoder \[0\] \+ "
                                            r"depth\.decoder \[1, 2, 3, 4, 5, 6, 7, 8\] are not "
                                            r"0\.\.k-1 and k\.\.9"):
    conv.convert_sgdepth(tmp_path / "nine.pth")
  torch.save(dict(state, **{"depth.decoder.blocks.step_9.extra": torch.zeros(1)}),
             tmp_path / "stray.pth")
  with pytest.raises(CheckpointError, match=r"1 unexpected keys: depth\.decoder\.blocks\.step_9\."
                                            r"extra"):
    conv.convert_sgdepth(tmp_path / "stray.pth")


def test_every_converter_names_a_file_of_another_network(tmp_path):
  """The README: "A file given to the wrong converter is named for what it looks like". A
  MonoDepth2 encoder.pth given to the Lite-Mono, MonoViT, Depth Anything V2 and Mask2Former
  converters was refused as 'not a ...' without saying what it is (only the strict key check
  and the MonoDepth2 and SGDepth converters named it)."""
  from weights_convert.depth_anything_v2 import convert_depth_anything_v2
  from weights_convert.litemono import convert_litemono
  from weights_convert.mask2former import convert_mask2former
  from weights_convert.monovit import convert_monovit
  md2 = tmp_path / "encoder.pth"
  torch.save({"encoder.conv1.weight": torch.zeros(4, 3, 7, 7), "height": 64, "width": 96}, md2)
  depth = tmp_path / "depth.pth"
  torch.save({"decoder.0.conv.conv.weight": torch.zeros(4, 4, 3, 3)}, depth)
  named = r"its keys look like a ResNet encoder\.pth \(`pitta-jax convert monodepth2 --encoder`\)"
  for convert in (lambda: convert_litemono(md2, depth), lambda: convert_monovit(md2, depth),
                  lambda: convert_depth_anything_v2(md2, "official"),
                  lambda: convert_depth_anything_v2(md2, "hf"),
                  lambda: convert_mask2former(md2, "hf"),
                  lambda: convert_mask2former(md2, "detectron2")):
    with pytest.raises(CheckpointError, match=named):
      convert()
  # MonoDepth2's depth.pth given to HR-Depth's converter: a list of 20 missing twins, unnamed
  from weights_convert.hrdepth import convert_hrdepth
  torch.save({**tm.ResnetEncoder(18).state_dict(), "height": 64, "width": 96}, md2)
  with pytest.raises(CheckpointError, match=r"its keys look like a MonoDepth2 depth\.pth "
                                            r"\(`pitta-jax convert monodepth2 --depth`\)$"):
    convert_hrdepth(md2, depth)
