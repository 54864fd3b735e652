"""MonoDepth2 PyTorch checkpoints (`mono_640x192/` layout) -> Flax variables for `DepthNet`/`PoseNet`.

An explicit key table maps each PyTorch name to a Flax path and a layout transform:
conv `OIHW -> HWIO`; BN `weight/bias -> params scale/bias`, `running_mean/var -> batch_stats
mean/var`; `num_batches_tracked` and the ImageNet classifier `encoder.fc.*` are dropped (upstream
saves the whole torchvision ResNet); `height`, `width`, `use_stereo` are metadata. Loading is
strict: a key the table does not know, a key the table needs but the file lacks, or a shape
that differs from the Flax model's, each fails naming the key and file.

    python -m weights_convert monodepth2 --encoder encoder.pth --depth depth.pth \
        [--pose-encoder pose_encoder.pth --pose pose.pth] --out DIR
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from weights_convert import rules as R
from weights_convert.pth import (METADATA_KEYS, CheckpointError, flag_entry, int_entry,
                                 load_state_dict)
from weights_convert.strict import layout_of

RESNET_BLOCKS = {18: ("basic", (2, 2, 2, 2)), 34: ("basic", (3, 4, 6, 3)),
                 50: ("bottleneck", (3, 4, 6, 3))}
# upstream's decoder ModuleList order: (upconv, 4, 0), (upconv, 4, 1), ..., (upconv, 0, 1), dispconv 0..3
DECODER_ORDER = tuple(f"upconv_{i}_{j}" for i in range(4, -1, -1) for j in (0, 1)) + tuple(
    f"dispconv_{s}" for s in range(4))
POSE_ORDER = ("squeeze", "pose_0", "pose_1", "pose_2")


def encoder_rules(num_layers: int, prefix: str = "encoder.", root: tuple[str, ...] = ("encoder",)
                  ) -> R.Rules:
  """Key table of MonoDepth2's `ResnetEncoder` (torchvision names under `prefix`) -> `root`."""
  kind, blocks = RESNET_BLOCKS[num_layers]
  rules: R.Rules = []
  R.conv(rules, ("params",) + root + ("conv1",), f"{prefix}conv1", bias=False)
  R.batch_norm(rules, root + ("bn1",), f"{prefix}bn1")
  n_convs = 3 if kind == "bottleneck" else 2
  for stage, n_blocks in enumerate(blocks, start=1):
    for b in range(n_blocks):
      tname, fmod = f"{prefix}layer{stage}.{b}", root + (f"layer{stage}_{b}",)
      for c in range(1, n_convs + 1):
        R.conv(rules, ("params",) + fmod + (f"conv{c}",), f"{tname}.conv{c}", bias=False)
        R.batch_norm(rules, fmod + (f"bn{c}",), f"{tname}.bn{c}")
      if b == 0 and (stage > 1 or kind == "bottleneck"):
        R.conv(rules, ("params",) + fmod + ("downsample_conv",), f"{tname}.downsample.0",
               bias=False)
        R.batch_norm(rules, fmod + ("downsample_bn",), f"{tname}.downsample.1")
  return rules


def depth_decoder_rules(prefix: str = "decoder.", root: tuple[str, ...] = ("decoder",)) -> R.Rules:
  """`decoder.{k}.conv.conv.*` (ConvBlock) for the 10 upconvs, `decoder.{k}.conv.*` (Conv3x3)
  for the 4 dispconvs."""
  rules: R.Rules = []
  for k, name in enumerate(DECODER_ORDER):
    torch_name = f"{prefix}{k}.conv.conv" if name.startswith("upconv") else f"{prefix}{k}.conv"
    R.conv(rules, ("params",) + root + (name,), torch_name)
  return rules


def pose_decoder_rules() -> R.Rules:
  rules: R.Rules = []
  for k, name in enumerate(POSE_ORDER):
    R.conv(rules, ("params", "decoder", name), f"net.{k}")
  return rules


