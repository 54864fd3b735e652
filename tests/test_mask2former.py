"""Parity of the Flax Mask2Former + converters with Hugging Face's PyTorch Mask2Former.

Reference: `transformers.Mask2FormerForUniversalSegmentation` built offline with the Swin-T
COCO panoptic architecture (133 classes, 100 queries, 9 decoder layers, 6 deformable encoder
layers), random seeded weights with norms, biases, relative position biases and the deformable
sampling offsets / attention weights moved away from their trivial initial values, and the
mask projection bias spread so that the decoder's attention masks block some pixels, all
pixels (rows that must be unblocked) or none. Its state dict is saved as `.safetensors`,
converted by `weights_convert.mask2former` (no torch), and compared at 192x640, float32,
max abs 1e-4: backbone stages, pixel decoder (multi-scale + mask features), class and mask
logits of all 10 predictions (HF's masked attention given our attention masks, see `hf_out`),
and the attention masks themselves (equal up to logits within 1e-4 of the threshold).
HF's inference semantics agree with upstream detectron2 here (its SwinBackbone partitions
windows at every resolution, `always_partition=True`, as D2SwinTransformer does).

The detectron2 converter is tested on a `.pkl` written from the same weights through the
inverse of its key table; the key names themselves are checked against a literal list taken
from upstream's modules (facebookresearch/Mask2Former).
"""

from __future__ import annotations

import pickle
import re
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import safetensors.numpy as safetensors_numpy  # test extra: the reference writer
import torch
import torch.nn.functional as F
import transformers  # test extra: the reference model
from flax.traverse_util import flatten_dict, unflatten_dict

from pitta_jax import panoptic
from pitta_jax.models.mask2former import msdeform
from pitta_jax.models.mask2former import (InferenceConfig, Mask2Former, Mask2FormerConfig,
                                          mask_logits_to_image, network, predict, preprocess,
                                          load_mask2former, resized_shape, segment)

from weights_convert import mask2former as wc
from weights_convert import rules as R
from weights_convert.pth import CheckpointError

torch.set_num_threads(2)
# PITTA's frame size; every Swin stage (48x160 .. 6x20) needs window padding, and stage 4 is
# lower than the window (HF's SwinBackbone partitions it anyway, as upstream)
H, W = 192, 640
TOL = 1e-4


def _randomize_(model: torch.nn.Module, seed: int) -> None:
  """Moves every parameter away from its trivial initial value (seeded)."""
  g = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for name, p in model.named_parameters():
      noise = torch.randn(p.shape, generator=g)
      if "norm" in name and name.endswith("weight") and p.ndim == 1:
        p.copy_(1 + 0.2 * noise)  # LayerNorm / GroupNorm scale
      elif name.endswith("bias"):
        p.add_(0.05 * noise)
      elif "relative_position_bias_table" in name:
        p.copy_(0.5 * noise)
      elif "sampling_offsets.weight" in name or "attention_weights.weight" in name:
        p.copy_(0.05 * noise)  # fractional, input-dependent sampling points
    bias = model.model.pixel_level_module.decoder.mask_projection.bias
    bias.copy_(torch.randn(bias.shape, generator=g))  # queries fully blocked / fully open


def _hf_model(seed: int = 0):
  torch.manual_seed(seed)
  swin = transformers.SwinConfig(
      embed_dim=96, depths=[2, 2, 6, 2], num_heads=[3, 6, 12, 24], window_size=7,
      out_features=["stage1", "stage2", "stage3", "stage4"], drop_path_rate=0.0)
  config = transformers.Mask2FormerConfig(backbone_config=swin, num_labels=133)
  model = transformers.Mask2FormerForUniversalSegmentation(config).eval()
  _randomize_(model, seed + 1)
  return model


class Reference:
  """The HF model, its checkpoint file and state dict (NumPy), and the input."""


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Reference:
  ref = Reference()
  ref.model = _hf_model()
  ref.state = {k: v.detach().numpy().copy() for k, v in ref.model.state_dict().items()}
  ref.path = tmp_path_factory.mktemp("hf") / "model.safetensors"
  safetensors_numpy.save_file(ref.state, str(ref.path))
  ref.x = np.random.RandomState(0).randn(1, 3, H, W).astype(np.float32)  # normalised image
  return ref


@pytest.fixture(scope="module")
def converted(reference):
  return wc.convert_mask2former(reference.path, "hf")


