"""Mask2Former checkpoints (detectron2 `.pkl`, Hugging Face `.safetensors`) -> Flax variables.

Two explicit key tables map PyTorch names to the Flax paths of `pitta_jax.models.mask2former`:

* detectron2 / upstream facebookresearch/Mask2Former (`model_final_*.pkl`, a pickled dict
  whose "model" entry holds NumPy arrays): `backbone.*` (D2SwinTransformer),
  `sem_seg_head.pixel_decoder.*` (MSDeformAttnPixelDecoder), `sem_seg_head.predictor.*`
  (MultiScaleMaskedTransformerDecoder).
* Hugging Face `Mask2FormerForUniversalSegmentation` (`model.safetensors` or
  `pytorch_model.bin`): `model.pixel_level_module.encoder.*` (SwinBackbone),
  `model.pixel_level_module.decoder.*`, `model.transformer_module.*`, `class_predictor.*`.
  Hub checkpoints written by transformers 4.x name the Swin blocks
  `encoder.encoder.layers.N.blocks.M.attention.self.query` (or `encoder.model.encoder...`)
  and the stage norms `hidden_states_norms.0..3`; they are renamed to the current
  `encoder.swin.encoder.layers.N.blocks.M.attention.q_proj` / `hidden_states_norms.stage1..4`
  names first (as is detectron2's pre-v2 `predictor.static_query` -> `query_feat`).

A rule maps one Flax parameter to its PyTorch source(s) in PyTorch layout: one tensor, the
row-concatenation of several (HF's separate Swin q/k/v -> our fused `qkv`), or a row slice of
one (`nn.MultiheadAttention.in_proj_weight` -> our `q_proj`/`k_proj`/`v_proj`); then the
layout transform: linear `.T`, conv `OIHW -> HWIO`, other tensors as they are. R.Rules are
invertible (`rules.to_state_dict`), which the tests use to write a detectron2 checkpoint.
Loading is strict: every key of the file not used by a rule (and not a known buffer such as
`relative_position_index` or `criterion.empty_weight`) and every key a rule needs but the file
lacks is listed, and the conversion fails; a shape mismatch names the key.

    python -m weights_convert mask2former --from {detectron2,hf} CKPT --out DIR
"""

from __future__ import annotations

import argparse
import json
import os
import re
import struct
from pathlib import Path

import numpy as np

from weights_convert import rules as R
from weights_convert.pth import (CheckpointError, check_names, checked_path,
                                 is_safetensors_file, load_pth, load_pth_or_pickle)
from weights_convert.strict import looks_like

from pitta_jax.models.mask2former.load import CONFIG_JSON, PARAMS_DIR


# ------------------------------------------------------------------------------ key tables


