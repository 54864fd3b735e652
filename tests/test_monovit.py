"""Parity of the Flax MonoViT + converter with an independent PyTorch MonoViT.

Reference: `tests/torch_monovit.py`, upstream's MPViT + HR decoder with upstream's state_dict
names, random weights (activations O(1), disparities spread over (0, 1)) and random BN
statistics, saved with `torch.save` in the released layouts, converted by
`weights_convert.monovit` (no torch), and compared at 96x64 (sides must be multiples of 32):

* the released network, MPViT-small, as the 640x192 release (encoder.pth with its
  height/width/use_stereo entries + depth.pth): eval-mode disparities at the 4 scales, 1e-4 max
  abs (float32);
* a small MPViT layout (fewer paths and layers, narrower; every module kind, and in stage 0
  2 paths of 2 MHCA layers sharing their position encodings) as a high-resolution release (one
  DataParallel DeepNet file): train-mode-BN disparities (1e-4, float32) and running statistics;
  the float64 gradient of a loss on the encoder's feature maps w.r.t. every encoder BN and LN
  gamma/beta (1e-9 relative: rounding, measured 4e-14); the other release layout; the strict-loading errors.

XLA's compile time, not the arithmetic, dominates: MPViT-small's float64 backward takes ~30 s of
CPU to compile, its train-mode forward another ~5 s, hence the small layout there (on
MPViT-small both were measured once at the same levels: train-BN disparities within 5e-7,
norm gradients of a disparity loss within 2e-13 relative).
"""

from __future__ import annotations

import argparse
import copy
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from flax.traverse_util import flatten_dict, unflatten_dict

import torch_monovit as tm
from pitta_jax.models.monovit import SPEC, MonoViT
from pitta_jax.models.monovit.mpvit import MPViT
from weights_convert.monovit import add_arguments, convert_monovit, run
from weights_convert.pth import CheckpointError

torch.set_num_threads(2)

H, W = 64, 96  # multiples of 32; 2x3 at 1/32
DECODER_GAIN = 1.3  # He-like scale for the ReLU/ELU decoder: disparities spread over (0, 1)
META = {"height": 192, "width": 640, "use_stereo": False}
SMALL = {"num_path": (2, 3, 3, 3), "num_layers": (1, 3, 6, 3), "embed_dims": (64, 128, 216, 288),
         "mlp_ratios": (4, 4, 4, 4), "num_heads": (8, 8, 8, 8)}  # upstream's mpvit_small
TINY = {"num_path": (2, 1, 1, 1), "num_layers": (2, 1, 1, 1), "embed_dims": (64, 64, 96, 128),
        "mlp_ratios": (4, 2, 2, 3), "num_heads": (8, 8, 8, 8)}  # stem width 64: upstream decoder


def _randomized(enc, dec, seed: int):
  tm.randomize_(enc, seed)
  tm.randomize_(dec, seed + 1, gain=DECODER_GAIN)
  return enc.eval(), dec.eval()