@pytest.fixture(scope="module")
def flax_out(reference, converted):
  cfg, variables = converted
  start = time.perf_counter()
  out = jax.block_until_ready(network(Mask2Former(cfg), variables,
                                      jnp.asarray(reference.x.transpose(0, 2, 3, 1))))
  print(f"\nFlax Mask2Former at {H}x{W}: compile + run {time.perf_counter() - start:.1f} s")
  return jax.tree_util.tree_map(np.asarray, out)


@pytest.fixture(scope="module")
def hf_out(reference, flax_out):
  """HF's forward pass, its masked attention given *our* attention masks.

  The attention masks threshold the predicted masks (sigmoid < 0.5): a logit within float32
  rounding of 0 may fall on either side in two correct implementations, and such a flip
  changes the following layers by ~1e-4. So HF's mask predictor is hooked: it records the
  mask HF computes (compared with ours in `test_attention_masks_agree`) and passes ours on;
  all outputs are then compared without that ill-conditioning.
  """
  predictor = reference.model.model.transformer_module.decoder.mask_predictor
  heads = reference.model.config.num_attention_heads
  own, own_logits = [], []

  def hook(module, inputs, output):
    mask_logits, attention = output
    small = F.interpolate(mask_logits, size=inputs[2], mode="bilinear", align_corners=False)
    own_logits.append(small.flatten(2)[0].numpy())  # (Q, h * w)
    own.append(attention[0].numpy())  # head 0 of batch 0; all heads are equal
    k = len(own) - 1
    if k < len(flax_out["attention_masks"]):  # batch b, head h -> row b * heads + h
      ours = np.repeat(flax_out["attention_masks"][k], heads, axis=0)
      return mask_logits, torch.from_numpy(ours)
    return output

  handle = predictor.register_forward_hook(hook)
  try:
    with torch.no_grad():
      out = reference.model(pixel_values=torch.from_numpy(reference.x),
                            output_hidden_states=True, output_auxiliary_logits=True)
  finally:
    handle.remove()
  aux = out.auxiliary_logits
  return {
      "backbone": [f.numpy() for f in out.encoder_hidden_states],
      "multi_scale": [f.numpy() for f in out.pixel_decoder_hidden_states],
      "mask_features": out.pixel_decoder_last_hidden_state.numpy(),
      "logits": [a["class_queries_logits"].numpy() for a in aux]
                + [out.class_queries_logits.numpy()],
      "masks": [a["masks_queries_logits"].numpy() for a in aux]
               + [out.masks_queries_logits.numpy()],
      "own_attention_masks": own[:-1], "own_attention_logits": own_logits[:-1],
  }


def _nchw(a: np.ndarray) -> np.ndarray:
  return a.transpose(0, 3, 1, 2)


def _check(name: str, ours: np.ndarray, ref: np.ndarray) -> None:
  diff = float(np.abs(ours - ref).max())
  print(f"{name:<22} max|diff| {diff:.2e}  (max|ref| {np.abs(ref).max():.2f})")
  assert ours.shape == ref.shape, name
  assert diff < TOL, name


# ------------------------------------------------------------------------------ parity


def test_config_inferred_from_checkpoint(converted):
  cfg, _ = converted
  assert cfg == Mask2FormerConfig()  # Swin-T, COCO panoptic


def test_config_inferred_from_other_shapes(reference):
  """The architecture is read from the checkpoint, not assumed: a Swin with window 12 (the
  384-pixel Swin-B / Swin-L configs: relative position tables of (2 * 12 - 1)^2 = 529 rows),
  200 queries and 80 + 1 classes is inferred as such."""
  state = dict(reference.state)
  swin = "model.pixel_level_module.encoder.swin.encoder.layers"
  for i in range(4):
    key = f"{swin}.{i}.blocks.0.attention.relative_position_bias.relative_position_bias_table"
    state[key] = np.zeros((529, state[key].shape[1]), np.float32)
  state["class_predictor.weight"] = np.zeros((81, 256), np.float32)
  state["model.transformer_module.queries_features.weight"] = np.zeros((200, 256), np.float32)
  cfg = wc.infer_config(state, "hf", "x.safetensors")
  assert (cfg.swin.window_size, cfg.num_queries, cfg.num_classes) == (12, 200, 80)
  assert cfg.swin.depths == (2, 2, 6, 2) and cfg.swin.num_heads == (3, 6, 12, 24)


def test_backbone_parity(hf_out, flax_out):
  for i, (ours, ref) in enumerate(zip(flax_out["backbone"], hf_out["backbone"])):
    _check(f"backbone res{i + 2}", _nchw(ours), ref)