def detectron2_rules(cfg) -> R.Rules:
  """Key table of upstream Mask2Former (detectron2) names for `Mask2Former(cfg)`."""
  r: R.Rules = []
  bb, c = ("params", "backbone"), cfg.hidden_dim
  R.conv(r, bb + ("patch_embed_proj",), "backbone.patch_embed.proj")
  R.layer_norm(r, bb + ("patch_embed_norm",), "backbone.patch_embed.norm")
  for i, depth in enumerate(cfg.swin.depths):
    for j in range(depth):
      s, f = f"backbone.layers.{i}.blocks.{j}", bb + (f"stage{i}_block{j}",)
      R.layer_norm(r, f + ("norm1",), f"{s}.norm1")
      R.linear(r, f + ("attn", "qkv"), f"{s}.attn.qkv")
      R.linear(r, f + ("attn", "proj"), f"{s}.attn.proj")
      R.param(r, f + ("attn", "relative_position_bias_table"),
             f"{s}.attn.relative_position_bias_table")
      R.layer_norm(r, f + ("norm2",), f"{s}.norm2")
      R.linear(r, f + ("fc1",), f"{s}.mlp.fc1")
      R.linear(r, f + ("fc2",), f"{s}.mlp.fc2")
    if i < len(cfg.swin.depths) - 1:
      s, f = f"backbone.layers.{i}.downsample", bb + (f"stage{i}_downsample",)
      R.layer_norm(r, f + ("norm",), f"{s}.norm")
      R.linear(r, f + ("reduction",), f"{s}.reduction", bias=False)
    R.layer_norm(r, bb + (f"norm{i}",), f"backbone.norm{i}")

  pd, p = ("params", "pixel_decoder"), "sem_seg_head.pixel_decoder"
  for lvl in range(3):
    R.conv(r, pd + (f"input_proj{lvl}_conv",), f"{p}.input_proj.{lvl}.0")
    R.layer_norm(r, pd + (f"input_proj{lvl}_norm",), f"{p}.input_proj.{lvl}.1")
  R.param(r, pd + ("level_embed",), f"{p}.transformer.level_embed")
  for k in range(cfg.enc_layers):
    s, f = f"{p}.transformer.encoder.layers.{k}", pd + (f"encoder_layer{k}",)
    for name in ("sampling_offsets", "attention_weights", "value_proj", "output_proj"):
      R.linear(r, f + ("self_attn", name), f"{s}.self_attn.{name}")
    R.layer_norm(r, f + ("norm1",), f"{s}.norm1")
    R.linear(r, f + ("linear1",), f"{s}.linear1")
    R.linear(r, f + ("linear2",), f"{s}.linear2")
    R.layer_norm(r, f + ("norm2",), f"{s}.norm2")
  R.conv(r, pd + ("adapter1_conv",), f"{p}.adapter_1", bias=False)
  R.layer_norm(r, pd + ("adapter1_norm",), f"{p}.adapter_1.norm")
  R.conv(r, pd + ("layer1_conv",), f"{p}.layer_1", bias=False)
  R.layer_norm(r, pd + ("layer1_norm",), f"{p}.layer_1.norm")
  R.conv(r, pd + ("mask_features",), f"{p}.mask_features")

  td, p = ("params", "predictor"), "sem_seg_head.predictor"
  for i in range(cfg.dec_layers):
    f = td + (f"layer{i}",)
    cross = f"{p}.transformer_cross_attention_layers.{i}"
    R.in_proj(r, f + ("cross_attn",), f"{cross}.multihead_attn", c)
    R.layer_norm(r, f + ("cross_norm",), f"{cross}.norm")
    R.in_proj(r, f + ("self_attn",), f"{p}.transformer_self_attention_layers.{i}.self_attn", c)
    R.layer_norm(r, f + ("self_norm",), f"{p}.transformer_self_attention_layers.{i}.norm")
    R.linear(r, f + ("linear1",), f"{p}.transformer_ffn_layers.{i}.linear1")
    R.linear(r, f + ("linear2",), f"{p}.transformer_ffn_layers.{i}.linear2")
    R.layer_norm(r, f + ("ffn_norm",), f"{p}.transformer_ffn_layers.{i}.norm")
  R.layer_norm(r, td + ("decoder_norm",), f"{p}.decoder_norm")
  R.param(r, td + ("query_feat",), f"{p}.query_feat.weight")
  R.param(r, td + ("query_embed",), f"{p}.query_embed.weight")
  R.param(r, td + ("level_embed",), f"{p}.level_embed.weight")
  R.linear(r, td + ("class_embed",), f"{p}.class_embed")
  for n in range(3):
    R.linear(r, td + (f"mask_embed_{n}",), f"{p}.mask_embed.layers.{n}")
  return r


HF_SWIN = "model.pixel_level_module.encoder"
HF_PIXEL = "model.pixel_level_module.decoder"
HF_TRANSFORMER = "model.transformer_module"


