"""`pitta-jax`: one entry point, subcommands. Thin: parse, build configs, call the library.

User errors (missing or corrupt files, bad data, bad options) print one line and exit with
status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from typing import Callable, NoReturn

from pitta_jax.data.errors import DataError
from pitta_jax.text import first_and_count

# what --images / --source-images take (`predict.expand_images`)
IMAGES_HELP = ("an image file, a directory, a glob (quote it; ** for any depth of folders) or a "
               ".txt list of image paths, one per line")


def _add_predict(sub) -> None:
  p = sub.add_parser(
      "predict", help="run a converted depth network on images, write .npy and colour PNGs",
      description="Run a weights directory (from `pitta-jax convert NETWORK` or "
                  "`train-source`) on images: each is resized to the size the weights were "
                  "trained at (Depth Anything V2: its aspect ratio kept, each side at least the "
                  "trained one, multiples of 14, as upstream's infer_image); "
                  "writes <stem>_disp.npy (the MonoDepth2 family: the scaled disparity in "
                  "[0.01, 10] that MonoDepth2's test_simple.py saves, as (H, W); Depth Anything "
                  "V2: its relative inverse depth; its metric models: metres), "
                  "<stem>_depth.npy (MonoDepth2 family: at the network's resolution, 1 / "
                  "scaled disparity in [0.1, 100]; Depth Anything V2: at the image's size, as "
                  "infer_image, 1 / max(disparity, 1e-6), so up to 1e6 where it predicts 0, e.g. "
                  "sky; its metric models: the depth itself) and <stem>_disp.png (near = "
                  "bright).")
  p.add_argument("--weights", required=True, help="weights directory (holds model.json)")
  p.add_argument("--images", required=True, help=IMAGES_HELP)
  p.add_argument("--out", required=True, help="output directory")
  p.add_argument("--height", type=int, help="input height (default: the weights' training size; "
                 "Depth Anything V2: from each image, its aspect ratio kept; must follow the "
                 "network's size rule, e.g. a multiple of 32 or 14)")
  p.add_argument("--width", type=int, help="input width (with --height)")
  p.add_argument("--quiet", action="store_true", help="no progress bar")
  p.set_defaults(func=_run_predict)


def _size(args) -> tuple[int, int] | None:
  """(--height, --width), or None when neither is given."""
  from pitta_jax.models.spec import MAX_SIDE
  if (args.height is None) != (args.width is None):
    raise ValueError("give both --height and --width, or neither")
  if args.height is None:
    return None
  if min(args.height, args.width) < 1:
    raise ValueError(f"--height/--width must be positive, got {args.height}x{args.width}")
  if max(args.height, args.width) > MAX_SIDE:
    raise ValueError(f"--height/--width: {args.height}x{args.width} is more than {MAX_SIDE} "
                     f"pixels on a side")
  return args.height, args.width


def _run_predict(args) -> int:
  from pitta_jax.outputs import open_output_dir
  from pitta_jax.predict import predict_images
  with open_output_dir(args.out) as held:
    written = predict_images(args.weights, args.images, args.out, args.quiet, _size(args),
                             held.check)
  print(f"wrote {len(written)} predictions to {args.out}")
  return 0


def _add_segment(sub) -> None:
  p = sub.add_parser(
      "segment", help="run a converted Mask2Former on images, write COCO panoptic PNG + JSON",
      description="Panoptic segmentation with a Mask2Former weights directory (from `pitta-jax "
                  "convert mask2former --from {detectron2,hf} CKPT --out DIR`). Writes per "
                  "image OUT/<stem>.png (COCO panoptic: id = R + 256 G + 256^2 B, 0 = void) "
                  "and OUT/<stem>.json ({\"segments_info\": [...]}, COCO category ids), at the "
                  "image's own size: the input of `--segmentation png:OUT` (or the folder "
                  "reader's panoptic_dir option). By default each image enters the network at "
                  "its own size, zero-padded to a multiple of 32 (no upscaling to 800 pixels; "
                  "--detectron2-resize for upstream's test-time scale).",
      epilog="example: pitta-jax segment --weights weights/m2f_swin_t --images 'seq/*.png' "
             "--out seq_panoptic; then pitta-jax adapt --dataset folder --root seq "
             "--segmentation png:seq_panoptic ...")
  p.add_argument("--weights", required=True, metavar="DIR",
                 help="Mask2Former weights directory (config.json + params)")
  p.add_argument("--images", required=True, metavar="PATH",
                 help=IMAGES_HELP)
  p.add_argument("--out", required=True, metavar="OUT", help="output directory")
  p.add_argument("--height", type=int, metavar="H", help="resize images to H x W for the network "
                                                         "(with --width; default: own size)")
  p.add_argument("--width", type=int, metavar="W", help="network input width (with --height)")
  p.add_argument("--detectron2-resize", action="store_true",
                 help="resize each image as upstream's test time (detectron2 ResizeShortestEdge: "
                      "shortest edge 800, longest at most 1333, aspect kept): upstream's maps, "
                      "~4x the pixels of a 192x640 frame (fed at 400x1333)")
  p.add_argument("--quiet", action="store_true", help="no progress bar")
  p.set_defaults(func=_run_segment)


def _run_segment(args) -> int:
  from pitta_jax.outputs import open_output_dir
  from pitta_jax.segment import DETECTRON2_RESIZE, segment_images
  size = _size(args)
  if args.detectron2_resize and size is not None:
    raise ValueError("--detectron2-resize and --height/--width both choose the input size: "
                     "give one")
  with open_output_dir(args.out) as held:
    written = segment_images(args.weights, args.images, args.out,
                             DETECTRON2_RESIZE if args.detectron2_resize else size, args.quiet,
                             held.check)
  print(f"wrote {len(written)} panoptic maps to {args.out}")
  return 0


def _add_convert(sub) -> None:
  from weights_convert import cli as convert_cli
  p = sub.add_parser("convert", help="convert PyTorch checkpoints (same as python -m weights_convert)",
                     description="Convert PyTorch checkpoints to pitta-jax weights; no torch needed.")
  convert_cli.add_subcommands(p)
  p.set_defaults(func=lambda args: convert_cli.run(args))


def _method_config_classes() -> list[tuple[type, str]]:
  """(config class, namespace): AdaptConfig's `adapt` and every registered method with knobs."""
  import dataclasses
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.methods import METHODS
  return [(AdaptConfig, "adapt")] + [(cls, name) for name, (cls, _) in METHODS.items()
                                     if dataclasses.fields(cls)]


