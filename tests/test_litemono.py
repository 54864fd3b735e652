"""Parity of the Flax Lite-Mono + converter with an independent PyTorch Lite-Mono.

Reference: `tests/torch_litemono.py`, a PyTorch Lite-Mono (base model) with upstream's state_dict
names, random O(1) weights and non-trivial BN statistics, saved with `torch.save` as upstream's
trainer lays it out (encoder.pth with height/width/use_stereo, depth.pth), converted by
`weights_convert.litemono` (which does not use torch), and compared output by output.
Tolerances: 1e-4 max abs on disparities (float32); 1e-6 relative on float64 gradients (measured
~3e-8: the float32 sin map of the position encoding).
Inputs are 96x64 (the smallest comfortable multiple of 16) to keep compile and run times low.
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
import flax.linen as nn
from flax.traverse_util import flatten_dict, unflatten_dict

import torch_litemono as tl
from pitta_jax.checkpoint import load_tree
from pitta_jax.models.litemono import SPEC
from weights_convert.litemono import convert_litemono, run
from weights_convert.pth import CheckpointError

torch.set_num_threads(2)
H, W = 64, 96
METADATA = {"height": 192, "width": 640, "use_stereo": False}


def _save(root, model="lite-mono", seed=0, meta=METADATA):
  """Random torch encoder + decoder saved as encoder.pth (+ metadata) and depth.pth."""
  enc = tl.LiteMono(model, meta["height"], meta["width"])
  dec = tl.DepthDecoder(enc.num_ch_enc)
  tl.randomize_(enc, 2 * seed)
  tl.randomize_(dec, 2 * seed + 1)
  root.mkdir(parents=True, exist_ok=True)
  torch.save(dict(enc.state_dict(), **meta), root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  return root / "encoder.pth", root / "depth.pth"


def _load_torch(paths, dtype=torch.float32, meta=METADATA):
  """A fresh torch model from the saved files (train mode mutates BN statistics)."""
  enc = tl.LiteMono("lite-mono", meta["height"], meta["width"])
  enc.load_state_dict({k: v for k, v in torch.load(paths[0]).items() if k not in meta})
  dec = tl.DepthDecoder(enc.num_ch_enc)
  dec.load_state_dict(torch.load(paths[1]))
  return enc.to(dtype), dec.to(dtype)


def _torch_disps(enc, dec, x_nhwc, dtype=torch.float32):
  out = dec(enc(torch.from_numpy(x_nhwc).to(dtype).permute(0, 3, 1, 2)))
  return [out[("disp", s)].permute(0, 2, 3, 1) for s in range(3)]


def _image(seed=0, batch=1):
  return np.random.default_rng(seed).uniform(0, 1, (batch, H, W, 3)).astype(np.float32)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
  root = tmp_path_factory.mktemp("litemono_640x192")
  paths = _save(root)
  config, variables = convert_litemono(*paths)
  return {"root": root, "paths": paths, "config": config, "variables": variables}


@pytest.fixture(scope="module")
def fns(base):
  net = SPEC.build(base["config"])
  eval_fn = jax.jit(lambda v, x: net.apply(v, x, train=False))
  train_fn = jax.jit(lambda v, x: net.apply(v, x, train=True, mutable=["batch_stats"]))
  return eval_fn, train_fn


def test_config_and_variant(base):
  assert base["config"] == {"model": "lite-mono", "height": 192, "width": 640, "use_stereo": False}
  n = sum(a.size for a in jax.tree_util.tree_leaves(base["variables"]["params"]))
  assert 3.0e6 < n < 3.2e6  # upstream's table: 3.1M parameters


def test_eval_mode_disparities_match_torch(base, fns):
  enc, dec = _load_torch(base["paths"])
  x = _image(seed=1, batch=2)
  with torch.no_grad():
    ref = [r.numpy() for r in _torch_disps(enc.eval(), dec.eval(), x)]
  out = fns[0](base["variables"], x)
  assert len(out) == 3
  for s in range(3):
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref[s])))
    print(f"eval {W}x{H} scale {s}: max abs diff {diff:.2e} (disp range {ref[s].min():.3f}.."
          f"{ref[s].max():.3f})")
    assert out[s].shape == ref[s].shape == (2, H >> s, W >> s, 1)
    assert diff < 1e-4


def test_train_mode_bn_matches_torch(base, fns):
  """Train-mode BN: batch statistics (biased) to normalise, unbiased into the running estimate."""
  enc, dec = _load_torch(base["paths"])
  enc.train(), dec.train()
  x = _image(seed=2, batch=2)
  with torch.no_grad():
    ref = [r.numpy() for r in _torch_disps(enc, dec, x)]
  out, new_vars = fns[1](base["variables"], x)
  for s in range(3):
    diff = float(np.max(np.abs(np.asarray(out[s]) - ref[s])))
    print(f"train-BN {W}x{H} scale {s}: max abs diff {diff:.2e}")
    assert diff < 1e-4
  stats = new_vars["batch_stats"]["encoder"]
  for torch_bn, flax_bn in ((enc.downsample_layers[0][1].bn_gelu.bn, "downsample_layers_0_1/bn"),
                            (enc.stages[2][8].bn1, "stages_2_8/bn1")):
    bs = stats[flax_bn.split("/")[0]][flax_bn.split("/")[1]]
    d_mean = float(np.max(np.abs(np.asarray(bs["mean"]) - torch_bn.running_mean.numpy())))
    d_var = float(np.max(np.abs(np.asarray(bs["var"]) - torch_bn.running_var.numpy())
                         / torch_bn.running_var.numpy()))
    print(f"{flax_bn}: running mean max abs diff {d_mean:.2e}, var max rel diff {d_var:.2e}")
    assert d_mean < 1e-5 and d_var < 1e-5


def test_norm_gradients_match_torch_autograd_float64(base):
  """d(loss)/d(encoder BN and LN gamma, beta), train-mode BN, float64 JAX vs float64 torch."""
  rng = np.random.default_rng(5)
  weights = [rng.normal(size=(1, H >> s, W >> s, 1)) for s in range(3)]
  x = _image(seed=3)

  enc, dec = _load_torch(base["paths"], torch.float64)
  enc.train(), dec.train()
  disps = _torch_disps(enc, dec, x, torch.float64)
  loss_t = sum((d * torch.from_numpy(w)).mean() for d, w in zip(disps, weights))
  loss_t.backward()
  ref = tl.norm_grads(enc)

  net = SPEC.build(base["config"])

  def loss_fn(norm_leaves, variables, x, weights):
    """The loss as a function of the norm leaves; everything else is an argument, not a
    constant baked into the program (3M constants would make the compile several times slower)."""
    flat = flatten_dict(variables["params"]["encoder"], sep="/")
    encoder = unflatten_dict({**flat, **norm_leaves}, sep="/")
    params = dict(variables["params"], encoder=encoder)
    out = net.apply({"params": params, "batch_stats": variables["batch_stats"]}, x, train=True)
    return sum(jnp.mean(d * w) for d, w in zip(out, weights))

  with jax.enable_x64(True):
    f64 = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), t)
    variables = f64(base["variables"])
    flat = flatten_dict(variables["params"]["encoder"], sep="/")
    norm_layers = {k.rsplit("/", 1)[0] for k in flat if k.endswith("/scale")}  # BN and LN
    norms = {k: v for k, v in flat.items() if k.rsplit("/", 1)[0] in norm_layers}
    loss_j, grads = jax.jit(jax.value_and_grad(loss_fn))(
        norms, variables, f64(x), f64(weights))
    grads = {k: np.asarray(v) for k, v in grads.items()}
    loss_j = float(loss_j)

  assert set(grads) == set(ref)
  bn = sorted({k.rsplit("/", 1)[0] for k in ref if "/bn" in k})
  ln = sorted({k.rsplit("/", 1)[0] for k in ref if "/norm" in k})
  assert len(bn) == 3 + 15 and len(ln) == 6  # stem BN-GELUs + DilatedConv bn1; LGFI norm_xca, norm
  rel = {k: float(np.max(np.abs(grads[k] - ref[k])) / np.max(np.abs(ref[k]))) for k in ref}
  worst_bn = max(v for k, v in rel.items() if "/bn" in k)
  worst_ln = max(v for k, v in rel.items() if "/norm" in k)
  print(f"loss float64: jax {loss_j:.12f} torch {loss_t.item():.12f}")
  print(f"gamma/beta grads, worst max-relative diff: BN ({2 * len(bn)} leaves) {worst_bn:.2e}, "
        f"LN ({2 * len(ln)} leaves) {worst_ln:.2e}")
  np.testing.assert_allclose(loss_j, loss_t.item(), rtol=1e-8)  # float32 sin map: ~1e-10
  assert worst_bn < 1e-6 and worst_ln < 1e-6


def test_training_size_selects_upstream_dilations(tmp_path, base):
  """encoder.pth's height/width select the dilation rates (1, 2, 5, ... at 1024x320); the rates
  of every model size and training size agree with the reference's (running the network for
  each would cost one compile per table entry)."""
  from pitta_jax.models.litemono import VARIANTS, dilations_for
  for model in VARIANTS:
    for hw in ((192, 640), (320, 1024)):
      assert dilations_for(model, *hw) == tuple(map(tuple, tl.dilation_table(model, *hw))), model
  enc_state = torch.load(base["paths"][0])
  torch.save(dict(enc_state, height=320, width=1024), tmp_path / "encoder.pth")
  config, variables = convert_litemono(tmp_path / "encoder.pth", base["paths"][1])
  assert (config["height"], config["width"]) == (320, 1024)
  module = SPEC.build(config)
  rates = [m.dilation for m in _bound_modules(module, variables, "ddwconv")]
  assert rates == [d for stage in dilations_for("lite-mono", 320, 1024) for d in stage]


def _bound_modules(module, variables, name: str) -> list:
  """The submodules called `name`, in creation order, of `module` run once on a tiny input."""
  found = []

  def keep(next_fun, args, kwargs, context):
    if context.module.name == name and context.method_name == "__call__":
      found.append(context.module)
    return next_fun(*args, **kwargs)

  with nn.intercept_methods(keep):
    jax.eval_shape(lambda v: module.apply(v, jnp.zeros((1, 16, 16, 3))), variables)
  return found


def test_run_writes_a_weights_directory(base, tmp_path):
  enc, depth = base["paths"]
  out = run(argparse.Namespace(encoder=enc, depth=depth, model=None, out=tmp_path / "w"))
  meta = json.loads((out / "model.json").read_text())
  assert meta["architecture"] == SPEC.name == "litemono"
  assert {k: meta[k] for k in base["config"]} == base["config"]
  loaded = load_tree(out / "depth")
  for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(base["variables"])):
    np.testing.assert_array_equal(a, b)


def test_input_size_must_be_multiple_of_16(base):
  SPEC.check_size(192, 640)
  with pytest.raises(ValueError, match="multiples of 16"):
    SPEC.build(base["config"]).apply(base["variables"], np.zeros((1, 72, 96, 3), np.float32))


# --- strict loading -------------------------------------------------------------------------------

def test_unexpected_missing_and_misshapen_keys_are_named(base, tmp_path):
  enc_path, dep_path = base["paths"]
  enc_state = torch.load(enc_path)
  extra = dict(enc_state, **{"stages.1.2.extra.weight": torch.zeros(1)})
  torch.save(extra, tmp_path / "extra.pth")
  with pytest.raises(CheckpointError,
                     match=r"extra.pth: 1 unexpected keys: stages.1.2.extra.weight"):
    convert_litemono(tmp_path / "extra.pth", dep_path)
  # an LGFI block's LayerNorm is used (only the DilatedConv blocks' `norm` is ignorable)
  missing = {k: v for k, v in enc_state.items() if not k.startswith("stages.2.9.norm.")}
  torch.save(missing, tmp_path / "missing.pth")
  with pytest.raises(CheckpointError,
                     match=r"2 missing keys: stages.2.9.norm.bias, stages.2.9.norm.weight"):
    convert_litemono(tmp_path / "missing.pth", dep_path)
  wrong = dict(enc_state, **{"stages.0.3.xca.temperature": torch.ones(6, 1, 1)})
  torch.save(wrong, tmp_path / "wrong.pth")
  with pytest.raises(CheckpointError, match=r"stages.0.3.xca.temperature has shape \(6, 1, 1\)"):
    convert_litemono(tmp_path / "wrong.pth", dep_path)
  dec_state = torch.load(dep_path)
  dropped = {k: v for k, v in dec_state.items() if not k.startswith("decoder.7.")}
  torch.save(dropped, tmp_path / "depth_missing.pth")
  with pytest.raises(CheckpointError,
                     match=r"depth_missing.pth: 2 missing keys: decoder.7.conv.bias"):
    convert_litemono(enc_path, tmp_path / "depth_missing.pth")


def test_unused_dilated_conv_norms_are_optional_and_untrained_sizes_refused(base, tmp_path):
  enc_path, dep_path = base["paths"]
  enc_state = torch.load(enc_path)
  lean = {k: v for k, v in enc_state.items() if not (k.startswith("stages.0.1.norm."))}
  torch.save(lean, tmp_path / "lean.pth")
  _, variables = convert_litemono(tmp_path / "lean.pth", dep_path)
  for a, b in zip(jax.tree_util.tree_leaves(variables),
                  jax.tree_util.tree_leaves(base["variables"])):
    np.testing.assert_array_equal(a, b)
  torch.save(dict(enc_state, height=256, width=512), tmp_path / "odd.pth")
  with pytest.raises(CheckpointError, match=r"odd.pth: lite-mono defines dilation rates only"):
    convert_litemono(tmp_path / "odd.pth", dep_path)


def test_use_stereo_is_carried_over_and_one_file_twice_is_named(base, tmp_path):
  """encoder.pth's `use_stereo` (upstream's trainer writes it) reaches the config, where it
  selects MonoDepth2's x5.4 stereo scaling in evaluation instead of the median; one file given
  as both encoder and decoder is named as such."""
  enc_path, dep_path = base["paths"]
  torch.save(dict(torch.load(enc_path), use_stereo=True), tmp_path / "stereo.pth")
  assert convert_litemono(tmp_path / "stereo.pth", dep_path)[0]["use_stereo"] is True
  # the text 'False' (a non-empty string) was read as true, and evaluation scaled by x5.4
  torch.save(dict(torch.load(enc_path), use_stereo="False"), tmp_path / "text.pth")
  with pytest.raises(CheckpointError, match=r"text\.pth: its 'use_stereo' entry is 'False', "
                                            r"expected True or False"):
    convert_litemono(tmp_path / "text.pth", dep_path)
  with pytest.raises(CheckpointError, match=r"encoder\.pth: keys .* also occur in "
                                            r".*encoder\.pth; .*the same file\?"):
    convert_litemono(enc_path, enc_path)


def test_xca_gradient_at_a_zero_token_is_torchs():
  """Reference: upstream's XCA (torch_litemono) under torch autograd, float64. Queries and keys
  of 0 (zero tokens through a bias-free qkv, e.g. a constant input after LayerNorm) are
  F.normalize'd over the tokens at a norm of 0, where torch's derivative is finite; the JAX
  sqrt-of-sum form gave NaN gradients for the qkv weights there."""
  from pitta_jax.models.litemono.encoder import XCA
  dim, heads, b, n = 8, 2, 1, 5
  ref = tl.XCA(dim, heads, qkv_bias=False).double()
  tl_rng = torch.Generator().manual_seed(0)
  with torch.no_grad():
    for p in ref.parameters():
      p.copy_(torch.randn(p.shape, generator=tl_rng, dtype=torch.float64))
  x = np.zeros((b, n, dim))  # every token 0: each channel's queries and keys have norm 0
  xt = torch.tensor(x, requires_grad=True)
  w = torch.randn(b, n, dim, generator=tl_rng, dtype=torch.float64)
  (ref(xt) * w).sum().backward()
  params = {"qkv": {"kernel": ref.qkv.weight.detach().numpy().T},
            "temperature": ref.temperature.detach().numpy(),
            "proj": {"kernel": ref.proj.weight.detach().numpy().T,
                     "bias": ref.proj.bias.detach().numpy()}}
  module = XCA(dim, heads, qkv_bias=False)
  with jax.enable_x64(True):
    def loss(params, x):
      return jnp.sum(module.apply({"params": params}, x) * jnp.asarray(w.numpy()))
    grads, gx = jax.grad(loss, argnums=(0, 1))(jax.tree_util.tree_map(jnp.asarray, params),
                                               jnp.asarray(x))
  np.testing.assert_allclose(np.asarray(grads["qkv"]["kernel"]), ref.qkv.weight.grad.numpy().T,
                             rtol=1e-9, atol=1e-12)
  np.testing.assert_allclose(np.asarray(grads["temperature"]), ref.temperature.grad.numpy(),
                             rtol=1e-9, atol=1e-12)
  np.testing.assert_allclose(np.asarray(gx), xt.grad.numpy(), rtol=1e-9, atol=1e-12)
