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
from pathlib import Path
from typing import Callable

import numpy as np

from weights_convert.pth import CheckpointError, load_pth
from weights_convert.strict import check_keys

Transform = Callable[[np.ndarray], np.ndarray]
# torch key -> (flax path (collection, module..., leaf), transform)
KeyTable = dict[str, tuple[tuple[str, ...], Transform]]

METADATA_KEYS = ("height", "width", "use_stereo")
RESNET_BLOCKS = {18: ("basic", (2, 2, 2, 2)), 34: ("basic", (3, 4, 6, 3)),
                 50: ("bottleneck", (3, 4, 6, 3))}
# upstream's decoder ModuleList order: (upconv, 4, 0), (upconv, 4, 1), ..., (upconv, 0, 1), dispconv 0..3
DECODER_ORDER = tuple(f"upconv_{i}_{j}" for i in range(4, -1, -1) for j in (0, 1)) + tuple(
    f"dispconv_{s}" for s in range(4))
POSE_ORDER = ("squeeze", "pose_0", "pose_1", "pose_2")


def conv_kernel(w: np.ndarray) -> np.ndarray:
  """PyTorch conv weight (O, I, kH, kW) -> Flax kernel (kH, kW, I, O)."""
  return np.ascontiguousarray(np.transpose(w, (2, 3, 1, 0)))


def identity(w: np.ndarray) -> np.ndarray:
  return np.ascontiguousarray(w)


def _conv(table: KeyTable, torch_name: str, flax_mod: tuple[str, ...], bias: bool) -> None:
  table[f"{torch_name}.weight"] = (("params",) + flax_mod + ("kernel",), conv_kernel)
  if bias:
    table[f"{torch_name}.bias"] = (("params",) + flax_mod + ("bias",), identity)


def _bn(table: KeyTable, torch_name: str, flax_mod: tuple[str, ...]) -> None:
  table[f"{torch_name}.weight"] = (("params",) + flax_mod + ("scale",), identity)
  table[f"{torch_name}.bias"] = (("params",) + flax_mod + ("bias",), identity)
  table[f"{torch_name}.running_mean"] = (("batch_stats",) + flax_mod + ("mean",), identity)
  table[f"{torch_name}.running_var"] = (("batch_stats",) + flax_mod + ("var",), identity)


def encoder_table(num_layers: int, prefix: str = "encoder.") -> KeyTable:
  """Key table for MonoDepth2's `ResnetEncoder` (torchvision names under `encoder.`)."""
  kind, blocks = RESNET_BLOCKS[num_layers]
  table: KeyTable = {}
  root = ("encoder",)
  _conv(table, f"{prefix}conv1", root + ("conv1",), bias=False)
  _bn(table, f"{prefix}bn1", root + ("bn1",))
  n_convs = 3 if kind == "bottleneck" else 2
  for stage, n_blocks in enumerate(blocks, start=1):
    for b in range(n_blocks):
      tname, fmod = f"{prefix}layer{stage}.{b}", root + (f"layer{stage}_{b}",)
      for c in range(1, n_convs + 1):
        _conv(table, f"{tname}.conv{c}", fmod + (f"conv{c}",), bias=False)
        _bn(table, f"{tname}.bn{c}", fmod + (f"bn{c}",))
      if b == 0 and (stage > 1 or kind == "bottleneck"):
        _conv(table, f"{tname}.downsample.0", fmod + ("downsample_conv",), bias=False)
        _bn(table, f"{tname}.downsample.1", fmod + ("downsample_bn",))
  return table


def depth_decoder_table() -> KeyTable:
  """`decoder.{k}.conv.conv.*` (ConvBlock) for the 10 upconvs, `decoder.{k}.conv.*` (Conv3x3)
  for the 4 dispconvs."""
  table: KeyTable = {}
  for k, name in enumerate(DECODER_ORDER):
    torch_name = f"decoder.{k}.conv.conv" if name.startswith("upconv") else f"decoder.{k}.conv"
    _conv(table, torch_name, ("decoder", name), bias=True)
  return table


def pose_decoder_table() -> KeyTable:
  table: KeyTable = {}
  for k, name in enumerate(POSE_ORDER):
    _conv(table, f"net.{k}", ("decoder", name), bias=True)
  return table


def _is_ignorable(key: str) -> bool:
  """Keys upstream checkpoints carry that the network does not use."""
  return (key.endswith("num_batches_tracked") or key.startswith("encoder.fc.")
          or key in METADATA_KEYS)


def infer_num_layers(state: dict, path: str) -> int:
  """ResNet depth from the encoder's keys: Bottleneck blocks have conv3; 18 vs 34 by block count."""
  if "encoder.layer1.0.conv3.weight" in state:
    return 50
  n_layer3 = len({k.split(".")[2] for k in state if k.startswith("encoder.layer3.")})
  if n_layer3 == 2:
    return 18
  if n_layer3 == 6:
    return 34
  raise CheckpointError(f"{path}: cannot tell the ResNet depth from its keys "
                        f"(encoder.layer3 has {n_layer3} blocks; expected 2 (ResNet-18) or 6 (ResNet-34))")


