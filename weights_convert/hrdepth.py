"""HR-Depth's released `encoder.pth` + `depth.pth` -> Flax variables for `HRDepthNet`.

encoder.pth is MonoDepth2's: the torchvision ResNet as `encoder.*` (MonoDepth2's key table;
`encoder.fc.*` and `num_batches_tracked` unused) plus the entries `height`, `width` (the training
input size, which becomes the config's) and `use_stereo`, which is not carried over: HR-Depth's
predictions are median-scaled per frame whatever the training, its MS releases too
(`--eval.alignment stereo` scores them x5.4, as MonoDepth2's stereo weights are).

depth.pth is the state dict of upstream's `HRDepthDecoder`, whose layers live in an
`nn.ModuleDict` `convs` that is *also* registered as `decoder = nn.ModuleList(convs.values())`;
so every tensor is stored twice, `convs.<name>.*` and `decoder.<index>.*` (index = position in
the ModuleDict's insertion order). The table reads `convs.<name>.*`; each `decoder.<index>.*`
twin must be present and equal to it (checked; a differing or lone twin is an error). Per layer:

  X_ij_Conv_0/1 (ConvBlock)    conv.conv.weight/bias -> X_ij_Conv_k/kernel, bias
  X_ij_attention (fSEModule)   fc.0.weight, fc.2.weight (linear, no bias) -> fc_0, fc_2;
                               conv_se.weight/bias -> conv_se
  X_ij_downsample (Conv1x1)    conv.weight (no bias) -> X_ij_downsample/kernel
  dispConvScale{s} (Conv3x3)   conv.weight/bias -> dispConvScale{s}

X_00_Conv_0 .. X_03_Conv_0 are built by upstream but never called in its forward: their keys
(and twins) are declared unused.

    python -m weights_convert hrdepth --encoder encoder.pth --depth depth.pth --out DIR
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from weights_convert import rules as R
from weights_convert.monodepth2 import (METADATA_KEYS, encoder_rules,
                                        infer_num_layers)
from weights_convert.pth import CheckpointError, int_entry, load_state_dict
from weights_convert.strict import looks_like, shown

# upstream layer kind -> the PyTorch parameter names of one layer (relative to the layer)
PARAMS = {
    "block": ("conv.conv.weight", "conv.conv.bias"),  # ConvBlock
    "attention": ("fc.0.weight", "fc.2.weight", "conv_se.weight", "conv_se.bias"),  # fSEModule
    "downsample": ("conv.weight",),  # Conv1x1
    "disp": ("conv.weight", "conv.bias"),  # Conv3x3
}
UNUSED = tuple(f"X_0{j}_Conv_0" for j in range(4))  # built upstream, never called in forward


def _kind(name: str) -> str:
  if name.endswith("_attention"):
    return "attention"
  if name.endswith("_downsample"):
    return "downsample"
  return "disp" if name.startswith("dispConvScale") else "block"


def upstream_layers() -> list[str]:
  """The `convs` names in upstream's ModuleDict insertion order (= the `decoder.<index>` order):
  the Conv_0 of every node column by column (and X_04_Conv_1 after X_04_Conv_0), the attention
  nodes, the other nodes' (downsample,) Conv_1, the 4 disparity heads."""
  from pitta_jax.models.hrdepth.decoder import ATTENTION_NODES, NODES
  names = []
  for j in range(5):
    for i in range(5 - j):
      names.append(f"X_{i}{j}_Conv_0")
      if (i, j) == (0, 4):
        names.append("X_04_Conv_1")
  names += [f"X_{r}{c}_attention" for r, c in ATTENTION_NODES]
  for r, c in NODES:
    if (r, c) not in ATTENTION_NODES:
      names += ([f"X_{r}{c}_downsample"] if c > 1 else []) + [f"X_{r + 1}{c - 1}_Conv_1"]
  return names + [f"dispConvScale{s}" for s in range(4)]


def twin_keys() -> dict[str, str]:
  """`decoder.<index>.<param>` -> its twin `convs.<name>.<param>`, for every upstream layer."""
  return {f"decoder.{i}.{p}": f"convs.{name}.{p}"
          for i, name in enumerate(upstream_layers()) for p in PARAMS[_kind(name)]}


def check_twins(state: dict, twins: dict[str, str], path: str) -> None:
  """Each `decoder.*` / `convs.*` pair is present together and holds equal values."""
  problems = []
  for dkey, ckey in twins.items():
    if (dkey in state) != (ckey in state):
      have, lack = (dkey, ckey) if dkey in state else (ckey, dkey)
      problems.append(f"{have} without its twin {lack}")
    elif dkey in state and not np.array_equal(np.asarray(state[dkey]), np.asarray(state[ckey])):
      problems.append(f"{dkey} differs from its twin {ckey}")
  if problems:  # a file without any `convs.*` key is another network's: named as such
    other = "" if any(k.startswith("convs.") for k in state) else looks_like(state)
    raise CheckpointError(f"{path}: `decoder.<i>` and `convs.<name>` are the same upstream "
                          f"layers, but " + shown(problems, sep="; ") + other)


