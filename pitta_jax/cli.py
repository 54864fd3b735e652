"""`pitta-jax`: one entry point, subcommands. Thin: parse, build configs, call the library.

User errors (missing or corrupt files, bad data, bad options) print one line and exit with
status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys

from pitta_jax.data.errors import DataError


def _add_predict(sub) -> None:
  p = sub.add_parser(
      "predict", help="run a converted MonoDepth2 on images, write depth .npy and colour PNGs",
      description="Run a MonoDepth2 weights directory (from `pitta-jax convert monodepth2` or "
                  "`train-source`) on images: each is resized to the network's input size; "
                  "writes <stem>_disp.npy, <stem>_depth.npy (network resolution) and "
                  "<stem>_disp.png.")
  p.add_argument("--weights", required=True, help="weights directory (holds model.json)")
  p.add_argument("--images", required=True, help="an image file, a directory, or a glob (quote it)")
  p.add_argument("--out", required=True, help="output directory")
  p.add_argument("--quiet", action="store_true", help="no progress bar")
  p.set_defaults(func=_run_predict)


def _run_predict(args) -> int:
  from pitta_jax.predict import predict_images
  written = predict_images(args.weights, args.images, args.out, args.quiet)
  print(f"wrote {len(written)} predictions to {args.out}")
  return 0


def _add_convert(sub) -> None:
  from weights_convert import cli as convert_cli
  p = sub.add_parser("convert", help="convert PyTorch checkpoints (same as python -m weights_convert)",
                     description="Convert PyTorch checkpoints to pitta-jax weights; no torch needed.")
  convert_cli.add_subcommands(p)
  p.set_defaults(func=lambda args: convert_cli.run(args))


def build_parser() -> argparse.ArgumentParser:
  parser = argparse.ArgumentParser(
      prog="pitta-jax",
      description="PITTA: pose-agnostic, instance-aware test-time adaptation of monocular depth "
                  "networks, in JAX.")
  sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
  _add_predict(sub)
  _add_convert(sub)
  return parser


def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  try:
    return args.func(args)
  except (DataError, FileNotFoundError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    return 130


if __name__ == "__main__":
  sys.exit(main())