def test_pixel_decoder_parity(hf_out, flax_out):
  for i, (ours, ref) in enumerate(zip(flax_out["multi_scale"], hf_out["multi_scale"])):
    _check(f"pixel decoder 1/{32 >> i}", _nchw(ours), ref)
  _check("mask features 1/4", _nchw(flax_out["mask_features"]), hf_out["mask_features"])


def test_transformer_decoder_parity(hf_out, flax_out):
  assert flax_out["pred_logits"].shape == (10, 1, 100, 134)
  for layer in range(10):
    _check(f"class logits {layer}", flax_out["pred_logits"][layer], hf_out["logits"][layer])
    _check(f"mask logits {layer}", flax_out["pred_masks"][layer], hf_out["masks"][layer])


def test_attention_masks_agree(hf_out, flax_out):
  """Our attention masks = HF's, except where HF's resized logit is within 1e-4 of 0."""
  assert len(flax_out["attention_masks"]) == len(hf_out["own_attention_masks"]) == 9
  for layer in range(9):
    ours = flax_out["attention_masks"][layer][0]  # (Q, h * w)
    theirs = hf_out["own_attention_masks"][layer]
    logits = hf_out["own_attention_logits"][layer]
    assert ours.shape == theirs.shape
    flipped = ours != theirs
    print(f"attention mask {layer}: {int(flipped.sum())} of {ours.size} differ, "
          f"min|logit| {np.abs(logits).min():.1e}")
    assert (np.abs(logits[flipped]) < 1e-4).all()


def test_parity_exercises_masked_attention(flax_out):
  """The fixture is non-trivial: the attention masks block some, all and no pixels."""
  all_blocked = partial = 0
  for blocked in flax_out["attention_masks"]:
    blocked = blocked[0]  # (Q, hw)
    all_blocked += int(blocked.all(-1).sum())
    partial += int((blocked.any(-1) & ~blocked.all(-1)).sum())
  print(f"queries fully blocked (then unblocked): {all_blocked}, partially blocked: {partial}")
  assert all_blocked > 0 and partial > 0


# ------------------------------------------------------------------------------ converters


def _equal_trees(a, b) -> None:
  fa, fb = flatten_dict(a), flatten_dict(b)
  assert fa.keys() == fb.keys()
  for k in fa:
    np.testing.assert_array_equal(np.asarray(fa[k]), np.asarray(fb[k]), err_msg="/".join(k))


# Upstream names (mask2former/modeling/backbone/swin.py, pixel_decoder/msdeformattn.py,
# transformer_decoder/mask2former_transformer_decoder.py), indices as N.
D2_PATTERNS = {
    "backbone.patch_embed.proj.weight", "backbone.patch_embed.proj.bias",
    "backbone.patch_embed.norm.weight", "backbone.patch_embed.norm.bias",
    *(f"backbone.layers.N.blocks.N.{m}.{p}" for m in ("norm1", "attn.qkv", "attn.proj", "norm2",
                                                     "mlp.fc1", "mlp.fc2")
      for p in ("weight", "bias")),
    "backbone.layers.N.blocks.N.attn.relative_position_bias_table",
    "backbone.layers.N.downsample.reduction.weight",
    "backbone.layers.N.downsample.norm.weight", "backbone.layers.N.downsample.norm.bias",
    "backbone.normN.weight", "backbone.normN.bias",
    *(f"sem_seg_head.pixel_decoder.input_proj.N.N.{p}" for p in ("weight", "bias")),
    "sem_seg_head.pixel_decoder.transformer.level_embed",
    *(f"sem_seg_head.pixel_decoder.transformer.encoder.layers.N.{m}.{p}"
      for m in ("self_attn.sampling_offsets", "self_attn.attention_weights",
                "self_attn.value_proj", "self_attn.output_proj", "norm1", "linear1", "linear2",
                "norm2") for p in ("weight", "bias")),
    "sem_seg_head.pixel_decoder.mask_features.weight",
    "sem_seg_head.pixel_decoder.mask_features.bias",
    "sem_seg_head.pixel_decoder.adapter_N.weight",
    "sem_seg_head.pixel_decoder.adapter_N.norm.weight",
    "sem_seg_head.pixel_decoder.adapter_N.norm.bias",
    "sem_seg_head.pixel_decoder.layer_N.weight",
    "sem_seg_head.pixel_decoder.layer_N.norm.weight",
    "sem_seg_head.pixel_decoder.layer_N.norm.bias",
    *(f"sem_seg_head.predictor.{layer}.N.{attn}.{p}"
      for layer, attn in (("transformer_self_attention_layers", "self_attn"),
                          ("transformer_cross_attention_layers", "multihead_attn"))
      for p in ("in_proj_weight", "in_proj_bias", "out_proj.weight", "out_proj.bias")),
    *(f"sem_seg_head.predictor.{layer}.N.norm.{p}"
      for layer in ("transformer_self_attention_layers", "transformer_cross_attention_layers",
                    "transformer_ffn_layers") for p in ("weight", "bias")),
    *(f"sem_seg_head.predictor.transformer_ffn_layers.N.{m}.{p}"
      for m in ("linear1", "linear2") for p in ("weight", "bias")),
    "sem_seg_head.predictor.decoder_norm.weight", "sem_seg_head.predictor.decoder_norm.bias",
    "sem_seg_head.predictor.query_feat.weight", "sem_seg_head.predictor.query_embed.weight",
    "sem_seg_head.predictor.level_embed.weight",
    "sem_seg_head.predictor.class_embed.weight", "sem_seg_head.predictor.class_embed.bias",
    "sem_seg_head.predictor.mask_embed.layers.N.weight",
    "sem_seg_head.predictor.mask_embed.layers.N.bias",
}