def decoder_rules() -> R.Rules:
  """Key table of the decoder layers the forward uses, read from `convs.<name>.*`."""
  rules: R.Rules = []
  for name in upstream_layers():
    if name in UNUSED:
      continue
    root, src = ("params", "decoder", name), f"convs.{name}"
    kind = _kind(name)
    if kind == "attention":
      R.linear(rules, root + ("fc_0",), f"{src}.fc.0", bias=False)
      R.linear(rules, root + ("fc_2",), f"{src}.fc.2", bias=False)
      R.conv(rules, root + ("conv_se",), f"{src}.conv_se")
    elif kind == "downsample":
      R.conv(rules, root, f"{src}.conv", bias=False)
    else:
      R.conv(rules, root, f"{src}.conv.conv" if kind == "block" else f"{src}.conv")
  return rules


def _encoder_ignorable(key: str) -> bool:
  """encoder.pth keys the network does not use: BN step counters, the ImageNet classifier,
  MonoDepth2's metadata entries (height/width are read separately)."""
  return (key.endswith("num_batches_tracked") or key.startswith("encoder.fc.")
          or key in METADATA_KEYS)


def convert_hrdepth(encoder: str | os.PathLike, depth: str | os.PathLike) -> tuple[dict, dict]:
  """Converts HR-Depth's encoder.pth + depth.pth to Flax variables of `HRDepthNet`.

  Returns:
    (config, variables): config = {"num_layers", "height", "width"} (height/width from
    encoder.pth); variables = {"params", "batch_stats"} of float32 NumPy arrays.
  """
  from flax.traverse_util import unflatten_dict
  from pitta_jax.models.hrdepth import SPEC
  from pitta_jax.models.hrdepth.network import NUM_LAYERS

  enc_state, dec_state = load_state_dict(encoder), load_state_dict(depth)
  if any(isinstance(k, str) and k.startswith("encoder.features.") for k in enc_state):
    raise CheckpointError(f"{encoder}: a MobileNetV3 encoder (Lite-HR-Depth); only HR-Depth "
                          f"with a ResNet-{'/'.join(map(str, NUM_LAYERS))} encoder is implemented")
  num_layers = infer_num_layers(enc_state, str(encoder))
  if num_layers not in NUM_LAYERS:
    raise CheckpointError(f"{encoder}: a ResNet-{num_layers} encoder; HR-Depth's decoder fits "
                          f"ResNet-{'/'.join(map(str, NUM_LAYERS))}")
  for key in ("height", "width"):
    if key not in enc_state:
      raise CheckpointError(f"{encoder}: no {key!r} entry; HR-Depth's encoder.pth stores the "
                            f"training input size as 'height' and 'width'")
  config = {"num_layers": num_layers, "height": int_entry(enc_state, "height", encoder),
            "width": int_entry(enc_state, "width", encoder)}
  SPEC.check_size(config["height"], config["width"])
  expected = R.expected_shapes(SPEC.build(config), (1, 64, 64, 3))
  flat = R.apply_rules(enc_state, encoder_rules(num_layers), _encoder_ignorable, str(encoder),
                       expected, cover=False)
  twins = twin_keys()
  check_twins(dec_state, twins, str(depth))
  unused = {f"convs.{name}.{p}" for name in UNUSED for p in PARAMS["block"]}
  flat.update(R.apply_rules(dec_state, decoder_rules(), lambda k: k in twins or k in unused,
                            str(depth), expected, cover=False))
  R.check_covered(flat, expected)
  return config, unflatten_dict(flat)


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--encoder", required=True, help="encoder.pth (ResNet keys `encoder.*`, "
                      "plus `height`, `width`, `use_stereo`)")
  parser.add_argument("--depth", required=True, help="depth.pth (`convs.<name>.*` and their "
                      "twins `decoder.<index>.*`)")
  parser.add_argument("--out", required=True, help="output weights directory")


def run(args: argparse.Namespace) -> Path:
  import jax
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.models.hrdepth import SPEC
  config, variables = convert_hrdepth(args.encoder, args.depth)
  out = save_weights(args.out, SPEC.name, config, variables,
                     source={"encoder": str(args.encoder), "depth": str(args.depth)})
  n = sum(a.size for a in jax.tree_util.tree_leaves(variables))
  print(f"converted HR-Depth ResNet-{config['num_layers']} ({config['width']}x{config['height']}, "
        f"{n:,} values) -> {out}")
  return out