def hf_rules(cfg) -> R.Rules:
  """Key table of Hugging Face `Mask2FormerForUniversalSegmentation` (current names)."""
  r: R.Rules = []
  bb, c = ("params", "backbone"), cfg.hidden_dim
  e = f"{HF_SWIN}.swin"
  R.conv(r, bb + ("patch_embed_proj",), f"{e}.embeddings.patch_embeddings.projection")
  R.layer_norm(r, bb + ("patch_embed_norm",), f"{e}.embeddings.norm")
  for i, depth in enumerate(cfg.swin.depths):
    for j in range(depth):
      s, f = f"{e}.encoder.layers.{i}.blocks.{j}", bb + (f"stage{i}_block{j}",)
      R.layer_norm(r, f + ("norm1",), f"{s}.layernorm_before")
      R.fused_linear(r, f + ("attn", "qkv"), [f"{s}.attention.{n}_proj" for n in "qkv"])
      R.linear(r, f + ("attn", "proj"), f"{s}.attention.o_proj")
      R.param(r, f + ("attn", "relative_position_bias_table"),
             f"{s}.attention.relative_position_bias.relative_position_bias_table")
      R.layer_norm(r, f + ("norm2",), f"{s}.layernorm_after")
      R.linear(r, f + ("fc1",), f"{s}.mlp.fc1")
      R.linear(r, f + ("fc2",), f"{s}.mlp.fc2")
    if i < len(cfg.swin.depths) - 1:
      s, f = f"{e}.encoder.layers.{i}.downsample", bb + (f"stage{i}_downsample",)
      R.layer_norm(r, f + ("norm",), f"{s}.norm")
      R.linear(r, f + ("reduction",), f"{s}.reduction", bias=False)
    R.layer_norm(r, bb + (f"norm{i}",), f"{HF_SWIN}.hidden_states_norms.stage{i + 1}")

  pd, p = ("params", "pixel_decoder"), HF_PIXEL
  for lvl in range(3):
    R.conv(r, pd + (f"input_proj{lvl}_conv",), f"{p}.input_projections.{lvl}.0")
    R.layer_norm(r, pd + (f"input_proj{lvl}_norm",), f"{p}.input_projections.{lvl}.1")
  R.param(r, pd + ("level_embed",), f"{p}.level_embed")
  for k in range(cfg.enc_layers):
    s, f = f"{p}.encoder.layers.{k}", pd + (f"encoder_layer{k}",)
    for name in ("sampling_offsets", "attention_weights", "value_proj", "output_proj"):
      R.linear(r, f + ("self_attn", name), f"{s}.self_attn.{name}")
    R.layer_norm(r, f + ("norm1",), f"{s}.self_attn_layer_norm")
    R.linear(r, f + ("linear1",), f"{s}.fc1")
    R.linear(r, f + ("linear2",), f"{s}.fc2")
    R.layer_norm(r, f + ("norm2",), f"{s}.final_layer_norm")
  R.conv(r, pd + ("adapter1_conv",), f"{p}.adapter_1.0", bias=False)
  R.layer_norm(r, pd + ("adapter1_norm",), f"{p}.adapter_1.1")
  R.conv(r, pd + ("layer1_conv",), f"{p}.layer_1.0", bias=False)
  R.layer_norm(r, pd + ("layer1_norm",), f"{p}.layer_1.1")
  R.conv(r, pd + ("mask_features",), f"{p}.mask_projection")

  td, p = ("params", "predictor"), HF_TRANSFORMER
  for i in range(cfg.dec_layers):
    s, f = f"{p}.decoder.layers.{i}", td + (f"layer{i}",)
    R.in_proj(r, f + ("cross_attn",), f"{s}.cross_attn", c)
    R.layer_norm(r, f + ("cross_norm",), f"{s}.cross_attn_layer_norm")
    for n in ("q_proj", "k_proj", "v_proj", "out_proj"):
      R.linear(r, f + ("self_attn", n), f"{s}.self_attn.{n}")
    R.layer_norm(r, f + ("self_norm",), f"{s}.self_attn_layer_norm")
    R.linear(r, f + ("linear1",), f"{s}.fc1")
    R.linear(r, f + ("linear2",), f"{s}.fc2")
    R.layer_norm(r, f + ("ffn_norm",), f"{s}.final_layer_norm")
  R.layer_norm(r, td + ("decoder_norm",), f"{p}.decoder.layernorm")
  R.param(r, td + ("query_feat",), f"{p}.queries_features.weight")
  R.param(r, td + ("query_embed",), f"{p}.queries_embedder.weight")
  R.param(r, td + ("level_embed",), f"{p}.level_embed.weight")
  R.linear(r, td + ("class_embed",), "class_predictor")
  for n in range(3):
    R.linear(r, td + (f"mask_embed_{n}",), f"{p}.decoder.mask_predictor.mask_embedder.{n}.0")
  return r


