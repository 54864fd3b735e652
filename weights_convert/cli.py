"""Command line of the converters: `python -m weights_convert {monodepth2,...}`.

Also mounted as `pitta-jax convert ...`. A user error (missing or corrupt file, wrong keys or
shapes) prints one line and exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys

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


def run(args: argparse.Namespace) -> int:
  from pitta_jax.outputs import open_output_dir
  try:
    with open_output_dir(args.out):  # checked and locked before reading any checkpoint
      args.convert_fn(args)
  except (CheckpointError, FileNotFoundError, ValueError) as e:
    if getattr(args, "debug", False):
      raise
    print(f"error: {e}", file=sys.stderr)
    return 2
  except OSError as e:  # a full disk, a read-only directory, ...
    if getattr(args, "debug", False):
      raise
    where = f"{e.filename}: " if getattr(e, "filename", None) else ""
    print(f"error: {where}{e.strerror or e}", file=sys.stderr)
    return 2
  return 0


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(
      prog="python -m weights_convert",
      description="Convert PyTorch checkpoints to pitta-jax (Flax/orbax) weights. No torch needed.")
  add_subcommands(parser)
  return run(parser.parse_args(argv))