def _add_method_configs(p, every: bool = False) -> None:
  """`--adapt.*` and, for every registered method with knobs, `--<method>.*`; a name several of
  them share (`--lr`, `--window`, `--ld-weight`) is a shared alias (`_route_method_aliases`;
  `every`: the demo's, which sets it in every method, and whose rows, not --adapt.method, pick
  the methods). What the demo always refuses (--adapt.method, a shared name that one method has
  twice) is not shown in its --help."""
  from pitta_jax.config_cli import (add_config_arguments, add_shared_aliases, ambiguous_names,
                                    shared_names)
  configs = _method_config_classes()
  shared = shared_names(configs)
  for cls, name in configs:
    title = ("adaptation (the paper's setting where it states one; docs/method.md)"
             if name == "adapt" else f"method {name} (" + (
                 "its rows of --demo.methods)" if every else f"used with --method {name})"))
    add_config_arguments(p, cls, name, title, shared=shared,
                         hidden=("method",) if every and name == "adapt" else ())
  add_shared_aliases(p, shared, "flags several methods have (" + (
      "every method's" if every else "the selected method's") + ")", every, configs[0],
      hidden=ambiguous_names(configs) if every else ())


def _route_method_aliases(args, method: str | None) -> None:
  """Shared aliases onto their namespaced flags: the method's field, else `--adapt.*`'s
  (`method` None: every config that has the name, as the demo runs them all)."""
  from pitta_jax.config_cli import route_aliases
  configs = _method_config_classes()
  spaces = [name for _, name in configs]
  if method is None:
    route_aliases(args, configs, spaces, every=True)
  else:
    route_aliases(args, configs, [s for s in (method, "adapt") if s in spaces])


def _check_method_flags(args, method) -> None:
  """ValueError naming the flag: another method's `--<name>.*` flags, or `--adapt`'s optimiser
  flags for a method that steps its own optimiser (the baselines), would be ignored."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.config_cli import given_fields, given_flags, typed_flag
  for _, name in _method_config_classes():
    given = given_flags(args, name)
    if name not in ("adapt", method.name) and given:
      raise ValueError(f"{given[0]} is a flag of --method {name}, not of --method {method.name}")
  given = given_fields(AdaptConfig, args, "adapt")
  own = sorted(given & {"optimizer", "lr", "momentum"})
  if method.optimizer is not None and own:
    raise ValueError(f"{typed_flag(args, 'adapt.' + own[0])} does not apply to --method "
                     f"{method.name}: it steps its own optimiser (set it with its "
                     f"--{method.name}.* flags)")
  updating = sorted(given & {"optimizer", "lr", "momentum", "steps_per_frame", "selector",
                             "reset_every", "skip_nonfinite"})
  if not method.adapts and updating:
    raise ValueError(f"{typed_flag(args, 'adapt.' + updating[0])} does not apply to --method "
                     f"{method.name}: it never updates the network")


def _method_configs_from_args(args) -> dict:
  """Every registered method's config from its `--<method>.*` flags (validated)."""
  from pitta_jax.config_cli import config_from_args
  from pitta_jax.methods import METHODS
  return {name: config_from_args(cls, args, name) for name, (cls, _) in METHODS.items()}


def _method_from_args(args, cfg):
  from pitta_jax.config_cli import config_from_args
  from pitta_jax.methods import build, method_config_class
  return build(cfg.method, config_from_args(method_config_class(cfg.method), args, cfg.method))


def _add_demo(sub) -> None:
  from pitta_jax.config_cli import add_config_arguments
  from pitta_jax.demo import DemoConfig
  p = sub.add_parser(
      "demo", help="the embedded synthetic benchmark end to end (no downloads, no arguments)",
      description="Load the clear-weather source MonoDepth2 of the synthetic "
                  "driving benchmark (shipped), then run No adaptation / BN batch stats / PITTA "
                  "(and with --demo.methods the baselines CoMoDa, Ada-Depth, ActMAD, CoTTA, each "
                  "+ L_d) on fog, rain, night and snow sequences; print the 7 metrics and "
                  "write results.json, results.csv, table.md and figures/ to --out.")
  add_config_arguments(p, DemoConfig, "demo", "demo")
  _add_method_configs(p, every=True)
  p.add_argument("--retrain", action="store_true", help="retrain the source model (ignore cache)")
  p.add_argument("--quiet", action="store_true",
                 help="no progress bars and no table on the terminal (table.md has it)")
  p.set_defaults(func=_run_demo)


def _run_demo(args) -> int:
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.config_cli import config_from_args
  from pitta_jax.demo import DemoConfig, run_demo
  from pitta_jax.methods.pitta import PittaConfig
  from pitta_jax.source_model import SourceConfig, enable_compilation_cache, load_or_train_source
  demo = config_from_args(DemoConfig, args, "demo")  # validated before any work
  _route_method_aliases(args, None)
  from pitta_jax.config_cli import given_fields
  given = given_fields(AdaptConfig, args, "adapt")
  if "method" in given:
    raise ValueError("--method: the demo runs the rows of --demo.methods (e.g. --demo.methods "
                     "none,bn,pitta,cotta)")
  adapt = config_from_args(AdaptConfig, args, "adapt")
  pitta = config_from_args(PittaConfig, args, "pitta")
  configs = _method_configs_from_args(args)
  from pitta_jax.demo import ROWS
  from pitta_jax.methods import build
  for key in demo.methods:  # a flag given wins over a row's own setting: say so
    kept = [f"--{k.replace('_', '-')} {getattr(adapt, k)}" for k, v in build(ROWS[key][1]).setting
            if k in given and getattr(adapt, k) != v]
    if kept:
      print(f"note: {ROWS[key][0]} runs with {', '.join(kept)} as given, not its own setting",
            file=sys.stderr)
  from pitta_jax.outputs import open_output_dir
  from pitta_jax.report import check_results_owner
  with open_output_dir(demo.out, "--demo.out") as held:  # checked and locked before any work
    check_results_owner(demo.out, "demo")
    enable_compilation_cache()  # the process's choice, made here, not by the library
    if args.retrain:
      load_or_train_source(SourceConfig(), quiet=args.quiet, retrain=True)
    run_demo(demo, adapt, pitta, quiet=args.quiet, method_configs=configs, given=given,
             check_out=held.check)
  return 0