# Buffers and unused tensors the checkpoints carry (not parameters of the network; pixel_mean
# and pixel_std are checked first, `_check_pixel_statistics`).
_IGNORED_D2 = re.compile(r"(.*\.relative_position_index|criterion\.empty_weight|pixel_(mean|std))$")
_IGNORED_HF = re.compile(
    r"(.*\.relative_position_index|criterion\.empty_weight|"
    + re.escape(HF_SWIN) + r"\.(swin\.)?layernorm\.(weight|bias))$")

# Older names -> the names of the key tables, applied in order to every key.
# detectron2: Mask2Former checkpoints before `_version = 2` call the query features static_query.
_D2_RENAMES = ((r"^sem_seg_head\.predictor\.static_query\.", "sem_seg_head.predictor.query_feat."),)
# Hugging Face: hub checkpoints converted with transformers 4.x hold the Swin backbone as
# `encoder.model.*` (conversion script) or `encoder.embeddings/encoder.*`, with BERT-style block
# names (`attention.self.query`, `intermediate.dense`, ...) and numbered `hidden_states_norms.i`.
_SWIN = re.escape(HF_SWIN)
_HF_RENAMES = (
    (rf"^{_SWIN}\.(model\.)?(embeddings|encoder|layernorm)\.", HF_SWIN + r".swin.\2."),
    (rf"^{_SWIN}\.hidden_states_norms\.(\d+)\.",
     lambda m: f"{HF_SWIN}.hidden_states_norms.stage{int(m.group(1)) + 1}."),
    (r"\.attention\.self\.(query|key|value)\.",
     lambda m: {"query": ".attention.q_proj.", "key": ".attention.k_proj.",
                "value": ".attention.v_proj."}[m.group(1)]),
    (r"\.attention\.self\.relative_position_bias_table$",
     ".attention.relative_position_bias.relative_position_bias_table"),
    (r"\.attention\.self\.relative_position_index$", ".attention.relative_position_index"),
    (r"\.attention\.output\.dense\.", ".attention.o_proj."),
    (r"\.intermediate\.dense\.", ".mlp.fc1."),
    (r"\.blocks\.(\d+)\.output\.dense\.", r".blocks.\1.mlp.fc2."),
)


def normalize_keys(state: dict, source: str, path: str) -> dict:
  """Renames older key names in `state` to the names of the key tables (others unchanged)."""
  renames = _D2_RENAMES if source == "detectron2" else _HF_RENAMES
  out, origin = {}, {}
  for key, value in state.items():
    new = key
    if source == "detectron2" or key.startswith(HF_SWIN + "."):  # HF: only the Swin keys
      for pattern, repl in renames:
        new = re.sub(pattern, repl, new)
    if new in out:
      raise CheckpointError(f"{path}: keys {origin[new]!r} and {key!r} both mean {new!r}")
    out[new], origin[new] = value, key
  return out


# ------------------------------------------------------------------------------ conversion


def _count(state: dict, pattern: str) -> int:
  """Number of distinct values of the integer group in `pattern` among the keys."""
  rx = re.compile(pattern)
  return len({m.group(1) for k in state if (m := rx.match(k))})


