"""Parity of the Flax Depth Anything V2 + converter with PyTorch, for both checkpoint formats.

References: transformers' `DepthAnythingForDepthEstimation` (the `hf` format) and
`tests/torch_depth_anything_v2.py`, upstream's architecture with its state_dict names (the
`official` format; transformers lacks upstream's position-embedding resize). One set of random
weights (scaled so that activations stay O(1)) is drawn in upstream's layout and written as
upstream's `.pth` and as a Hub-style `model.safetensors` (+ `config.json`); each file is
converted by `weights_convert.depth_anything_v2` (torch-free) and compared with its own
reference: outputs within 1e-4 max abs (float32), at 518x518 (the stored 37x37 position grid,
no resize) and 644x196 (resized), and the gradient of a scalar loss w.r.t. every encoder
LayerNorm gamma/beta in float64 within 2e-5 relative (measured ~1.6e-6: the position
embeddings are resized in float32 on both sides). The tests use a narrow 4-block ViT
(width 48, 3 heads) for time; the real ViT-S/14 + DPT sizes are checked by conversion (key
tables, sizes inferred from the weights), and their full-size parity (518x518 and 644x196, both
formats, float64 gradients) is `full_size_vits_matches_torch`, run by
`python benchmarks/dav2_full_parity.py` (about a minute of CPU, outside the timed suite).

float32: torch's own float32 output is further from its float64 one than ours (measured at
518x518: torch 7.2e-5, JAX 8.0e-6 max abs), so the float32 differences printed here are mostly
torch's rounding. float64: both torch models resize the position embeddings in float32
(upstream's `.float()`, transformers' `.to(torch.float32)`), which bounds the float64 agreement
at ~1e-6 relative in outputs and up to ~2e-4 in the smallest gradient leaves of the full ViT-S.
"""

from __future__ import annotations

import argparse
import json
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from flax.traverse_util import flatten_dict, unflatten_dict
from safetensors.torch import save_file

import torch_depth_anything_v2 as tda
from pitta_jax.checkpoint import load_tree
from pitta_jax.models.depth_anything_v2 import SPEC, build
from pitta_jax.models.depth_anything_v2.dinov2 import pos_embed_matrix
from weights_convert import depth_anything_v2 as conv
from weights_convert.pth import CheckpointError

torch.set_num_threads(2)

MEAN = np.array([0.485, 0.456, 0.406])
STD = np.array([0.229, 0.224, 0.225])
# the narrow test network: (width, blocks, heads, HF out_indices, features, neck widths, head width)
SMALL = dict(hidden=48, depth=4, heads=3, out_indices=[1, 2, 3, 4], features=16,
             neck=[8, 16, 24, 32], head_hidden=8)
VITS = dict(hidden=384, depth=12, heads=6, out_indices=[3, 6, 9, 12], features=64,
            neck=[48, 96, 192, 384], head_hidden=32)
VITS_CONFIG = dict(encoder="vits", embed_dim=384, depth=12, num_heads=6, mlp_ratio=4.0,
                   layer_idx=[2, 5, 8, 11], pos_grid=37, features=64,
                   out_channels=[48, 96, 192, 384], head_features=32, height=518, width=518)
HUB_NAMES = ((".attention.q_proj.", ".attention.attention.query."),
             (".attention.k_proj.", ".attention.attention.key."),
             (".attention.v_proj.", ".attention.attention.value."),
             (".attention.o_proj.", ".attention.output.dense."))


def _hf_model(arch: dict, state: dict, **head):
  """transformers' Depth Anything (V2 layout) holding `state` (transformers 5 names), eval mode;
  `head`: DepthAnythingConfig's depth_estimation_type / max_depth."""
  from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config
  backbone = Dinov2Config(image_size=518, patch_size=14, hidden_size=arch["hidden"],
                          num_hidden_layers=arch["depth"], num_attention_heads=arch["heads"],
                          mlp_ratio=4, out_indices=arch["out_indices"], apply_layernorm=True,
                          reshape_hidden_states=False, layer_norm_eps=1e-6, hidden_act="gelu")
  config = DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=arch["hidden"],
                               patch_size=14, neck_hidden_sizes=arch["neck"],
                               fusion_hidden_size=arch["features"],
                               head_hidden_size=arch["head_hidden"], **head)
  model = DepthAnythingForDepthEstimation(config).eval()
  model.load_state_dict(state, strict=True)
  return model


def _write_checkpoints(root, arch: dict, seed: int):
  """Random weights in upstream's layout -> root/official/depth_anything_v2.pth and
  root/hf/model.safetensors (Hub names). Returns (upstream torch model, transformers-5 state)."""
  off = tda.randomize_(tda.DepthAnythingV2(
      arch["hidden"], arch["depth"], arch["heads"], [i - 1 for i in arch["out_indices"]],
      arch["features"], arch["neck"], arch["head_hidden"]), seed)
  official_state = off.state_dict()
  (root / "official").mkdir(parents=True)
  torch.save(official_state, root / "official" / "depth_anything_v2.pth")
  state = tda.hf_state_from_official(official_state, arch["depth"])
  hub = {}
  for k, v in state.items():
    for new, old in HUB_NAMES:
      k = k.replace(new, old)
    hub[k] = v
  (root / "hf").mkdir()
  save_file(hub, str(root / "hf" / "model.safetensors"))
  return off, state