def _pattern(key: str) -> str:
  """Indices -> N: `layers.3.` -> `layers.N.`, `backbone.norm2.` -> `backbone.normN.`, ..."""
  key = re.sub(r"\.\d+(?=\.)", ".N", key)
  key = re.sub(r"^backbone\.norm\d+\.", "backbone.normN.", key)
  return re.sub(r"\.(adapter|layer)_\d+\.", r".\1_N.", key)


def test_detectron2_key_table_names_and_shapes(converted):
  cfg, variables = converted
  state = R.to_state_dict(variables, wc.detectron2_rules(cfg))
  assert {_pattern(k) for k in state} == D2_PATTERNS
  backbone = 4 + 13 * sum(cfg.swin.depths) + 3 * 3 + 2 * 4  # embed, blocks, merging, norms
  pixel_decoder = 4 * 3 + 1 + 16 * 6 + 2 + 3 + 3  # input_proj, level_embed, encoder, FPN
  predictor = 18 * 9 + 2 + 3 + 2 + 6  # layers, norm, queries + level_embed, class, mask MLP
  assert len(state) == backbone + pixel_decoder + predictor
  shapes = {  # from upstream's constructors (input_proj.0 reads res5, 768 channels)
      "backbone.layers.0.blocks.1.attn.qkv.weight": (288, 96),
      "backbone.layers.2.blocks.0.attn.relative_position_bias_table": (169, 12),
      "backbone.layers.0.downsample.reduction.weight": (192, 384),
      "sem_seg_head.pixel_decoder.input_proj.0.0.weight": (256, 768, 1, 1),
      "sem_seg_head.pixel_decoder.input_proj.2.0.weight": (256, 192, 1, 1),
      "sem_seg_head.pixel_decoder.adapter_1.weight": (256, 96, 1, 1),
      "sem_seg_head.pixel_decoder.layer_1.weight": (256, 256, 3, 3),
      "sem_seg_head.pixel_decoder.transformer.encoder.layers.0.self_attn.sampling_offsets.weight":
          (192, 256),
      "sem_seg_head.predictor.transformer_cross_attention_layers.8.multihead_attn.in_proj_weight":
          (768, 256),
      "sem_seg_head.predictor.class_embed.weight": (134, 256),
      "sem_seg_head.predictor.mask_embed.layers.2.weight": (256, 256),
  }
  for key, shape in shapes.items():
    assert state[key].shape == shape, key