def infer_config(state: dict, source: str, path: str):
  """Architecture (`Mask2FormerConfig`) from the checkpoint's keys and shapes."""
  from pitta_jax.models.mask2former import Mask2FormerConfig
  from pitta_jax.models.mask2former.swin import SwinConfig
  if source == "detectron2":
    bb, pd, td = "backbone", "sem_seg_head.pixel_decoder", "sem_seg_head.predictor"
    layers, blocks = rf"{bb}\.layers\.", "blocks"
    patch = f"{bb}.patch_embed.proj.weight"
    table = f"{bb}.layers.{{i}}.blocks.0.attn.relative_position_bias_table"
    enc = rf"{re.escape(pd)}\.transformer\.encoder\.layers\.(\d+)\."
    dec = rf"{re.escape(td)}\.transformer_ffn_layers\.(\d+)\."
    cls_w, query = f"{td}.class_embed.weight", f"{td}.query_feat.weight"
    ffn = f"{td}.transformer_ffn_layers.0.linear1.weight"
    enc_ffn = f"{pd}.transformer.encoder.layers.0.linear1.weight"
    mask_w = f"{pd}.mask_features.weight"
  else:
    bb = f"{HF_SWIN}.swin"
    layers, blocks = rf"{re.escape(bb)}\.encoder\.layers\.", "blocks"
    patch = f"{bb}.embeddings.patch_embeddings.projection.weight"
    table = (f"{bb}.encoder.layers.{{i}}.blocks.0.attention.relative_position_bias."
             "relative_position_bias_table")
    enc = rf"{re.escape(HF_PIXEL)}\.encoder\.layers\.(\d+)\."
    dec = rf"{re.escape(HF_TRANSFORMER)}\.decoder\.layers\.(\d+)\."
    cls_w, query = "class_predictor.weight", f"{HF_TRANSFORMER}.queries_features.weight"
    ffn = f"{HF_TRANSFORMER}.decoder.layers.0.fc1.weight"
    enc_ffn = f"{HF_PIXEL}.encoder.layers.0.fc1.weight"
    mask_w = f"{HF_PIXEL}.mask_projection.weight"
  try:
    n_stages = _count(state, layers + r"(\d+)\.")
    depths = tuple(_count(state, layers + rf"{i}\.{blocks}\.(\d+)\.") for i in range(n_stages))
    heads = tuple(int(state[table.format(i=i)].shape[1]) for i in range(n_stages))
    window = int(round((np.sqrt(state[table.format(i=0)].shape[0]) + 1) / 2))
    p = state[patch]
    swin = SwinConfig(patch_size=int(p.shape[-1]), embed_dim=int(p.shape[0]), depths=depths,
                      num_heads=heads, window_size=window)
    return Mask2FormerConfig(
        swin=swin, num_classes=int(state[cls_w].shape[0]) - 1,
        num_queries=int(state[query].shape[0]), hidden_dim=int(state[query].shape[1]),
        dim_feedforward=int(state[ffn].shape[0]), dec_layers=_count(state, dec),
        mask_dim=int(state[mask_w].shape[0]), conv_dim=int(state[mask_w].shape[1]),
        enc_layers=_count(state, enc), enc_dim_feedforward=int(state[enc_ffn].shape[0]))
  except (KeyError, AttributeError, IndexError) as e:
    raise CheckpointError(f"{path}: not a {source} Mask2Former checkpoint with a Swin backbone "
                          f"({type(e).__name__}: {e}){looks_like(state)}") from None


def expected_shapes(cfg) -> dict[tuple[str, ...], tuple[int, ...]]:
  """Flax path -> shape of `Mask2Former(cfg)`'s variables (abstract evaluation, no compute)."""
  from pitta_jax.models.mask2former import Mask2Former
  return R.expected_shapes(Mask2Former(cfg), (1, 64, 64, 3))


# ------------------------------------------------------------------------------ file readers

_SAFETENSORS_DTYPES = {
    "F64": "<f8", "F32": "<f4", "F16": "<f2", "I64": "<i8", "I32": "<i4", "I16": "<i2",
    "I8": "i1", "U8": "u1", "U16": "<u2", "U32": "<u4", "U64": "<u8", "BOOL": "?",
}


