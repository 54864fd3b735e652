"""Command line of the converters: `python -m weights_convert {monodepth2,...}`.

Also mounted as `pitta-jax convert ...`. A user error (missing or corrupt file, wrong keys or
shapes) prints one line and exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys

from weights_convert import mask2former, monodepth2
from weights_convert.pth import CheckpointError

# converter name -> (help, add_arguments, run)
CONVERTERS = {
    "monodepth2": ("MonoDepth2 encoder/depth(/pose) .pth files -> a pitta-jax weights directory",
                   monodepth2.add_arguments, monodepth2.run),
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
  try:
    args.convert_fn(args)
  except (CheckpointError, FileNotFoundError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  return 0


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(
      prog="python -m weights_convert",
      description="Convert PyTorch checkpoints to pitta-jax (Flax/orbax) weights. No torch needed.")
  add_subcommands(parser)
  return run(parser.parse_args(argv))