@pytest.fixture(scope="module")
def small(tmp_path_factory):
  """The narrow network in both formats, its torch references and both conversions."""
  root = tmp_path_factory.mktemp("dav2_small")
  off, state = _write_checkpoints(root, SMALL, seed=0)
  hf = _hf_model(SMALL, state)
  hf.config.to_json_file(str(root / "hf" / "config.json"))  # as a Hub snapshot has it
  arch = {"num_heads": SMALL["heads"], "layer_idx": [i - 1 for i in SMALL["out_indices"]]}
  converted = {"hf": conv.convert_depth_anything_v2(root / "hf" / "model.safetensors", "hf"),
               "official": conv.convert_depth_anything_v2(
                   root / "official" / "depth_anything_v2.pth", "official", arch)}
  fns = {fmt: jax.jit(lambda v, x, m=build(cfg): m.apply(v, x)[0])
         for fmt, (cfg, _) in converted.items()}
  return {"root": root, "torch": {"hf": hf, "official": off}, "state": state,
          "converted": converted, "fns": fns, "cache": {}}


def _image(h, w, seed=0, batch=1):
  return np.random.default_rng(seed).uniform(0, 1, (batch, h, w, 3)).astype(np.float32)


def _torch_input(x: np.ndarray, dtype=torch.float32) -> torch.Tensor:
  return torch.from_numpy((x.astype(np.float64) - MEAN) / STD).to(dtype).permute(0, 3, 1, 2)


def _torch_depth(model, fmt: str, x: np.ndarray) -> np.ndarray:
  """(B, H, W, 1) relative inverse depth of a torch reference."""
  with torch.no_grad():
    out = model(_torch_input(x))
    out = out.predicted_depth if fmt == "hf" else out
  return out[..., None].numpy()


def _reference(small, fmt, hw):
  key = (fmt, hw)
  if key not in small["cache"]:
    small["cache"][key] = _torch_depth(small["torch"][fmt], fmt, _image(*hw, seed=hw[1]))
  return small["cache"][key]


def test_torch_references_agree_without_resize(small):
  """Sanity of the test's own official -> hf renaming (`tda.hf_state_from_official`, loaded
  strictly): at the stored grid both torch models, holding the same weights, compute the same
  function."""
  d = float(np.max(np.abs(_reference(small, "hf", (518, 518)) -
                          _reference(small, "official", (518, 518)))))
  print(f"518x518 transformers vs upstream-layout torch: max abs diff {d:.2e}")
  assert d < 1e-5


@pytest.mark.parametrize("hw", [(518, 518), (196, 644)])
@pytest.mark.parametrize("fmt", ["official", "hf"])
def test_outputs_match_torch(small, fmt, hw):
  x = _image(*hw, seed=hw[1])
  ref = _reference(small, fmt, hw)
  # at the stored 37x37 grid the resize rule (the configs' only difference) is not used, so the
  # program compiled for the official config serves the hf variables too
  fn = small["fns"]["official" if hw == (518, 518) else fmt]
  out = np.asarray(fn(small["converted"][fmt][1], x))
  diff = float(np.max(np.abs(out - ref)))
  scale = float(np.max(np.abs(ref)))
  print(f"{fmt} {hw[1]}x{hw[0]}: max abs diff {diff:.2e} (output max {scale:.3f}, "
        f"relative {diff / scale:.2e}, {np.mean(ref > 0):.0%} positive)")
  assert out.shape == ref.shape == (1, *hw, 1)
  assert diff < 1e-4 * max(1.0, scale)


def test_resize_rules_differ_between_formats(small):
  """Off the stored grid the two upstreams differ (0.1 offset or not): each conversion records
  its rule, and the torch references disagree measurably where the rules are not matched."""
  cfg_o, cfg_h = small["converted"]["official"][0], small["converted"]["hf"][0]
  assert (cfg_o["pos_offset"], cfg_h["pos_offset"]) == (0.1, 0.0)
  assert dict(cfg_o, pos_offset=0.0) == cfg_h  # config.json gave the hf file's heads and layers
  d = float(np.max(np.abs(_reference(small, "hf", (196, 644)) -
                          _reference(small, "official", (196, 644)))))
  print(f"644x196 transformers vs upstream resize rule: max abs diff {d:.2e}")
  assert d > 1e-3


@pytest.mark.parametrize("grid", [(5, 7), (14, 46), (40, 37)])
def test_pos_embed_resize_matches_torch(grid):
  table = np.random.default_rng(1).normal(size=(1, 4, 9, 9)).astype(np.float32)  # (1, C, g, g)
  for offset in (0.1, 0.0):
    if offset:
      kw = {"scale_factor": ((grid[0] + offset) / 9, (grid[1] + offset) / 9)}
    else:
      kw = {"size": grid}
    ref = torch.nn.functional.interpolate(torch.from_numpy(table), mode="bicubic",
                                          antialias=False, **kw).numpy()[0]
    mh, mw = pos_embed_matrix(9, grid[0], offset), pos_embed_matrix(9, grid[1], offset)
    out = np.einsum("ph,chw,qw->cpq", mh, table[0], mw)
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)  # torch weights in float32