def _add_train_source(sub) -> None:
  from pitta_jax.config_cli import add_config_arguments
  from pitta_jax.models.registry import MODELS
  from pitta_jax.source_model import CACHE_ROOT_TEXT, NETWORK_LR, SourceConfig
  lrs = ", ".join(f"{name} {lr:g}" for name, lr in sorted(NETWORK_LR.items()))
  trainable = [name for name, spec in MODELS.items() if spec.output == "sigmoid_disparity"]
  p = sub.add_parser(
      "train-source", help="train a clear-domain source network of the synthetic benchmark",
      description="Train a depth network from scratch on clear synthetic frames with a "
                  "supervised depth loss (default MonoDepth2 ResNet-18, the shipped model; "
                  f"--source.model: {' | '.join(trainable)}; "
                  f"--source.lr defaults to {SourceConfig.lr:g} except for {lrs}). Cached "
                  f"under {CACHE_ROOT_TEXT}, by config hash. Prints a JSON report whose "
                  "\"weights_dir\" is the weights directory (usable with --weights).")
  add_config_arguments(p, SourceConfig, "source", "training")
  p.add_argument("--retrain", action="store_true", help="ignore a cached (or shipped) model")
  p.add_argument("--ship", action="store_true",
                 help="maintainers: also write the model (float16) and its clear-domain metrics "
                      "into the package (pitta_jax/assets/), where this config finds it")
  p.add_argument("--quiet", action="store_true", help="no progress bar")
  p.set_defaults(func=_run_train_source)


def _run_train_source(args) -> int:
  import json
  from pitta_jax.config_cli import apply_unless_given, config_from_args
  from pitta_jax.source_model import (ASSETS, SourceConfig, load_or_train_source,
                                      network_defaults, ship_source)
  cfg = config_from_args(SourceConfig, args, "source")
  cfg, own = apply_unless_given(cfg, network_defaults(cfg.model), args, "source")
  if own:
    print(f"note: {cfg.model} trains at --source.lr {cfg.lr} (the default 1e-3 does not train "
          f"it; give the flag to change it)", file=sys.stderr)
  if args.ship and not os.access(ASSETS if ASSETS.is_dir() else ASSETS.parent, os.W_OK):
    raise ValueError(f"--ship: {ASSETS} is not writable (ship from a source checkout)")
  weights, report = load_or_train_source(cfg, quiet=args.quiet, retrain=args.retrain)
  print(json.dumps(report, indent=2))
  if args.ship:
    print(f"shipped: {ship_source(cfg, quiet=args.quiet)}")
  return 0


DATASETS = ("drivingstereo", "kitti", "waymo", "folder", "synthetic")


def _model_names() -> list[str]:
  from pitta_jax.models.registry import MODELS
  return sorted(MODELS)


def _models_without_source_model() -> str:
  """The networks the synthetic benchmark trains no source model for (`sources.open_weights`:
  only the MonoDepth2 family's sigmoid disparity), for --model's help."""
  from pitta_jax.models.registry import MODELS
  return " and ".join(n for n in sorted(MODELS) if MODELS[n].output != "sigmoid_disparity")


def _add_adapt(sub, name: str) -> None:
  from pitta_jax.config_cli import add_config_arguments
  from pitta_jax.run import EvalConfig
  from pitta_jax.source_model import CACHE_ROOT_TEXT
  adapting = name == "adapt"
  p = sub.add_parser(
      name, help=("adapt a depth network online with PITTA (or another method) and evaluate"
                  if adapting else "evaluate a depth network without adaptation"),
      description=("Online test-time adaptation over a frame sequence (predict-then-adapt), "
                   "evaluated with the 7 Eigen metrics (MonoDepth2 protocol)." if adapting else
                   "Evaluate the network as it is (running BN statistics, no update).")
                  + f" Compiled steps are kept under xla/ in the cache root ({CACHE_ROOT_TEXT}),"
                    " so a rerun or a --resume skips the compiles.")
  p.add_argument("--dataset", choices=DATASETS, required=True,
                 help="synthetic (the embedded benchmark, no --root) or a real dataset at "
                      "--root (layouts: docs/datasets.md)")
  p.add_argument("--root", help="dataset root (not needed for synthetic)")
  p.add_argument("--weights", help="weights directory; default for synthetic: the cached "
                 "source model of --model (trained on first use)")
  p.add_argument("--model", choices=_model_names(),
                 help="the network (default: the one the weights' model.json names; on synthetic "
                      f"without --weights: monodepth2). {_models_without_source_model()} "
                      f"need --weights")
  p.add_argument("--segmentation", default="gt",
                 help="gt (the dataset's own panoptic maps; the default), png:DIR "
                      "(COCO-panoptic PNG + JSON per frame stem), or mask2former:DIR (converted "
                      "Mask2Former weights)")
  p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                 help="reader option, repeatable (e.g. weather=foggy size=half for "
                      "drivingstereo; domain=fog num_frames=100 seed=3 for synthetic, whose "
                      "default domain is clear, the source domain: no shift; docs/datasets.md)")
  p.add_argument("--out", default="pitta_out/" + name,
                 help=f"output directory (default: pitta_out/{name}): results.json (every "
                      f"frame's metrics and logs, the configs), results.csv and table.md, and "
                      f"checkpoints/ with --checkpoint-every; a run into a directory with an "
                      f"earlier run's results removes them when it starts (a refused --resume "
                      f"keeps them)")
  p.add_argument("--checkpoint-every", type=int, default=0, metavar="K",
                 help="save the run's state (parameters, optimiser and method state) and the "
                      "results so far after every K frames (and on Ctrl-C) under "
                      "OUT/checkpoints (default 0: none)")
  p.add_argument("--source-images", metavar="PATH",
                 help=f"source-domain images ({IMAGES_HELP}) for methods that "
                      "need source data (ActMAD's statistics); default on synthetic: clear-"
                      "weather training streets")
  p.add_argument("--replay-root", metavar="DIR",
                 help="source-domain replay frames for CoMoDa: a KITTI raw root as downloaded "
                      "(<date>/<date>_drive_<nnnn>_sync/image_02/data/, <date>/"
                      "calib_cam_to_cam.txt)")
  p.add_argument("--source-stats", metavar="FILE",
                 help="ActMAD's source statistics written by `pitta-jax source-stats` (instead "
                      "of computing them from --source-images)")
  p.add_argument("--resume", action="store_true",
                 help="continue from the newest checkpoint under OUT/checkpoints (the frames "
                      "it holds are not run again; results equal an uninterrupted run's)")
  p.add_argument("--quiet", action="store_true",
                 help="no progress bars and no table on the terminal (the results files have it)")
  # the evaluation protocol first: its short aliases (--min-depth, --max-depth) stay its own
  # when a method's config has a field of the same name (CoMoDa's MonoDepth2 loss)
  add_config_arguments(p, EvalConfig, "eval", "evaluation")
  if adapting:
    _add_method_configs(p)
  p.set_defaults(func=_run_adapt, adapting=adapting)