def read_safetensors(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """Reads a `.safetensors` file: u64 LE header size, JSON header, then the raw tensor bytes."""
  path = checked_path(path)
  with open(path, "rb") as f:
    data = f.read()
  if len(data) < 8:
    raise CheckpointError(f"{path}: too short for a safetensors file")
  (n,) = struct.unpack("<Q", data[:8])
  if 8 + n > len(data):
    raise CheckpointError(f"{path}: header length {n} exceeds the file size {len(data)}"
                          + ("" if data[8:9] == b"{" else " (not a safetensors file?)"))
  try:
    header = json.loads(data[8:8 + n])
  except (UnicodeDecodeError, json.JSONDecodeError) as e:
    raise CheckpointError(f"{path}: corrupt safetensors header ({e})") from None
  if not isinstance(header, dict):
    raise CheckpointError(f"{path}: corrupt safetensors header (a {type(header).__name__}, "
                          f"not an object of tensors)")
  body = memoryview(data)[8 + n:]
  out = {}
  for name, info in header.items():
    if name == "__metadata__":
      continue
    if not (isinstance(info, dict) and isinstance(info.get("dtype"), str)
            and isinstance(info.get("shape"), list)
            and all(isinstance(d, int) and not isinstance(d, bool) and d >= 0
                    for d in info["shape"])
            and isinstance(info.get("data_offsets"), list) and len(info["data_offsets"]) == 2
            and all(isinstance(o, int) and not isinstance(o, bool)
                    for o in info["data_offsets"])):
      raise CheckpointError(f"{path}: corrupt safetensors header: {name} needs a dtype, a shape "
                            f"of non-negative integers and two integer data_offsets, got "
                            f"{str(info)[:120]}")
    dtype_name, shape, (start, stop) = info["dtype"], info["shape"], info["data_offsets"]
    if dtype_name == "BF16":
      import ml_dtypes
      dtype = np.dtype(ml_dtypes.bfloat16)
    elif dtype_name in _SAFETENSORS_DTYPES:
      dtype = np.dtype(_SAFETENSORS_DTYPES[dtype_name])
    else:
      raise CheckpointError(f"{path}: {name} has unsupported dtype {dtype_name}")
    count = int(np.prod(shape, dtype=np.int64))
    if not 0 <= start <= stop <= len(body) or stop - start != count * dtype.itemsize:
      raise CheckpointError(f"{path}: {name} has inconsistent data offsets {start}..{stop}")
    out[name] = np.frombuffer(body[start:stop], dtype=dtype).reshape(shape).copy()
  return out


def read_checkpoint(path: str | os.PathLike, source: str) -> dict[str, np.ndarray]:
  """A flat name -> array dict from a detectron2 `.pkl` / `.pth` or an HF checkpoint."""
  path = str(path)
  if source == "detectron2":
    obj = load_pth_or_pickle(path)  # .pkl pickles and torch files, whatever their suffix
    if isinstance(obj, dict) and isinstance(obj.get("model"), dict):
      obj = obj["model"]
  elif source == "hf":
    safetensors = path.endswith(".safetensors") or is_safetensors_file(checked_path(path))
    obj = read_safetensors(path) if safetensors else load_pth(path)  # (a Hub blob: no name)
  else:
    raise ValueError(f"unknown source {source!r}; expected 'detectron2' or 'hf'")
  if not isinstance(obj, dict):
    raise CheckpointError(f"{path}: expected a dict of tensors, found a {type(obj).__name__}")
  check_names(obj, path)
  return {k: (np.asarray(v) if np.isscalar(v) else v) for k, v in obj.items()}


def _check_pixel_statistics(state: dict[str, np.ndarray], path: str) -> None:
  """A detectron2 checkpoint may carry the input normalisation it was trained with (buffers
  `pixel_mean` / `pixel_std`, 0-255 RGB); the network normalises with the Swin configs' values
  (`model.PIXEL_MEAN` / `PIXEL_STD`), so other values are refused rather than ignored."""
  from pitta_jax.models.mask2former.model import PIXEL_MEAN, PIXEL_STD
  for name, want in (("pixel_mean", PIXEL_MEAN), ("pixel_std", PIXEL_STD)):
    if name in state:
      got = np.asarray(state[name], np.float64).ravel()
      if got.shape != (3,) or not np.allclose(got, want, rtol=0, atol=1e-3):
        raise CheckpointError(f"{path}: {name} {np.round(got, 3).tolist()} differs from the "
                              f"{list(want)} (RGB, 0-255) this network normalises with")


def convert_mask2former(path: str | os.PathLike, source: str, cfg=None):
  """Converts a Mask2Former checkpoint file.

  Args:
    path: detectron2 `.pkl` (or `.pth`), or HF `.safetensors` (or `pytorch_model.bin`).
    source: "detectron2" or "hf".
    cfg: the architecture; default: inferred from the checkpoint.

  Returns:
    (Mask2FormerConfig, variables {"params": ...} of float32 NumPy arrays).
  """
  from flax.traverse_util import unflatten_dict
  state = read_checkpoint(path, source)
  _check_pixel_statistics(state, str(path))
  state = normalize_keys(state, source, str(path))
  cfg = cfg or infer_config(state, source, str(path))
  rules = detectron2_rules(cfg) if source == "detectron2" else hf_rules(cfg)
  ignored = _IGNORED_D2 if source == "detectron2" else _IGNORED_HF
  flat = R.apply_rules(state, rules, lambda k: bool(ignored.match(k)), str(path),
                       expected_shapes(cfg))
  return cfg, unflatten_dict(flat)


# ------------------------------------------------------------------------------ weights dir


def save_mask2former(out_dir: str | os.PathLike, cfg, variables: dict, source: dict | None = None
                     ) -> Path:
  """Writes DIR/config.json ({"architecture": "mask2former", "config": ..., "source": ...})
  and DIR/params (orbax) holding the variables."""
  from pitta_jax.checkpoint import save_tree, writing_weights
  from pitta_jax.outputs import atomic_write_text
  with writing_weights(out_dir, CONFIG_JSON) as out:
    save_tree(out / PARAMS_DIR, variables)
    meta = {"architecture": "mask2former", "config": cfg.to_dict(), "source": source or {}}
    # last and atomic: a directory with a config.json is complete
    atomic_write_text(out / CONFIG_JSON, json.dumps(meta, indent=2) + "\n")
  return out


# ------------------------------------------------------------------------------ command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--from", dest="source", required=True, choices=("detectron2", "hf"),
                      help="checkpoint kind: upstream/detectron2 .pkl, or Hugging Face "
                           "Mask2FormerForUniversalSegmentation .safetensors / .bin")
  parser.add_argument("checkpoint", help="the checkpoint file")
  parser.add_argument("--out", required=True, help="output weights directory")


def run(args: argparse.Namespace) -> Path:
  import jax
  cfg, variables = convert_mask2former(args.checkpoint, args.source)
  out = save_mask2former(args.out, cfg, variables,
                         {"file": str(args.checkpoint), "format": args.source})
  n = sum(a.size for a in jax.tree_util.tree_leaves(variables))
  print(f"converted Mask2Former (Swin embed {cfg.swin.embed_dim}, depths {cfg.swin.depths}, "
        f"{cfg.num_classes} classes, {n:,} values) -> {out}")
  return out


def main(argv: list[str] | None = None) -> int:
  """`python -m weights_convert mask2former ...` without the shared dispatcher."""
  import sys
  parser = argparse.ArgumentParser(prog="python -m weights_convert mask2former",
                                   description="Mask2Former checkpoint -> pitta-jax weights")
  add_arguments(parser)
  args = parser.parse_args(argv)
  try:
    run(args)
  except (CheckpointError, FileNotFoundError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  return 0