def test_detectron2_pkl_through_the_cli(tmp_path, converted, capsys):
  """A detectron2 checkpoint (model zoo layout, with buffers and the pre-v2 query name),
  converted by the command line into a weights directory that loads the same variables."""
  cfg, variables = converted
  state = R.to_state_dict(variables, wc.detectron2_rules(cfg))
  state["sem_seg_head.predictor.static_query.weight"] = state.pop(
      "sem_seg_head.predictor.query_feat.weight")
  for i, depth in enumerate(cfg.swin.depths):
    for j in range(depth):
      state[f"backbone.layers.{i}.blocks.{j}.attn.relative_position_index"] = np.zeros(
          (49, 49), np.int64)
  state["criterion.empty_weight"] = np.ones(134, np.float32)
  # detectron2's buffers, (3, 1, 1): the Swin configs' RGB normalisation (checked, not used)
  state["pixel_mean"] = np.array([123.675, 116.28, 103.53], np.float32).reshape(3, 1, 1)
  state["pixel_std"] = np.array([58.395, 57.12, 57.375], np.float32).reshape(3, 1, 1)
  path = tmp_path / "model_final.pkl"
  with open(path, "wb") as f:
    pickle.dump({"model": state, "__author__": "test", "matching_heuristics": True}, f)
  out = tmp_path / "m2f"
  assert wc.main(["--from", "detectron2", str(path), "--out", str(out)]) == 0
  assert (out / "config.json").is_file()
  module, loaded = load_mask2former(out)
  assert isinstance(module, Mask2Former) and module.config == cfg
  _equal_trees(loaded, variables)
  assert wc.main(["--from", "detectron2", str(tmp_path / "missing.pkl"), "--out",
                  str(tmp_path / "x")]) == 2
  assert "missing.pkl" in capsys.readouterr().err
  # BGR order (detectron2's default for its ResNet configs): refused, naming the file and buffer
  state["pixel_mean"] = state["pixel_mean"][::-1].copy()
  with open(tmp_path / "bgr.pkl", "wb") as f:
    pickle.dump({"model": state}, f)
  assert wc.main(["--from", "detectron2", str(tmp_path / "bgr.pkl"), "--out",
                  str(tmp_path / "y")]) == 2
  err = capsys.readouterr().err
  assert "bgr.pkl" in err and "pixel_mean" in err and not (tmp_path / "y").exists()
  # a buffer of another shape (here 6 values) is refused in one line too, not a traceback
  with pytest.raises(CheckpointError, match=r"six\.pkl: pixel_std .* differs"):
    wc._check_pixel_statistics({"pixel_std": np.tile(state["pixel_std"].ravel(), 2)}, "six.pkl")


def test_detectron2_reader_tells_pickles_from_torch_files_by_content(tmp_path, converted):
  """The same checkpoint as a plain pickle named .pth, a torch.save zip named .pt and a legacy
  torch.save named .ckpt: each is read by what it is, not by its suffix."""
  cfg, variables = converted
  state = R.to_state_dict(variables, wc.detectron2_rules(cfg))
  with open(tmp_path / "plain.pth", "wb") as f:
    pickle.dump({"model": state, "__author__": "test"}, f)
  tensors = {"model": {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in state.items()}}
  torch.save(tensors, tmp_path / "zip.pt")
  torch.save(tensors, tmp_path / "legacy.ckpt", _use_new_zipfile_serialization=False)
  for name in ("plain.pth", "zip.pt", "legacy.ckpt"):
    got = wc.read_checkpoint(tmp_path / name, "detectron2")
    assert set(got) == set(state), name
    for key, value in state.items():
      np.testing.assert_array_equal(got[key], value, err_msg=f"{name}: {key}")


def _legacy_hf_names(state: dict) -> dict:
  """transformers 4.x hub layout: `encoder.model.*`, BERT-style Swin names, numbered norms."""
  out = {}
  for k, v in state.items():
    k = k.replace("encoder.swin.embeddings.", "encoder.model.embeddings.")
    k = k.replace("encoder.swin.encoder.", "encoder.encoder.")
    for new, old in (("attention.q_proj.", "attention.self.query."),
                     ("attention.k_proj.", "attention.self.key."),
                     ("attention.v_proj.", "attention.self.value."),
                     ("attention.o_proj.", "attention.output.dense."),
                     ("mlp.fc1.", "intermediate.dense."), ("mlp.fc2.", "output.dense."),
                     ("attention.relative_position_bias.relative_position_bias_table",
                      "attention.self.relative_position_bias_table")):
      k = k.replace(new, old)
    k = re.sub(r"hidden_states_norms\.stage(\d)\.",
               lambda m: f"hidden_states_norms.{int(m.group(1)) - 1}.", k)
    out[k] = v
    if k.endswith("attention.self.relative_position_bias_table"):
      out[k.replace("_bias_table", "_index")] = np.zeros((49, 49), np.int64)
  return out


def _apply_hf(state, cfg, path):
  """The Hugging Face key table applied strictly, as `convert_mask2former --from hf` does."""
  return R.apply_rules(state, wc.hf_rules(cfg), lambda k: bool(wc._IGNORED_HF.match(k)), path,
                       wc.expected_shapes(cfg))