@pytest.fixture(scope="module")
def released(tmp_path_factory):
  """Random torch MonoViT saved as the 640x192 release (encoder.pth + depth.pth) and converted."""
  root = tmp_path_factory.mktemp("monovit_640x192")
  enc, dec = _randomized(tm.mpvit_small(), tm.DepthDecoder(), 0)
  torch.save({**enc.state_dict(), **META}, root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  config, variables = convert_monovit(root / "encoder.pth", root / "depth.pth")
  return {"root": root, "enc": enc, "dec": dec, "config": config, "variables": variables}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
  """A small-layout MonoViT saved as a high-resolution release (DataParallel DeepNet file) and
  as encoder.pth + depth.pth."""
  root = tmp_path_factory.mktemp("monovit_tiny")
  e = TINY["embed_dims"]
  enc, dec = _randomized(tm.MPViT(num_stages=4, **{k: list(v) for k, v in TINY.items()}),
                         tm.DepthDecoder(ch_enc=(e[0], e[1], e[2], e[3], e[3])), 10)
  torch.save(torch.nn.DataParallel(tm.DeepNet(enc, dec)).state_dict(), root / "deepnet.pth")
  torch.save({**enc.state_dict(), **META}, root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  config, variables = convert_monovit(None, root / "deepnet.pth", height=320, width=1024)
  return {"root": root, "enc": enc, "dec": dec, "config": config, "variables": variables}


def _run_once(fn, *args):
  """`jax.jit(fn)(*args)` for a program that runs once: compiled with XLA:CPU's LLVM backend
  optimisation off, which halves the compile time that dominates these tests (XLA's own HLO
  passes still run; the results are checked against torch all the same)."""
  compiled = jax.jit(fn).lower(*args).compile({"xla_backend_optimization_level": 0})
  return compiled(*args)


def _image(seed: int, batch: int = 1) -> np.ndarray:
  return np.random.default_rng(seed).uniform(0, 1, (batch, H, W, 3)).astype(np.float32)


def _nchw(x: np.ndarray, dtype=torch.float32) -> torch.Tensor:
  return torch.from_numpy(x).to(dtype).permute(0, 3, 1, 2)


def _compare(out, ref_dict, label: str) -> None:
  for s in range(4):
    ref = ref_dict[("disp", s)].detach().permute(0, 2, 3, 1).numpy()
    assert out[s].shape == ref.shape == (ref.shape[0], H >> s, W >> s, 1)
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref)))
    print(f"{label} scale {s}: max abs diff {diff:.2e} (torch disparity range "
          f"{ref.min():.3f}..{ref.max():.3f})")
    assert diff < 1e-4


def test_config_and_spec(released, tiny):
  assert released["config"] == {**META, **{k: list(v) for k, v in SMALL.items()}}
  assert SPEC.build(released["config"]) == MonoViT()  # MPViT-small is the default layout
  assert tiny["config"] == {"height": 320, "width": 1024, **{k: list(v) for k, v in TINY.items()}}
  assert SPEC.build(json.loads(json.dumps(tiny["config"]))) == MonoViT(**TINY)
  assert (SPEC.name, SPEC.output, SPEC.size_multiple, SPEC.default_size, SPEC.encoder) == (
      "monovit", "sigmoid_disparity", 32, (192, 640), "encoder")
  SPEC.check_size(H, W)


def test_eval_mode_matches_torch(released):
  x = _image(0)
  with torch.no_grad():
    ref = released["dec"](released["enc"](_nchw(x)))
  out = _run_once(lambda v, x: MonoViT().apply(v, x, train=False), released["variables"], x)
  _compare(out, ref, f"eval {W}x{H}")


def test_train_mode_bn_matches_torch(tiny):
  """Train-mode BN (batch statistics; biased to normalise, unbiased into the running estimate)."""
  enc = tm.bn_train_(copy.deepcopy(tiny["enc"]))  # fresh copies: train mode mutates them
  dec = copy.deepcopy(tiny["dec"]).eval()
  x = _image(7, batch=2)
  with torch.no_grad():
    ref = dec(enc(_nchw(x)))
  out, new_vars = _run_once(
      lambda v, x: MonoViT(**TINY).apply(v, x, train=True, mutable=["batch_stats"]),
      tiny["variables"], x)
  _compare(out, ref, f"train-BN {W}x{H} batch 2")
  for torch_bn, path in ((enc.mhca_stages[3].aggregate.bn, ("mhca_stages_3", "aggregate", "bn")),
                         (enc.stem[0].bn, ("stem_0", "bn"))):
    bs = new_vars["batch_stats"]["encoder"]
    for p in path:
      bs = bs[p]
    d_mean = float(np.max(np.abs(np.asarray(bs["mean"]) - torch_bn.running_mean.numpy())))
    d_var = float(np.max(np.abs(np.asarray(bs["var"]) / torch_bn.running_var.numpy() - 1)))
    print(f"{'/'.join(path)} running mean max abs diff {d_mean:.2e}, var max rel diff {d_var:.2e}")
    assert d_mean < 1e-4 and d_var < 1e-4


def _is_norm_leaf(path: str, flat: dict) -> bool:
  """BN/LN scale or bias (a module with a `scale` is a norm layer)."""
  module, leaf = path.rsplit("/", 1)
  return leaf in ("scale", "bias") and f"{module}/scale" in flat