def _is_ignorable(key: str) -> bool:
  """Keys upstream checkpoints carry that the network does not use."""
  return (key.endswith("num_batches_tracked") or key.startswith("encoder.fc.")
          or key in METADATA_KEYS)


def infer_num_layers(state: dict, path: str) -> int:
  """ResNet depth from the encoder's keys: Bottleneck blocks have conv3 (50 vs 101/152 by the
  block count of layer3: 6, 23, 36); 18 vs 34 by the same count (2, 6)."""
  n_layer3 = len({k.split(".")[2] for k in state
                  if isinstance(k, str) and k.startswith("encoder.layer3.")})
  if "encoder.layer1.0.conv3.weight" in state:
    if n_layer3 == 6:
      return 50
    deeper = {23: "ResNet-101", 36: "ResNet-152"}.get(n_layer3, "deeper ResNet")
    raise CheckpointError(f"{path}: a {deeper} encoder (encoder.layer3 has {n_layer3} "
                          f"Bottleneck blocks); ResNet-18, 34 and 50 are supported")
  if not any(isinstance(k, str) and k.startswith("encoder.") for k in state):
    found = next((k for k in state if k not in METADATA_KEYS), None)
    other = layout_of(k for k in state if isinstance(k, str))
    guess = f"its keys look like {other}" if other else "is it a decoder?"
    if other is None or "monodepth2" in other:
      guess += "; check that the encoder and decoder files are not swapped"
    raise CheckpointError(f"{path}: holds no ResNet encoder (no `encoder.*` key"
                          + (f"; found e.g. {found!r}" if found else "") + f"): {guess}")
  if n_layer3 == 2:
    return 18
  if n_layer3 == 6:
    return 34
  raise CheckpointError(f"{path}: cannot tell the ResNet depth from its keys "
                        f"(encoder.layer3 has {n_layer3} blocks; expected 2 (ResNet-18) or 6 "
                        f"(ResNet-34))")