def test_hf_legacy_key_names(reference, converted):
  cfg, variables = converted
  legacy = _legacy_hf_names(reference.state)
  assert "model.pixel_level_module.encoder.encoder.layers.0.blocks.0.attention.self.query.weight" \
      in legacy and "model.pixel_level_module.encoder.hidden_states_norms.0.weight" in legacy
  state = wc.normalize_keys(legacy, "hf", "legacy")
  flat = _apply_hf(state, cfg, "legacy")
  _equal_trees(unflatten_dict(flat), variables)
  # an old and a current name of one tensor in the same file: refused, both named (not one
  # silently dropped, whichever came last)
  old, new = ("model.pixel_level_module.encoder.hidden_states_norms.0.weight",
              "model.pixel_level_module.encoder.hidden_states_norms.stage1.weight")
  with pytest.raises(CheckpointError, match=re.escape(f"mixed: keys {old!r} and {new!r} both "
                                                      f"mean {new!r}")):
    wc.normalize_keys({old: legacy[old], new: legacy[old] + 1}, "hf", "mixed")


def test_strict_loading_lists_every_bad_key(reference, converted):
  cfg, _ = converted
  state = wc.normalize_keys(dict(reference.state), "hf", "x.safetensors")
  del state["class_predictor.bias"]
  del state["model.transformer_module.decoder.layers.3.fc1.weight"]
  state["model.extra_head.weight"] = np.zeros(3, np.float32)
  with pytest.raises(CheckpointError) as e:
    _apply_hf(state, cfg, "x.safetensors")
  msg = str(e.value)
  for key in ("class_predictor.bias", "model.transformer_module.decoder.layers.3.fc1.weight",
              "model.extra_head.weight"):
    assert key in msg
  assert "2 missing keys" in msg and "1 unexpected keys" in msg
  with pytest.raises(CheckpointError, match="not a detectron2 Mask2Former checkpoint"):
    wc.infer_config(reference.state, "detectron2", "hf_file.pkl")  # the wrong --from


def test_shape_mismatch_names_the_key(reference, converted):
  cfg, _ = converted
  state = wc.normalize_keys(dict(reference.state), "hf", "x.safetensors")
  key = "model.pixel_level_module.decoder.encoder.layers.2.fc1.weight"
  state[key] = np.zeros((1000, 256), np.float32)
  with pytest.raises(CheckpointError, match=re.escape(key) + r".*\(1000, 256\)"):
    _apply_hf(state, cfg, "x.safetensors")


def test_safetensors_reader_matches_the_library(tmp_path):
  import ml_dtypes
  rs = np.random.RandomState(1)
  arrays = {"f32": rs.randn(3, 4).astype(np.float32), "f16": rs.randn(5).astype(np.float16),
            "i64": np.arange(6, dtype=np.int64).reshape(2, 3), "u8": np.arange(4, dtype=np.uint8),
            "scalar": np.array(2.5, np.float32), "empty": np.zeros((0, 3), np.float32)}
  path = tmp_path / "t.safetensors"
  safetensors_numpy.save_file(arrays, str(path), metadata={"format": "np"})
  got = wc.read_safetensors(path)
  assert got.keys() == arrays.keys()
  for k, v in arrays.items():
    assert got[k].dtype == v.dtype and got[k].shape == v.shape, k
    np.testing.assert_array_equal(got[k], v)
  bf16 = tmp_path / "bf16.safetensors"
  from safetensors.torch import save_file
  save_file({"w": torch.tensor([1.5, -2.0, 3.25], dtype=torch.bfloat16)}, str(bf16))
  w = wc.read_safetensors(bf16)["w"]
  assert w.dtype == ml_dtypes.bfloat16
  np.testing.assert_array_equal(w.astype(np.float32), [1.5, -2.0, 3.25])
  (tmp_path / "bad.safetensors").write_bytes(b"\xff" * 8 + b"{}")
  with pytest.raises(CheckpointError, match="header length"):
    wc.read_safetensors(tmp_path / "bad.safetensors")
  # malformed headers: one line naming the file (were KeyError / AttributeError tracebacks)
  for header, what in ((b'[1, 2]', "a list, not an object"),
                       (b'{"w": {"shape": [1], "data_offsets": [0, 4]}}', "w needs a dtype"),
                       (b'{"w": {"dtype": "F32", "shape": ["x"], "data_offsets": [0, 4]}}',
                        "w needs a dtype, a shape of non-negative integers")):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(len(header).to_bytes(8, "little") + header + b"\0" * 4)
    with pytest.raises(CheckpointError, match=re.escape(f"{bad}: corrupt safetensors header")
                       + ".*" + re.escape(what)):
      wc.read_safetensors(bad)
  # a tensor whose byte range does not hold its shape: named, not a reshape traceback
  header = b'{"w": {"dtype": "F32", "shape": [2], "data_offsets": [0, 4]}}'
  bad.write_bytes(len(header).to_bytes(8, "little") + header + b"\0" * 4)
  with pytest.raises(CheckpointError, match=re.escape(f"{bad}: w has inconsistent data offsets")):
    wc.read_safetensors(bad)
  with pytest.raises(CheckpointError, match="nope.safetensors: no such file"):
    wc.read_safetensors(tmp_path / "nope.safetensors")


