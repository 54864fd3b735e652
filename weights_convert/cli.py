"""Command line of the converters: `python -m weights_convert {monodepth2,...}`.

Also mounted as `pitta-jax convert ...`. A user error (missing or corrupt file, wrong keys or
shapes) prints one line and exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse

from pitta_jax.checkpoint import INCOMPLETE, MODEL_JSON
from pitta_jax.cli import report_error
from pitta_jax.models.mask2former.load import CONFIG_JSON, PARAMS_DIR
from weights_convert import (depth_anything_v2, hrdepth, litemono, mask2former, monodepth2,
                             monovit, sgdepth)
from weights_convert.pth import CheckpointError

# converter name -> (help, add_arguments, run)
CONVERTERS = {
    "monodepth2": ("MonoDepth2 encoder/depth(/pose) .pth files -> a pitta-jax weights directory",
                   monodepth2.add_arguments, monodepth2.run),
    "sgdepth": ("SGDepth model.pth (depth path; seg/pose heads ignored) -> a weights directory",
                sgdepth.add_arguments, sgdepth.run),
    "hrdepth": ("HR-Depth encoder.pth + depth.pth -> a weights directory",
                hrdepth.add_arguments, hrdepth.run),
    "litemono": ("Lite-Mono encoder.pth + depth.pth -> a weights directory",
                 litemono.add_arguments, litemono.run),
    "monovit": ("MonoViT encoder.pth + depth.pth (or a whole-network depth.pth) -> a weights "
                "directory", monovit.add_arguments, monovit.run),
    "depth-anything-v2": ("Depth Anything V2 (official .pth or Hugging Face .safetensors) -> a "
                          "weights directory", depth_anything_v2.add_arguments,
                          depth_anything_v2.run),
    "mask2former": ("Mask2Former (detectron2 .pkl / Hugging Face .safetensors) -> a pitta-jax "
                    "weights directory", mask2former.add_arguments, mask2former.run),
}


def add_subcommands(parser: argparse.ArgumentParser) -> None:
  sub = parser.add_subparsers(dest="converter", required=True, metavar="CONVERTER")
  for name, (help_text, add_arguments, run) in CONVERTERS.items():
    p = sub.add_parser(name, help=help_text, description=help_text)
    add_arguments(p)
    p.set_defaults(convert_fn=run)


# what a converter writes under --out: a depth network's weights directory, or Mask2Former's
DEPTH_WRITTEN = (MODEL_JSON, "depth", "pose")
MASK2FORMER_WRITTEN = (CONFIG_JSON, PARAMS_DIR)
WRITTEN = DEPTH_WRITTEN + MASK2FORMER_WRITTEN


def check_output_replaceable(out: str, converter: str | None = None) -> None:
  """ValueError when --out holds something the `converter` would replace (a depth network's
  model.json, depth/, pose/; Mask2Former's config.json, params/; all five for None) that is not
  earlier pitta-jax weights: a dataset's depth/ folder, a user's own model.json. Earlier weights
  (a model.json or Mask2Former's config.json naming an architecture, beside orbax checkpoint
  folders) are replaced, as a rerun expects; the other network's weights are refused (one
  network per directory); anything else in --out (the .pth files converted, a Hub snapshot's
  own config.json beside a depth conversion) is left alone."""
  import json
  from pathlib import Path
  if not out:
    raise ValueError("--out: an empty path (give the weights directory to write)")
  path = Path(out)

  def is_description(p: Path) -> bool:
    try:
      meta = json.loads(p.read_text()) if p.is_file() else None
    except (OSError, ValueError):
      return False
    return isinstance(meta, dict) and "architecture" in meta

  def is_checkpoint(p: Path) -> bool:
    return p.is_dir() and any((p / m).is_file() for m in ("_METADATA", "_CHECKPOINT_METADATA"))

  def is_weights(name: str) -> bool:
    """--out/name is pitta-jax weights' own: a description naming an architecture, or an orbax
    checkpoint folder (a Hub snapshot's own config.json is neither)."""
    return (is_description(path / name) if name in (MODEL_JSON, CONFIG_JSON)
            else is_checkpoint(path / name))

  # what this converter writes, and the other kind of weights (none when it is not known)
  if converter is None:
    written, other, kind = WRITTEN, (), ""
  elif converter == "mask2former":
    written, other, kind = MASK2FORMER_WRITTEN, DEPTH_WRITTEN[:2], "a depth network's"
  else:
    written, other, kind = DEPTH_WRITTEN, MASK2FORMER_WRITTEN, "Mask2Former"
  if path.is_dir() and any(map(is_weights, other)):  # one network's weights per directory
    raise ValueError(f"--out {out}: holds {kind} weights ({', '.join(other)}); the "
                     f"{converter} weights need a directory of their own")
  present = [name for name in written if (path / name).exists()] if path.is_dir() else []
  if not present:
    return
  descriptions = [n for n in present if n in (MODEL_JSON, CONFIG_JSON)]
  foreign = [n for n in present if not is_weights(n)]
  # an interrupted conversion's checkpoints (marked, without their description) are ours too
  if foreign or not (descriptions or (path / INCOMPLETE).is_file()):
    names = foreign or present
    shown = ", ".join(f"{n}/" if (path / n).is_dir() else n for n in names)
    raise ValueError(f"--out {out}: its {shown} would be replaced and "
                     f"{'are' if len(names) > 1 else 'is'} not earlier pitta-jax weights: choose "
                     f"a new or empty directory")


def check_inputs_outside_output(args: argparse.Namespace) -> None:
  """ValueError when an input file or directory given on the command line lies where the
  converter writes (--out/model.json, --out/depth, ...): it would be replaced."""
  from pathlib import Path
  out = Path(args.out).resolve()
  targets = [out / name for name in WRITTEN]
  for flag, value in vars(args).items():
    if flag == "out" or not isinstance(value, str) or not value or not Path(value).exists():
      continue
    path = Path(value).resolve()
    hit = next((t for t in targets if path == t or t in path.parents), None)
    if hit is not None:
      raise ValueError(f"--out {args.out} would overwrite the input --{flag.replace('_', '-')} "
                       f"{value} (converters write {', '.join(WRITTEN)} there): choose another "
                       f"--out")


def run(args: argparse.Namespace) -> int:
  from pitta_jax.outputs import open_output_dir
  try:
    check_inputs_outside_output(args)  # the more specific message first
    check_output_replaceable(args.out, args.converter)
    with open_output_dir(args.out):  # checked and locked before reading any checkpoint
      args.convert_fn(args)
  except Exception as e:
    return report_error(e, getattr(args, "debug", False), (CheckpointError,))
  return 0


def main(argv: list[str] | None = None) -> int:
  from pitta_jax.config_cli import ArgumentParser  # one-line usage errors, as `pitta-jax convert`
  parser = ArgumentParser(
      prog="python -m weights_convert",
      description="Convert PyTorch checkpoints to pitta-jax (Flax/orbax) weights. No torch needed.")
  parser.add_argument("--debug", action="store_true",
                      help="show the full traceback of an error instead of one line")
  add_subcommands(parser)
  return run(parser.parse_args(argv))