# InvRes ends in a BN whose output only reaches the aggregate 1x1 conv + train-mode BN: a per-
# channel shift of it is removed by that BN's batch mean, so d(loss)/d(beta) is exactly 0 (both
# frameworks give ~1e-19 rounding noise there, which has no relative accuracy).
STRUCTURALLY_ZERO = "/InvRes/conv2/bn/bias"


def test_norm_gradients_match_torch_float64(tiny):
  """d(loss)/d(every encoder BN and LN gamma, beta), train-mode BN, float64 JAX vs torch.

  The loss weighs the encoder's 5 feature maps: every encoder norm layer reaches it, and the
  decoder (no norm layer; standard ops and `layers.Conv`, whose gradient test_conv_vjp checks)
  would triple the cost of this test with its float64 backward at full resolution.
  """
  x = _image(11)
  rng = np.random.default_rng(5)
  e = TINY["embed_dims"]  # feature maps at 1/2 .. 1/32 with these channels:
  weights = [rng.normal(size=(1, H >> s, W >> s, c))
             for s, c in zip(range(1, 6), (e[0], e[1], e[2], e[3], e[3]))]
  enc = tm.bn_train_(copy.deepcopy(tiny["enc"]).double())
  feats = enc(_nchw(x, torch.float64))
  loss_t = sum((f.permute(0, 2, 3, 1) * torch.from_numpy(w)).mean() for f, w in zip(feats, weights))
  loss_t.backward()
  ref = tm.norm_grads(enc)

  encoder = MPViT(**TINY)
  with jax.enable_x64(True):
    variables = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64),
                                       {c: v["encoder"] for c, v in tiny["variables"].items()})
    flat = flatten_dict(variables["params"], sep="/")
    norms = {k: v for k, v in flat.items() if _is_norm_leaf(k, flat)}
    rest = {k: v for k, v in flat.items() if k not in norms}

    def loss_fn(norms, rest, batch_stats, x, weights):
      params = unflatten_dict({**rest, **norms}, sep="/")
      feats = encoder.apply({"params": params, "batch_stats": batch_stats}, x, train=True)
      return sum(jnp.mean(f * w) for f, w in zip(feats, weights))

    loss_j, grads = _run_once(jax.value_and_grad(loss_fn), norms, rest, variables["batch_stats"],
                              jnp.asarray(x, jnp.float64), [jnp.asarray(w) for w in weights])
    grads = {k: np.asarray(v) for k, v in grads.items()}
  n_bn, n_ln = 2 + 5 + 4 * 4, 2 * 7  # stem, patch embeds, InvRes + aggregate; 7 MHCA blocks
  assert set(grads) == set(ref) and len(ref) == 2 * (n_bn + n_ln)
  zero = [k for k in ref if k.endswith(STRUCTURALLY_ZERO)]
  scale = max(float(np.max(np.abs(r))) for r in ref.values())
  for k in zero:
    assert max(np.max(np.abs(ref[k])), np.max(np.abs(grads[k]))) < 1e-12 * scale, k
  rel = {k: float(np.max(np.abs(grads[k] - ref[k])) / np.max(np.abs(ref[k])))
         for k in ref if k not in zero}
  is_ln = lambda k: "/norm1/" in k or "/norm2/" in k
  rel_bn = max(v for k, v in rel.items() if not is_ln(k))
  rel_ln = max(v for k, v in rel.items() if is_ln(k))
  print(f"loss float64: jax {float(loss_j):.12f} torch {loss_t.item():.12f}")
  print(f"encoder norm gamma/beta grads, worst max-relative diff: {n_bn} BN layers {rel_bn:.2e}, "
        f"{n_ln} LN layers {rel_ln:.2e} ({len(zero)} structurally zero BN betas: |grad| < 1e-12 "
        f"of the largest)")
  np.testing.assert_allclose(float(loss_j), loss_t.item(), rtol=1e-10)
  assert max(rel_bn, rel_ln) < 1e-9