def adapt_config(args):
  """(AdaptConfig, method, notes) of `pitta-jax adapt`'s flags: the method's published setting
  (`Method.setting`, e.g. CoTTA and Ada-Depth adapt every parameter) where no flag says
  otherwise, with a note saying so; what it requires (`Method.requires`) stays the user's to
  give (ValueError naming the flag, before any work)."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.config_cli import apply_unless_given, flag_dest, config_from_args
  _route_method_aliases(args, getattr(args, flag_dest("adapt", "method"), None)
                        or AdaptConfig().method)
  cfg = config_from_args(AdaptConfig, args, "adapt")
  method = _method_from_args(args, cfg)
  _check_method_flags(args, method)
  cfg, own = apply_unless_given(cfg, method.setting, args, "adapt")
  notes = []
  if own:
    notes.append(f"--method {method.name} runs in its own setting: "
                 + ", ".join(f"--{k.replace('_', '-')} {v}" for k, v in own.items())
                 + " (give the flag to change it)")
  method.check(cfg)
  return cfg, method, notes


def dataset_evaluation(eval_cfg, protocol, args):
  """(EvalConfig, note or None): the dataset's own evaluation protocol (`FrameSequence.
  evaluation`, e.g. the Garg crop of KITTI's Eigen split) where no --eval flag says otherwise,
  with a note naming the flags it set."""
  from pitta_jax.config_cli import apply_unless_given
  eval_cfg, own = apply_unless_given(eval_cfg, protocol, args, "eval")
  if not own:
    return eval_cfg, None
  flags = ", ".join(f"--eval.{k.replace('_', '-')} {str(v).lower() if isinstance(v, bool) else v}"
                    for k, v in own.items())
  return eval_cfg, (f"dataset {args.dataset} is evaluated with its published protocol: {flags} "
                    f"(give the flag to change it)")


def _run_adapt(args) -> int:
  import dataclasses
  from pathlib import Path
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.config_cli import config_from_args
  from pitta_jax.methods import build
  from pitta_jax.outputs import open_output_dir, rounded_or_none
  from pitta_jax.report import Row, check_results_owner, clear_earlier_results, write_results
  from pitta_jax.run import EvalConfig, checkpoint_chunk_size, metric_factor, run_sequence
  from pitta_jax.checkpoint import read_model_json
  from pitta_jax.sources import (check_dataset_args, check_model, check_run_needs,
                                 check_stats_method, check_unique_options, lacks_panoptic_maps,
                                 method_resources, open_frames, open_weights)
  notes = []
  if args.adapting:
    cfg, method, notes = adapt_config(args)
  else:
    cfg = AdaptConfig(method="none", bn_stats="running")
    method = build("none")
  eval_cfg = config_from_args(EvalConfig, args, "eval")
  if args.checkpoint_every < 0:
    raise ValueError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
  if args.resume and not args.checkpoint_every:
    raise ValueError("--resume needs --checkpoint-every K (the same K as the interrupted run)")
  chunk = checkpoint_chunk_size(cfg.chunk_size, args.checkpoint_every)
  if chunk != cfg.chunk_size:
    notes.append(f"--checkpoint-every {args.checkpoint_every} runs chunks of {chunk} frames, "
                 f"not --chunk-size {cfg.chunk_size} (a multiple of the chunk size keeps it; "
                 f"small chunks run slower)")
  weights_config = None
  if args.weights:  # cheap checks first: the weights' description, the dataset, the method's needs
    weights_spec, weights_config = read_model_json(args.weights)
    check_model(args.model, weights_spec.name, args.weights)
    if (args.adapting and method.metres and method.config.depth_scale is None
        and metric_factor(weights_spec, weights_config) is None):
      notes.append(f"--method {method.name}'s thresholds are in metres and these weights predict "
                   f"depth up to scale (no stereo pairs in training): their units are taken as "
                   f"metres; --{method.name}.depth-scale F sets the factor")
  check_unique_options(args.option)
  check_dataset_args(args.dataset, args.root, args.option, args.segmentation)
  source_flags = [f for f, v in (("--source-images", args.source_images),
                                 ("--replay-root", args.replay_root),
                                 ("--source-stats", args.source_stats)) if v]
  if method.prepare is None and source_flags:
    if args.adapting:
      notes.append(f"--method {method.name} uses no source-domain data: {', '.join(source_flags)} "
                   f"ignored")
    args.source_images = args.replay_root = args.source_stats = None
  if args.source_stats and len(source_flags) > 1:  # the statistics file would win, silently
    raise DataError(None, f"{' and '.join(source_flags)}: --source-stats holds the statistics "
                          f"the source data would give; give one of them")
  with open_output_dir(args.out) as held:  # checked and locked first; removed if a check fails
    check_results_owner(args.out, args.command)
    checkpoints = Path(args.out) / "checkpoints"
    if args.checkpoint_every and checkpoints.exists() and not checkpoints.is_dir():
      raise DataError(checkpoints, "is a file; --checkpoint-every writes a directory there")
    if args.source_stats:
      from pitta_jax.source_stats import read_source_stats
      check_stats_method(method, args.source_stats)
      read_source_stats(args.source_stats)  # the file's format; its layers once weights load
    # the data against the method's needs, from file lists and model.json only
    reader = check_run_needs(method, args.dataset, args.root, args.option, args.segmentation,
                             args.replay_root, weights_config, bool(source_flags), notes)
    notes += list(reader.notes if reader is not None else ())
    if reader is not None and all(f.depth is None for f in reader.files):
      remedy = " (--option depth_dir=DIR)" if args.dataset == "folder" else ""
      if not args.adapting:  # nothing to do: evaluation without ground truth
        raise DataError(None, f"dataset {args.dataset} has no ground-truth depth to evaluate "
                              f"against{remedy}")
      notes.append(f"dataset {args.dataset} has no ground-truth depth: the run adapts and logs, "
                   f"nothing is scored{remedy}")
    if (reader is not None and args.adapting
        and lacks_panoptic_maps(method.config, args.segmentation, [reader])):
      from pitta_jax.methods.depth_refining import instance_uses
      remedy = "--option panoptic_dir=DIR, " if args.dataset == "folder" else ""
      notes.append(f"dataset {args.dataset} has no panoptic maps: no frame has instances, so "
                   f"{' and '.join(instance_uses(method.config))} ({remedy}--segmentation "
                   f"png:DIR or mask2former:DIR)")
    if reader is not None:
      eval_cfg, protocol_note = dataset_evaluation(eval_cfg, reader.evaluation, args)
      notes += [protocol_note] if protocol_note else []
    for note in notes:
      print(f"note: {note}", file=sys.stderr)
    from pitta_jax.source_model import enable_compilation_cache
    enable_compilation_cache()  # as the demo: a rerun or a --resume loads the compiled steps
    weights = open_weights(args.weights, args.dataset, quiet=args.quiet, model=args.model)
    frames = open_frames(args.dataset, args.root, args.option, args.segmentation,
                         weights.height, weights.width, reader=reader)
    resources = method_resources(method, weights, args.dataset, args.source_images,
                                 args.replay_root, args.source_stats, quiet=args.quiet)
    out = args.out
    res = run_sequence(weights, frames, cfg, method, eval_cfg, name=f"{args.dataset} {cfg.method}",
                       quiet=args.quiet,
                       checkpoint_dir=f"{out}/checkpoints" if args.checkpoint_every else None,
                       checkpoint_every=args.checkpoint_every, resume=args.resume,
                       resources=resources, on_start=lambda: _frames_start(args, out),
                       data=run_data(args), check_out=held.check)
    # fps over every frame: after --resume, the earlier call's time up to its checkpoint too;
    # steady_fps: this call's chunks after the step compiled; compile_seconds: those that did
    row = Row(args.dataset, cfg.method, res.mean, {"fps": rounded_or_none(res.total_fps, 2),
                                                     "steady_fps": rounded_or_none(res.steady_fps,
                                                                                   2),
                                                     "compile_seconds": round(
                                                         res.compile_seconds, 1),
                                                     "frames": len(res.frame_names),
                                                     "n_skipped": res.n_skipped,
                                                     "n_excluded": len(res.excluded)},
              status=res.status + ("; means over its finite frames" if res.nonfinite else ""))
    meta = {"command": args.command, "dataset": args.dataset, "root": args.root,
            "options": args.option, "segmentation": args.segmentation, "notes": notes,
            "source": {"images": args.source_images, "replay_root": args.replay_root,
                       "stats": args.source_stats},
            "weights": None if args.weights is None else str(args.weights),
            "adapt": dataclasses.asdict(cfg),
            "method": {"name": method.name, **dataclasses.asdict(method.config)},
            "eval": dataclasses.asdict(eval_cfg),
            "per_frame": res.per_frame,
            "excluded_frames": {"count": len(res.excluded), "names": res.excluded,
                                "reason": "no valid ground-truth pixel"},
            "nonfinite_frames": {"count": len(res.nonfinite), "names": res.nonfinite,
                                 "first_index": res.diverged_at,
                                 "reason": "predicted depth not finite (the method diverged)"},
            "resumed_at_frame": res.resumed_at,
            "seconds": {"total": round(res.total_seconds, 2),
                        "this_call": round(res.seconds, 2)},
            "logs": {k: v.tolist() for k, v in res.logs.items()}}
    held.check()  # --out still the directory this command locked
    table = write_results(out, [row], meta, group_title="Dataset")
    if not args.quiet:
      print(table)
    if res.excluded:
      print(f"{len(res.excluded)} frame(s) without valid ground truth excluded from the means: "
            f"{first_and_count(res.excluded, 5)}")
    if res.nonfinite:
      print(f"warning: {res.status}; the means cover the frames whose depth is finite "
            f"(not {first_and_count(res.nonfinite, 5)})", file=sys.stderr)
    if not res.per_frame and not res.nonfinite:
      print(f"warning: {res.status}", file=sys.stderr)
    ran = len(res.frame_names) - res.resumed_at
    steady = (f", {res.steady_fps:.2f} after the {res.compile_seconds:.1f} s of the chunks "
              f"that compiled" if res.steady_fps == res.steady_fps else "")  # not NaN
    speed = f" ({ran} run now at {res.fps:.2f} frames/s{steady})" if ran > 0 else ""
    print(f"{len(res.frame_names)} frames{speed}; results in {out}/")
  return 0


def run_data(args) -> dict:
  """What a run's frames are beyond their names, for its checkpoints' fingerprint: the dataset
  flags (a synthetic frame's name holds its domain and seed, not --option severity or the
  traffic; a folder's names not its depth_dir or --segmentation maps) and the method's source
  data (unused flags are None by now), so that a --resume with other ones is refused."""
  from pathlib import Path
  return {"dataset": args.dataset,
          "root": str(Path(args.root).resolve()) if args.root else None,
          "options": sorted(args.option or []), "segmentation": args.segmentation,
          "source": {name: str(Path(value).resolve()) if value else None
                     for name, value in (("images", args.source_images),
                                         ("replay_root", args.replay_root),
                                         ("stats", args.source_stats))}}


def _add_source_stats(sub) -> None:
  import dataclasses
  from pitta_jax.configs import help_of
  from pitta_jax.methods.actmad import ActmadConfig
  layers = next(f for f in dataclasses.fields(ActmadConfig) if f.name == "layers")
  p = sub.add_parser(
      "source-stats", help="compute ActMAD's source statistics once and write them (.npz)",
      description="Per-location mean and variance of the selected BatchNorm outputs over "
                  "source-domain images (resized to the weights' input size), written "
                  "atomically to an .npz with the network, size and layers it holds; then "
                  "`pitta-jax adapt --method actmad --source-stats FILE` uses it.",
      epilog="example: pitta-jax source-stats --weights weights/mono_640x192 --images "
             "'kitti_raw/2011_09_26/*/image_02/data/*.jpg' --out stats/mono_640x192.npz")
  p.add_argument("--weights", required=True, metavar="DIR", help="weights directory")
  p.add_argument("--images", required=True, metavar="PATH",
                 help=f"source-domain images: {IMAGES_HELP}")
  p.add_argument("--out", required=True, metavar="FILE", help="the .npz file to write")
  p.add_argument("--layers", metavar="REGEX",
                 help=help_of(layers).replace("%", "%%"))
  p.add_argument("--quiet", action="store_true", help="no progress bar")
  p.set_defaults(func=_run_source_stats)


def _run_source_stats(args) -> int:
  from pathlib import Path
  from pitta_jax.checkpoint import load_weights, read_model_json
  from pitta_jax.methods import build
  from pitta_jax.methods.actmad import RESOURCE, ActmadConfig
  from pitta_jax.methods.base import SourceData
  from pitta_jax.source_stats import matched_layers, save_source_stats
  from pitta_jax.sources import read_source_images
  try:
    cfg = ActmadConfig() if args.layers is None else ActmadConfig(layers=args.layers)
  except ValueError as e:
    raise ValueError(f"--{e}") from None
  if Path(args.out).is_dir():
    raise ValueError(f"--out {args.out}: is a directory; name the .npz file to write")
  from pitta_jax.outputs import check_writable_file
  check_writable_file(args.out)  # found now, not after the statistics are computed
  if Path(args.out).exists():  # replace only an earlier statistics file, never another file
    from pitta_jax.source_stats import read_source_stats
    try:
      read_source_stats(args.out)
    except DataError:
      raise ValueError(f"--out {args.out}: exists and is not a statistics file; it is not "
                       "overwritten (name a new .npz file)") from None
  _, config = read_model_json(args.weights)  # cheap checks first
  images = read_source_images(args.images, config["height"], config["width"])
  if len(images) < 2:
    raise DataError(args.images, f"{len(images)} image(s); the variance needs at least 2")
  weights = load_weights(args.weights)
  matched_layers(weights, cfg.layers, "--layers")
  source = SourceData(images, progress=None if args.quiet else "source statistics")
  stats = build("actmad", cfg).prepare(weights.network(), weights.depth, source)[RESOURCE]
  save_source_stats(args.out, stats, weights, cfg.layers, len(images))
  print(f"wrote the statistics of {len(stats)} layers over {len(images)} images to {args.out}")
  return 0


def _add_experiment(sub) -> None:
  p = sub.add_parser(
      "experiment", help="the paper's Tables 1-5 and the sensitivity study (experiments/)",
      description="Run one of the paper's tables: table1..table5 or sensitivity; "
                  "`pitta-jax experiment table1 --help` lists its flags.", add_help=False)
  p.add_argument("args", nargs=argparse.REMAINDER,
                 help="NAME [flags]: table1 table2 table3 table4 table5 sensitivity")
  p.set_defaults(func=lambda args: __import__("experiments").main(
      args.args + (["--debug"] if args.debug and "--debug" not in args.args else [])))


def build_parser() -> argparse.ArgumentParser:
  from pitta_jax.config_cli import ArgumentParser
  parser = ArgumentParser(
      prog="pitta-jax",
      description="PITTA: pose-agnostic, instance-aware test-time adaptation of monocular depth "
                  "networks, in JAX.")
  parser.add_argument("--debug", action="store_true",
                      help="show the full traceback of an error instead of one line")
  sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
  _add_demo(sub)
  _add_adapt(sub, "adapt")
  _add_adapt(sub, "evaluate")
  _add_train_source(sub)
  _add_source_stats(sub)
  _add_predict(sub)
  _add_segment(sub)
  _add_convert(sub)
  _add_experiment(sub)
  return parser


def _chosen_parser(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser:
  """The parser of the command the line chose, down to its last level (`convert monodepth2`'s),
  whose --help lists the flags that the command takes."""
  while True:
    subs = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    if subs is None or getattr(args, subs.dest, None) not in subs.choices:
      return parser
    parser = subs.choices[getattr(args, subs.dest)]


class Terminated(KeyboardInterrupt):
  """SIGTERM (a job scheduler's stop, `kill`), raised where the command runs so that it stops
  as on Ctrl-C: the last completed chunk checkpointed, the output directory unlocked."""
  signum = int(signal.SIGTERM)


class HungUp(Terminated):
  """SIGHUP (the terminal or ssh session closed), stopping the command as SIGTERM does (it
  ended at once, without the last chunk's checkpoint)."""
  signum = int(signal.SIGHUP)


def say_stopped(message: str) -> None:
  """A stopped command's line on stderr; a terminal that closed (SIGHUP) cannot show it, and
  the command still ends with its status."""
  try:
    print(message, file=sys.stderr)
    sys.stderr.flush()
  except OSError:
    pass


def exit_status(e: KeyboardInterrupt) -> int:
  """A stopped command's exit status, as a shell reports a process the signal ended: 128 + the
  signal's number (130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP)."""
  return 128 + (e.signum if isinstance(e, Terminated) else 2)


@contextlib.contextmanager
def terminate_as_interrupt():
  """While the command runs, SIGTERM raises `Terminated` and SIGHUP `HungUp` (the previous
  handlers are restored after; only the CLI's own process does this, never library code).

  A signal's exception raised while Python runs a finaliser or a gc callback (JAX frees device
  buffers from one) is printed and dropped by Python, and the command would run on: while the
  command runs, `sys.unraisablehook` sends such a Ctrl-C or SIGTERM again, so that it lands
  where the command can stop."""
  import threading
  if threading.current_thread() is not threading.main_thread():
    yield
    return

  def stop(signum, frame):
    raise HungUp() if signum == signal.SIGHUP else Terminated()

  resent: list[tuple[threading.Timer, type[KeyboardInterrupt], list]] = []

  def resend(unraisable):
    if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
      signum = (unraisable.exc_type.signum if issubclass(unraisable.exc_type, Terminated)
                else signal.SIGINT)
      fired: list = []

      def fire():
        fired.append(True)
        os.kill(os.getpid(), signum)

      # from another thread, a moment later: a handler run inside this hook would be dropped too
      timer = threading.Timer(0.01, fire)
      timer.daemon = True
      resent.append((timer, unraisable.exc_type, fired))
      timer.start()
    else:
      previous_hook(unraisable)

  previous, previous_hook = signal.signal(signal.SIGTERM, stop), sys.unraisablehook
  previous_hup = signal.signal(signal.SIGHUP, stop)
  sys.unraisablehook = resend
  try:
    yield
  finally:
    for timer, _, _ in resent:  # before the handlers go: a signal sent meanwhile still lands
      timer.cancel()
      timer.join()
    signal.signal(signal.SIGTERM, previous)
    signal.signal(signal.SIGHUP, previous_hup)
    sys.unraisablehook = previous_hook
  # the command ended before a signal sent again arrived: it stops here, not after main returns
  late = [kind for _, kind, fired in resent if not fired]
  if late:
    raise late[0]()


def _quiet_libraries() -> Callable[[], None]:
  """Silences the libraries' own log lines: OpenCV's (e.g. "[ WARN:0@...] PNG input buffer is
  incomplete": the readers raise a one-line error for the same file, which they would precede)
  and orbax's through absl (a full disk during a checkpoint save printed hundreds of lines of
  its threads' tracebacks before the error line; its failures reach the command as
  exceptions), and tensorstore's "Event loop is closed" (`_quiet_unraisable`, while the command
  runs: `terminate_as_interrupt` restores the hook it found). The command's choice, unless
  --debug; the library leaves them alone. Returns what puts OpenCV's and absl's levels back
  (`interruptible` calls it once the command is done: `main` run in-process, e.g. by a script
  that registers its own network first, leaves the process's logging as it found it)."""
  import logging
  import cv2.utils.logging as cv_logging
  cv_level, absl_level = cv_logging.getLogLevel(), logging.getLogger("absl").level
  cv_logging.setLogLevel(cv_logging.LOG_LEVEL_SILENT)
  logging.getLogger("absl").setLevel(logging.CRITICAL)
  sys.unraisablehook = _quiet_unraisable(sys.unraisablehook)

  def restore() -> None:
    cv_logging.setLogLevel(cv_level)
    logging.getLogger("absl").setLevel(absl_level)
  return restore


def _quiet_unraisable(hook: Callable) -> Callable:
  """`hook` (a sys.unraisablehook) without the "RuntimeError: Event loop is closed" tracebacks
  that tensorstore's write callbacks raise once orbax's save has failed and closed its event
  loop: a full disk printed ~170 of them, 4 lines each, around the one error line (the
  save's own error reaches the command). Any other unraisable exception goes to `hook`."""
  def quiet(unraisable) -> None:
    error = unraisable.exc_value
    if not (isinstance(error, RuntimeError) and str(error) == "Event loop is closed"):
      hook(unraisable)
  return quiet


def error_line(error: BaseException) -> str:
  """What a command prints after "error: " for an expected error: "FILE: reason" for an
  OSError that names its file (a full disk, a read-only directory), else the error's text."""
  if isinstance(error, OSError) and error.strerror:
    return f"{error.filename}: {error.strerror}" if error.filename else error.strerror
  return str(error)


def out_of_memory(error: BaseException) -> str | None:
  """The one line for running out of memory: XLA's RESOURCE_EXHAUSTED (a 16384x16384 input
  ended in a traceback), NumPy's or Python's MemoryError and OpenCV's failed allocation (an
  image buffer of a huge size); None for any other error."""
  hint = "(a smaller --height/--width, --chunk-size or image?)"
  if isinstance(error, MemoryError):
    return f"out of memory: {str(error) or type(error).__name__} {hint}"
  if type(error).__name__ == "error" and "Insufficient memory)" in str(error):  # cv2.error
    what = str(error).partition("Insufficient memory)")[2].split(" in function")[0].strip()
    return f"out of memory: {what} {hint}"
  if not (type(error).__name__ in ("JaxRuntimeError", "XlaRuntimeError")
          and "RESOURCE_EXHAUSTED" in str(error)):
    return None
  import jax  # imported by the command that ran out
  return (f"out of {jax.default_backend().upper()} memory: "
          f"{str(error).splitlines()[0].split(': ', 1)[-1]} {hint}")


# errors a user can act on (a bad flag, input or file; a full disk): one line and exit 2
USER_ERRORS: tuple[type[Exception], ...] = (DataError, ValueError, TypeError, OSError)


def report_error(error: Exception, debug: bool, also: tuple[type[Exception], ...] = ()) -> int:
  """A command's handler of its errors (call it from `except Exception`): prints "error: " and
  one line on stderr and returns the exit status 2 for an error the user can act on
  (`USER_ERRORS` and the command's own `also`; XLA running out of memory); re-raises any other
  error, and every error under --debug (`debug`), with its traceback."""
  message = error_line(error) if isinstance(error, USER_ERRORS + also) else out_of_memory(error)
  if debug or message is None:
    raise error
  print(f"error: {message}", file=sys.stderr)
  return 2


def interruptible(body: Callable[[], int], debug: bool | None = None,
                  in_process: bool = False) -> int:
  """A console entry's `body` with Ctrl-C and SIGTERM handled from its first line: while it
  imports and parses too, a signal stops it with one line and exit 130 / 143 (a traceback
  before, and a Ctrl-C that landed in JAX's gc callback during the imports was dropped: the run
  went on and exited 0). The command's own handlers, inside, say more where they can. Unless
  `debug` (default: --debug on the command line) the libraries' log lines are silenced
  (`_quiet_libraries`), and what the process still prints after a signal. `in_process`: the
  caller's process goes on after the command (`main(argv)` from a script), so the libraries'
  log levels are put back once the command has returned, raised or been interrupted."""
  from pitta_jax.source_model import repairing_compilation_cache
  debug = ("--debug" in sys.argv) if debug is None else debug
  restore = None
  try:
    with terminate_as_interrupt(), repairing_compilation_cache():
      if not debug:
        restore = _quiet_libraries()
      return body()
  except KeyboardInterrupt as e:
    if not debug:
      _silence_teardown()
    say_stopped("interrupted")
    return exit_status(e)
  finally:
    if in_process and restore is not None:
      restore()


def main(argv: list[str] | None = None) -> int:
  """The `pitta-jax` command line `argv` (default: `sys.argv[1:]`, the console script). Called
  with an explicit `argv` from a script (e.g. one that registers its own network or method
  first: README 'Adding a network or a method'), the process's logging levels are left as they
  were."""
  in_process = argv is not None
  argv = list(sys.argv[1:] if argv is None else argv)
  return interruptible(lambda: _main(argv), "--debug" in argv, in_process)


def _main(argv: list[str]) -> int:
  if argv[:1] == ["experiment"]:  # its own parsers (flags such as --help belong to the table)
    import experiments
    return experiments.main(argv[1:])
  parser = build_parser()
  args, unknown = parser.parse_known_args(argv)
  top = [a for a in unknown if a in parser._option_string_actions]
  if top:  # pitta-jax's own flag (--debug) after the command
    parser.error(f"{top[0]} goes before the command: pitta-jax {top[0]} {args.command} ...")
  if unknown:  # named with the command's --help, where its flags are (not pitta-jax --help)
    _chosen_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
  try:
    return args.func(args)
  except Exception as e:
    return report_error(e, args.debug)
  except KeyboardInterrupt as e:
    if not args.debug:  # the process ends now: what the save threads still report is noise
      _silence_teardown()
    from pitta_jax.run import checkpointed_frames
    checkpointing = getattr(args, "checkpoint_every", 0)  # adapt and evaluate
    if checkpointing and not getattr(args, "frames_started", False):
      # before `_frames_start` the checkpoints there may be another run's, not yet removed
      say_stopped("interrupted before its first frame")
      return exit_status(e)
    saved = checkpointing and checkpointed_frames(os.path.join(args.out, "checkpoints"))
    say_stopped("interrupted" + (f"; its first {saved} frames are checkpointed: run the same "
                                 "command with --resume to continue" if saved else
                                 "; no checkpoint was saved yet" if checkpointing else ""))
    return exit_status(e)


def _frames_start(args, out: str) -> None:
  """adapt's and evaluate's `run_sequence(on_start=...)`: an earlier run's result files go
  (a refused --resume has kept them), and from now on the checkpoints under --out are this
  run's (an earlier run's are removed or resumed by then), which the stopped line counts."""
  from pitta_jax.report import clear_earlier_results
  clear_earlier_results(out)
  args.frames_started = True


def _silence_teardown() -> None:
  """An interrupted command's process ends (`exit_with`); until then the asyncio loops of
  orbax's save threads, stopped mid-write, may print finalisers' 'Exception ignored' tracebacks
  after the 'interrupted' line. The command owns its process, so it drops them (not with
  --debug; their absl log lines are already silenced by `_quiet_libraries`)."""
  sys.unraisablehook = lambda unraisable: None


def exit_with(code: int) -> NoReturn:
  """Ends the process with a command's exit code. A failed or interrupted command ends it at
  once (`os._exit`, after flushing): JAX may still be compiling on a thread of its own (a Ctrl-C
  is handled only once the compile returns to Python, and another may be under way), and
  tensorstore's reads of a damaged checkpoint may still be pending; the interpreter's teardown
  frees what they use, which crashed the process (SIGSEGV instead of exit 130) or printed
  asyncio tracebacks after the error line. Every file the command writes is closed by then.
  A command that succeeded ends through the interpreter's teardown with Ctrl-C ignored: its
  work is done, and a Ctrl-C landing in JAX's exit handler printed a traceback."""
  sys.stdout.flush()
  sys.stderr.flush()
  if code:
    os._exit(code)
  if threading.current_thread() is threading.main_thread():
    signal.signal(signal.SIGINT, signal.SIG_IGN)
  sys.exit(code)


def console() -> NoReturn:
  """The `pitta-jax` console script."""
  exit_with(main())


if __name__ == "__main__":
  console()