# ------------------------------------------------------------------------------ components


@pytest.mark.parametrize("size", [(20, 31), (3, 4), (7, 2), (64, 96)])
def test_resize_bilinear_matches_torch(size):
  x = np.random.RandomState(2).randn(2, 7, 9, 3).astype(np.float32)
  ours = np.asarray(jax.jit(msdeform.resize_bilinear, static_argnums=1)(jnp.asarray(x), size))
  ref = F.interpolate(torch.from_numpy(x).permute(0, 3, 1, 2), size=size, mode="bilinear",
                      align_corners=False).permute(0, 2, 3, 1).numpy()
  np.testing.assert_allclose(ours, ref, atol=1e-5)  # float32 tap weights differ by ~1 ulp


def test_deformable_sampling_matches_grid_sample():
  """Gathers vs transformers' `multi_scale_deformable_attention` (torch grid_sample, zeros)."""
  from transformers.models.mask2former.modeling_mask2former import \
      multi_scale_deformable_attention
  shapes = ((3, 5), (6, 10), (12, 20))
  s = sum(h * w for h, w in shapes)
  rs = np.random.RandomState(3)
  value = rs.randn(2, s, 4, 8).astype(np.float32)
  loc = (rs.rand(2, 7, 4, 3, 5, 2) * 1.6 - 0.3).astype(np.float32)  # some points outside
  weights = rs.rand(2, 7, 4, 3, 5).astype(np.float32)
  core = jax.jit(msdeform.ms_deform_attn_core, static_argnums=1)
  ours = np.asarray(core(jnp.asarray(value), shapes, jnp.asarray(loc), jnp.asarray(weights)))
  ref = multi_scale_deformable_attention(torch.from_numpy(value), list(shapes),
                                         torch.from_numpy(loc), torch.from_numpy(weights)).numpy()
  np.testing.assert_allclose(ours, ref, atol=2e-5)


@pytest.mark.parametrize("height, width", [(6, 9), (1, 2)])
def test_position_embedding_matches_hf(height, width):
  """Also on a map of one row (the 1/32 level of a 32-pixel-high input), where the 1e-6 of the
  normalisation (coordinate / (H + 1e-6)) moves the first features by ~6e-6."""
  from transformers.models.mask2former.modeling_mask2former import \
      Mask2FormerSinePositionEmbedding
  pe = Mask2FormerSinePositionEmbedding(num_position_features=128, normalize=True)
  ref = pe((1, 256, height, width), "cpu", torch.float32)[0].permute(1, 2, 0).numpy()
  np.testing.assert_allclose(msdeform.position_embedding_sine(height, width, 128), ref,
                             atol=2e-6)


def test_resized_shape_is_detectron2_resize_shortest_edge():
  cfg = InferenceConfig()
  assert resized_shape(480, 640, cfg) == (800, 1067)  # 640 * 800 / 480 = 1066.7
  assert resized_shape(192, 640, cfg) == (400, 1333)  # long side capped at 1333
  assert resized_shape(1000, 500, cfg) == (1333, 667)
  assert resized_shape(192, 640, InferenceConfig(input_size=(192, 640))) == (192, 640)


def test_preprocess_normalises_and_pads():
  img = np.random.RandomState(4).rand(40, 50, 3).astype(np.float32)
  x = np.asarray(jax.jit(preprocess, static_argnums=1)(jnp.asarray(img), (40, 50)))
  assert x.shape == (1, 64, 64, 3)
  mean, std = np.array([123.675, 116.28, 103.53]), np.array([58.395, 57.12, 57.375])
  np.testing.assert_allclose(x[0, :40, :50], (img * 255 - mean) / std, atol=1e-5)
  assert not x[0, 40:].any() and not x[0, :, 50:].any()  # zero padding after normalisation