def _ln_grads_torch(model, fmt, x, weights):
  """Torch float64 autograd of mean(out * weights) w.r.t. every encoder LayerNorm gamma/beta,
  keyed by the Flax path (blocks_i/norm1|norm2, norm) and scale|bias."""
  model = model.to(torch.float64)
  model.zero_grad()
  out = model(_torch_input(x, torch.float64))
  out = out.predicted_depth if fmt == "hf" else out
  loss = (out * torch.from_numpy(weights[..., 0])).mean()
  loss.backward()
  if fmt == "hf":
    pattern = r"^backbone\.(?:encoder\.layer\.(\d+)\.(norm[12])|(layernorm))\.(weight|bias)$"
  else:
    pattern = r"^pretrained\.(?:blocks\.(\d+)\.(norm[12])|(norm))\.(weight|bias)$"
  grads = {}
  for name, p in model.named_parameters():
    m = re.match(pattern, name)
    if m:
      module = f"blocks_{m.group(1)}/{m.group(2)}" if m.group(1) else "norm"
      leaf = "scale" if m.group(4) == "weight" else "bias"
      grads[f"{module}/{leaf}"] = p.grad.numpy().copy()
  model.to(torch.float32)
  return loss.item(), grads


def _ln_grads_jax(cfg, variables, x, weights):
  """JAX float64 value and gradient of the same loss w.r.t. the encoder LayerNorm gamma/beta
  (only those leaves are differentiated, as in adaptation)."""
  module = build(cfg)
  with jax.enable_x64(True):
    flat = {k: jnp.asarray(v, jnp.float64)
            for k, v in flatten_dict(variables["params"], sep="/").items()}
    is_ln = lambda k: re.fullmatch(r"encoder/(blocks_\d+/)?norm\d?/(scale|bias)", k) is not None
    ln = {k: v for k, v in flat.items() if is_ln(k)}
    rest = {k: v for k, v in flat.items() if not is_ln(k)}

    def loss_fn(ln, rest, x, w):
      params = unflatten_dict({**ln, **rest}, sep="/")
      return jnp.mean(module.apply({"params": params}, x)[0] * w)

    loss, grads = jax.jit(jax.value_and_grad(loss_fn))(
        ln, rest, jnp.asarray(x, jnp.float64), jnp.asarray(weights, jnp.float64))
    return float(loss), {k[len("encoder/"):]: np.asarray(v) for k, v in grads.items()}


@pytest.mark.parametrize("fmt", ["official", "hf"])
def test_layernorm_gradients_match_torch_float64(small, fmt):
  """d mean(w * depth) / d(encoder LayerNorm gamma, beta) at 98x70 (position grid resized)."""
  x = _image(70, 98, seed=3).astype(np.float64)
  w = np.random.default_rng(4).normal(size=(1, 70, 98, 1))
  loss_t, ref = _ln_grads_torch(small["torch"][fmt], fmt, x, w)
  loss_j, grads = _ln_grads_jax(*small["converted"][fmt], x, w)
  assert set(grads) == set(ref) and len(ref) == 2 * 2 * SMALL["depth"] + 2
  rel = max(float(np.max(np.abs(grads[k] - ref[k])) / np.max(np.abs(ref[k]))) for k in ref)
  print(f"{fmt} float64: loss jax {loss_j:.12f} torch {loss_t:.12f}; LayerNorm gamma/beta "
        f"grads, worst max-relative diff over {len(ref)} leaves {rel:.2e}")
  # not 1e-12: both torch models resize the position embeddings in float32 (upstream's
  # `.float()`, transformers' `.to(torch.float32)`), models.interpolate's matrices are float32
  # constants, and the random-sign weights cancel ~1000x in the mean
  np.testing.assert_allclose(loss_j, loss_t, rtol=1e-5)
  assert rel < 2e-5


def test_train_flag_changes_nothing(small):
  """No BatchNorm, no dropout: train=True traces to the same program as train=False."""
  cfg, variables = small["converted"]["hf"]
  module, x = build(cfg), jnp.zeros((1, 28, 42, 3))
  jaxprs = [str(jax.make_jaxpr(lambda v, x, t=t: module.apply(v, x, train=t))(variables, x))
            for t in (False, True)]
  assert jaxprs[0] == jaxprs[1]


def test_vits_converts_from_either_format_with_upstream_sizes(tmp_path):
  """The real ViT-S/14 + DPT widths: sizes inferred from the weights without overrides (no
  config.json) and both formats give bitwise the same variables. (Its forward parity at full
  size is `full_size_vits_matches_torch`, not collected for time: `python
  benchmarks/dav2_full_parity.py` runs it.)"""
  _write_checkpoints(tmp_path, VITS, seed=1)
  cfg_o, var_o = conv.convert_depth_anything_v2(tmp_path / "official" / "depth_anything_v2.pth")
  cfg_h, var_h = conv.convert_depth_anything_v2(tmp_path / "hf" / "model.safetensors", "hf")
  assert cfg_o == dict(VITS_CONFIG, pos_offset=0.1) and cfg_h == dict(VITS_CONFIG, pos_offset=0.0)
  flat_o, flat_h = flatten_dict(var_o), flatten_dict(var_h)
  assert flat_o.keys() == flat_h.keys()
  for k in flat_o:
    np.testing.assert_array_equal(flat_o[k], flat_h[k])
  # upstream's ViT-S model holds 24,785,089 values (the paper's 24.8M); the converted ones lack
  # the unused mask token (384) and refinenet4.resConfUnit1 (2 x (64 * 64 * 9 + 64))
  official = torch.load(tmp_path / "official" / "depth_anything_v2.pth")
  n_file = sum(v.numel() for v in official.values())
  assert n_file == 24_785_089
  assert sum(a.size for a in flat_o.values()) == n_file - 384 - 2 * (64 * 64 * 9 + 64)


