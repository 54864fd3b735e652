"""Lite-Mono PyTorch checkpoints (noahzn/Lite-Mono `encoder.pth` + `depth.pth`) -> Flax variables.

The encoder file is upstream's `LiteMono.state_dict()` plus the trainer's `height`, `width`,
`use_stereo` entries; the depth file is `DepthDecoder.state_dict()`. An explicit key table
(built from the architecture, `weights_convert.rules`) maps each PyTorch name to a Flax path
of `pitta_jax.models.litemono.LiteMono`: conv `OIHW -> HWIO` (depthwise `(C, 1, 3, 3) ->
(3, 3, 1, C)`), linear `.T`, BN `weight/bias -> params scale/bias` and `running_mean/var ->
batch_stats mean/var`, LayerNorm `weight/bias -> scale/bias`, layer scales and XCA
temperatures as they are.

Keys the network does not use, declared one by one: `*.num_batches_tracked` (BN bookkeeping),
the metadata `height`/`width`/`use_stereo`, and `stages.i.j.norm.{weight,bias}` of every
DilatedConv block (upstream creates that LayerNorm but its forward never calls it; the LGFI
blocks' `norm` *is* used and is converted). No module is registered under two names (the
decoder's `convs` is a plain dict; only `decoder = nn.ModuleList(...)` reaches the state dict).
Loading is strict: unknown, missing or misshapen keys each fail naming the key and the file.

The model size (lite-mono, -small, -tiny, -8m) is read from the widths and block counts in the
keys; the training size (height, width) selects upstream's dilation rates.

    python -m weights_convert litemono --encoder encoder.pth --depth depth.pth --out DIR
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path


from weights_convert import rules as R
from weights_convert.pth import (METADATA_KEYS, CheckpointError, flag_entry, int_entry,
                                 load_state_dict)
from weights_convert.strict import looks_like

# upstream's decoder ModuleList order: (upconv, 2, 0), (upconv, 2, 1), ..., (upconv, 0, 1),
# then dispconv 0..2
DECODER_ORDER = tuple(f"upconv_{i}_{j}" for i in range(2, -1, -1) for j in (0, 1)) + tuple(
    f"dispconv_{s}" for s in range(3))
_STAGE_KEY = re.compile(r"^stages\.(\d)\.(\d+)\.")


def _is_lgfi(depth: int, j: int, global_blocks: int) -> bool:
  """Upstream's rule: the last `global_blocks` blocks of a stage are LGFI, the rest DilatedConv."""
  return j > depth - global_blocks - 1


def encoder_rules(model: str, root: tuple[str, ...] = ("encoder",)) -> R.Rules:
  """Key table of upstream `LiteMono(model)` (keys at the top level of encoder.pth) -> `root`."""
  from pitta_jax.models.litemono import encoder as E
  variant = E.VARIANTS[model]
  p = ("params",) + root
  rules: R.Rules = []
  for k in range(3):
    R.conv(rules, p + (f"downsample_layers_0_{k}", "conv"), f"downsample_layers.0.{k}.conv",
           bias=False)
    R.batch_norm(rules, root + (f"downsample_layers_0_{k}", "bn"),
                 f"downsample_layers.0.{k}.bn_gelu.bn")
  R.conv(rules, p + ("stem2_0", "conv"), "stem2.0.conv", bias=False)
  for i, (depth, heads) in enumerate(zip(variant.depths, E.HEADS)):
    if i > 0:
      R.conv(rules, p + (f"downsample_layers_{i}_0", "conv"), f"downsample_layers.{i}.0.conv",
             bias=False)
    for j in range(depth):
      t, f = f"stages.{i}.{j}", (f"stages_{i}_{j}",)
      if not _is_lgfi(depth, j, E.GLOBAL_BLOCKS[i]):  # DilatedConv
        R.conv(rules, p + f + ("ddwconv",), f"{t}.ddwconv.conv", bias=False)
        R.batch_norm(rules, root + f + ("bn1",), f"{t}.bn1")
      else:  # LGFI
        if E.USE_POS_EMBD[i]:
          R.conv(rules, p + f + ("pos_embd", "token_projection"), f"{t}.pos_embd.token_projection")
        R.layer_norm(rules, p + f + ("norm_xca",), f"{t}.norm_xca")
        R.linear(rules, p + f + ("xca", "qkv"), f"{t}.xca.qkv")
        R.param(rules, p + f + ("xca", "temperature"), f"{t}.xca.temperature")
        R.linear(rules, p + f + ("xca", "proj"), f"{t}.xca.proj")
        R.param(rules, p + f + ("gamma_xca",), f"{t}.gamma_xca")
        R.layer_norm(rules, p + f + ("norm",), f"{t}.norm")
      R.linear(rules, p + f + ("pwconv1",), f"{t}.pwconv1")
      R.linear(rules, p + f + ("pwconv2",), f"{t}.pwconv2")
      R.param(rules, p + f + ("gamma",), f"{t}.gamma")
  return rules


def unused_encoder_keys(model: str) -> frozenset[str]:
  """The DilatedConv blocks' never-called LayerNorm `stages.i.j.norm.{weight,bias}`."""
  from pitta_jax.models.litemono import encoder as E
  depths = E.VARIANTS[model].depths
  return frozenset(f"stages.{i}.{j}.norm.{leaf}" for i, depth in enumerate(depths)
                   for j in range(depth) if not _is_lgfi(depth, j, E.GLOBAL_BLOCKS[i])
                   for leaf in ("weight", "bias"))