def apply_table(state: dict, table: KeyTable, path: str, expected: dict[tuple[str, ...], tuple]
                ) -> dict[tuple[str, ...], np.ndarray]:
  """Maps a flat PyTorch state dict through `table`, strictly.

  Args:
    state: torch key -> array (as `load_pth` returns it).
    table: the key table.
    path: file name, for messages.
    expected: Flax path -> shape of the target model (from `jax.eval_shape` of its init).
  """
  check_keys(path, state, table, _is_ignorable)
  flat = {}
  for key, (fpath, transform) in table.items():
    value = state[key]
    if not isinstance(value, np.ndarray):
      raise CheckpointError(f"{path}: {key} is a {type(value).__name__}, expected a tensor")
    arr = transform(value.astype(np.float32))
    want = expected.get(fpath)
    if want is None:
      raise CheckpointError(f"{path}: {key} maps to {'/'.join(fpath)}, which the model lacks")
    if tuple(arr.shape) != tuple(want):
      raise CheckpointError(f"{path}: {key} has shape {tuple(value.shape)} (-> {tuple(arr.shape)} "
                            f"in Flax layout), the model expects {tuple(want)} at {'/'.join(fpath)}")
    flat[fpath] = arr
  return flat


def _expected_shapes(module, channels: int, height: int = 64, width: int = 64) -> dict:
  import jax
  import jax.numpy as jnp
  from flax.traverse_util import flatten_dict
  shapes = jax.eval_shape(module.init, jax.random.PRNGKey(0),
                          jnp.zeros((1, height, width, channels), jnp.float32))
  return {k: v.shape for k, v in flatten_dict(shapes).items()}


def _read_state(path: str | os.PathLike) -> dict:
  state = load_pth(path)
  if not isinstance(state, dict):
    raise CheckpointError(f"{path}: expected a state dict, found a {type(state).__name__}")
  return state


def _meta(state: dict, key: str, default, path):
  value = state.get(key, default)
  if isinstance(value, np.ndarray) and value.size == 1:
    value = value.item()
  if key in ("height", "width"):
    if not isinstance(value, (int, np.integer)) or value <= 0:
      raise CheckpointError(f"{path}: extra entry {key!r} = {value!r} is not a positive int")
    return int(value)
  return bool(value)


def convert_monodepth2(encoder: str | os.PathLike, depth: str | os.PathLike,
                       pose_encoder: str | os.PathLike | None = None,
                       pose: str | os.PathLike | None = None, num_layers: int | None = None):
  """Converts MonoDepth2 checkpoint files to Flax variables.

  Returns:
    (ModelConfig, depth_variables, pose_variables or None); variables are nested dicts
    {"params": ..., "batch_stats": ...} of float32 NumPy arrays.
  """
  from flax.traverse_util import unflatten_dict
  from pitta_jax.checkpoint import ModelConfig
  from pitta_jax.models.depth_decoder import DepthNet
  from pitta_jax.models.pose import PoseNet

  if (pose_encoder is None) != (pose is None):
    raise CheckpointError("--pose-encoder and --pose go together: give both or neither")
  enc_state = _read_state(encoder)
  dec_state = _read_state(depth)
  num_layers = num_layers or infer_num_layers(enc_state, str(encoder))
  overlap = set(enc_state) & set(dec_state) - set(METADATA_KEYS)
  if overlap:
    raise CheckpointError(f"{depth}: keys {sorted(overlap)[:4]} also occur in {encoder}; "
                          f"are the encoder and decoder files swapped or the same file?")
  expected = _expected_shapes(DepthNet(num_layers), 3)
  flat = apply_table(enc_state, encoder_table(num_layers), str(encoder), expected)
  flat.update(apply_table(dec_state, depth_decoder_table(), str(depth), expected))
  missing = sorted("/".join(k) for k in expected if k not in flat)
  if missing:  # the tables and the model disagree: a bug here, not in the file
    raise AssertionError(f"key tables do not cover model paths {missing[:6]}")
  config = ModelConfig(
      num_layers=num_layers,
      height=_meta(enc_state, "height", 192, encoder),
      width=_meta(enc_state, "width", 640, encoder),
      use_stereo=_meta(enc_state, "use_stereo", False, encoder),
      source={"encoder": str(encoder), "depth": str(depth),
              "pose_encoder": str(pose_encoder) if pose_encoder else None,
              "pose": str(pose) if pose else None})
  depth_vars = unflatten_dict(flat)

  pose_vars = None
  if pose_encoder is not None:
    pe_state, pd_state = _read_state(pose_encoder), _read_state(pose)
    pose_layers = infer_num_layers(pe_state, str(pose_encoder))
    expected_pose = _expected_shapes(PoseNet(pose_layers), 6)
    pflat = apply_table(pe_state, encoder_table(pose_layers), str(pose_encoder), expected_pose)
    pflat.update(apply_table(pd_state, pose_decoder_table(), str(pose), expected_pose))
    pose_vars = unflatten_dict(pflat)
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
  from pitta_jax.checkpoint import save_monodepth2
  config, depth_vars, pose_vars = convert_monodepth2(
      args.encoder, args.depth, args.pose_encoder, args.pose, args.num_layers)
  out = save_monodepth2(args.out, config, depth_vars, pose_vars)
  import jax
  n = sum(a.size for a in jax.tree_util.tree_leaves((depth_vars, pose_vars)))
  print(f"converted MonoDepth2 ResNet-{config.num_layers} ({config.width}x{config.height}, "
        f"{'with' if pose_vars else 'no'} pose net, {n:,} values) -> {out}")
  return out