def full_size_vits_matches_torch(tmp_path):
  """Real ViT-S/14 + DPT at 518x518 (stored grid) and 644x196 (resized), both formats, against
  transformers and upstream's layout; LayerNorm gradients in float64 at 182x126."""
  off, state = _write_checkpoints(tmp_path, VITS, seed=1)
  refs = {"official": off, "hf": _hf_model(VITS, state)}
  converted = {
      "official": conv.convert_depth_anything_v2(tmp_path / "official" / "depth_anything_v2.pth"),
      "hf": conv.convert_depth_anything_v2(tmp_path / "hf" / "model.safetensors", "hf")}
  for fmt, (cfg, variables) in converted.items():
    fn = jax.jit(lambda v, x, m=build(cfg): m.apply(v, x)[0])
    for hw in ((518, 518), (196, 644)):
      x = _image(*hw, seed=hw[1])
      ref = _torch_depth(refs[fmt], fmt, x)
      out = np.asarray(fn(variables, x))
      diff, scale = float(np.max(np.abs(out - ref))), float(np.max(np.abs(ref)))
      print(f"ViT-S {fmt} {hw[1]}x{hw[0]}: max abs diff {diff:.2e} (output max {scale:.3f}, "
            f"relative {diff / scale:.2e})")
      assert diff < 1e-4 * max(1.0, scale)
    x = _image(126, 182, seed=3).astype(np.float64)
    w = np.random.default_rng(4).normal(size=(1, 126, 182, 1))
    _, ref = _ln_grads_torch(refs[fmt], fmt, x, w)
    _, grads = _ln_grads_jax(cfg, variables, x, w)
    rel = max(float(np.max(np.abs(grads[k] - ref[k])) / np.max(np.abs(ref[k]))) for k in ref)
    print(f"ViT-S {fmt} float64 LayerNorm grads ({len(ref)} leaves): worst max-relative "
          f"diff {rel:.2e}")
    assert len(ref) == 50 and rel < 1e-3


def test_transformers5_names_convert_like_hub_names(small, tmp_path):
  """A state dict saved from transformers >= 5 (attention.q_proj ...) converts identically."""
  save_file(small["state"], str(tmp_path / "model.safetensors"))
  cfg, variables = conv.convert_depth_anything_v2(tmp_path / "model.safetensors", "hf",
                                                  {"num_heads": 3, "layer_idx": [0, 1, 2, 3]})
  ref_cfg, ref = small["converted"]["hf"]
  assert dict(cfg, encoder="custom") == dict(ref_cfg, encoder="custom")
  for a, b in zip(jax.tree_util.tree_leaves(variables), jax.tree_util.tree_leaves(ref)):
    np.testing.assert_array_equal(a, b)


def test_hf_safetensors_is_known_by_its_content_not_its_name(small, tmp_path):
  """A Hub cache blob (a hash for a name, no suffix) or MODEL.SAFETENSORS converts as
  model.safetensors does; it had been refused as 'not a PyTorch checkpoint but a safetensors
  file ... --from hf', under --from hf."""
  ref_cfg, ref = small["converted"]["hf"]
  for name in ("5f3a9c0e1d", "MODEL.SAFETENSORS"):
    blob = tmp_path / name
    blob.write_bytes((small["root"] / "hf" / "model.safetensors").read_bytes())
    cfg, variables = conv.convert_depth_anything_v2(blob, "hf", {"num_heads": 3,
                                                                "layer_idx": [0, 1, 2, 3]})
    assert dict(cfg, encoder="custom") == dict(ref_cfg, encoder="custom")
    for a, b in zip(jax.tree_util.tree_leaves(variables), jax.tree_util.tree_leaves(ref)):
      np.testing.assert_array_equal(a, b)


def test_hf_config_json_is_read(small, tmp_path):
  """Heads and layers from config.json; its depth_estimation_type and max_depth say relative
  (max_depth 1) or metric (max_depth > 0 metres); anything else is refused."""
  cfg = small["converted"]["hf"][0]
  assert cfg["num_heads"] == 3 and cfg["layer_idx"] == [0, 1, 2, 3]  # from config.json
  assert "max_depth" not in cfg
  meta = json.loads((small["root"] / "hf" / "config.json").read_text())
  (tmp_path / "model.safetensors").write_bytes(
      (small["root"] / "hf" / "model.safetensors").read_bytes())
  for change, message in [({"depth_estimation_type": "metric", "max_depth": 20}, None),
                          ({"depth_estimation_type": "metric", "max_depth": 0},
                           r"a metric model needs max_depth > 0, got 0"),
                          ({"depth_estimation_type": "ordinal"},
                           r"depth_estimation_type 'ordinal'; expected relative or metric"),
                          ({"max_depth": 5}, r"max_depth 5 scales the relative model's output"),
                          # 0 heads was a ZeroDivisionError traceback, 5 (not dividing the
                          # width 48) was blamed on a --num-heads flag not given
                          *[({"backbone_config": dict(meta["backbone_config"],
                                                      num_attention_heads=h)}, message)
                            for h, message in [
                                (0, r"backbone_config\.num_attention_heads must be a positive "
                                    r"int, got 0"),
                                ("3", r"num_attention_heads must be a positive int, got '3'"),
                                (5, r"config\.json's num_attention_heads 5 does not divide the "
                                    r"ViT's width 48")]],
                          ({"backbone_config": dict(meta["backbone_config"],
                                                    out_indices=[1, 1, 1, 1])},
                           r"out_indices / out_features must name increasing blocks"),
                          # three maps, or a stage past the 4 blocks: named as config.json's
                          # (the weights file was blamed, in the network's words)
                          *[({"backbone_config": dict(meta["backbone_config"], out_indices=i)},
                             r"config\.json's out_indices / out_features \(as blocks: stage K "
                             r"is block K - 1\) \[.*\] must name 4 of the ViT's 4 blocks")
                            for i in ([2, 3, 4], [1, 2, 3, 5])],
                          ({"backbone_config": {k: v for k, v in meta["backbone_config"].items()
                                                if k != "out_indices"} | {
                                                    "out_features": ["stem", "stage2"]}},
                           r"out_indices / out_features must name increasing blocks")]:
    (tmp_path / "config.json").write_text(json.dumps(dict(meta, **change)))
    if message is None:
      config, _ = conv.convert_depth_anything_v2(tmp_path / "model.safetensors", "hf")
      assert config["max_depth"] == 20.0
      continue
    with pytest.raises(CheckpointError, match=message):
      conv.convert_depth_anything_v2(tmp_path / "model.safetensors", "hf")
  # transformers counts negative out_indices from the end of the depth + 1 stages (the
  # embeddings are stage 0): [-4, -3, -2, -1] of 4 blocks are stages 1..4 (it was refused)
  (tmp_path / "config.json").write_text(json.dumps(dict(meta, backbone_config=dict(
      meta["backbone_config"], out_indices=[-4, -3, -2, -1]))))
  config, _ = conv.convert_depth_anything_v2(tmp_path / "model.safetensors", "hf")
  assert config["layer_idx"] == [0, 1, 2, 3] == cfg["layer_idx"]