@pytest.mark.parametrize("size", [(20, 25), (17, 31), (64, 80)])
def test_preprocess_resizes_like_pil_bilinear(size):
  """detectron2's ResizeShortestEdge resizes with PIL's bilinear filter, which widens its
  triangle kernel when shrinking (antialiasing); ours on the 0-255 values matches PIL's on a
  float image ("F" mode, no uint8 rounding) when shrinking, stretching and both at once."""
  from PIL import Image
  img = np.random.RandomState(4).rand(40, 50, 3).astype(np.float32)
  x = np.asarray(jax.jit(preprocess, static_argnums=1)(jnp.asarray(img), size))
  ref = np.stack([np.asarray(Image.fromarray(img[..., c] * 255, mode="F").resize(
      (size[1], size[0]), Image.BILINEAR)) for c in range(3)], -1)
  mean, std = np.array([123.675, 116.28, 103.53]), np.array([58.395, 57.12, 57.375])
  np.testing.assert_allclose(x[0, :size[0], :size[1]], (ref - mean) / std, atol=1e-5)


def test_mask_logits_resized_back_like_detectron2():
  """F.interpolate to the padded input, crop to the resized image, F.interpolate to the image."""
  masks = np.random.RandomState(5).randn(3, 16, 24).astype(np.float32)  # 1/4 of 64x96
  resize = jax.jit(mask_logits_to_image, static_argnums=(1, 2))
  ours = np.asarray(resize(jnp.asarray(masks), (50, 90), (37, 70)))
  t = F.interpolate(torch.from_numpy(masks)[None], size=(64, 96), mode="bilinear",
                    align_corners=False)[:, :, :50, :90]
  ref = F.interpolate(t, size=(37, 70), mode="bilinear", align_corners=False)[0].numpy()
  np.testing.assert_allclose(ours, ref, atol=1e-5)


# ------------------------------------------------------------------------------ segment API


def test_segment_api_end_to_end(converted, flax_out):
  """`segment` = panoptic_inference(predict(...)) with the configured thresholds and COCO ids.

  A 150x500 image is resized to the parity test's input size (H, W), so the network is the
  already compiled one. Every query predicts car, and the mask embeddings are shifted along
  the mask features' constant bias so that the masks cover pixels; with overlap threshold 0
  every query that owns pixels becomes a segment (with the default 0.8 nearly none).
  """
  cfg, variables = converted
  params = flatten_dict(variables)
  bias = np.zeros(134, np.float32)
  bias[2] = 10.0  # every query: car (contiguous 2) with probability 0.994
  params[("params", "predictor", "class_embed", "bias")] = bias
  params[("params", "predictor", "class_embed", "kernel")] = np.zeros((256, 134), np.float32)
  feature_bias = params[("params", "pixel_decoder", "mask_features", "bias")]
  params[("params", "predictor", "mask_embed_2", "bias")] = (
      params[("params", "predictor", "mask_embed_2", "bias")]
      + 3.0 * feature_bias / np.sum(feature_bias**2))  # mask logits + about 3
  variables = unflatten_dict(params)
  module = Mask2Former(cfg)
  image = np.random.RandomState(6).rand(150, 500, 3).astype(np.float32)
  icfg = InferenceConfig(input_size=(H, W), overlap_threshold=0.0)
  id_map, segments = segment(module, variables, image, icfg)
  assert id_map.shape == (150, 500) and id_map.dtype == np.int32
  logits, masks = predict(module, variables, image, icfg)
  assert logits.shape == (100, 134) and masks.shape == (100, 150, 500)
  ref_map, ref_segments = panoptic.panoptic_inference(np.asarray(logits), np.asarray(masks),
                                                      overlap_threshold=0.0)
  np.testing.assert_array_equal(id_map, ref_map)
  print(f"{len(segments)} segments")
  assert len(segments) == len(ref_segments) > 1
  for s, r in zip(segments, ref_segments):
    assert (s.id, s.isthing, r.category_id, s.category_id) == (r.id, True, 2, 3)  # COCO car = 3
  assert set(np.unique(id_map)) <= {0} | {s.id for s in segments}
  default_map, default_segments = panoptic.panoptic_inference(np.asarray(logits),
                                                              np.asarray(masks))
  assert len(default_segments) < len(segments)  # the threshold was passed through
