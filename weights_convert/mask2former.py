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
layout transform: linear `.T`, conv `OIHW -> HWIO`, other tensors as they are. Rules are
invertible (`to_state_dict`), which the tests use to write a detectron2 checkpoint.
Loading is strict: every key of the file not used by a rule (and not a known buffer such as
`relative_position_index` or `criterion.empty_weight`) and every key a rule needs but the file
lacks is listed, and the conversion fails; a shape mismatch names the key.

    python -m weights_convert mask2former --from {detectron2,hf} CKPT --out DIR
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import re
import struct
from pathlib import Path
from typing import NamedTuple

import numpy as np

from weights_convert.strict import check_keys
from weights_convert.pth import CheckpointError, load_pickle, load_pth

CONFIG_JSON = "config.json"
PARAMS_DIR = "params"


class Rule(NamedTuple):
  """Flax parameter `flax` (a path under "params") <- PyTorch `sources` (see module docstring).

  kind: "linear" (weight, transposed), "conv" (OIHW -> HWIO) or "param" (as is).
  rows: (start, stop) row slice of the single source, or None.
  """
  flax: tuple[str, ...]
  kind: str
  sources: tuple[str, ...]
  rows: tuple[int, int] | None = None


Rules = list[Rule]


# ------------------------------------------------------------------------------ rule helpers


def _linear(rules: Rules, flax: tuple[str, ...], src: str, bias: bool = True,
            rows: tuple[int, int] | None = None) -> None:
  rules.append(Rule(flax + ("kernel",), "linear", (f"{src}.weight",), rows))
  if bias:
    rules.append(Rule(flax + ("bias",), "param", (f"{src}.bias",), rows))


def _fused_linear(rules: Rules, flax: tuple[str, ...], srcs: list[str]) -> None:
  rules.append(Rule(flax + ("kernel",), "linear", tuple(f"{s}.weight" for s in srcs)))
  rules.append(Rule(flax + ("bias",), "param", tuple(f"{s}.bias" for s in srcs)))


def _conv(rules: Rules, flax: tuple[str, ...], weight: str, bias: str | None) -> None:
  rules.append(Rule(flax + ("kernel",), "conv", (weight,)))
  if bias is not None:
    rules.append(Rule(flax + ("bias",), "param", (bias,)))


def _norm(rules: Rules, flax: tuple[str, ...], src: str) -> None:
  rules.append(Rule(flax + ("scale",), "param", (f"{src}.weight",)))
  rules.append(Rule(flax + ("bias",), "param", (f"{src}.bias",)))


def _param(rules: Rules, flax: tuple[str, ...], src: str) -> None:
  rules.append(Rule(flax, "param", (src,)))


def _in_proj(rules: Rules, flax: tuple[str, ...], src: str, dim: int) -> None:
  """`nn.MultiheadAttention` -> q_proj, k_proj, v_proj (rows of in_proj_*), out_proj."""
  for n, name in enumerate(("q_proj", "k_proj", "v_proj")):
    rows = (n * dim, (n + 1) * dim)
    rules.append(Rule(flax + (name, "kernel"), "linear", (f"{src}.in_proj_weight",), rows))
    rules.append(Rule(flax + (name, "bias"), "param", (f"{src}.in_proj_bias",), rows))
  _linear(rules, flax + ("out_proj",), f"{src}.out_proj")


# ------------------------------------------------------------------------------ key tables