def test_training_checkpoints_unwrap_as_the_plain_file(small, tmp_path):
  """A state dict saved under "model" with DataParallel's `module.` names (a training script's
  checkpoint) converts to the plain file's parameters."""
  arch = {"num_heads": SMALL["heads"], "layer_idx": [i - 1 for i in SMALL["out_indices"]]}
  plain = torch.load(small["root"] / "official" / "depth_anything_v2.pth")
  ddp = {"module." + k: v for k, v in plain.items()}
  torch.save({"model": ddp, "optimizer": {}, "epoch": 3}, tmp_path / "latest.pth")
  config, variables = conv.convert_depth_anything_v2(tmp_path / "latest.pth", "official", arch)
  assert config == small["converted"]["official"][0]
  want = small["converted"]["official"][1]
  got_leaves, want_leaves = jax.tree_util.tree_leaves(variables), jax.tree_util.tree_leaves(want)
  assert len(got_leaves) == len(want_leaves)
  for a, b in zip(got_leaves, want_leaves):
    np.testing.assert_array_equal(a, b)


@pytest.fixture(scope="module")
def metric(tmp_path_factory):
  """A small upstream metric model (metric_depth/dpt.py: sigmoid x max_depth head) saved under
  its release name, and transformers' metric model with the same weights (Hub names and a
  config.json, as a Hub snapshot)."""
  root = tmp_path_factory.mktemp("dav2_metric")
  off = tda.randomize_(tda.DepthAnythingV2(
      SMALL["hidden"], SMALL["depth"], SMALL["heads"], [i - 1 for i in SMALL["out_indices"]],
      SMALL["features"], SMALL["neck"], SMALL["head_hidden"], max_depth=80.0), seed=3)
  torch.save(off.state_dict(), root / "depth_anything_v2_metric_vkitti_vits.pth")
  state = tda.hf_state_from_official(off.state_dict(), SMALL["depth"])
  hf = _hf_model(SMALL, state, depth_estimation_type="metric", max_depth=80)
  (root / "hf").mkdir()
  save_file({k: v.contiguous() for k, v in hf.state_dict().items()},
            str(root / "hf" / "model.safetensors"))
  hf.config.to_json_file(str(root / "hf" / "config.json"))
  return root, off, hf


@pytest.mark.parametrize("fmt", ["official", "hf"])
def test_metric_models_match_upstream(metric, fmt):
  """Upstream's metric model (official: --max-depth 80 for the file named metric; hf: from its
  config.json) -> architecture depth_anything_v2_metric, whose output is depth in metres: the
  torch model's output, and the spec's depth is that output."""
  from pitta_jax.models.registry import get_spec
  root, off, hf = metric
  arch = {"num_heads": SMALL["heads"], "layer_idx": [i - 1 for i in SMALL["out_indices"]]}
  if fmt == "official":
    path = root / "depth_anything_v2_metric_vkitti_vits.pth"
    config, variables = conv.convert_depth_anything_v2(path, "official",
                                                       {**arch, "max_depth": 80.0})
  else:
    config, variables = conv.convert_depth_anything_v2(root / "hf" / "model.safetensors", "hf")
  assert config["max_depth"] == 80.0
  spec = get_spec("depth_anything_v2_metric")
  x = _image(196, 644, seed=7)
  out = np.asarray(jax.jit(lambda v, x: spec.build(config).apply(v, x)[0])(variables, x))
  ref = _torch_depth(off if fmt == "official" else hf, fmt, x)
  diff = float(np.max(np.abs(out - ref)))
  print(f"{fmt} metric: output {ref.min():.2f}..{ref.max():.2f} m, max abs diff {diff:.2e}")
  assert 0 < ref.min() and ref.max() < 80 and ref.max() - ref.min() > 1.0
  assert diff < 1e-4 * 80
  np.testing.assert_allclose(np.asarray(spec.to_depth(jnp.asarray(out))), out)
  with pytest.raises(ValueError, match="the relative architecture needs max_depth 0"):
    get_spec("depth_anything_v2").build(config)


