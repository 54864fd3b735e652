"""MonoViT PyTorch checkpoints -> Flax variables for `pitta_jax.models.monovit.MonoViT`.

Two released layouts (upstream zxcqlf/MonoViT, README's Google Drive folders):

* 640x192 models: `encoder.pth` (the `MPViT` state dict plus MonoDepth2's `height`, `width`,
  `use_stereo`) and `depth.pth` (the HR decoder's state dict);
* 1024x320 / 1280x384 models: one `depth.pth` holding `DeepNet` saved through `nn.DataParallel`,
  keys `module.encoder.*` and `module.decoder.*` (upstream's `evaluate_hr_depth.py` strips the
  first 7 characters); no size entries, so `--height`/`--width` are required.

The MPViT layout (paths, MHCA layers, widths, MLP ratios and heads per stage; MPViT-small in
every MonoViT release) is read from the encoder's keys and shapes and recorded in the config.
A `module.` prefix is stripped when every key of a file carries it (a file that mixes both is an
error). An explicit key table (`weights_convert.rules`) maps each PyTorch name to a Flax path:
conv OIHW -> HWIO, Linear transposed, BN `weight/bias` -> `scale/bias` and `running_mean/var` ->
batch_stats `mean/var`, LN `weight/bias` -> `scale/bias`.

Keys that appear more than once because one module is registered under several names are
folded explicitly, after checking that every copy equals the canonical one:
* each `MHCAEncoder`'s shared `cpe` and `crpe` (canonical `mhca_blks.P.cpe.*` / `.crpe.*`) also
  appear as `MHCA_layers.L.cpe.*`, `MHCA_layers.L.crpe.*` and `MHCA_layers.L.factoratt_crpe.crpe.*`;
* every decoder module appears as `convs.<name>.*` (canonical) and `decoder.<k>.*` (the
  ModuleList of the same modules in the ModuleDict's insertion order).

Ignorable keys: `num_batches_tracked` (BN counters, unused with momentum 0.1), the metadata
`height`/`width`/`use_stereo`, and the decoder's `X_00_Conv_0` .. `X_03_Conv_0` (both names),
which upstream's construction loop builds but its forward never calls. Every other key must be
used, and every key the table needs must be there; shapes and finiteness are checked.

    python -m weights_convert monovit --encoder encoder.pth --depth depth.pth --out DIR
    python -m weights_convert monovit --depth depth.pth --height 320 --width 1024 --out DIR
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path
from typing import Callable

import numpy as np

from weights_convert import rules as R
from weights_convert.pth import (METADATA_KEYS, CheckpointError, flag_entry, int_entry,
                                 load_state_dict)
from weights_convert.strict import check_keys, looks_like

NUM_STAGES = 4  # the decoder takes the stem and four stage outputs
DECODER_UNUSED = ("X_00_Conv_0", "X_01_Conv_0", "X_02_Conv_0", "X_03_Conv_0")
DISP_CONVS = tuple(f"dispconv{i}" for i in range(4))


def decoder_module_order() -> tuple[str, ...]:
  """Names of upstream's `DepthDecoder.convs` in insertion order (= `decoder.<k>` indices)."""
  names = [f"f{i}" for i in (4, 3, 2, 1)]
  for j in range(5):
    for i in range(5 - j):
      names.append(f"X_{i}{j}_Conv_0")
      if i == 0 and j == 4:
        names.append("X_04_Conv_1")
  names += [f"X_{p}_attention" for p in ("31", "22", "13", "04")]
  for p in ("01", "11", "21", "02", "12", "03"):
    row, col = int(p[0]), int(p[1])
    if col != 1:
      names.append(f"X_{p}_downsample")
    names.append(f"X_{row + 1}{col - 1}_Conv_1")
  return tuple(names) + DISP_CONVS


# ------------------------------------------------------------------------------ layout


def _indices(state: dict, pattern: str) -> list[int]:
  """Sorted distinct integers N of the keys matching `pattern` (a regex with one `(\\d+)`)."""
  regex = re.compile(pattern)
  return sorted({int(m.group(1)) for k in state if (m := regex.match(k))})