def detectron2_rules(cfg) -> Rules:
  """Key table of upstream Mask2Former (detectron2) names for `Mask2Former(cfg)`."""
  r: Rules = []
  bb, c = ("params", "backbone"), cfg.hidden_dim
  _conv(r, bb + ("patch_embed_proj",), "backbone.patch_embed.proj.weight",
        "backbone.patch_embed.proj.bias")
  _norm(r, bb + ("patch_embed_norm",), "backbone.patch_embed.norm")
  for i, depth in enumerate(cfg.swin.depths):
    for j in range(depth):
      s, f = f"backbone.layers.{i}.blocks.{j}", bb + (f"stage{i}_block{j}",)
      _norm(r, f + ("norm1",), f"{s}.norm1")
      _linear(r, f + ("attn", "qkv"), f"{s}.attn.qkv")
      _linear(r, f + ("attn", "proj"), f"{s}.attn.proj")
      _param(r, f + ("attn", "relative_position_bias_table"),
             f"{s}.attn.relative_position_bias_table")
      _norm(r, f + ("norm2",), f"{s}.norm2")
      _linear(r, f + ("fc1",), f"{s}.mlp.fc1")
      _linear(r, f + ("fc2",), f"{s}.mlp.fc2")
    if i < len(cfg.swin.depths) - 1:
      s, f = f"backbone.layers.{i}.downsample", bb + (f"stage{i}_downsample",)
      _norm(r, f + ("norm",), f"{s}.norm")
      _linear(r, f + ("reduction",), f"{s}.reduction", bias=False)
    _norm(r, bb + (f"norm{i}",), f"backbone.norm{i}")

  pd, p = ("params", "pixel_decoder"), "sem_seg_head.pixel_decoder"
  for lvl in range(3):
    _conv(r, pd + (f"input_proj{lvl}_conv",), f"{p}.input_proj.{lvl}.0.weight",
          f"{p}.input_proj.{lvl}.0.bias")
    _norm(r, pd + (f"input_proj{lvl}_norm",), f"{p}.input_proj.{lvl}.1")
  _param(r, pd + ("level_embed",), f"{p}.transformer.level_embed")
  for k in range(cfg.enc_layers):
    s, f = f"{p}.transformer.encoder.layers.{k}", pd + (f"encoder_layer{k}",)
    for name in ("sampling_offsets", "attention_weights", "value_proj", "output_proj"):
      _linear(r, f + ("self_attn", name), f"{s}.self_attn.{name}")
    _norm(r, f + ("norm1",), f"{s}.norm1")
    _linear(r, f + ("linear1",), f"{s}.linear1")
    _linear(r, f + ("linear2",), f"{s}.linear2")
    _norm(r, f + ("norm2",), f"{s}.norm2")
  _conv(r, pd + ("adapter1_conv",), f"{p}.adapter_1.weight", None)
  _norm(r, pd + ("adapter1_norm",), f"{p}.adapter_1.norm")
  _conv(r, pd + ("layer1_conv",), f"{p}.layer_1.weight", None)
  _norm(r, pd + ("layer1_norm",), f"{p}.layer_1.norm")
  _conv(r, pd + ("mask_features",), f"{p}.mask_features.weight", f"{p}.mask_features.bias")

  td, p = ("params", "predictor"), "sem_seg_head.predictor"
  for i in range(cfg.dec_layers):
    f = td + (f"layer{i}",)
    cross = f"{p}.transformer_cross_attention_layers.{i}"
    _in_proj(r, f + ("cross_attn",), f"{cross}.multihead_attn", c)
    _norm(r, f + ("cross_norm",), f"{cross}.norm")
    _in_proj(r, f + ("self_attn",), f"{p}.transformer_self_attention_layers.{i}.self_attn", c)
    _norm(r, f + ("self_norm",), f"{p}.transformer_self_attention_layers.{i}.norm")
    _linear(r, f + ("linear1",), f"{p}.transformer_ffn_layers.{i}.linear1")
    _linear(r, f + ("linear2",), f"{p}.transformer_ffn_layers.{i}.linear2")
    _norm(r, f + ("ffn_norm",), f"{p}.transformer_ffn_layers.{i}.norm")
  _norm(r, td + ("decoder_norm",), f"{p}.decoder_norm")
  _param(r, td + ("query_feat",), f"{p}.query_feat.weight")
  _param(r, td + ("query_embed",), f"{p}.query_embed.weight")
  _param(r, td + ("level_embed",), f"{p}.level_embed.weight")
  _linear(r, td + ("class_embed",), f"{p}.class_embed")
  for n in range(3):
    _linear(r, td + (f"mask_embed_{n}",), f"{p}.mask_embed.layers.{n}")
  return r


HF_SWIN = "model.pixel_level_module.encoder"
HF_PIXEL = "model.pixel_level_module.decoder"
HF_TRANSFORMER = "model.transformer_module"