def test_metric_files_need_their_max_depth(metric, small, tmp_path):
  """The metric releases have the relative models' keys: a file named metric, a checkpoint of
  upstream's metric_depth/train.py (it stores "previous_best") and a Hub snapshot of a Metric
  repository without its config.json are refused without --max-depth; a relative HF
  config.json contradicts --max-depth."""
  root, off, _ = metric
  arch = {"num_heads": SMALL["heads"], "layer_idx": [i - 1 for i in SMALL["out_indices"]]}
  ddp = {"module." + k: v for k, v in off.state_dict().items()}
  torch.save({"model": ddp, "optimizer": {}, "epoch": 3, "previous_best": {"d1": 0.9}},
             tmp_path / "latest.pth")
  snapshot = tmp_path / "models--depth-anything--Depth-Anything-V2-Metric-Outdoor-Small-hf"
  (snapshot / "snapshots" / "abc123").mkdir(parents=True)
  (snapshot / "snapshots" / "abc123" / "model.safetensors").write_bytes(
      (root / "hf" / "model.safetensors").read_bytes())
  for path, fmt, why in [
      (root / "depth_anything_v2_metric_vkitti_vits.pth", "official",
       "named 'depth_anything_v2_metric_vkitti_vits.pth'"),
      (tmp_path / "latest.pth", "official", "a checkpoint of upstream's metric_depth/train.py"),
      (snapshot / "snapshots" / "abc123" / "model.safetensors", "hf",
       "named 'models--depth-anything--Depth-Anything-V2-Metric-Outdoor-Small-hf'")]:
    with pytest.raises(CheckpointError, match=re.escape(f"{why}, i.e. a metric model (sigmoid x "
                                                        f"max_depth head, the relative model's "
                                                        f"keys): give its max_depth")):
      conv.convert_depth_anything_v2(path, fmt, arch)
  config, _ = conv.convert_depth_anything_v2(tmp_path / "latest.pth", "official",
                                             {**arch, "max_depth": 20.0})
  assert config["max_depth"] == 20.0
  with pytest.raises(CheckpointError, match=r"--max-depth 80 but the config\.json beside it says "
                                            r"depth_estimation_type relative"):
    conv.convert_depth_anything_v2(small["root"] / "hf" / "model.safetensors", "hf",
                                   {"max_depth": 80.0})


def test_unknown_vit_size_needs_heads_and_layers(small):
  with pytest.raises(CheckpointError, match=r"\['num_heads', 'layer_idx'\]"):
    conv.convert_depth_anything_v2(small["root"] / "official" / "depth_anything_v2.pth")


def test_wrong_format_is_named(small):
  with pytest.raises(CheckpointError, match="use --from official"):
    conv.convert_depth_anything_v2(small["root"] / "official" / "depth_anything_v2.pth", "hf")


def test_unexpected_missing_and_misshapen_keys_are_named(small, tmp_path):
  arch = {"num_heads": 3, "layer_idx": [0, 1, 2, 3]}
  state = torch.load(small["root"] / "official" / "depth_anything_v2.pth")

  def convert(s):
    torch.save(s, tmp_path / "ckpt.pth")
    return conv.convert_depth_anything_v2(tmp_path / "ckpt.pth", "official", arch)

  with pytest.raises(CheckpointError,
                     match=r"1 unexpected keys: depth_head\.readout_projects\.0\.weight"):
    convert(dict(state, **{"depth_head.readout_projects.0.weight": torch.zeros(1)}))
  with pytest.raises(CheckpointError, match=r"2 missing keys: pretrained\.blocks\.1\.ls1\.gamma, "
                                            r"pretrained\.blocks\.2\.norm2\.bias"):
    convert({k: v for k, v in state.items()
             if k not in ("pretrained.blocks.1.ls1.gamma", "pretrained.blocks.2.norm2.bias")})
  key = "depth_head.scratch.refinenet2.out_conv.weight"
  with pytest.raises(CheckpointError, match=re.escape(key) + r" has shape \(16, 16, 3, 3\)"):
    convert(dict(state, **{key: torch.zeros(16, 16, 3, 3)}))
  # the unused upstream modules are ignorable (the fixture converted them), look-alikes are not
  assert "depth_head.scratch.refinenet4.resConfUnit1.conv1.weight" in state
  with pytest.raises(CheckpointError, match=r"1 unexpected keys: pretrained\.mask_tokens"):
    convert(dict(state, **{"pretrained.mask_tokens": torch.zeros(1, 48)}))
  key = "backbone.encoder.layer.3.attention.attention.key.bias"
  hub = conv.read_state(small["root"] / "hf" / "model.safetensors", "hf")
  save_file({k: torch.from_numpy(v) for k, v in hub.items() if k != key},
            str(tmp_path / "model.safetensors"))
  with pytest.raises(CheckpointError, match=r"1 missing keys: " + re.escape(key)):
    conv.convert_depth_anything_v2(tmp_path / "model.safetensors", "hf", arch)
  # a head count that does not divide the width (48) is named (NumPy's reshape error was not)
  official = small["root"] / "official" / "depth_anything_v2.pth"
  with pytest.raises(CheckpointError, match=re.escape(str(official)) + r": num_heads "
                     r"\(--num-heads\) 5 does not divide the ViT's width 48"):
    conv.convert_depth_anything_v2(official, "official", {**arch, "num_heads": 5})


