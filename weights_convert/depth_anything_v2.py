"""Depth Anything V2 checkpoints (upstream `.pth`, Hugging Face `.safetensors`) -> Flax variables.

Two explicit key tables map PyTorch names to the Flax paths of
`pitta_jax.models.depth_anything_v2.DepthAnythingV2`:

* upstream DepthAnything/Depth-Anything-V2 (`depth_anything_v2_vits.pth`, a plain state dict of
  `DepthAnythingV2`): `pretrained.*` (DINOv2, fused `attn.qkv`, `ls1.gamma`) and `depth_head.*`
  (`projects.i`, `resize_layers.{0,1,3}`, `scratch.layer{i}_rn`, `scratch.refinenet{1..4}`,
  `scratch.output_conv1`, `scratch.output_conv2.{0,2}`);
* Hugging Face `DepthAnythingForDepthEstimation` (`model.safetensors` or `pytorch_model.bin`):
  `backbone.*` (Dinov2Backbone: separate `attention.attention.query/key/value`, fused here with
  `rules.fused_linear`; `attention.output.dense`; `layer_scale1.lambda1`), `neck.*`
  (`reassemble_stage.layers.i.projection/resize`, `convs.i`, `fusion_stage.layers.k` = upstream
  `refinenet{4 - k}`, i.e. in reverse order) and `head.conv1..3`. Hub files carry these
  (transformers 4.x) names; transformers >= 5 holds the attention as `attention.q_proj/k_proj/
  v_proj/o_proj` in memory, and a state dict saved from it is renamed to the Hub names first.

Layouts: linear weight transposed, conv OIHW -> HWIO, ConvTranspose2d (in, out, k, k) read as
OIHW -> (k, k, out, in) (`dpt.ConvTransposeNoOverlap`), everything else as it is.

Ignored keys, each unused by the network: the DINOv2 `mask_token` (masked-image pretraining
only), and upstream's `refinenet4.resConfUnit1` / HF's `fusion_stage.layers.0.residual_layer1`
(built but never called: the first fusion block has no skip input). No module is registered
under two names in either format. Every other key must be used; loading is strict (unexpected,
missing and misshapen keys are named).

The architecture comes from the weights' shapes (width, depth, MLP width, position grid, head
widths); the number of heads and the blocks the head reads are not in the weights: they come
from upstream's table for ViT-S/B/L (`VIT_VARIANTS`), from a `config.json` beside an HF file
when there is one, or from `arch` overrides (`--num-heads`, `--layer-idx`). Depth Anything V1
checkpoints have the same keys but read the last four blocks: give `--layer-idx` for them (an
official V1 file, named `depth_anything_vit{s,b,l}14.pth` upstream, is refused without it,
`v1_evidence`).
The position-embedding resize rule differs between the two implementations (see
`models/depth_anything_v2/dinov2.py`) and is recorded as config["pos_offset"]: 0.1 upstream, 0 HF.

Metric models (upstream `metric_depth/`, the Hub's `Depth-Anything-V2-Metric-*`) have the same
keys and shapes, with a sigmoid x max_depth head: nothing in the weights says so, so the
converter takes `max_depth` from `--max-depth` (or an HF config.json with
depth_estimation_type "metric") and writes the architecture `depth_anything_v2_metric`; a file
named metric or a checkpoint of upstream's metric_depth/train.py (its "previous_best" entry)
is refused without it (`metric_evidence`), rather than converted as a relative model.

    python -m weights_convert depth-anything-v2 --from {official,hf} CKPT [--max-depth M] --out DIR
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
from pathlib import Path
from typing import Any, Mapping, NamedTuple

from weights_convert import rules as R
from weights_convert.mask2former import read_safetensors
from weights_convert.pth import (CheckpointError, checked_path, is_safetensors_file, load_pth,
                                 unwrap_state_dict)
from weights_convert.strict import check_keys, looks_like

FORMATS = ("official", "hf")
# keys the network does not use (see the module docstring)
_IGNORED = {
    "official": re.compile(r"^pretrained\.mask_token$"
                           r"|^depth_head\.scratch\.refinenet4\.resConfUnit1\."),
    "hf": re.compile(r"^backbone\.embeddings\.mask_token$"
                     r"|^neck\.fusion_stage\.layers\.0\.residual_layer1\."),
}
# transformers >= 5 in-memory attention names -> Hub (transformers 4.x) names
_HF5_RENAMES = (
    (".attention.q_proj.", ".attention.attention.query."),
    (".attention.k_proj.", ".attention.attention.key."),
    (".attention.v_proj.", ".attention.attention.value."),
    (".attention.o_proj.", ".attention.output.dense."),
)
RESIZED = (0, 1, 3)  # resize_layers with parameters (2 is the identity)
ENC, HEAD = ("params", "encoder"), ("params", "depth_head")


# ------------------------------------------------------------------------------ key tables


def official_rules(cfg: Mapping[str, Any]) -> R.Rules:
  """Key table of upstream `DepthAnythingV2` names."""
  r: R.Rules = []
  R.conv(r, ENC + ("patch_embed",), "pretrained.patch_embed.proj")
  R.param(r, ENC + ("cls_token",), "pretrained.cls_token")
  R.param(r, ENC + ("pos_embed",), "pretrained.pos_embed")
  for i in range(cfg["depth"]):
    s, f = f"pretrained.blocks.{i}", ENC + (f"blocks_{i}",)
    R.layer_norm(r, f + ("norm1",), f"{s}.norm1")
    R.linear(r, f + ("attn", "qkv"), f"{s}.attn.qkv")
    R.linear(r, f + ("attn", "proj"), f"{s}.attn.proj")
    R.param(r, f + ("ls1", "gamma"), f"{s}.ls1.gamma")
    R.layer_norm(r, f + ("norm2",), f"{s}.norm2")
    R.linear(r, f + ("mlp", "fc1"), f"{s}.mlp.fc1")
    R.linear(r, f + ("mlp", "fc2"), f"{s}.mlp.fc2")
    R.param(r, f + ("ls2", "gamma"), f"{s}.ls2.gamma")
  R.layer_norm(r, ENC + ("norm",), "pretrained.norm")

  h = "depth_head"
  for i in range(4):
    R.conv(r, HEAD + (f"projects_{i}",), f"{h}.projects.{i}")
    if i in RESIZED:
      R.conv(r, HEAD + (f"resize_layers_{i}",), f"{h}.resize_layers.{i}")
    R.conv(r, HEAD + (f"layer{i + 1}_rn",), f"{h}.scratch.layer{i + 1}_rn", bias=False)
  for n in range(1, 5):
    s, f = f"{h}.scratch.refinenet{n}", HEAD + (f"refinenet{n}",)
    for unit in (("resConfUnit1", "resConfUnit2") if n < 4 else ("resConfUnit2",)):
      R.conv(r, f + (unit, "conv1"), f"{s}.{unit}.conv1")
      R.conv(r, f + (unit, "conv2"), f"{s}.{unit}.conv2")
    R.conv(r, f + ("out_conv",), f"{s}.out_conv")
  R.conv(r, HEAD + ("output_conv1",), f"{h}.scratch.output_conv1")
  R.conv(r, HEAD + ("output_conv2_0",), f"{h}.scratch.output_conv2.0")
  R.conv(r, HEAD + ("output_conv2_2",), f"{h}.scratch.output_conv2.2")
  return r


def hf_rules(cfg: Mapping[str, Any]) -> R.Rules:
  """Key table of Hugging Face `DepthAnythingForDepthEstimation` (Hub) names."""
  r: R.Rules = []
  e = "backbone.embeddings"
  R.conv(r, ENC + ("patch_embed",), f"{e}.patch_embeddings.projection")
  R.param(r, ENC + ("cls_token",), f"{e}.cls_token")
  R.param(r, ENC + ("pos_embed",), f"{e}.position_embeddings")
  for i in range(cfg["depth"]):
    s, f = f"backbone.encoder.layer.{i}", ENC + (f"blocks_{i}",)
    R.layer_norm(r, f + ("norm1",), f"{s}.norm1")
    R.fused_linear(r, f + ("attn", "qkv"),
                   [f"{s}.attention.attention.{n}" for n in ("query", "key", "value")])
    R.linear(r, f + ("attn", "proj"), f"{s}.attention.output.dense")
    R.param(r, f + ("ls1", "gamma"), f"{s}.layer_scale1.lambda1")
    R.layer_norm(r, f + ("norm2",), f"{s}.norm2")
    R.linear(r, f + ("mlp", "fc1"), f"{s}.mlp.fc1")
    R.linear(r, f + ("mlp", "fc2"), f"{s}.mlp.fc2")
    R.param(r, f + ("ls2", "gamma"), f"{s}.layer_scale2.lambda1")
  R.layer_norm(r, ENC + ("norm",), "backbone.layernorm")

  for i in range(4):
    s = f"neck.reassemble_stage.layers.{i}"
    R.conv(r, HEAD + (f"projects_{i}",), f"{s}.projection")
    if i in RESIZED:
      R.conv(r, HEAD + (f"resize_layers_{i}",), f"{s}.resize")
    R.conv(r, HEAD + (f"layer{i + 1}_rn",), f"neck.convs.{i}", bias=False)
  for k in range(4):  # fusion_stage.layers.k is upstream's refinenet{4 - k}
    s, f = f"neck.fusion_stage.layers.{k}", HEAD + (f"refinenet{4 - k}",)
    units = (("residual_layer1", "resConfUnit1"), ("residual_layer2", "resConfUnit2"))
    for hf_unit, unit in (units if k > 0 else units[1:]):
      R.conv(r, f + (unit, "conv1"), f"{s}.{hf_unit}.convolution1")
      R.conv(r, f + (unit, "conv2"), f"{s}.{hf_unit}.convolution2")
    R.conv(r, f + ("out_conv",), f"{s}.projection")
  R.conv(r, HEAD + ("output_conv1",), "head.conv1")
  R.conv(r, HEAD + ("output_conv2_0",), "head.conv2")
  R.conv(r, HEAD + ("output_conv2_2",), "head.conv3")
  return r


# ------------------------------------------------------------------------------ reading


def read_state(path: str | os.PathLike, source: str, max_depth: float | None = None) -> dict:
  """A flat name -> array dict; HF names of transformers >= 5 renamed to the Hub names.

  A file that is a metric model by its name or origin (`metric_evidence`) needs `max_depth`."""
  path = str(path)
  if source not in FORMATS:
    raise ValueError(f"unknown source {source!r}; expected one of {FORMATS}")
  train_checkpoint = False
  if path.endswith(".safetensors") or is_safetensors_file(checked_path(path)):
    obj = read_safetensors(path)  # (by its content too: a Hub cache blob has no name)
  else:
    obj = load_pth(path)
    train_checkpoint = isinstance(obj, dict) and "previous_best" in obj
    obj = unwrap_state_dict(obj, path)  # {"model"|"state_dict": ...}, DataParallel's module.
  evidence = ("a checkpoint of upstream's metric_depth/train.py" if train_checkpoint
              else metric_evidence(path, source))
  if evidence and max_depth is None:
    raise CheckpointError(f"{path}: {evidence}, i.e. a metric model (sigmoid x max_depth head, "
                          f"the relative model's keys): give its max_depth (--max-depth; "
                          f"upstream: 20 for the Hypersim models, 80 for the Virtual KITTI ones)")
  if source == "official":
    return obj
  state = {}
  for key, value in obj.items():
    new = key
    for old, hub in _HF5_RENAMES:
      new = new.replace(old, hub)
    if new in state:
      raise CheckpointError(f"{path}: {key} and {new} both present (the same attention weight "
                            f"under its transformers 5 and 4 names)")
    state[new] = value
  return state


def metric_evidence(path: str, source: str) -> str | None:
  """Why `path` is a metric model, or None. Upstream's metric releases
  (`depth_anything_v2_metric_{hypersim,vkitti}_vit*.pth`, the Hub's
  `Depth-Anything-V2-Metric-*-hf`) have the relative models' keys and shapes, so only the name
  (or an HF snapshot's config.json, `_hf_config_beside`) tells them apart."""
  p = Path(path)
  if source == "official":
    parts = [p.name]
  elif p.with_name("config.json").is_file():
    return None  # the config's depth_estimation_type decides
  else:  # the file, its folder, and a Hub cache's snapshots/<hash>/ under the repo folder
    parts = [p.name] + [q.name for q in list(p.parents)[:3]]
  named = next((part for part in parts if "metric" in part.lower()), None)
  return None if named is None else f"named {named!r}"


# Depth Anything V1's released files (LiheYoung/Depth-Anything `checkpoints/`), e.g.
# depth_anything_vits14.pth; V2's are depth_anything_v2_vits.pth
_V1_NAME = re.compile(r"depth_anything_vit[sblg]14", re.IGNORECASE)


def v1_evidence(path: str, source: str) -> str | None:
  """Why `path` is a Depth Anything V1 release, or None. V1's official `.pth` files have V2's
  keys and shapes, but V1's head reads the ViT's last four blocks (not V2's `layer_idx`), so a
  V1 file converted with V2's blocks gives a network of wrong outputs; only its name (upstream's
  `depth_anything_vit{s,b,l}14.pth`) tells it apart. A Hugging Face V1 snapshot carries its
  blocks in its config.json, so only the official format is judged."""
  name = Path(path).name
  if source != "official" or not _V1_NAME.search(name):
    return None
  return f"named {name!r}"


class _ShapeKeys(NamedTuple):
  """The keys whose shapes tell a format's architecture."""
  cls_token: str
  pos_embed: str
  block_norm1: str  # regex, group 1 = block index
  fc1: str  # MLP input layer of block 0
  project: str  # projects.{i}, formatted with i
  layer1_rn: str
  output_conv2_0: str


_SHAPE_KEYS = {
    "official": _ShapeKeys(
        "pretrained.cls_token", "pretrained.pos_embed",
        r"^pretrained\.blocks\.(\d+)\.norm1\.weight$", "pretrained.blocks.0.mlp.fc1.weight",
        "depth_head.projects.{}.weight", "depth_head.scratch.layer1_rn.weight",
        "depth_head.scratch.output_conv2.0.weight"),
    "hf": _ShapeKeys(
        "backbone.embeddings.cls_token", "backbone.embeddings.position_embeddings",
        r"^backbone\.encoder\.layer\.(\d+)\.norm1\.weight$",
        "backbone.encoder.layer.0.mlp.fc1.weight",
        "neck.reassemble_stage.layers.{}.projection.weight", "neck.convs.0.weight",
        "head.conv2.weight"),
}


def _shape(state: dict, key: str, path: str, source: str) -> tuple[int, ...]:
  if key not in state:
    other = [f for f in FORMATS if f != source][0]
    hint = (f" (its keys look like the {other!r} format: use --from {other})"
            if _SHAPE_KEYS[other].cls_token in state else looks_like(state))
    raise CheckpointError(f"{path}: {key} not found; not a Depth Anything V2 {source!r} "
                          f"checkpoint{hint}")
  return tuple(getattr(state[key], "shape", ()))


def _hf_config_beside(path: str, depth: int) -> dict | None:
  """The `config.json` next to an HF weights file (a Hub snapshot), or None."""
  cfg_path = Path(path).with_name("config.json")
  if not cfg_path.is_file():
    return None
  try:
    cfg = json.loads(cfg_path.read_text())
  except (OSError, json.JSONDecodeError) as e:
    raise CheckpointError(f"{cfg_path}: unreadable ({e})") from None
  kind = cfg.get("depth_estimation_type", "relative")
  max_depth = cfg.get("max_depth")
  arch = {}
  if kind == "metric":  # transformers' head: sigmoid x max_depth
    if not (isinstance(max_depth, (int, float)) and not isinstance(max_depth, bool)
            and math.isfinite(max_depth) and max_depth > 0):
      raise CheckpointError(f"{cfg_path}: a metric model needs max_depth > 0, got {max_depth!r}")
    arch["max_depth"] = float(max_depth)
  elif kind != "relative":
    raise CheckpointError(f"{cfg_path}: depth_estimation_type {kind!r}; expected relative or "
                          f"metric")
  elif max_depth not in (None, 1):  # transformers multiplies even the ReLU output by it
    raise CheckpointError(f"{cfg_path}: max_depth {max_depth!r} scales the relative model's "
                          f"output; only 1 (upstream's relative model) is supported")
  backbone = cfg.get("backbone_config") or {}
  if "num_attention_heads" in backbone:
    heads = backbone["num_attention_heads"]
    if not (isinstance(heads, int) and not isinstance(heads, bool) and heads >= 1):
      raise CheckpointError(f"{cfg_path}: backbone_config.num_attention_heads must be a "
                            f"positive int, got {heads!r}")
    arch["num_heads"] = heads
  # hidden-state indices (stage names "stageK"): 0 is the embeddings, K the output of block K - 1;
  # transformers takes negative indices from the end of the depth + 1 stages, as Python does
  names = backbone.get("out_features") or []
  stages = backbone.get("out_indices") or [
      int(n[len("stage"):]) if isinstance(n, str) and n[len("stage"):].isdigit() else n
      for n in names]
  if stages:
    stages = [i + depth + 1 if isinstance(i, int) and not isinstance(i, bool) and i < 0 else i
              for i in stages]
    if not (all(isinstance(i, int) and not isinstance(i, bool) and i >= 1 for i in stages)
            and list(stages) == sorted(set(stages))):
      raise CheckpointError(f"{cfg_path}: backbone_config's out_indices / out_features must "
                            f"name increasing blocks (stage1, stage2, ...), got {stages!r}")
    arch["layer_idx"] = [i - 1 for i in stages]
  return arch


def infer_config(state: dict, source: str, path: str, arch: Mapping[str, Any] | None = None
                 ) -> dict[str, Any]:
  """The model.json config (architecture of `DepthAnythingV2`, height/width, encoder name)."""
  from pitta_jax.models.depth_anything_v2 import VIT_VARIANTS
  from pitta_jax.models.depth_anything_v2 import dinov2
  keys = _SHAPE_KEYS[source]
  embed_dim = _shape(state, keys.cls_token, path, source)[-1]
  n_pos = _shape(state, keys.pos_embed, path, source)[1] - 1
  grid = math.isqrt(n_pos)
  if grid * grid != n_pos:
    raise CheckpointError(f"{path}: {keys.pos_embed} holds {n_pos} patch positions, not a "
                          f"square grid")
  depth = len({m.group(1) for k in state if (m := re.match(keys.block_norm1, k))})
  mlp_hidden = _shape(state, keys.fc1, path, source)[0]

  variant = next((n for n, v in VIT_VARIANTS.items()
                  if (v.embed_dim, v.depth) == (embed_dim, depth)), None)
  known = dict(num_heads=VIT_VARIANTS[variant].num_heads,
               layer_idx=list(VIT_VARIANTS[variant].layer_idx)) if variant else {}
  if source == "hf":
    known.update(_hf_config_beside(path, depth) or {})
  unknown = sorted(set(arch or {}) - {"num_heads", "layer_idx", "max_depth"})
  if unknown:
    raise ValueError(f"arch overrides {unknown} are not num_heads / layer_idx / max_depth")
  given = (arch or {}).get("max_depth")
  config_says = known.get("max_depth")  # an HF config.json's metric max_depth; None: relative
  if (given is not None and given != config_says and source == "hf"
      and Path(path).with_name("config.json").is_file()):
    says = (f"max_depth {config_says:g}" if config_says is not None
            else "depth_estimation_type relative")
    raise CheckpointError(f"{path}: --max-depth {given:g} but the config.json beside it says "
                          f"{says}")
  known.update(arch or {})
  missing = [k for k in ("num_heads", "layer_idx") if k not in known]
  if missing:
    raise CheckpointError(f"{path}: a ViT with width {embed_dim} and {depth} blocks is not one "
                          f"of {sorted(VIT_VARIANTS)}; give {missing} explicitly "
                          f"(--num-heads, --layer-idx)")
  config_json = Path(path).with_name("config.json")
  if embed_dim % known["num_heads"]:
    said = ("num_heads (--num-heads)" if "num_heads" in (arch or {}) else
            f"{config_json}'s num_attention_heads")
    raise CheckpointError(f"{path}: {said} {known['num_heads']} does not divide the ViT's width "
                          f"{embed_dim} (each head takes width / num_heads features)")
  idx = list(known["layer_idx"])
  if len(idx) != 4 or max(idx) >= depth:  # the DPT head's four maps, from the ViT's blocks
    said = ("layer_idx (--layer-idx)" if "layer_idx" in (arch or {}) else
            f"{config_json}'s out_indices / out_features (as blocks: stage K is block K - 1)"
            if source == "hf" and config_json.is_file() else "layer_idx")
    raise CheckpointError(f"{path}: {said} {idx} must name 4 of the ViT's {depth} blocks "
                          f"(0-based), one per feature map of the DPT head")
  standard = variant is not None and (known["num_heads"], tuple(known["layer_idx"])) == (
      VIT_VARIANTS[variant].num_heads, VIT_VARIANTS[variant].layer_idx)
  return {
      "encoder": variant if standard else "custom",
      "embed_dim": int(embed_dim), "depth": depth, "num_heads": int(known["num_heads"]),
      "mlp_ratio": mlp_hidden / embed_dim, "layer_idx": [int(i) for i in known["layer_idx"]],
      "pos_grid": grid,
      "pos_offset": dinov2.OFFICIAL_POS_OFFSET if source == "official" else dinov2.HF_POS_OFFSET,
      "features": int(_shape(state, keys.layer1_rn, path, source)[0]),
      "out_channels": [int(_shape(state, keys.project.format(i), path, source)[0])
                       for i in range(4)],
      "head_features": int(_shape(state, keys.output_conv2_0, path, source)[0]),
      "height": grid * dinov2.PATCH_SIZE, "width": grid * dinov2.PATCH_SIZE,
      **({"max_depth": float(known["max_depth"])} if known.get("max_depth") else {}),
  }


def _check_overrides(arch: dict) -> None:
  """Refuses an override that no network could take, before any file is read (the block count
  that bounds layer_idx is the checkpoint's, checked once it is read)."""
  heads, idx, max_depth = arch.get("num_heads"), arch.get("layer_idx"), arch.get("max_depth")
  if heads is not None and not (isinstance(heads, int) and heads >= 1):
    raise ValueError(f"num_heads (--num-heads) must be a positive int, got {heads!r}")
  if idx is not None and not (len(idx) > 0 and all(isinstance(i, int) and i >= 0 for i in idx)
                              and list(idx) == sorted(set(idx))):
    raise ValueError(f"layer_idx (--layer-idx) must be increasing 0-based block numbers, got "
                     f"{idx!r}")
  if max_depth is not None and not (math.isfinite(max_depth) and max_depth > 0):
    raise ValueError(f"max_depth (--max-depth) must be > 0 (metres), got {max_depth}")


def _block_numbers(text: str) -> list[int]:
  """--layer-idx's value: comma-separated ints."""
  try:
    return [int(i) for i in text.split(",")]
  except ValueError:
    raise argparse.ArgumentTypeError(f"expected comma-separated block numbers such as 2,5,8,11, "
                                     f"got {text!r}") from None


def convert_depth_anything_v2(path: str | os.PathLike, source: str = "official",
                              arch: Mapping[str, Any] | None = None):
  """Converts a Depth Anything V2 checkpoint file.

  Args:
    path: upstream `.pth`, or HF `.safetensors` / `pytorch_model.bin`.
    source: "official" (upstream) or "hf".
    arch: overrides of the fields the weights cannot tell, {"num_heads": ..., "layer_idx": [...],
      "max_depth": ...}; max_depth > 0 (metres) makes it a metric model (upstream's
      metric_depth/, a sigmoid x max_depth head on the same weights; an HF snapshot's
      config.json says so itself). A file named as a metric model needs it.

  Returns:
    (config dict for model.json / `SPEC.build`, variables {"params": ...} of float32 NumPy
    arrays; the network has no batch statistics).
  """
  from flax.traverse_util import unflatten_dict
  from pitta_jax.models.depth_anything_v2 import build
  _check_overrides(arch or {})
  max_depth = (arch or {}).get("max_depth")
  state = read_state(path, source, max_depth)
  v1 = v1_evidence(str(path), source)
  if v1 and "layer_idx" not in (arch or {}):
    raise CheckpointError(f"{path}: {v1}, i.e. Depth Anything V1: V2's keys, but its head reads "
                          f"the ViT's last four blocks, not V2's: give them with --layer-idx "
                          f"(8,9,10,11 for ViT-S and ViT-B, 20,21,22,23 for ViT-L)")
  config = infer_config(state, source, str(path), arch)
  rules = official_rules(config) if source == "official" else hf_rules(config)
  ignorable = lambda k: bool(_IGNORED[source].match(k))
  # the key check first: it needs no trace of the model (`apply_rules` repeats it)
  check_keys(str(path), state, {s for rule in rules for s in rule.sources}, ignorable)
  try:
    expected = R.expected_shapes(build(config), (1, 28, 28, 3))
  except ValueError as e:  # e.g. a layer_idx beyond the depth
    raise CheckpointError(f"{path}: {e}") from None
  flat = R.apply_rules(state, rules, ignorable, str(path), expected)
  return config, unflatten_dict(flat)


# ------------------------------------------------------------------------------ command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--from", dest="source", required=True, choices=FORMATS,
                      help="checkpoint kind: upstream depth_anything_v2_vits.pth (official), or "
                           "Hugging Face DepthAnythingForDepthEstimation .safetensors / .bin (hf)")
  parser.add_argument("checkpoint", help="the checkpoint file")
  parser.add_argument("--num-heads", type=int,
                      help="attention heads (default: from the ViT size, or the HF config.json)")
  parser.add_argument("--layer-idx", type=_block_numbers,
                      help="comma-separated 0-based blocks the DPT head reads (default: upstream's "
                           "2,5,8,11 for ViT-S/B, 4,11,17,23 for ViT-L)")
  parser.add_argument("--max-depth", type=float,
                      help="convert a metric model (upstream's metric_depth/ releases: its head "
                           "ends in sigmoid x max_depth, depth in metres) with this max_depth: "
                           "20 for the Hypersim models, 80 for the Virtual KITTI ones; an HF "
                           "snapshot's config.json gives it itself")
  parser.add_argument("--out", required=True, help="output weights directory")


def run(args: argparse.Namespace) -> Path:
  import jax
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.models.depth_anything_v2 import METRIC_SPEC, SPEC
  arch = {k: v for k, v in (("num_heads", args.num_heads), ("layer_idx", args.layer_idx),
                            ("max_depth", args.max_depth)) if v is not None}
  config, variables = convert_depth_anything_v2(args.checkpoint, args.source, arch or None)
  metric = bool(config.get("max_depth"))
  out = save_weights(args.out, (METRIC_SPEC if metric else SPEC).name, config, variables,
                     source={"file": str(args.checkpoint), "format": args.source})
  n = sum(a.size for a in jax.tree_util.tree_leaves(variables))
  kind = f"metric, max_depth {config['max_depth']:g} m, " if metric else ""
  print(f"converted Depth Anything V2 ({kind}{config['encoder']}: width {config['embed_dim']}, "
        f"{config['depth']} blocks, {n:,} values, trained at {config['width']}x{config['height']}) "
        f"-> {out}")
  return out