def test_both_layouts_convert_identically(tiny, tmp_path):
  """DeepNet via DataParallel (`module.encoder.*`, `module.decoder.*`, no size entries) and
  encoder.pth + depth.pth give the same variables; the former needs the size given."""
  root = tiny["root"]
  with pytest.raises(CheckpointError, match="--height and --width"):
    convert_monovit(None, root / "deepnet.pth")
  config, variables = convert_monovit(root / "encoder.pth", root / "depth.pth")
  assert (config["height"], config["width"], config["use_stereo"]) == (192, 640, False)
  # the text 'False' (a non-empty string) was read as true, and evaluation scaled by x5.4
  torch.save(dict(torch.load(root / "encoder.pth"), use_stereo="False"), tmp_path / "text.pth")
  with pytest.raises(CheckpointError, match=r"text\.pth: its 'use_stereo' entry is 'False', "
                                            r"expected True or False"):
    convert_monovit(tmp_path / "text.pth", root / "depth.pth")
  leaves = jax.tree_util.tree_leaves
  for a, b in zip(leaves(variables), leaves(tiny["variables"])):
    np.testing.assert_array_equal(a, b)


def test_run_writes_a_weights_directory(tiny, tmp_path):
  parser = argparse.ArgumentParser()
  add_arguments(parser)
  args = parser.parse_args(["--depth", str(tiny["root"] / "deepnet.pth"), "--height", "320",
                            "--width", "1024", "--out", str(tmp_path / "w")])
  out = run(args)
  meta = json.loads((out / "model.json").read_text())
  assert (meta["architecture"], meta["height"], meta["width"]) == ("monovit", 320, 1024)
  assert meta["num_layers"] == list(TINY["num_layers"]) and (out / "depth").is_dir()
  assert "use_stereo" not in meta  # the single file records none: median scaling
  # the mono+stereo release, which records no use_stereo either: evaluated with x5.4
  args = parser.parse_args(["--depth", str(tiny["root"] / "deepnet.pth"), "--height", "320",
                            "--width", "1024", "--use-stereo", "--out", str(tmp_path / "ms")])
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.run import model_alignment
  assert json.loads((run(args) / "model.json").read_text())["use_stereo"] is True
  assert model_alignment(load_weights(tmp_path / "ms")) == "stereo"


def test_input_size_must_be_multiple_of_32(tiny):
  with pytest.raises(ValueError, match="multiples of 32"):
    MonoViT(**TINY).apply(tiny["variables"], np.zeros((1, 80, 96, 3), np.float32))


# --- strict loading --------------------------------------------------------------------------


def test_unexpected_missing_and_misshapen_keys_are_named(tiny, tmp_path):
  root = tiny["root"]
  state = torch.load(root / "depth.pth")
  bad = {k: v for k, v in state.items() if not k.startswith(("convs.dispconv3.", "decoder.36."))}
  bad["convs.dispconv9.conv.weight"] = torch.zeros(1)
  torch.save(bad, tmp_path / "keys.pth")
  with pytest.raises(CheckpointError, match=r"1 unexpected keys: convs.dispconv9.conv.weight; "
                     r"4 missing keys: convs.dispconv3.conv.bias, convs.dispconv3.conv.weight, "
                     r"decoder.36.conv.bias, decoder.36.conv.weight"):
    convert_monovit(root / "encoder.pth", tmp_path / "keys.pth")
  wrong = dict(state)
  for k in ("convs.X_40_Conv_0.conv.conv.weight", "decoder.8.conv.conv.weight"):
    wrong[k] = torch.zeros(256, 512, 1, 1)  # a 1x1 kernel instead of 3x3
  torch.save(wrong, tmp_path / "shape.pth")
  with pytest.raises(CheckpointError,
                     match=r"convs.X_40_Conv_0.conv.conv.weight has shape \(256, 512, 1, 1\)"):
    convert_monovit(root / "encoder.pth", tmp_path / "shape.pth")