def test_cli_writes_a_weights_directory_spec_builds(small, tmp_path):
  parser = argparse.ArgumentParser()
  conv.add_arguments(parser)
  args = parser.parse_args(["--from", "official", str(small["root"] / "official" /
                            "depth_anything_v2.pth"), "--num-heads", "3", "--layer-idx", "0,1,2,3",
                            "--out", str(tmp_path / "out")])
  out = conv.run(args)
  meta = json.loads((out / "model.json").read_text())
  assert meta["architecture"] == SPEC.name == "depth_anything_v2"
  assert meta["source"]["format"] == "official" and (meta["height"], meta["width"]) == (518, 518)
  cfg, variables = small["converted"]["official"]
  assert build(meta).layer_idx == build(cfg).layer_idx == (0, 1, 2, 3)
  for a, b in zip(jax.tree_util.tree_leaves(load_tree(out / "depth")),
                  jax.tree_util.tree_leaves(variables)):
    np.testing.assert_array_equal(a, b)


def test_spec_and_input_sizes(small):
  assert (SPEC.output, SPEC.alignment, SPEC.size_multiple, SPEC.default_size, SPEC.encoder) == (
      "relative_inverse_depth", "scale_shift", 14, (518, 518), "encoder")
  SPEC.check_size(196, 644)
  with pytest.raises(ValueError, match="multiples of 14"):
    SPEC.check_size(192, 640)
  cfg, variables = small["converted"]["hf"]
  with pytest.raises(ValueError, match="multiples of 14"):
    build(cfg).apply(variables, np.zeros((1, 192, 640, 3), np.float32))
  assert "encoder" in variables["params"] and "depth_head" in variables["params"]


def test_predict_keeps_the_aspect_ratio_as_infer_image():
  """Upstream's infer_image: Resize(518, 518, keep_aspect_ratio=True, ensure_multiple_of=14,
  resize_method="lower_bound"). Hand values: KITTI's 375x1242 -> scale 518/375 -> 518 x
  1715.6 -> 1722 (123 patches); 480x640 -> 518 x 690.7 -> 686 (49 patches); a square image
  -> 518x518; MonoDepth2 resizes to its trained size whatever the image (test_simple.py)."""
  from pitta_jax.models.monodepth2 import SPEC as MONODEPTH2
  assert SPEC.inference_size((375, 1242), (518, 518)) == (518, 1722)
  assert SPEC.inference_size((480, 640), (518, 518)) == (518, 686)
  assert SPEC.inference_size((300, 300), (518, 518)) == (518, 518)
  assert SPEC.inference_size((1242, 375), (518, 518)) == (1722, 518)
  assert MONODEPTH2.inference_size((375, 1242), (192, 640)) == (192, 640)  # test_simple.py