def convert_monodepth2(encoder: str | os.PathLike, depth: str | os.PathLike,
                       pose_encoder: str | os.PathLike | None = None,
                       pose: str | os.PathLike | None = None, num_layers: int | None = None,
                       notes: list[str] | None = None):
  """Converts MonoDepth2 checkpoint files to Flax variables.

  notes: where given, what the user should know is appended (an encoder without the training
  size entries, which upstream's training always writes: MonoDepth2's default size is taken).

  Returns:
    (config, depth_variables, pose_variables or None): config is the model.json dict of the
    MonoDepth2 registry entry (num_layers, height, width, use_stereo[, pose_num_layers]);
    variables are nested dicts {"params": ..., "batch_stats": ...} of float32 NumPy arrays.
  """
  from flax.traverse_util import unflatten_dict
  from pitta_jax.models.depth_decoder import DepthNet
  from pitta_jax.models.monodepth2 import DEFAULT_SIZE
  from pitta_jax.models.pose import PoseNet
  from pitta_jax.models.registry import get_spec

  if (pose_encoder is None) != (pose is None):
    raise CheckpointError("--pose-encoder and --pose go together: give both or neither")
  enc_state = load_state_dict(encoder)
  missing = [p for p in (pose_encoder, pose) if p is not None and not os.path.exists(p)]
  if missing and flag_entry(enc_state, "use_stereo", encoder):
    raise CheckpointError(f"{missing[0]}: no such file; a stereo-trained release (use_stereo in "
                          f"{encoder}) may ship no pose network: leave out --pose-encoder and "
                          f"--pose")
  dec_state = load_state_dict(depth)
  num_layers = num_layers or infer_num_layers(enc_state, str(encoder))
  overlap = set(enc_state) & set(dec_state) - set(METADATA_KEYS)
  if overlap:
    raise CheckpointError(f"{depth}: keys {sorted(overlap)[:4]} also occur in {encoder}; "
                          f"are the encoder and decoder files swapped or the same file?")
  expected = R.expected_shapes(DepthNet(num_layers), (1, 64, 64, 3))
  flat = R.apply_rules(enc_state, encoder_rules(num_layers), _is_ignorable, str(encoder),
                       expected, cover=False)
  flat.update(R.apply_rules(dec_state, depth_decoder_rules(), _is_ignorable, str(depth),
                            expected, cover=False))
  R.check_covered(flat, expected)
  present = [k for k in ("height", "width") if k in enc_state]
  absent = [k for k in ("height", "width") if k not in present]
  if len(present) == 1:  # half a size is no training size
    raise CheckpointError(f"{encoder}: has a {present[0]!r} entry but no {absent[0]!r} entry")
  if absent and notes is not None:
    notes.append(f"{encoder} has no 'height' and 'width' entries (upstream's training writes "
                 f"them): taken as trained at MonoDepth2's {DEFAULT_SIZE[1]}x{DEFAULT_SIZE[0]}")
  config = {"num_layers": num_layers,
            "height": int_entry(enc_state, "height", encoder, DEFAULT_SIZE[0]),
            "width": int_entry(enc_state, "width", encoder, DEFAULT_SIZE[1]),
            "use_stereo": flag_entry(enc_state, "use_stereo", encoder)}
  try:  # the size the weights were trained at must be one the network takes
    get_spec("monodepth2").check_size(config["height"], config["width"])
  except ValueError as e:
    raise CheckpointError(f"{encoder}: its 'height' and 'width' entries: {e}") from None
  depth_vars = unflatten_dict(flat)

  pose_vars = None
  if pose_encoder is not None:
    pe_state, pd_state = load_state_dict(pose_encoder), load_state_dict(pose)
    pose_layers = infer_num_layers(pe_state, str(pose_encoder))
    expected_pose = R.expected_shapes(PoseNet(pose_layers), (1, 64, 64, 6))
    pflat = R.apply_rules(pe_state, encoder_rules(pose_layers), _is_ignorable,
                          str(pose_encoder), expected_pose, cover=False)
    pflat.update(R.apply_rules(pd_state, pose_decoder_rules(), _is_ignorable, str(pose),
                               expected_pose, cover=False))
    R.check_covered(pflat, expected_pose)
    pose_vars = unflatten_dict(pflat)
    config["pose_num_layers"] = pose_layers
  return config, depth_vars, pose_vars


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--encoder", required=True, help="encoder.pth (ResNet keys `encoder.*`, "
                      "plus `height`, `width`, `use_stereo`)")
  parser.add_argument("--depth", required=True, help="depth.pth (`decoder.N.*`)")
  parser.add_argument("--pose-encoder", help="pose_encoder.pth (first conv takes 6 channels)")
  parser.add_argument("--pose", help="pose.pth (`net.0..3`)")
  parser.add_argument("--num-layers", type=int, choices=sorted(RESNET_BLOCKS),
                      help="ResNet depth (default: inferred from the encoder's keys)")
  parser.add_argument("--out", required=True, help="output weights directory")


def run(args: argparse.Namespace) -> Path:
  from pitta_jax.checkpoint import save_weights
  notes: list[str] = []
  config, depth_vars, pose_vars = convert_monodepth2(
      args.encoder, args.depth, args.pose_encoder, args.pose, args.num_layers, notes)
  for note in notes:
    print(f"note: {note}", file=sys.stderr)
  source = {"encoder": str(args.encoder), "depth": str(args.depth),
            "pose_encoder": args.pose_encoder and str(args.pose_encoder),
            "pose": args.pose and str(args.pose)}
  out = save_weights(args.out, "monodepth2", config, depth_vars, pose_vars, source)
  import jax
  n = sum(a.size for a in jax.tree_util.tree_leaves((depth_vars, pose_vars)))
  print(f"converted MonoDepth2 ResNet-{config['num_layers']} ({config['width']}x{config['height']}, "
        f"{'with' if pose_vars else 'no'} pose net, {n:,} values) -> {out}")
  return out