def hf_rules(cfg) -> Rules:
  """Key table of Hugging Face `Mask2FormerForUniversalSegmentation` (current names)."""
  r: Rules = []
  bb, c = ("params", "backbone"), cfg.hidden_dim
  e = f"{HF_SWIN}.swin"
  _conv(r, bb + ("patch_embed_proj",), f"{e}.embeddings.patch_embeddings.projection.weight",
        f"{e}.embeddings.patch_embeddings.projection.bias")
  _norm(r, bb + ("patch_embed_norm",), f"{e}.embeddings.norm")
  for i, depth in enumerate(cfg.swin.depths):
    for j in range(depth):
      s, f = f"{e}.encoder.layers.{i}.blocks.{j}", bb + (f"stage{i}_block{j}",)
      _norm(r, f + ("norm1",), f"{s}.layernorm_before")
      _fused_linear(r, f + ("attn", "qkv"), [f"{s}.attention.{n}_proj" for n in "qkv"])
      _linear(r, f + ("attn", "proj"), f"{s}.attention.o_proj")
      _param(r, f + ("attn", "relative_position_bias_table"),
             f"{s}.attention.relative_position_bias.relative_position_bias_table")
      _norm(r, f + ("norm2",), f"{s}.layernorm_after")
      _linear(r, f + ("fc1",), f"{s}.mlp.fc1")
      _linear(r, f + ("fc2",), f"{s}.mlp.fc2")
    if i < len(cfg.swin.depths) - 1:
      s, f = f"{e}.encoder.layers.{i}.downsample", bb + (f"stage{i}_downsample",)
      _norm(r, f + ("norm",), f"{s}.norm")
      _linear(r, f + ("reduction",), f"{s}.reduction", bias=False)
    _norm(r, bb + (f"norm{i}",), f"{HF_SWIN}.hidden_states_norms.stage{i + 1}")

  pd, p = ("params", "pixel_decoder"), HF_PIXEL
  for lvl in range(3):
    _conv(r, pd + (f"input_proj{lvl}_conv",), f"{p}.input_projections.{lvl}.0.weight",
          f"{p}.input_projections.{lvl}.0.bias")
    _norm(r, pd + (f"input_proj{lvl}_norm",), f"{p}.input_projections.{lvl}.1")
  _param(r, pd + ("level_embed",), f"{p}.level_embed")
  for k in range(cfg.enc_layers):
    s, f = f"{p}.encoder.layers.{k}", pd + (f"encoder_layer{k}",)
    for name in ("sampling_offsets", "attention_weights", "value_proj", "output_proj"):
      _linear(r, f + ("self_attn", name), f"{s}.self_attn.{name}")
    _norm(r, f + ("norm1",), f"{s}.self_attn_layer_norm")
    _linear(r, f + ("linear1",), f"{s}.fc1")
    _linear(r, f + ("linear2",), f"{s}.fc2")
    _norm(r, f + ("norm2",), f"{s}.final_layer_norm")
  _conv(r, pd + ("adapter1_conv",), f"{p}.adapter_1.0.weight", None)
  _norm(r, pd + ("adapter1_norm",), f"{p}.adapter_1.1")
  _conv(r, pd + ("layer1_conv",), f"{p}.layer_1.0.weight", None)
  _norm(r, pd + ("layer1_norm",), f"{p}.layer_1.1")
  _conv(r, pd + ("mask_features",), f"{p}.mask_projection.weight", f"{p}.mask_projection.bias")

  td, p = ("params", "predictor"), HF_TRANSFORMER
  for i in range(cfg.dec_layers):
    s, f = f"{p}.decoder.layers.{i}", td + (f"layer{i}",)
    _in_proj(r, f + ("cross_attn",), f"{s}.cross_attn", c)
    _norm(r, f + ("cross_norm",), f"{s}.cross_attn_layer_norm")
    for n in ("q_proj", "k_proj", "v_proj", "out_proj"):
      _linear(r, f + ("self_attn", n), f"{s}.self_attn.{n}")
    _norm(r, f + ("self_norm",), f"{s}.self_attn_layer_norm")
    _linear(r, f + ("linear1",), f"{s}.fc1")
    _linear(r, f + ("linear2",), f"{s}.fc2")
    _norm(r, f + ("ffn_norm",), f"{s}.final_layer_norm")
  _norm(r, td + ("decoder_norm",), f"{p}.decoder.layernorm")
  _param(r, td + ("query_feat",), f"{p}.queries_features.weight")
  _param(r, td + ("query_embed",), f"{p}.queries_embedder.weight")
  _param(r, td + ("level_embed",), f"{p}.level_embed.weight")
  _linear(r, td + ("class_embed",), "class_predictor")
  for n in range(3):
    _linear(r, td + (f"mask_embed_{n}",), f"{p}.decoder.mask_predictor.mask_embedder.{n}.0")
  return r


# Buffers and unused tensors the checkpoints carry (not parameters of the network).
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


def _to_flax(t: np.ndarray, kind: str) -> np.ndarray:
  if kind == "linear":
    return np.ascontiguousarray(t.T)
  if kind == "conv":
    return np.ascontiguousarray(np.transpose(t, (2, 3, 1, 0)))
  return np.ascontiguousarray(t)