def test_shared_module_copies_must_agree(tiny, tmp_path):
  """The duplicate names of one shared module are checked equal, not silently dropped."""
  root = tiny["root"]
  state = torch.load(root / "encoder.pth")
  alias = "mhca_stages.0.mhca_blks.1.MHCA_layers.1.factoratt_crpe.crpe.conv_list.1.weight"
  state[alias] = state[alias] + 1.0
  torch.save(state, tmp_path / "encoder.pth")
  with pytest.raises(CheckpointError, match=rf"{alias} differs from "
                     r"mhca_stages.0.mhca_blks.1.crpe.conv_list.1.weight"):
    convert_monovit(tmp_path / "encoder.pth", root / "depth.pth")
  dec = torch.load(root / "depth.pth")
  dec["decoder.0.conv_se.bias"] = dec["decoder.0.conv_se.bias"] * 2
  torch.save(dec, tmp_path / "depth.pth")
  with pytest.raises(CheckpointError, match=r"decoder.0.conv_se.bias differs from "
                     r"convs.f4.conv_se.bias"):
    convert_monovit(root / "encoder.pth", tmp_path / "depth.pth")


def test_wrong_files_are_named(tiny):
  root = tiny["root"]
  with pytest.raises(CheckpointError, match=r"depth.pth: expected MPViT patch_embed_stages"):
    convert_monovit(root / "depth.pth", root / "encoder.pth")  # swapped
  with pytest.raises(CheckpointError, match=r"deepnet.pth: holds a whole DeepNet"):
    convert_monovit(root / "encoder.pth", root / "deepnet.pth")


def test_partial_data_parallel_prefix_is_an_error(tiny, tmp_path):
  state = torch.load(tiny["root"] / "depth.pth")
  state = {("module." + k if k.startswith("convs.") else k): v for k, v in state.items()}
  torch.save(state, tmp_path / "depth.pth")
  with pytest.raises(CheckpointError, match="expected all or none"):
    convert_monovit(tiny["root"] / "encoder.pth", tmp_path / "depth.pth")


def test_a_given_size_must_agree_with_the_file_and_a_given_use_stereo_wins(tiny):
  """encoder.pth records its training size (192x640 here): --height/--width that contradict it
  are refused, named; --use-stereo given explicitly is taken over the file's `use_stereo`
  entry (the entry is the default only when the flag is not given)."""
  root = tiny["root"]
  with pytest.raises(CheckpointError, match=r"encoder\.pth: records height = 192, but 320 was "
                                            r"given"):
    convert_monovit(root / "encoder.pth", root / "depth.pth", height=320, width=640)
  config, _ = convert_monovit(root / "encoder.pth", root / "depth.pth", height=192, width=640,
                              use_stereo=True)
  assert (config["height"], config["width"], config["use_stereo"]) == (192, 640, True)


def test_a_given_size_is_checked_before_any_file_is_read(tmp_path, capsys):
  """--height/--width outside MonoViT's size rule (positive multiples of 32) are refused naming
  the flags before the checkpoint is read, as SGDepth's are: they were taken as given, the file
  read and converted, and then refused by the weights' writer without naming a flag."""
  from weights_convert.cli import main
  with pytest.raises(ValueError, match=r"^--height/--width: input size 640x100 \(WxH\) is not "
                                       r"supported by monovit"):
    convert_monovit(None, tmp_path / "absent.pth", height=100, width=640)
  with pytest.raises(ValueError, match=r"^--height/--width: input size 640x0 "):
    convert_monovit(tmp_path / "absent.pth", tmp_path / "absent.pth", height=0)
  out = tmp_path / "w"
  assert main(["monovit", "--depth", str(tmp_path / "absent.pth"), "--height", "-320",
               "--width", "1024", "--out", str(out)]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: --height/--width: input size 1024x-320 ") and err.count("\n") == 1
  assert not out.exists()


def test_a_stage_whose_widths_do_not_divide_is_not_an_mpvit_stage(tiny):
  """The layout is read from shapes: an MLP width that is no multiple of the stage width (an
  MPViT MLP is mlp_ratio x width) is named as not an MPViT stage, rather than floored into a
  ratio that then fails on some shape."""
  from weights_convert.monovit import infer_layout
  state = torch.load(tiny["root"] / "encoder.pth")
  state["mhca_stages.0.mhca_blks.0.MHCA_layers.0.mlp.fc1.weight"] = torch.zeros(100, 64)
  with pytest.raises(CheckpointError, match=r"^enc\.pth: mhca_stages\.0 has width 64, MLP width "
                                            r"100 and 8 channels per head; not an MPViT stage$"):
    infer_layout(state, "enc.pth")