def test_runs_feed_the_frames_aspect_ratio_resized_as_infer_image(small, tmp_path):
  """A run (adapt, the tables) feeds Depth Anything V2 as upstream's infer_image does: the
  frame's aspect ratio kept (here 30x100 -> 28x98 at a trained 28x28: scale 28/30, 93.3 -> 98)
  and the image resized by cv2.INTER_CUBIC, not clipped, then normalised. Reference: the
  torch model on that input (upstream's pipeline), depth = 1 / disparity."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights, save_weights
  from pitta_jax.data.frame import Frame
  from pitta_jax.run import run_sequence
  cfg, variables = small["converted"]["official"]
  save_weights(tmp_path / "w", SPEC.name, {**cfg, "height": 28, "width": 28}, variables)
  weights = load_weights(tmp_path / "w")
  image = _image(30, 100, seed=3)[0]
  image[:4] = 1.0   # a bright band: cubic overshoots past 1 at its edge, upstream keeps that
  res = run_sequence(weights, [Frame(image=image)], AdaptConfig(method="none", selector="encoder_ln"),
                     quiet=True,
                     keep=[0])
  depth = res.kept_depths[0]
  assert depth.shape == (28, 98)
  import cv2
  resized = cv2.resize(image, (98, 28), interpolation=cv2.INTER_CUBIC)
  assert resized.max() > 1.0
  ref = np.maximum(_torch_depth(small["torch"]["official"], "official", resized[None])[0, ..., 0],
                   1e-6)                                               # (28, 98) disparity
  np.testing.assert_allclose(1.0 / depth, ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())


def test_predict_writes_infer_image_outputs_at_the_image_size(small, tmp_path):
  """`predict` as upstream's infer_image: aspect ratio kept, bicubic input, the output resized
  to the image with bilinear align_corners=True (torch's interpolate as infer_image calls it)."""
  import cv2
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.data.image_io import read_image
  from pitta_jax.predict import predict_images
  cfg, variables = small["converted"]["official"]
  save_weights(tmp_path / "w", SPEC.name, {**cfg, "height": 28, "width": 28}, variables)
  rgb = (np.random.default_rng(4).uniform(0, 1, (30, 100, 3)) * 255).astype(np.uint8)
  cv2.imwrite(str(tmp_path / "im.png"), rgb[..., ::-1])
  predict_images(tmp_path / "w", str(tmp_path / "im.png"), tmp_path / "pred", quiet=True)
  disp = np.load(tmp_path / "pred" / "im_disp.npy")
  assert disp.shape == (30, 100)
  assert cv2.imread(str(tmp_path / "pred" / "im_disp.png")).shape[:2] == (30, 100)
  x = cv2.resize(read_image(tmp_path / "im.png"), (98, 28), interpolation=cv2.INTER_CUBIC)
  out = torch.from_numpy(_torch_depth(small["torch"]["official"], "official", x[None])[..., 0])
  ref = torch.nn.functional.interpolate(out[:, None], (30, 100), mode="bilinear",
                                        align_corners=True)[0, 0].numpy()
  np.testing.assert_allclose(disp, ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())


def test_methods_with_source_data_are_refused():
  """ActMAD's source statistics are per location at one input size; Depth Anything V2's runs
  take each dataset's aspect ratio, so the pair is refused before any work (one line)."""
  import types
  from pitta_jax.data.errors import DataError
  from pitta_jax.methods import build as build_method
  from pitta_jax.sources import method_resources
  weights = types.SimpleNamespace(spec=SPEC, pose=None)
  with pytest.raises(DataError, match="--method actmad prepares source-domain data at one input "
                                      "size, but depth_anything_v2 takes each dataset's"):
    method_resources(build_method("actmad"), weights, "synthetic")
  assert method_resources(build_method("cotta"), weights, "synthetic") == {}


def test_layer_idx_overrides_are_refused_before_any_file_is_read(tmp_path):
  """Upstream's get_intermediate_layers reads the blocks in block order, each once: a
  --layer-idx out of order or repeated is refused naming the flag, before the checkpoint (here
  one that does not exist) is opened."""
  for idx in ([3, 2, 1, 0], [0, 1, 1, 2]):
    with pytest.raises(ValueError, match=re.escape(f"layer_idx (--layer-idx) must be increasing "
                                                   f"0-based block numbers, got {idx}")):
      conv.convert_depth_anything_v2(tmp_path / "absent.pth", "official", {"layer_idx": idx})


def test_a_position_table_that_is_no_square_grid_is_named():
  """DINOv2's pos_embed holds the class token and a square grid of patch positions (1 + 37^2 =
  1370 rows for upstream's 518x518): 1 + 1368 rows is no grid, named as such before anything
  else is read from the file."""
  state = {"pretrained.cls_token": np.zeros((1, 1, 8), np.float32),
           "pretrained.pos_embed": np.zeros((1, 1 + 1368, 8), np.float32)}
  with pytest.raises(CheckpointError, match=r"^x\.pth: pretrained\.pos_embed holds 1368 patch "
                                            r"positions, not a square grid$"):
    conv.infer_config(state, "official", "x.pth")


def test_a_vits_read_at_other_blocks_is_not_labelled_vits():
  """model.json's "encoder" names upstream's variant only when the weights are that variant as
  upstream builds it: ViT-S shapes (width 384, 12 blocks, 6 heads) read at upstream's blocks
  [2, 5, 8, 11] are "vits"; the same weights read at the last four blocks (Depth Anything V1's
  rule, `--layer-idx 8,9,10,11`) are "custom". Only the shapes of the keys are read."""
  def zeros(*shape):
    return np.broadcast_to(np.float32(0), shape)
  state = {"pretrained.cls_token": zeros(1, 1, 384), "pretrained.pos_embed": zeros(1, 1370, 384),
           **{f"pretrained.blocks.{i}.norm1.weight": zeros(384) for i in range(12)},
           "pretrained.blocks.0.mlp.fc1.weight": zeros(1536, 384),
           "depth_head.scratch.layer1_rn.weight": zeros(64, 48, 3, 3),
           "depth_head.scratch.output_conv2.0.weight": zeros(32, 32, 3, 3),
           **{f"depth_head.projects.{i}.weight": zeros(c, 384, 1, 1)
              for i, c in enumerate((48, 96, 192, 384))}}
  upstream = conv.infer_config(state, "official", "x.pth")
  assert (upstream["encoder"], upstream["num_heads"], upstream["layer_idx"]) == (
      "vits", 6, [2, 5, 8, 11])
  v1 = conv.infer_config(state, "official", "x.pth", {"layer_idx": [8, 9, 10, 11]})
  assert (v1["encoder"], v1["layer_idx"]) == ("custom", [8, 9, 10, 11])


def test_a_v1_release_needs_its_blocks(small, tmp_path):
  """Depth Anything V1's official files (depth_anything_vit{s,b,l}14.pth) have V2's keys and
  shapes but read the ViT's last four blocks: refused by their name without --layer-idx (V2's
  blocks would be taken silently), converted as given with it."""
  v1 = tmp_path / "depth_anything_vits14.pth"
  v1.write_bytes((small["root"] / "official" / "depth_anything_v2.pth").read_bytes())
  with pytest.raises(CheckpointError, match=re.escape(
      f"{v1}: named 'depth_anything_vits14.pth', i.e. Depth Anything V1: V2's keys, but its head "
      f"reads the ViT's last four blocks, not V2's: give them with --layer-idx")):
    conv.convert_depth_anything_v2(v1, "official", {"num_heads": SMALL["heads"]})
  last_four = list(range(SMALL["depth"] - 4, SMALL["depth"]))
  config, variables = conv.convert_depth_anything_v2(
      v1, "official", {"num_heads": SMALL["heads"], "layer_idx": last_four})
  assert config["layer_idx"] == last_four
  want = flatten_dict(small["converted"]["official"][1])
  assert all(np.array_equal(a, want[k]) for k, a in flatten_dict(variables).items())