def _shape(state: dict, key: str, path: str) -> tuple[int, ...]:
  """Shape of `state[key]`, a CheckpointError naming the key when it is absent."""
  if key not in state or not hasattr(state[key], "shape"):
    raise CheckpointError(f"{path}: missing key {key} (needed to tell the MPViT layout)")
  return tuple(state[key].shape)


def infer_layout(state: dict, path: str, prefix: str = "") -> dict[str, tuple[int, ...]]:
  """The MPViT layout (the `MonoViT` fields of `ARCH_FIELDS`) from the encoder's keys and shapes.

  Paths and layers are counted; widths read from the first patch embedding's BN; the MLP ratio
  from `fc1`; the heads from the first ConvRelPosEnc conv, which covers CRPE_WINDOW[0][1] heads.
  """
  from pitta_jax.models.monovit import ARCH_FIELDS
  from pitta_jax.models.monovit.mpvit import CRPE_WINDOW
  p = re.escape(prefix)
  stages = _indices(state, rf"{p}patch_embed_stages\.(\d+)\.")
  if stages != list(range(NUM_STAGES)):
    raise CheckpointError(f"{path}: expected MPViT patch_embed_stages.0..{NUM_STAGES - 1} keys"
                          f"{f' under {prefix!r}' if prefix else ''}, found stages {stages}"
                          f"{looks_like(state)}; is this a MonoViT encoder?")
  per_stage = []
  for s in stages:
    stage, blk = f"{prefix}mhca_stages.{s}", f"{prefix}mhca_stages.{s}.mhca_blks.0"
    dim = _shape(state, f"{prefix}patch_embed_stages.{s}.patch_embeds.0.patch_conv.bn.weight",
                 path)[0]
    hidden = _shape(state, f"{blk}.MHCA_layers.0.mlp.fc1.weight", path)[0]
    head_ch = _shape(state, f"{blk}.crpe.conv_list.0.weight", path)[0] // CRPE_WINDOW[0][1]
    if hidden % dim or head_ch == 0 or dim % head_ch:
      raise CheckpointError(f"{path}: {stage} has width {dim}, MLP width {hidden} and "
                            f"{head_ch} channels per head; not an MPViT stage")
    per_stage.append({
        "num_path": len(_indices(state, rf"{p}patch_embed_stages\.{s}\.patch_embeds\.(\d+)\.")),
        "num_layers": len(_indices(state, rf"{re.escape(blk)}\.MHCA_layers\.(\d+)\.")),
        "embed_dims": dim, "mlp_ratios": hidden // dim, "num_heads": dim // head_ch})
  return {k: tuple(st[k] for st in per_stage) for k in ARCH_FIELDS}


# ------------------------------------------------------------------------------ key tables


def _conv2d_bn(rules: R.Rules, module: tuple[str, ...], src: str) -> None:
  """Upstream `Conv2d_BN` `src` (`.conv`, `.bn`) -> Flax `module/conv`, `module/bn`."""
  R.conv(rules, ("params",) + module + ("conv",), f"{src}.conv", bias=False)
  R.batch_norm(rules, module + ("bn",), f"{src}.bn")


def encoder_rules(layout: dict, prefix: str = "", root: tuple[str, ...] = ("encoder",)
                  ) -> R.Rules:
  """Key table of upstream's `MPViT` (`infer_layout`'s layout) under `prefix` -> Flax `root`."""
  from pitta_jax.models.monovit.mpvit import CRPE_WINDOW
  rules: R.Rules = []
  for i in range(2):
    _conv2d_bn(rules, root + (f"stem_{i}",), f"{prefix}stem.{i}")
  for s, (n_path, n_layers) in enumerate(zip(layout["num_path"], layout["num_layers"])):
    for p in range(n_path):
      src = f"{prefix}patch_embed_stages.{s}.patch_embeds.{p}.patch_conv"
      mod = root + (f"patch_embed_stages_{s}", f"patch_embeds_{p}")
      R.conv(rules, ("params",) + mod + ("dwconv",), f"{src}.dwconv", bias=False)
      R.conv(rules, ("params",) + mod + ("pwconv",), f"{src}.pwconv", bias=False)
      R.batch_norm(rules, mod + ("bn",), f"{src}.bn")
    stage_src, stage = f"{prefix}mhca_stages.{s}", root + (f"mhca_stages_{s}",)
    inv_src, inv = f"{stage_src}.InvRes", stage + ("InvRes",)
    _conv2d_bn(rules, inv + ("conv1",), f"{inv_src}.conv1")
    R.conv(rules, ("params",) + inv + ("dwconv",), f"{inv_src}.dwconv", bias=False)
    R.batch_norm(rules, inv + ("norm",), f"{inv_src}.norm")
    _conv2d_bn(rules, inv + ("conv2",), f"{inv_src}.conv2")
    for p in range(n_path):
      blk_src, blk = f"{stage_src}.mhca_blks.{p}", ("params",) + stage + (f"mhca_blks_{p}",)
      R.conv(rules, blk + ("cpe", "proj"), f"{blk_src}.cpe.proj")
      for k in range(len(CRPE_WINDOW)):
        R.conv(rules, blk + ("crpe", f"conv_list_{k}"), f"{blk_src}.crpe.conv_list.{k}")
      for l in range(n_layers):
        lsrc, lay = f"{blk_src}.MHCA_layers.{l}", blk + (f"MHCA_layers_{l}",)
        R.layer_norm(rules, lay + ("norm1",), f"{lsrc}.norm1")
        R.linear(rules, lay + ("factoratt_crpe", "qkv"), f"{lsrc}.factoratt_crpe.qkv")
        R.linear(rules, lay + ("factoratt_crpe", "proj"), f"{lsrc}.factoratt_crpe.proj")
        R.layer_norm(rules, lay + ("norm2",), f"{lsrc}.norm2")
        R.linear(rules, lay + ("mlp", "fc1"), f"{lsrc}.mlp.fc1")
        R.linear(rules, lay + ("mlp", "fc2"), f"{lsrc}.mlp.fc2")
    _conv2d_bn(rules, stage + ("aggregate",), f"{stage_src}.aggregate")
  return rules


def encoder_aliases(layout: dict, prefix: str = "") -> dict[str, tuple[str, ...]]:
  """Canonical key -> its other names: each MHCAEncoder's shared `cpe` and `crpe`, also
  registered in every MHCABlock (`cpe`, `crpe`) and its attention (`factoratt_crpe.crpe`)."""
  from pitta_jax.models.monovit.mpvit import CRPE_WINDOW
  aliases: dict[str, tuple[str, ...]] = {}
  for s, (n_path, n_layers) in enumerate(zip(layout["num_path"], layout["num_layers"])):
    for p in range(n_path):
      blk = f"{prefix}mhca_stages.{s}.mhca_blks.{p}"
      suffixes = ["cpe.proj"] + [f"crpe.conv_list.{k}" for k in range(len(CRPE_WINDOW))]
      for suffix in suffixes:
        owners = [f"MHCA_layers.{l}" for l in range(n_layers)]
        if suffix.startswith("crpe"):
          owners += [f"MHCA_layers.{l}.factoratt_crpe" for l in range(n_layers)]
        for leaf in ("weight", "bias"):
          aliases[f"{blk}.{suffix}.{leaf}"] = tuple(f"{blk}.{o}.{suffix}.{leaf}" for o in owners)
  return aliases


def decoder_rules(prefix: str = "", root: tuple[str, ...] = ("decoder",)) -> R.Rules:
  """Key table of upstream's HR `DepthDecoder` (`convs.<name>.*` under `prefix`) -> `root`."""
  rules: R.Rules = []
  par = ("params",) + root
  for name in decoder_module_order():
    src = f"{prefix}convs.{name}"
    if name in DECODER_UNUSED:
      continue
    if name.startswith("f"):  # Attention_Module
      R.linear(rules, par + (name, "ca", "fc_0"), f"{src}.ca.fc.0", bias=False)
      R.linear(rules, par + (name, "ca", "fc_2"), f"{src}.ca.fc.2", bias=False)
      R.conv(rules, par + (name, "conv_se"), f"{src}.conv_se")
    elif name.endswith("_attention"):  # fSEModule
      R.linear(rules, par + (name, "fc_0"), f"{src}.fc.0", bias=False)
      R.linear(rules, par + (name, "fc_2"), f"{src}.fc.2", bias=False)
      R.conv(rules, par + (name, "conv_se"), f"{src}.conv_se")
    elif name.endswith("_downsample"):  # Conv1x1
      R.conv(rules, par + (name,), f"{src}.conv", bias=False)
    elif name in DISP_CONVS:  # Conv3x3
      R.conv(rules, par + (name,), f"{src}.conv")
    else:  # ConvBlock
      R.conv(rules, par + (name,), f"{src}.conv.conv")
  return rules


def decoder_aliases(rules: R.Rules, prefix: str = "") -> dict[str, tuple[str, ...]]:
  """`convs.<name>.<leaf>` -> (`decoder.<k>.<leaf>`,), k = the module's ModuleDict position."""
  index = {name: k for k, name in enumerate(decoder_module_order())}
  aliases = {}
  for rule in rules:
    for src in rule.sources:
      name, leaf = src[len(prefix) + len("convs."):].split(".", 1)
      aliases[src] = (f"{prefix}decoder.{index[name]}.{leaf}",)
  return aliases


def _ignorable(prefix: str) -> Callable[[str], bool]:
  unused_idx = [k for k, n in enumerate(decoder_module_order()) if n in DECODER_UNUSED]
  unused = tuple(f"{prefix}convs.{n}." for n in DECODER_UNUSED) + tuple(
      f"{prefix}decoder.{k}." for k in unused_idx)

  def ignorable(key: str) -> bool:
    """num_batches_tracked, metadata, and upstream's never-called X_00..X_03_Conv_0."""
    return key.endswith("num_batches_tracked") or key in METADATA_KEYS or key.startswith(unused)
  return ignorable


# ------------------------------------------------------------------------------ reading


def fold_aliases(state: dict, aliases: dict[str, tuple[str, ...]], path: str) -> dict:
  """`state` without the alias keys, after checking each equals its canonical key (a missing
  alias is `check_keys`'s to report).

  Raises:
    CheckpointError: an alias holds a different tensor than its canonical key (the file's copies
      of one shared module disagree).
  """
  out = dict(state)
  for canonical, names in aliases.items():
    for alias in names:
      if alias not in out:
        continue
      value = out.pop(alias)
      ref = state.get(canonical)
      if ref is not None and not (np.shape(value) == np.shape(ref) and np.array_equal(value, ref)):
        raise CheckpointError(f"{path}: {alias} differs from {canonical}; both name one shared "
                              f"module and must hold the same tensor")
  return out


def _size(state: dict, key: str, given: int | None, path: str) -> int:
  """The training size entry `key` of the file and/or the command line (they must agree)."""
  value = int_entry(state, key, path, None)
  if value is not None:
    if given is not None and given != value:
      raise CheckpointError(f"{path}: records {key} = {value}, but {given} was given")
    return int(value)
  if given is None:
    raise CheckpointError(f"{path}: has no {key!r} entry (a DeepNet/high-resolution release); "
                          f"give the training size with --height and --width")
  return int(given)


def convert_monovit(encoder: str | os.PathLike | None, depth: str | os.PathLike,
                    height: int | None = None, width: int | None = None,
                    use_stereo: bool | None = None):
  """Converts MonoViT checkpoint files to Flax variables.

  Args:
    encoder: encoder.pth, or None when `depth` is a whole `DeepNet` (high-resolution releases).
    depth: depth.pth (decoder state dict, or `[module.]encoder.*` + `[module.]decoder.*`).
    height, width: the training size; required when the files do not record it.
    use_stereo: trained with stereo pairs (evaluated with MonoDepth2's x5.4 instead of median
      scaling); the files' entry when None. The high-resolution single-file releases record
      none (upstream evaluates `mono+stereo_1024x320` with `--eval_stereo`): pass True there.

  Returns:
    (config, variables): config {"height", "width"[, "use_stereo"], and the MPViT layout lists
    "num_path", "num_layers", "embed_dims", "mlp_ratios", "num_heads"} for `SPEC.build`;
    variables {"params": ..., "batch_stats": ...}, nested dicts of float32 NumPy arrays.
  """
  from flax.traverse_util import unflatten_dict
  from pitta_jax.models.monovit import SPEC, MonoViT

  if height is not None or width is not None:  # before a file is read (as SGDepth's)
    try:  # a side not given is the file's: the default stands in for it here
      SPEC.check_size(SPEC.default_size[0] if height is None else int(height),
                      SPEC.default_size[1] if width is None else int(width))
    except ValueError as e:
      raise ValueError(f"--height/--width: {e}") from None
  if encoder is None:  # one DeepNet file
    state = load_state_dict(depth)
    layout = infer_layout(state, str(depth), "encoder.")
    enc_rules, dec_rules = encoder_rules(layout, "encoder."), decoder_rules("decoder.")
    aliases = {**encoder_aliases(layout, "encoder."), **decoder_aliases(dec_rules, "decoder.")}
    parts = [(str(depth), state, enc_rules + dec_rules, aliases, _ignorable("decoder."))]
    meta_state, meta_path = state, str(depth)
  else:
    enc_state, dec_state = load_state_dict(encoder), load_state_dict(depth)
    if any(k.startswith("encoder.") for k in dec_state):
      raise CheckpointError(f"{depth}: holds a whole DeepNet (`encoder.*` keys); convert it "
                            f"without --encoder")
    overlap = set(enc_state) & set(dec_state) - set(METADATA_KEYS)
    if overlap:
      raise CheckpointError(f"{depth}: keys {sorted(overlap)[:4]} also occur in {encoder}; are the "
                            f"encoder and decoder files swapped or the same file?")
    layout = infer_layout(enc_state, str(encoder))
    dec_rules = decoder_rules()
    parts = [(str(encoder), enc_state, encoder_rules(layout), encoder_aliases(layout),
              _ignorable("")),
             (str(depth), dec_state, dec_rules, decoder_aliases(dec_rules), _ignorable(""))]
    meta_state, meta_path = enc_state, str(encoder)
  # key, duplicate and metadata errors before tracing the model for its shapes (seconds)
  for path, state, rules, aliases, ignorable in parts:
    used = {s for rule in rules for s in rule.sources}
    used.update(a for names in aliases.values() for a in names)
    check_keys(path, state, used, ignorable)
  parts = [(path, fold_aliases(state, aliases, path), rules, ignorable)
           for path, state, rules, aliases, ignorable in parts]
  config = {"height": _size(meta_state, "height", height, meta_path),
            "width": _size(meta_state, "width", width, meta_path)}
  if use_stereo is not None:
    config["use_stereo"] = bool(use_stereo)
  elif "use_stereo" in meta_state:
    config["use_stereo"] = flag_entry(meta_state, "use_stereo", meta_path)
  config.update({k: list(v) for k, v in layout.items()})

  expected = R.expected_shapes(MonoViT(**layout), (1, 64, 64, 3))
  flat = {}
  for path, state, rules, ignorable in parts:
    flat.update(R.apply_rules(state, rules, ignorable, path, expected, cover=False))
  R.check_covered(flat, expected)
  return config, unflatten_dict(flat)


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--encoder", help="encoder.pth (MPViT keys plus `height`, `width`, "
                      "`use_stereo`); omit for a high-resolution release's single depth.pth")
  parser.add_argument("--depth", required=True, help="depth.pth (HR decoder `convs.*`/`decoder.*`, "
                      "or a whole DeepNet `module.encoder.*` + `module.decoder.*`)")
  parser.add_argument("--height", type=int, help="training height (when the files lack it)")
  parser.add_argument("--width", type=int, help="training width (when the files lack it)")
  parser.add_argument("--use-stereo", action="store_true", default=None,
                      help="the weights were trained with stereo pairs (e.g. the single-file "
                           "mono+stereo_1024x320 release, which records no use_stereo): "
                           "evaluated with MonoDepth2's x5.4 factor instead of median scaling")
  parser.add_argument("--out", required=True, help="output weights directory")


def run(args: argparse.Namespace) -> Path:
  import jax
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.models.monovit import SPEC
  config, variables = convert_monovit(args.encoder, args.depth, args.height, args.width,
                                      args.use_stereo)
  out = save_weights(args.out, SPEC.name, config, variables,
                     source={"encoder": str(args.encoder) if args.encoder else None,
                             "depth": str(args.depth)})
  n = sum(a.size for a in jax.tree_util.tree_leaves(variables))
  print(f"converted MonoViT (MPViT widths {config['embed_dims']}, layers {config['num_layers']}, "
        f"{config['width']}x{config['height']}, {n:,} values) -> {out}")
  return out