def _to_torch(a: np.ndarray, kind: str) -> np.ndarray:
  if kind == "linear":
    return np.ascontiguousarray(a.T)
  if kind == "conv":
    return np.ascontiguousarray(np.transpose(a, (3, 2, 0, 1)))
  return np.ascontiguousarray(a)


def apply_rules(state: dict, rules: Rules, ignored: re.Pattern, path: str,
                expected: dict[tuple[str, ...], tuple[int, ...]]
                ) -> dict[tuple[str, ...], np.ndarray]:
  """Converts a flat PyTorch state dict with `rules`, strictly (see the module docstring).

  Args:
    state: PyTorch name -> array.
    rules: the key table.
    ignored: names of buffers the file may carry and the network does not use.
    path: file name, for messages.
    expected: Flax path -> shape of the target model.

  Returns:
    Flax path ("params", ...) -> float32 array.
  """
  used = {s for rule in rules for s in rule.sources}
  check_keys(path, state, used, lambda k: bool(ignored.match(k)))
  flat = {}
  for rule in rules:
    parts = []
    for s in rule.sources:
      value = state[s]
      if not isinstance(value, np.ndarray):
        raise CheckpointError(f"{path}: {s} is a {type(value).__name__}, expected a tensor")
      parts.append(value.astype(np.float32))
    t = parts[0] if len(parts) == 1 else np.concatenate(parts, 0)
    if rule.rows is not None:
      start, stop = rule.rows
      if t.shape[0] < stop:
        raise CheckpointError(f"{path}: {rule.sources[0]} has shape {tuple(t.shape)}, expected "
                              f"at least {stop} rows")
      t = t[start:stop]
    arr = _to_flax(t, rule.kind)
    want = expected.get(rule.flax)
    name = "+".join(rule.sources) + (f"[{rule.rows[0]}:{rule.rows[1]}]" if rule.rows else "")
    if want is None:
      raise AssertionError(f"rule for {name} targets {'/'.join(rule.flax)}, not in the model")
    if tuple(arr.shape) != tuple(want):
      raise CheckpointError(f"{path}: {name} has shape {tuple(t.shape)} (-> {tuple(arr.shape)} "
                            f"in Flax layout), the model expects {tuple(want)} at "
                            f"{'/'.join(rule.flax[1:])}")
    flat[rule.flax] = arr
  uncovered = sorted("/".join(k) for k in expected if k not in flat)
  if uncovered:  # the tables and the model disagree: a bug here, not in the file
    raise AssertionError(f"key table does not cover model paths {uncovered}")
  return flat


def to_state_dict(variables: dict, rules: Rules) -> dict[str, np.ndarray]:
  """Inverse of `apply_rules`: Flax variables -> PyTorch-named float32 arrays."""
  from flax.traverse_util import flatten_dict
  flat = {k: np.asarray(v, np.float32) for k, v in flatten_dict(variables).items()}
  pieces: dict[str, list[tuple[int, np.ndarray]]] = collections.defaultdict(list)
  for rule in rules:
    t = _to_torch(flat[rule.flax], rule.kind)
    if len(rule.sources) > 1:
      for s, part in zip(rule.sources, np.split(t, len(rule.sources), axis=0)):
        pieces[s].append((0, part))
    else:
      pieces[rule.sources[0]].append((rule.rows[0] if rule.rows else 0, t))
  return {s: np.concatenate([a for _, a in sorted(ps, key=lambda x: x[0])], 0)
          if len(ps) > 1 else ps[0][1] for s, ps in pieces.items()}


def _count(state: dict, pattern: str) -> int:
  """Number of distinct values of the integer group in `pattern` among the keys."""
  rx = re.compile(pattern)
  return len({m.group(1) for k in state if (m := rx.match(k))})


def infer_config(state: dict, source: str, path: str):
  """Architecture (`Mask2FormerConfig`) from the checkpoint's keys and shapes."""
  from pitta_jax.models.mask2former import Mask2FormerConfig
  from pitta_jax.models.swin import SwinConfig
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
                          f"({type(e).__name__}: {e})") from None


