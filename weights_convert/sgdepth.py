"""SGDepth's released `model.pth` -> Flax variables for `pitta_jax.models.sgdepth.SGDepthNet`.

Upstream (ifnspaml/SGDepth `state_manager.py`) saves `torch.save(model.state_dict())` of the whole
multi-task `SGDepth`: a plain state dict, no wrapper and no metadata. Its keys:

  common.encoder.encoder.*        shared torchvision ResNet (its `fc` is set to None upstream, so
                                  no classifier keys) -> "encoder", MonoDepth2's encoder table
  common.decoder.blocks.step_k.conv.*   decoder steps 0 .. split-1, shared with segmentation
  depth.decoder.blocks.step_k.conv.*    decoder steps split .. 9 of the depth branch
  depth.multires.convs.s.*        sigmoid disparity heads, scale s (convs.0 = full resolution)
  seg.*                           segmentation branch: not part of the depth network (ignored)
  pose.*                          pose network: ignored, it is not MonoDepth2's pose net (its
                                  decoder predicts one 6-vector, `conv_3` with 6 outputs and no
                                  x0.01, on ImageNet-normalised frames), so `PoseNet` cannot run it
  *.num_batches_tracked           BN step counters, unused

Decoder step 2m is MonoDepth2's `upconv_{4-m}_0`, step 2m+1 `upconv_{4-m}_1`; each step's weights
are read from `common.decoder` or `depth.decoder`, whichever holds it (the split position is read
from the file: the common steps must be 0 .. split-1 and the depth steps the rest). Loading is
strict as in `weights_convert.monodepth2`. model.pth stores no input size: `--height`/`--width`
default to the released models' 640x192.

    python -m weights_convert sgdepth --model model.pth --out DIR
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

from weights_convert import rules as R
from weights_convert.monodepth2 import encoder_rules, infer_num_layers
from weights_convert.strict import layout_of
from weights_convert.pth import CheckpointError, load_state_dict

ENCODER_PREFIX = "common.encoder.encoder."
COMMON_DECODER, DEPTH_DECODER = "common.decoder.blocks.", "depth.decoder.blocks."
MULTIRES = "depth.multires.convs."
NUM_STEPS = 10  # PartialDecoder steps: (PreConvBlock, UpSkipBlock) for each of 5 stages
_STEP_RE = re.compile(r"^(common|depth)\.decoder\.blocks\.step_(\d+)\.")
_MULTIRES_RE = re.compile(r"^depth\.multires\.convs\.(\d+)\.")


def step_name(step: int) -> str:
  """PartialDecoder step -> the MonoDepth2 decoder layer it is (`upconv_{i}_{j}`)."""
  return f"upconv_{4 - step // 2}_{step % 2}"


def infer_split(state: dict, path: str) -> int:
  """Number of decoder steps in `common.decoder` (1 in the released models), checked against the
  steps of `depth.decoder`."""
  steps = {"common": set(), "depth": set()}
  for key in state:
    m = _STEP_RE.match(key)
    if m:
      steps[m.group(1)].add(int(m.group(2)))
  split = len(steps["common"])
  if steps["common"] != set(range(split)) or steps["depth"] != set(range(split, NUM_STEPS)):
    raise CheckpointError(
        f"{path}: decoder steps common.decoder {sorted(steps['common'])} + depth.decoder "
        f"{sorted(steps['depth'])} are not 0..k-1 and k..{NUM_STEPS - 1}; not an SGDepth model.pth?")
  return split


def infer_num_scales(state: dict, path: str) -> int:
  """Disparity heads in `depth.multires` (upstream --model-depth-resolutions, 4 released)."""
  heads = {int(m.group(1)) for m in map(_MULTIRES_RE.match, state) if m}
  if not heads or heads != set(range(len(heads))) or len(heads) > 4:
    raise CheckpointError(f"{path}: depth.multires.convs holds heads {sorted(heads)}, expected "
                          f"0..n-1 with n in 1..4")
  return len(heads)


def depth_rules(num_layers: int, split: int, num_scales: int) -> R.Rules:
  """Key table of the depth path: encoder, the 10 decoder steps, the disparity heads."""
  rules = encoder_rules(num_layers, prefix=ENCODER_PREFIX)
  for step in range(NUM_STEPS):
    prefix = COMMON_DECODER if step < split else DEPTH_DECODER
    R.conv(rules, ("params", "decoder", step_name(step)), f"{prefix}step_{step}.conv")
  for s in range(num_scales):
    R.conv(rules, ("params", "decoder", f"dispconv_{s}"), f"{MULTIRES}{s}")
  return rules


def _is_ignorable(key: str) -> bool:
  """Keys of model.pth the depth network does not use (see the module docstring)."""
  return key.endswith("num_batches_tracked") or key.startswith(("seg.", "pose."))


def convert_sgdepth(model: str | os.PathLike, height: int | None = None,
                    width: int | None = None) -> tuple[dict, dict]:
  """Converts SGDepth's `model.pth` to Flax variables of `SGDepthNet`.

  Args:
    model: the released `model.pth` (the state dict of upstream's whole `SGDepth`).
    height, width: the input size the weights were trained at (model.pth does not store it);
      default: `SPEC.default_size`.

  Returns:
    (config, variables): config = {"num_layers", "num_scales", "height", "width"} (JSON-able,
    what `SPEC.build` reads); variables = {"params", "batch_stats"} of float32 NumPy arrays.
  """
  from flax.traverse_util import unflatten_dict
  from pitta_jax.models.sgdepth import SPEC

  size = {"height": SPEC.default_size[0] if height is None else int(height),
          "width": SPEC.default_size[1] if width is None else int(width)}
  try:  # before the file is read
    SPEC.check_size(size["height"], size["width"])
  except ValueError as e:
    raise ValueError(f"--height/--width: {e}") from None
  state, path = load_state_dict(model), str(model)
  encoder_view = {k[len("common.encoder."):]: v for k, v in state.items()
                  if k.startswith(ENCODER_PREFIX)}  # MonoDepth2's `encoder.*` layout
  if not encoder_view:
    other = layout_of(k for k in state if isinstance(k, str))
    raise CheckpointError(f"{path}: not an SGDepth model.pth (no {ENCODER_PREFIX}* keys)"
                          + (f"; its keys look like {other}"
                             if other else ""))
  num_layers = infer_num_layers(encoder_view, path)
  split, num_scales = infer_split(state, path), infer_num_scales(state, path)
  config = {"num_layers": num_layers, "num_scales": num_scales, **size}
  expected = R.expected_shapes(SPEC.build(config), (1, 64, 64, 3))
  flat = R.apply_rules(state, depth_rules(num_layers, split, num_scales), _is_ignorable, path,
                       expected)
  return config, unflatten_dict(flat)


def add_arguments(parser: argparse.ArgumentParser) -> None:
  from pitta_jax.models.sgdepth import SPEC
  height, width = SPEC.default_size
  parser.add_argument("--model", required=True, help="SGDepth model.pth (state dict of the whole "
                      "SGDepth: common.*, depth.*, seg.*, pose.*)")
  parser.add_argument("--height", type=int, help=f"training input height (default {height}, "
                      f"the released models')")
  parser.add_argument("--width", type=int, help=f"training input width (default {width})")
  parser.add_argument("--out", required=True, help="output weights directory")


def run(args: argparse.Namespace) -> Path:
  import jax
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.models.sgdepth import SPEC
  config, variables = convert_sgdepth(args.model, args.height, args.width)
  out = save_weights(args.out, SPEC.name, config, variables, source={"model": str(args.model)})
  n = sum(a.size for a in jax.tree_util.tree_leaves(variables))
  print(f"converted SGDepth ResNet-{config['num_layers']} ({config['width']}x{config['height']}, "
        f"{config['num_scales']} scales, {n:,} values; seg and pose heads dropped) -> {out}")
  return out
