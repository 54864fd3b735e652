"""Parity of the Flax MonoDepth2 + converter with an independent PyTorch MonoDepth2.

Reference: `tests/torch_monodepth2.py`, a PyTorch MonoDepth2 with upstream's state_dict names,
random weights and non-trivial BN statistics, saved with `torch.save` in the zip and the legacy
format, converted by `weights_convert` (which does not use torch), and compared output by output.
Tolerances: 1e-4 max abs on disparities (float32); gradients 1e-9 relative in float64 (both
frameworks compute the same function: what is left is rounding, ~2e-14), and in float32 no
further from the float64 truth than torch's own float32 gradient.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

import torch_monodepth2 as tm
from pitta_jax import trainable
from pitta_jax.checkpoint import load_weights
from pitta_jax.models.depth_decoder import DepthNet
from pitta_jax.models.pose import PoseNet, transformation_from_parameters
from weights_convert.monodepth2 import convert_monodepth2
from weights_convert.pth import CheckpointError

torch.set_num_threads(2)


def _save_mono_folder(root, num_layers: int, legacy: bool, seed: int = 0, height=192, width=640):
  """Writes encoder.pth, depth.pth, pose_encoder.pth, pose.pth as upstream lays them out."""
  enc = tm.ResnetEncoder(num_layers)
  dec = tm.DepthDecoder(tm.num_ch_enc(num_layers))
  penc = tm.ResnetEncoder(num_layers, num_input_images=2)
  pdec = tm.PoseDecoder(tm.num_ch_enc(num_layers), 1, 2)
  for i, m in enumerate((enc, dec, penc, pdec)):
    tm.randomize_(m, seed * 10 + i)
  root.mkdir(parents=True, exist_ok=True)
  kw = {"_use_new_zipfile_serialization": False} if legacy else {}
  enc_state = dict(enc.state_dict())
  enc_state.update(height=height, width=width, use_stereo=False)  # upstream's extras
  torch.save(enc_state, root / "encoder.pth", **kw)
  torch.save(dec.state_dict(), root / "depth.pth", **kw)
  torch.save(penc.state_dict(), root / "pose_encoder.pth", **kw)
  torch.save(pdec.state_dict(), root / "pose.pth", **kw)
  return enc.eval(), dec.eval(), penc.eval(), pdec.eval()


def _paths(root):
  return (root / "encoder.pth", root / "depth.pth", root / "pose_encoder.pth", root / "pose.pth")


@pytest.fixture(scope="module")
def r18(tmp_path_factory):
  """ResNet-18 MonoDepth2 saved in both formats and converted from each."""
  root = tmp_path_factory.mktemp("mono_640x192")
  nets = _save_mono_folder(root / "zip", 18, legacy=False)
  _save_mono_folder(root / "legacy", 18, legacy=True)  # same seed -> same weights
  conv_zip = convert_monodepth2(*_paths(root / "zip"))
  conv_legacy = convert_monodepth2(*_paths(root / "legacy"))
  return {"root": root, "torch": nets, "zip": conv_zip, "legacy": conv_legacy}


@pytest.fixture(scope="module")
def depth_fns():
  net = DepthNet(18)
  eval_fn = jax.jit(lambda v, x: net.apply(v, x, train=False))
  train_fn = jax.jit(lambda v, x: net.apply(v, x, train=True, mutable=["batch_stats"]))
  return eval_fn, train_fn


def _image(h, w, seed=0, batch=1):
  rng = np.random.default_rng(seed)
  return rng.uniform(0, 1, (batch, h, w, 3)).astype(np.float32)


def _torch_disps(enc, dec, x_nhwc):
  with torch.no_grad():
    out = dec(enc(torch.from_numpy(x_nhwc).permute(0, 3, 1, 2)))
  return [out[("disp", s)].permute(0, 2, 3, 1).numpy() for s in range(4)]


def test_legacy_and_zip_convert_identically(r18):
  """Both torch serialisations of the same weights give bitwise identical Flax variables."""
  _, vz, pz = r18["zip"][0], r18["zip"][1], r18["zip"][2]
  _, vl, pl = r18["legacy"]
  for a, b in zip(jax.tree_util.tree_leaves((vz, pz)), jax.tree_util.tree_leaves((vl, pl))):
    np.testing.assert_array_equal(a, b)
  config = r18["zip"][0]
  assert (config["num_layers"], config["height"], config["width"], config["use_stereo"]) == (
      18, 192, 640, False)


@pytest.mark.parametrize("hw", [(192, 640), (96, 320)])
@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_eval_mode_disparities_match_torch(r18, depth_fns, hw, fmt):
  enc, dec, _, _ = r18["torch"]
  x = _image(*hw, seed=hw[0])
  ref = _torch_disps(enc.eval(), dec.eval(), x)
  out = depth_fns[0](r18[fmt][1], x)
  for s in range(4):
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref[s])))
    print(f"eval {fmt} {hw[1]}x{hw[0]} scale {s}: max abs diff {diff:.2e}")
    assert out[s].shape == ref[s].shape
    assert diff < 1e-4


@pytest.mark.parametrize("hw", [(192, 640), (96, 320)])
def test_train_mode_bn_matches_torch(r18, depth_fns, hw, tmp_path):
  """Train-mode BN: batch statistics (biased) to normalise, unbiased into the running estimate."""
  root = r18["root"] / "zip"
  enc = tm.ResnetEncoder(18)  # fresh copies: train mode mutates the running statistics
  dec = tm.DepthDecoder(tm.num_ch_enc(18))
  enc.load_state_dict({k: v for k, v in torch.load(root / "encoder.pth").items()
                       if k not in ("height", "width", "use_stereo")})
  dec.load_state_dict(torch.load(root / "depth.pth"))
  enc.train(), dec.train()
  x = _image(*hw, seed=7, batch=2)
  with torch.no_grad():
    out_t = dec(enc(torch.from_numpy(x).permute(0, 3, 1, 2)))
  out, new_vars = depth_fns[1](r18["zip"][1], x)
  for s in range(4):
    ref = out_t[("disp", s)].permute(0, 2, 3, 1).numpy()
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref)))
    print(f"train-BN {hw[1]}x{hw[0]} scale {s}: max abs diff {diff:.2e}")
    assert diff < 1e-4
  # running statistics after one momentum-0.1 update
  tm_mean = enc.encoder.layer3[1].bn2.running_mean.numpy()
  tm_var = enc.encoder.layer3[1].bn2.running_var.numpy()
  bs = new_vars["batch_stats"]["encoder"]["layer3_1"]["bn2"]
  d_mean = float(np.max(np.abs(np.asarray(bs["mean"]) - tm_mean)))
  d_var = float(np.max(np.abs(np.asarray(bs["var"]) - tm_var) / np.abs(tm_var)))
  print(f"running mean max abs diff {d_mean:.2e}, running var max rel diff {d_var:.2e}")
  assert d_mean < 1e-4 and d_var < 1e-4


def test_pose_net_matches_torch(r18):
  _, _, penc, pdec = r18["torch"]
  pose_vars = r18["zip"][2]
  x = _image(96, 320, seed=3, batch=2).repeat(2, axis=-1)
  x[..., 3:] = _image(96, 320, seed=4, batch=2)
  with torch.no_grad():
    aa_t, tr_t = pdec([penc(torch.from_numpy(x).permute(0, 3, 1, 2))])
  aa, tr = jax.jit(lambda v, x: PoseNet(18).apply(v, x))(pose_vars, x)
  d = max(float(np.max(np.abs(np.asarray(aa) - aa_t.numpy()))),
          float(np.max(np.abs(np.asarray(tr) - tr_t.numpy()))))
  scale = max(float(np.max(np.abs(aa_t.numpy()))), float(np.max(np.abs(tr_t.numpy()))))
  print(f"pose axisangle/translation max abs diff {d:.2e} of values up to {scale:.2e}")
  # relative to the outputs, which the decoder scales by 0.01 (~2e-3 here): float32 agreement
  # is ~1e-7 of them, and an error of a fraction of a percent must fail
  assert d < 1e-5 * scale
  # 4x4 matrix helper against a literal Rodrigues formula (hand-written in NumPy)
  m = np.asarray(transformation_from_parameters(aa[:, 0] * 50, tr[:, 0] * 50))
  for b in range(2):
    v = np.asarray(aa[b, 0, 0]) * 50
    th = np.linalg.norm(v)
    k = v / (th + 1e-7)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx
    np.testing.assert_allclose(m[b, :3, :3], rot, atol=1e-5)
    np.testing.assert_allclose(m[b, :3, 3], np.asarray(tr[b, 0, 0]) * 50, atol=1e-6)


def _bn_grads_torch(root, x, weights, dtype):
  """Torch autograd of loss = sum_s mean(w_s * disp_s) w.r.t. every encoder BN gamma/beta."""
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  enc.load_state_dict({k: v for k, v in torch.load(root / "encoder.pth").items()
                       if k not in ("height", "width", "use_stereo")})
  dec.load_state_dict(torch.load(root / "depth.pth"))
  enc, dec = enc.to(dtype).train(), dec.to(dtype).train()
  out = dec(enc(torch.from_numpy(x).to(dtype).permute(0, 3, 1, 2)))
  loss = sum((out[("disp", s)].permute(0, 2, 3, 1) * torch.from_numpy(weights[s]).to(dtype)).mean()
             for s in range(4))
  loss.backward()
  return loss.item(), tm.bn_grads(enc)


def _bn_grads_jax(variables, x, weights, dtype):
  from flax.traverse_util import flatten_dict
  cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), t)
  parts = trainable.split(cast(variables))
  net = DepthNet(18)

  def loss_fn(tr, frozen, batch_stats, x, weights):
    disps = net.apply(trainable.merge(tr, frozen, batch_stats), x, train=True)
    return sum(jnp.mean(d * w) for d, w in zip(disps, weights))

  loss, grads = jax.jit(jax.value_and_grad(loss_fn))(
      parts.trainable, parts.frozen, parts.batch_stats, cast(x), cast(weights))
  flat = flatten_dict(grads["encoder"], sep="/")
  return float(loss), {k: np.asarray(v, np.float64) for k, v in flat.items()}


def _worst_rel(grads, ref):
  """max over BN leaves of max|g - ref| / max|ref| (relative to each leaf's scale)."""
  assert set(grads) == set(ref) and len(ref) == 40
  return max(float(np.max(np.abs(grads[k] - ref[k])) / np.max(np.abs(ref[k]))) for k in ref)


def test_bn_gradient_matches_torch_autograd(r18):
  """d(loss)/d(encoder BN gamma, beta) with train-mode BN, against torch autograd.

  In float64 both frameworks compute the same function, so they agree to rounding (measured
  1.6e-14; bound 1e-9, far below any wrong term of the backward pass; the math: BN backward through batch statistics, reflection padding,
  nearest upsampling, ELU). In float32 the 1/32-scale BN layers of a batch-1 320x96 input
  normalise 30 values per channel and their gamma/beta gradients cancel to a few 1e-4, so
  *torch's own* float32 gradient is off its float64 one by up to a few 1e-2 there (measured
  5.6e-2; JAX float32: 4.8e-2). The float32 check is therefore that JAX float32 is no further
  from the float64 truth than torch float32 is.
  """
  root = r18["root"] / "zip"
  x = _image(96, 320, seed=11)
  rng = np.random.default_rng(5)
  weights = [rng.normal(size=(1, 96 >> s, 320 >> s, 1)).astype(np.float32) for s in range(4)]
  loss64_t, ref64 = _bn_grads_torch(root, x, weights, torch.float64)
  loss32_t, ref32 = _bn_grads_torch(root, x, weights, torch.float32)
  with jax.enable_x64(True):
    loss64_j, g64 = _bn_grads_jax(r18["zip"][1], x, weights, jnp.float64)
  loss32_j, g32 = _bn_grads_jax(r18["zip"][1], x, weights, jnp.float32)
  rel64 = _worst_rel(g64, ref64)
  rel32_jax, rel32_torch = _worst_rel(g32, ref64), _worst_rel(ref32, ref64)
  print(f"loss float64: jax {loss64_j:.10f} torch {loss64_t:.10f}; float32: jax {loss32_j:.7f} "
        f"torch {loss32_t:.7f}")
  print(f"BN gamma/beta grads, worst max-relative diff over 40 leaves: float64 jax vs torch "
        f"{rel64:.2e}; vs torch float64: jax float32 {rel32_jax:.2e}, torch float32 {rel32_torch:.2e}")
  np.testing.assert_allclose(loss64_j, loss64_t, rtol=1e-10)
  np.testing.assert_allclose(loss32_j, loss32_t, rtol=1e-5)
  assert rel64 < 1e-9
  assert rel32_jax < 2 * rel32_torch + 1e-4


@pytest.mark.parametrize("num_layers", [34, 50])
def test_deeper_resnets_convert_and_match(tmp_path, num_layers):
  enc, dec, _, _ = _save_mono_folder(tmp_path, num_layers, legacy=False, seed=num_layers)
  config, variables, _ = convert_monodepth2(tmp_path / "encoder.pth", tmp_path / "depth.pth")
  assert config["num_layers"] == num_layers
  x = _image(64, 96, seed=1)
  ref = _torch_disps(enc, dec, x)
  out = DepthNet(num_layers).apply(variables, x)
  diff = max(float(np.max(np.abs(np.asarray(o) - r))) for o, r in zip(out, ref))
  print(f"ResNet-{num_layers} 96x64 eval: max abs diff {diff:.2e}")
  assert diff < 1e-4


def test_input_size_must_be_multiple_of_32(r18):
  with pytest.raises(ValueError, match="multiples of 32"):
    DepthNet(18).apply(r18["zip"][1], np.zeros((1, 100, 320, 3), np.float32))


def test_cli_convert_and_load_in_one_call(r18, depth_fns, tmp_path):
  """`python -m weights_convert monodepth2 ...` writes a directory `load_weights` reads."""
  root = r18["root"] / "legacy"
  enc, depth, penc, pose = _paths(root)
  out = tmp_path / "converted"
  res = subprocess.run([sys.executable, "-m", "weights_convert", "monodepth2", "--encoder", enc,
                        "--depth", depth, "--pose-encoder", penc, "--pose", pose, "--out", out],
                       capture_output=True, text=True)
  assert res.returncode == 0, res.stderr
  loaded = load_weights(out)
  assert loaded.config["has_pose"] and loaded.height == 192 and loaded.width == 640
  assert loaded.spec.name == "monodepth2" and loaded.pose is not None
  for a, b in zip(jax.tree_util.tree_leaves((loaded.depth, loaded.pose)),
                  jax.tree_util.tree_leaves((r18["zip"][1], r18["zip"][2]))):
    np.testing.assert_array_equal(a, b)


# --- clear errors --------------------------------------------------------------------------------

def test_missing_file_is_named(r18, tmp_path):
  with pytest.raises(CheckpointError, match="nope.pth"):
    convert_monodepth2(tmp_path / "nope.pth", r18["root"] / "zip" / "depth.pth")


def test_truncated_file_is_named(r18, tmp_path):
  data = (r18["root"] / "zip" / "encoder.pth").read_bytes()
  bad = tmp_path / "encoder.pth"
  bad.write_bytes(data[: len(data) // 2])
  with pytest.raises(CheckpointError, match="encoder.pth"):
    convert_monodepth2(bad, r18["root"] / "zip" / "depth.pth")


def test_unexpected_missing_and_misshapen_keys_are_named(r18, tmp_path):
  state = torch.load(r18["root"] / "zip" / "depth.pth")
  extra = dict(state, **{"decoder.99.conv.weight": torch.zeros(1)})
  torch.save(extra, tmp_path / "extra.pth")
  with pytest.raises(CheckpointError, match=r"1 unexpected keys: decoder.99.conv.weight"):
    convert_monodepth2(r18["root"] / "zip" / "encoder.pth", tmp_path / "extra.pth")
  missing = {k: v for k, v in state.items() if not k.startswith("decoder.12.")}
  torch.save(missing, tmp_path / "missing.pth")
  with pytest.raises(CheckpointError, match=r"2 missing keys: decoder.12.conv.bias, decoder.12.conv.weight"):
    convert_monodepth2(r18["root"] / "zip" / "encoder.pth", tmp_path / "missing.pth")
  wrong = dict(state, **{"decoder.0.conv.conv.weight": torch.zeros(256, 512, 1, 1)})
  torch.save(wrong, tmp_path / "wrong.pth")
  with pytest.raises(CheckpointError, match=r"decoder.0.conv.conv.weight has shape \(256, 512, 1, 1\)"):
    convert_monodepth2(r18["root"] / "zip" / "encoder.pth", tmp_path / "wrong.pth")


def test_wrapped_and_data_parallel_saves_convert_like_plain_ones(r18, tmp_path):
  """A training script's {"state_dict": sd, "epoch": n} / {"model": sd} / PyTorch's recipe
  {"model_state_dict": sd, "optimizer_state_dict": ..., "loss": tensor} and DataParallel's
  `module.` names (torch.save of nn.DataParallel(encoder).state_dict()) are the same weights."""
  root = r18["root"] / "zip"
  state = torch.load(root / "encoder.pth")
  tensors = {k: v for k, v in state.items() if isinstance(v, torch.Tensor)}
  meta = {k: v for k, v in state.items() if not isinstance(v, torch.Tensor)}
  torch.save({"state_dict": state, "epoch": 19}, tmp_path / "wrapped.pth")
  torch.save({"model": state}, tmp_path / "model.pth")
  # PyTorch's checkpoint recipe, its loss a scalar tensor
  torch.save({"epoch": 19, "model_state_dict": state, "optimizer_state_dict": {"state": {}},
              "loss": torch.tensor(0.125)}, tmp_path / "recipe.pth")
  torch.save({**{f"module.{k}": v for k, v in tensors.items()}, **meta}, tmp_path / "dp.pth")
  _, want, _ = convert_monodepth2(root / "encoder.pth", root / "depth.pth")
  for name in ("wrapped.pth", "model.pth", "recipe.pth", "dp.pth"):
    _, got, _ = convert_monodepth2(tmp_path / name, root / "depth.pth")
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
      np.testing.assert_array_equal(a, b)


def test_a_compiled_models_save_converts_like_a_plain_one(r18, tmp_path):
  """torch.compile's wrapper names every weight `_orig_mod.<name>` (and DataParallel around it
  `module._orig_mod.<name>`): such saves were refused as unexpected keys; they are the same
  weights as the plain save."""
  root = r18["root"] / "zip"
  meta = {k: v for k, v in torch.load(root / "encoder.pth").items()
          if not isinstance(v, torch.Tensor)}
  # torch.compile(model).state_dict() names each weight `_orig_mod.<name>` (its OptimizedModule
  # holds the model as `_orig_mod`); written out here, as importing torch._dynamo takes seconds
  state = {f"_orig_mod.{k}": v for k, v in r18["torch"][0].state_dict().items()}
  torch.save({**state, **meta}, tmp_path / "compiled.pth")
  torch.save({**{f"module.{k}": v for k, v in state.items()}, **meta}, tmp_path / "both.pth")
  _, want, _ = convert_monodepth2(root / "encoder.pth", root / "depth.pth")
  for name in ("compiled.pth", "both.pth"):
    _, got, _ = convert_monodepth2(tmp_path / name, root / "depth.pth")
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
      np.testing.assert_array_equal(a, b)


def test_swapped_files_and_an_unusable_size_are_named(r18, tmp_path):
  root = r18["root"] / "zip"
  with pytest.raises(CheckpointError, match=r"depth\.pth: holds no ResNet encoder .*'decoder\..*"
                                            r"swapped"):
    convert_monodepth2(root / "depth.pth", root / "encoder.pth")
  state = torch.load(root / "encoder.pth")
  torch.save(dict(state, height=191), tmp_path / "h191.pth")
  with pytest.raises(CheckpointError, match=r"h191\.pth: its 'height' and 'width' entries: input "
                                            r"size 640x191 .* multiples of 32"):
    convert_monodepth2(tmp_path / "h191.pth", root / "depth.pth")
  # half a size is refused; none at all is MonoDepth2's default, said in a note
  torch.save({k: v for k, v in state.items() if k != "width"}, tmp_path / "nowidth.pth")
  with pytest.raises(CheckpointError, match=r"nowidth\.pth: has a 'height' entry but no 'width'"):
    convert_monodepth2(tmp_path / "nowidth.pth", root / "depth.pth")
  torch.save({k: v for k, v in state.items() if k not in ("height", "width")},
             tmp_path / "nosize.pth")
  notes = []
  config, _, _ = convert_monodepth2(tmp_path / "nosize.pth", root / "depth.pth", notes=notes)
  assert (config["height"], config["width"]) == (192, 640) and notes == [
      f"{tmp_path / 'nosize.pth'} has no 'height' and 'width' entries (upstream's training "
      f"writes them): taken as trained at MonoDepth2's 640x192"]


def test_convert_never_writes_over_its_inputs_and_replaces_old_weights_whole(r18, tmp_path,
                                                                             capsys):
  """Inputs at the paths a converter writes (OUT/model.json, OUT/depth) are refused before any
  work; converting into an earlier weights directory leaves none of the old files behind (an
  earlier pose network with a conversion that has none)."""
  import shutil
  from pitta_jax.cli import main
  enc, depth, penc, pose = _paths(r18["root"] / "zip")
  out = tmp_path / "w"
  out.mkdir()
  shutil.copy(enc, out / "model.json")
  assert main(["convert", "monodepth2", "--encoder", str(out / "model.json"), "--depth",
               str(depth), "--out", str(out)]) == 2
  err = capsys.readouterr().err
  assert f"--out {out} would overwrite the input --encoder {out / 'model.json'}" in err
  assert (out / "model.json").read_bytes() == open(enc, "rb").read()
  (out / "model.json").unlink()
  assert main(["convert", "monodepth2", "--encoder", str(enc), "--depth", str(depth),
               "--pose-encoder", str(penc), "--pose", str(pose), "--out", str(out)]) == 0
  assert (out / "pose").is_dir()
  assert main(["convert", "monodepth2", "--encoder", str(enc), "--depth", str(depth), "--out",
               str(out)]) == 0
  assert not (out / "pose").exists() and not load_weights(out).config["has_pose"]


def test_an_interrupted_convert_can_be_run_again(r18, tmp_path, monkeypatch, capsys):
  """A conversion interrupted after depth/ was written (no model.json yet) leaves the
  directory marked as weights being written; the same command then replaces it (it was
  refused as 'not earlier pitta-jax weights', and the user told to pick another directory)."""
  from pitta_jax import checkpoint
  from pitta_jax.cli import main
  enc, depth, penc, pose = _paths(r18["root"] / "zip")
  out = tmp_path / "w"
  args = ["convert", "monodepth2", "--encoder", str(enc), "--depth", str(depth),
          "--pose-encoder", str(penc), "--pose", str(pose), "--out", str(out)]
  real = checkpoint.save_tree

  def interrupted(path, tree):
    if os.path.basename(path) == "pose":
      raise KeyboardInterrupt
    return real(path, tree)
  monkeypatch.setattr(checkpoint, "save_tree", interrupted)
  assert main(args) == 130
  assert (out / "depth").is_dir() and (out / checkpoint.INCOMPLETE).is_file()
  assert not (out / "model.json").exists()
  monkeypatch.setattr(checkpoint, "save_tree", real)
  capsys.readouterr()
  assert main(args) == 0, capsys.readouterr().err
  assert load_weights(out).config["has_pose"] and not (out / checkpoint.INCOMPLETE).exists()
  # a rewrite of those complete weights interrupted midway: the old model.json must not stay
  # beside the new depth/ and the old pose/ (it would describe arrays it never saw)
  monkeypatch.setattr(checkpoint, "save_tree", interrupted)
  assert main(args) == 130
  assert not (out / "model.json").exists() and (out / checkpoint.INCOMPLETE).is_file()
  # the weights say why they are unusable: the conversion was cut short, run it again
  with pytest.raises(checkpoint.WeightsError, match="were being written when that stopped .* "
                                                    "run it again"):
    load_weights(out)


@pytest.mark.parametrize("layout", ["dataset", "user_json", "user_file_in_depth", "empty_path",
                                    "mask2former"])
def test_convert_refuses_to_replace_what_is_not_earlier_weights(r18, tmp_path, capsys, layout):
  """What a conversion writes (model.json, depth/, pose/) replaces only earlier weights: a
  dataset's depth/ folder, a user's model.json, or a depth/ beside a foreign model.json are
  refused before any work, one line, exit 2, untouched; other files in --out (the .pth files
  converted) are left alone; an empty --out is refused."""
  import json
  import shutil
  from pitta_jax.cli import main
  enc, depth, _, _ = _paths(r18["root"] / "zip")
  out = tmp_path / "out"
  (out / "depth").mkdir(parents=True)
  if layout == "dataset":
    (out / "depth" / "0000.png").write_bytes(b"ground truth")
    (out / "image").mkdir()
  elif layout == "user_json":
    shutil.rmtree(out / "depth")
    (out / "model.json").write_text(json.dumps({"notes": "mine"}))
  elif layout == "user_file_in_depth":
    (out / "depth" / "notes.txt").write_text("mine")
    (out / "model.json").write_text("not json")
  elif layout == "mask2former":  # another network's weights: not mixed with these
    shutil.rmtree(out / "depth")
    (out / "config.json").write_text(json.dumps({"architecture": "mask2former"}))
    (out / "params").mkdir()
  before = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
  target = "" if layout == "empty_path" else str(out)
  assert main(["convert", "monodepth2", "--encoder", str(enc), "--depth", str(depth), "--out",
               target]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and err.startswith(f"error: --out {target}".rstrip())
  assert {"empty_path": "an empty path", "mask2former": "holds Mask2Former weights (config.json, "
          "params); the monodepth2 weights need a directory of their own"}.get(
              layout, "not earlier pitta-jax weights") in err
  assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == before
  # the converted .pth files beside the weights: left alone
  shutil.rmtree(out)
  out.mkdir()
  shutil.copy(enc, out / "encoder.pth")
  assert main(["convert", "monodepth2", "--encoder", str(out / "encoder.pth"), "--depth",
               str(depth), "--out", str(out)]) == 0
  assert (out / "encoder.pth").is_file() and load_weights(out).config["num_layers"] == 18
  # a Hub snapshot's own config.json beside the file converted is neither Mask2Former weights
  # nor anything a depth conversion writes: left alone too (it was refused as Mask2Former's)
  shutil.rmtree(out)
  out.mkdir()
  shutil.copy(enc, out / "encoder.pth")
  hub = json.dumps({"architectures": ["DepthAnythingForDepthEstimation"]})
  (out / "config.json").write_text(hub)
  assert main(["convert", "monodepth2", "--encoder", str(out / "encoder.pth"), "--depth",
               str(depth), "--out", str(out)]) == 0, capsys.readouterr().err
  assert (out / "config.json").read_text() == hub and load_weights(out).config["num_layers"] == 18


# --- the key-table engine (weights_convert.rules) ------------------------------------------------

def test_rule_layouts_match_the_pytorch_modules_and_invert():
  """Each rule kind against the PyTorch module that owns the names (nn.Conv2d, nn.Linear,
  nn.MultiheadAttention's in_proj rows, two Linears fused by rows): the conv kernel entry by
  entry (OIHW -> HWIO, a 4x5 kernel so that no swap of axes passes by shape), the dense ones by
  `x @ kernel + bias` against the torch module's own output (q/k/v: torch's F.linear on the rows
  of in_proj that MultiheadAttention uses for each); `to_state_dict` gives the file back."""
  import itertools
  from flax.traverse_util import unflatten_dict
  from weights_convert import rules as R
  torch.manual_seed(0)
  conv, lin = torch.nn.Conv2d(3, 2, (4, 5)), torch.nn.Linear(3, 4)
  mha, q, k = torch.nn.MultiheadAttention(4, 2), torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
  state = {f"{name}.{key}": v.detach().numpy().copy()
           for name, m in (("conv", conv), ("lin", lin), ("attn", mha), ("q", q), ("k", k))
           for key, v in m.state_dict().items()}
  rules: R.Rules = []
  R.conv(rules, ("params", "c"), "conv")
  R.linear(rules, ("params", "l"), "lin")
  R.in_proj(rules, ("params", "a"), "attn", 4)
  R.fused_linear(rules, ("params", "qk"), ["q", "k"])
  expected = {("params", "c", "kernel"): (4, 5, 3, 2), ("params", "c", "bias"): (2,),
              ("params", "l", "kernel"): (3, 4), ("params", "l", "bias"): (4,),
              ("params", "qk", "kernel"): (3, 4), ("params", "qk", "bias"): (4,)}
  for name in ("q_proj", "k_proj", "v_proj", "out_proj"):
    expected[("params", "a", name, "kernel")] = (4, 4)
    expected[("params", "a", name, "bias")] = (4,)
  flat = R.apply_rules(state, rules, lambda key: False, "x.pth", expected)

  kernel, weight = flat[("params", "c", "kernel")], conv.weight.detach().numpy()
  for h, w, i, o in itertools.product(range(4), range(5), range(3), range(2)):
    assert kernel[h, w, i, o] == weight[o, i, h, w]

  def dense(path, x):
    return x @ flat[path + ("kernel",)] + flat[path + ("bias",)]
  x3 = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
  x4 = np.random.default_rng(1).normal(size=(5, 4)).astype(np.float32)
  with torch.no_grad():
    np.testing.assert_allclose(dense(("params", "l"), x3), lin(torch.from_numpy(x3)).numpy(),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dense(("params", "qk"), x3), torch.cat(
        [q(torch.from_numpy(x3)), k(torch.from_numpy(x3))], -1).numpy(), rtol=1e-5, atol=1e-6)
    for n, name in enumerate(("q_proj", "k_proj", "v_proj")):
      rows = slice(4 * n, 4 * (n + 1))
      want = torch.nn.functional.linear(torch.from_numpy(x4), mha.in_proj_weight[rows],
                                        mha.in_proj_bias[rows]).numpy()
      np.testing.assert_allclose(dense(("params", "a", name), x4), want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dense(("params", "a", "out_proj"), x4),
                               mha.out_proj(torch.from_numpy(x4)).numpy(), rtol=1e-5, atol=1e-6)

  back = R.to_state_dict(unflatten_dict(flat), rules)
  assert sorted(back) == sorted(state)
  for key, value in state.items():
    np.testing.assert_array_equal(back[key], value, err_msg=key)


def test_rules_engine_gives_float32_and_names_bad_entries():
  """A half- or double-precision tensor converts to float32 (what the networks and the weights
  directories hold) with its values; a non-tensor entry, a tensor with fewer rows than its slice
  needs, and a key table that leaves a model path uncovered each fail with one message naming
  the key, the file or the path."""
  from weights_convert import rules as R
  values = [[0.5, -1.25, 3.0], [2.0, 0.0, -0.75]]  # (out 2, in 3), exact in float16
  rules: R.Rules = []
  R.linear(rules, ("params", "w"), "w", bias=False)
  expected = {("params", "w", "kernel"): (3, 2)}
  for dtype in (np.float16, np.float64):
    flat = R.apply_rules({"w.weight": np.array(values, dtype)}, rules, lambda k: False, "x.pth",
                         expected)
    kernel = flat[("params", "w", "kernel")]
    assert kernel.dtype == np.float32
    np.testing.assert_array_equal(kernel, [[0.5, 2.0], [-1.25, 0.0], [3.0, -0.75]])
  with pytest.raises(CheckpointError, match=r"^x\.pth: w\.weight is a int, expected a tensor$"):
    R.apply_rules({"w.weight": 3}, rules, lambda k: False, "x.pth", expected)
  import ml_dtypes  # bfloat16 tensors convert; complex and integer ones (cast silently) do not
  flat = R.apply_rules({"w.weight": np.array(values, ml_dtypes.bfloat16)}, rules,
                       lambda k: False, "x.pth", expected)
  np.testing.assert_array_equal(flat[("params", "w", "kernel")], np.array(values).T)
  for dtype in (np.complex64, np.int64, bool):
    with pytest.raises(CheckpointError, match=rf"^x\.pth: w\.weight is a {np.dtype(dtype)} "
                                              rf"tensor, expected floating-point weights$"):
      R.apply_rules({"w.weight": np.array(values).astype(dtype)}, rules, lambda k: False,
                    "x.pth", expected)
  rows: R.Rules = []
  R.in_proj(rows, ("params", "a"), "attn", 2)  # q, k, v: rows 0:2, 2:4, 4:6
  short = {"attn.in_proj_weight": np.zeros((5, 2), np.float32),
           "attn.in_proj_bias": np.zeros(6, np.float32),
           "attn.out_proj.weight": np.zeros((2, 2), np.float32),
           "attn.out_proj.bias": np.zeros(2, np.float32)}
  shapes = {("params", "a", n, leaf): (2, 2) if leaf == "kernel" else (2,)
            for n in ("q_proj", "k_proj", "v_proj", "out_proj") for leaf in ("kernel", "bias")}
  with pytest.raises(CheckpointError, match=r"^x\.pth: attn\.in_proj_weight has shape \(5, 2\), "
                                            r"expected at least 6 rows$"):
    R.apply_rules(short, rows, lambda k: False, "x.pth", shapes)
  with pytest.raises(AssertionError, match=r"does not cover model paths \['params/b/kernel'\]"):
    R.apply_rules({"w.weight": np.array(values, np.float32)}, rules, lambda k: False, "x.pth",
                  {**expected, ("params", "b", "kernel"): (1, 1)})


# --- converter arguments and metadata -------------------------------------------------------------

def test_use_stereo_is_carried_over_and_absent_means_monocular(r18, tmp_path):
  """upstream's trainer saves `use_stereo` in encoder.pth; a stereo-trained encoder must give
  config["use_stereo"] True (evaluation then scales by MonoDepth2's x5.4 instead of the median),
  and an encoder without the entry is taken as monocular (the converter's documented default)."""
  root = r18["root"] / "zip"
  state = torch.load(root / "encoder.pth")
  torch.save(dict(state, use_stereo=True), tmp_path / "stereo.pth")
  torch.save({k: v for k, v in state.items() if k != "use_stereo"}, tmp_path / "no_flag.pth")
  assert convert_monodepth2(tmp_path / "stereo.pth", root / "depth.pth")[0]["use_stereo"] is True
  assert convert_monodepth2(tmp_path / "no_flag.pth", root / "depth.pth")[0]["use_stereo"] is False
  # a flag written as text was read as true ('False' is a non-empty string): refused instead
  torch.save(dict(state, use_stereo="False"), tmp_path / "text.pth")
  with pytest.raises(CheckpointError, match=r"text\.pth: its 'use_stereo' entry is 'False', "
                                            r"expected True or False"):
    convert_monodepth2(tmp_path / "text.pth", root / "depth.pth")
  torch.save(dict(state, use_stereo=torch.tensor(1)), tmp_path / "one.pth")
  assert convert_monodepth2(tmp_path / "one.pth", root / "depth.pth")[0]["use_stereo"] is True


def test_argument_mistakes_are_named(r18, tmp_path):
  """A pose encoder without the pose decoder is refused before any file is read; one file given as
  both encoder and decoder is named as such; a monocular encoder with a missing pose file names
  that file, without the stereo release hint (only a stereo-trained encoder gets it)."""
  enc, depth, penc, pose = _paths(r18["root"] / "zip")
  with pytest.raises(CheckpointError, match="--pose-encoder and --pose go together"):
    convert_monodepth2(enc, depth, pose_encoder=penc)
  with pytest.raises(CheckpointError, match=r"encoder\.pth: keys .* also occur in .*encoder\.pth;"
                                            r" .*the same file\?"):
    convert_monodepth2(enc, enc)
  with pytest.raises(CheckpointError, match=r"nope_pose\.pth") as info:
    convert_monodepth2(enc, depth, penc, tmp_path / "nope_pose.pth")
  assert "stereo" not in str(info.value)


def _md2_args(**kw):
  """`python -m weights_convert monodepth2`'s arguments, without the pose files by default."""
  import argparse
  return argparse.Namespace(**{"pose_encoder": None, "pose": None, "num_layers": None, **kw})


def test_run_records_the_sources_and_a_pose_net_of_another_depth(r18, tmp_path):
  """model.json's "source" names each input file under its own flag, and a pose encoder deeper
  than the depth encoder (ResNet-34 beside ResNet-18) is recorded as pose_num_layers (the field
  the registry builds the PoseNet from; it defaults to num_layers)."""
  import json
  from weights_convert import monodepth2
  enc, depth, _, _ = _paths(r18["root"] / "zip")
  penc, pose = tmp_path / "pose_encoder.pth", tmp_path / "pose.pth"
  torch.save(tm.ResnetEncoder(34, num_input_images=2).state_dict(), penc)
  torch.save(tm.PoseDecoder(tm.num_ch_enc(34), 1, 2).state_dict(), pose)
  out = monodepth2.run(_md2_args(encoder=enc, depth=depth, pose_encoder=penc, pose=pose,
                                 out=tmp_path / "w"))
  meta = json.loads((out / "model.json").read_text())
  assert meta["source"] == {"encoder": str(enc), "depth": str(depth), "pose_encoder": str(penc),
                            "pose": str(pose)}
  assert (meta["num_layers"], meta["pose_num_layers"]) == (18, 34)


def test_an_input_inside_an_earlier_checkpoint_folder_is_refused(r18, tmp_path, capsys):
  """An input file that lies inside OUT/depth/ of earlier weights would be deleted with the
  checkpoint folder it is in when the conversion replaces it: refused before any work, named."""
  import shutil
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.cli import main
  enc, depth, _, _ = _paths(r18["root"] / "zip")
  out = tmp_path / "w"
  save_weights(out, "monodepth2", {"num_layers": 18, "height": 192, "width": 640}, r18["zip"][1])
  inside = out / "depth" / "depth.pth"
  shutil.copy(depth, inside)
  assert main(["convert", "monodepth2", "--encoder", str(enc), "--depth", str(inside), "--out",
               str(out)]) == 2
  assert f"--out {out} would overwrite the input --depth {inside}" in capsys.readouterr().err
  assert inside.read_bytes() == open(depth, "rb").read()


def test_a_depth_folder_that_is_no_checkpoint_is_not_replaced_beside_a_description(tmp_path):
  """A model.json naming an architecture does not make everything beside it earlier weights:
  a depth/ folder without orbax's metadata files (here a user's notes) would be replaced by the
  conversion and is refused, named."""
  import json
  from weights_convert.cli import check_output_replaceable
  out = tmp_path / "w"
  (out / "depth").mkdir(parents=True)
  (out / "depth" / "notes.txt").write_text("mine")
  (out / "model.json").write_text(json.dumps({"architecture": "monodepth2"}))
  with pytest.raises(ValueError, match=re.escape(f"--out {out}: its depth/ would be replaced and "
                                                 f"is not earlier pitta-jax weights")):
    check_output_replaceable(str(out), "monodepth2")
  assert (out / "depth" / "notes.txt").read_text() == "mine"


def test_one_network_per_weights_directory(tmp_path):
  """A depth network's weights (a model.json naming an architecture, or an orbax depth/) refuse
  a Mask2Former conversion into their directory and Mask2Former's (config.json naming one, or
  an orbax params/) a depth conversion; files of the same names that are no pitta-jax weights
  (a Hub snapshot's config.json, a dataset's depth/ of PNGs) do not count as another network."""
  import json
  from weights_convert.cli import check_output_replaceable
  depth_net, m2f, plain = tmp_path / "depth_net", tmp_path / "m2f", tmp_path / "plain"
  (depth_net / "depth").mkdir(parents=True)
  (depth_net / "depth" / "_CHECKPOINT_METADATA").write_text("{}")
  (m2f / "params").mkdir(parents=True)
  (m2f / "params" / "_METADATA").write_text("{}")
  (plain / "depth").mkdir(parents=True)
  (plain / "depth" / "0000.png").write_bytes(b"ground truth")
  (plain / "config.json").write_text(json.dumps({"model_type": "depth_anything"}))
  with pytest.raises(ValueError, match=re.escape(f"--out {depth_net}: holds a depth network's "
                                                 f"weights (model.json, depth)")):
    check_output_replaceable(str(depth_net), "mask2former")
  with pytest.raises(ValueError, match=re.escape(f"--out {m2f}: holds Mask2Former weights "
                                                 f"(config.json, params)")):
    check_output_replaceable(str(m2f), "hrdepth")
  (depth_net / "depth" / "_CHECKPOINT_METADATA").unlink()
  (depth_net / "model.json").write_text(json.dumps({"architecture": "monodepth2"}))
  with pytest.raises(ValueError, match="holds a depth network's weights"):
    check_output_replaceable(str(depth_net), "mask2former")
  # Mask2Former's conversion would write plain's config.json (not pitta-jax's): refused as such
  with pytest.raises(ValueError, match=re.escape(f"--out {plain}: its config.json would be "
                                                 f"replaced and is not earlier pitta-jax")):
    check_output_replaceable(str(plain), "mask2former")
  (plain / "config.json").unlink()
  check_output_replaceable(str(plain), "mask2former")  # the dataset's depth/ stays beside