@functools.lru_cache(maxsize=4)
def expected_shapes(cfg) -> dict[tuple[str, ...], tuple[int, ...]]:
  """Flax path -> shape of `Mask2Former(cfg)`'s variables (abstract evaluation, no compute)."""
  import jax
  import jax.numpy as jnp
  from flax.traverse_util import flatten_dict
  from pitta_jax.models.mask2former import Mask2Former
  shapes = jax.eval_shape(Mask2Former(cfg).init, jax.random.PRNGKey(0),
                          jnp.zeros((1, 64, 64, 3), jnp.float32))
  return {k: tuple(v.shape) for k, v in flatten_dict(shapes).items()}


# ------------------------------------------------------------------------------ file readers

_SAFETENSORS_DTYPES = {
    "F64": "<f8", "F32": "<f4", "F16": "<f2", "I64": "<i8", "I32": "<i4", "I16": "<i2",
    "I8": "i1", "U8": "u1", "U16": "<u2", "U32": "<u4", "U64": "<u8", "BOOL": "?",
}


def read_safetensors(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """Reads a `.safetensors` file: u64 LE header size, JSON header, then the raw tensor bytes."""
  path = str(path)
  with open(path, "rb") as f:
    data = f.read()
  if len(data) < 8:
    raise CheckpointError(f"{path}: too short for a safetensors file")
  (n,) = struct.unpack("<Q", data[:8])
  if 8 + n > len(data):
    raise CheckpointError(f"{path}: header length {n} exceeds the file size {len(data)}")
  try:
    header = json.loads(data[8:8 + n])
  except (UnicodeDecodeError, json.JSONDecodeError) as e:
    raise CheckpointError(f"{path}: corrupt safetensors header ({e})") from None
  body = memoryview(data)[8 + n:]
  out = {}
  for name, info in header.items():
    if name == "__metadata__":
      continue
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
    obj = load_pth(path) if path.endswith(".pth") else load_pickle(path)
    if isinstance(obj, dict) and isinstance(obj.get("model"), dict):
      obj = obj["model"]
  elif source == "hf":
    obj = read_safetensors(path) if path.endswith(".safetensors") else load_pth(path)
  else:
    raise ValueError(f"unknown source {source!r}; expected 'detectron2' or 'hf'")
  if not isinstance(obj, dict):
    raise CheckpointError(f"{path}: expected a dict of tensors, found a {type(obj).__name__}")
  return {k: (np.asarray(v) if np.isscalar(v) else v) for k, v in obj.items()}


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
  state = normalize_keys(state, source, str(path))
  cfg = cfg or infer_config(state, source, str(path))
  rules = detectron2_rules(cfg) if source == "detectron2" else hf_rules(cfg)
  ignored = _IGNORED_D2 if source == "detectron2" else _IGNORED_HF
  flat = apply_rules(state, rules, ignored, str(path), expected_shapes(cfg))
  return cfg, unflatten_dict(flat)


# ------------------------------------------------------------------------------ weights dir


def save_mask2former(out_dir: str | os.PathLike, cfg, variables: dict, source: dict | None = None
                     ) -> Path:
  """Writes DIR/config.json ({"architecture": "mask2former", "config": ..., "source": ...})
  and DIR/params (orbax) holding the variables."""
  from pitta_jax.checkpoint import save_tree
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  save_tree(out / PARAMS_DIR, variables)
  meta = {"architecture": "mask2former", "config": cfg.to_dict(), "source": source or {}}
  (out / CONFIG_JSON).write_text(json.dumps(meta, indent=2) + "\n")
  return out


def load_mask2former(weights_dir: str | os.PathLike):
  """Loads a directory written by `save_mask2former` -> (Mask2Former module, variables).

  The variables are float32 device arrays {"params": ...}, ready for
  `pitta_jax.models.mask2former.segment(module, variables, image)`.
  """
  import jax
  from pitta_jax.checkpoint import load_tree
  from pitta_jax.models.mask2former import Mask2Former, Mask2FormerConfig
  root = Path(weights_dir)
  meta_path = root / CONFIG_JSON
  if not meta_path.is_file():
    raise FileNotFoundError(f"{meta_path}: not found; a Mask2Former weights directory is made by "
                            f"`python -m weights_convert mask2former --from ... CKPT --out DIR`")
  meta = json.loads(meta_path.read_text())
  if meta.get("architecture") != "mask2former":
    raise ValueError(f"{meta_path}: architecture {meta.get('architecture')!r} is not 'mask2former'")
  cfg = Mask2FormerConfig.from_dict(meta["config"])
  variables = load_tree(root / PARAMS_DIR)
  # on the device once, so that every `segment` call does not copy the weights again
  variables = jax.device_put(jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), variables))
  return Mask2Former(cfg), variables


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