def depth_decoder_rules(prefix: str = "decoder.", root: tuple[str, ...] = ("decoder",)) -> R.Rules:
  """`decoder.{k}.conv.conv.*` (ConvBlock) for the 6 upconvs, `decoder.{k}.conv.*` (Conv3x3)
  for the 3 dispconvs."""
  rules: R.Rules = []
  for k, name in enumerate(DECODER_ORDER):
    torch_name = f"{prefix}{k}.conv.conv" if name.startswith("upconv") else f"{prefix}{k}.conv"
    R.conv(rules, ("params",) + root + (name,), torch_name)
  return rules


def infer_model(state: dict, path: str) -> str:
  """The model size from the stage widths (downsampling conv outputs) and block counts."""
  from pitta_jax.models.litemono.encoder import VARIANTS
  try:
    dims = tuple(int(state[f"downsample_layers.{i}.0.conv.weight"].shape[0]) for i in range(3))
  except (KeyError, AttributeError) as e:
    raise CheckpointError(f"{path}: not a Lite-Mono encoder (no downsample_layers.N.0.conv."
                          f"weight tensor: {e}){looks_like(state)}") from None
  blocks: list[set[int]] = [set(), set(), set()]
  for key in state:
    m = _STAGE_KEY.match(key)
    if m and int(m.group(1)) < 3:
      blocks[int(m.group(1))].add(int(m.group(2)))
  depths = tuple(len(b) for b in blocks)
  for name, variant in VARIANTS.items():
    if variant.dims == dims and variant.depths == depths:
      return name
  raise CheckpointError(f"{path}: stage widths {dims} and block counts {depths} match no "
                        f"Lite-Mono model ({', '.join(VARIANTS)})")




def convert_litemono(encoder: str | os.PathLike, depth: str | os.PathLike,
                     model: str | None = None) -> tuple[dict, dict]:
  """Converts Lite-Mono's encoder.pth + depth.pth to Flax variables.

  Args:
    encoder, depth: upstream's files (a weights_N folder of the trainer).
    model: "lite-mono", "lite-mono-small", "lite-mono-tiny" or "lite-mono-8m" (default: read
      from the keys).

  Returns:
    (config, variables): config {"model", "height", "width", "use_stereo"} for `SPEC.build`
    (height/width: the training size stored in encoder.pth, 640x192 if absent); variables
    {"params": ..., "batch_stats": ...}, nested dicts of float32 NumPy arrays.
  """
  from flax.traverse_util import unflatten_dict
  from pitta_jax.models.litemono import DEFAULT_SIZE, SPEC

  enc_state, dec_state = load_state_dict(encoder), load_state_dict(depth)
  overlap = set(enc_state) & set(dec_state) - set(METADATA_KEYS)
  if overlap:
    raise CheckpointError(f"{depth}: keys {sorted(overlap)[:4]} also occur in {encoder}; "
                          f"are the encoder and decoder files swapped or the same file?")
  model = model or infer_model(enc_state, str(encoder))
  config = {"model": model,
            "height": int_entry(enc_state, "height", encoder, DEFAULT_SIZE[0]),
            "width": int_entry(enc_state, "width", encoder, DEFAULT_SIZE[1]),
            "use_stereo": flag_entry(enc_state, "use_stereo", encoder)}
  try:
    module = SPEC.build(config)
    expected = R.expected_shapes(module, (1, 64, 64, 3))
  except ValueError as e:  # an unknown model or a training size without upstream dilation rates
    raise CheckpointError(f"{encoder}: {e}") from None

  unused = unused_encoder_keys(model)
  enc_ignorable = lambda k: k.endswith("num_batches_tracked") or k in METADATA_KEYS or k in unused
  dec_ignorable = lambda k: k.endswith("num_batches_tracked")
  flat = R.apply_rules(enc_state, encoder_rules(model), enc_ignorable, str(encoder), expected,
                       cover=False)
  flat.update(R.apply_rules(dec_state, depth_decoder_rules(), dec_ignorable, str(depth), expected,
                            cover=False))
  R.check_covered(flat, expected)
  return config, unflatten_dict(flat)


def add_arguments(parser: argparse.ArgumentParser) -> None:
  from pitta_jax.models.litemono.encoder import VARIANTS
  parser.add_argument("--encoder", required=True, help="encoder.pth (LiteMono keys "
                      "`downsample_layers.*`, `stem2.*`, `stages.*`, plus `height`, `width`)")
  parser.add_argument("--depth", required=True, help="depth.pth (`decoder.N.*`)")
  parser.add_argument("--model", choices=sorted(VARIANTS),
                      help="model size (default: inferred from the encoder's keys)")
  parser.add_argument("--out", required=True, help="output weights directory")


def run(args: argparse.Namespace) -> Path:
  import jax
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.models.litemono import SPEC
  config, variables = convert_litemono(args.encoder, args.depth, args.model)
  out = save_weights(args.out, SPEC.name, config, variables,
                     source={"encoder": str(args.encoder), "depth": str(args.depth)})
  n = sum(a.size for a in jax.tree_util.tree_leaves(variables))
  print(f"converted {config['model']} ({config['width']}x{config['height']}, {n:,} values) "
        f"-> {out}")
  return out
