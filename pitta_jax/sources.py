"""Resolving the CLI's `--dataset/--root/--option/--segmentation/--weights` into frames and weights,
the methods' source-domain resources (`--source-images`, `--replay-root`, `--source-stats`), and
checking before any work that the data has what a method needs (`check_run_needs`).

`--option KEY=VALUE` values are typed from the target's annotations (the reader function's
parameters, or `SyntheticConfig`'s fields): `sequences=0001` stays the string "0001" for a str
option, `num_frames=3.5` is refused for an int one, and an unknown key lists the valid ones.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import os
import types
import typing
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from pitta_jax.checkpoint import Weights, load_weights
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame
from pitta_jax.data.sequence import FrameSequence

SEGMENTATIONS = ("gt", "png", "mask2former")


def split_options(items: Sequence[str], unique: bool = False) -> dict[str, str]:
  """["weather=foggy", "num_frames=100"] -> {"weather": "foggy", "num_frames": "100"} (text).
  A later KEY overrides an earlier one (a test case's options, appended to the user's), unless
  `unique`: then a DataError says it was given twice."""
  options: dict[str, str] = {}
  for item in items:
    key, sep, value = item.partition("=")
    key, value = key.strip(), value.strip()
    if not sep or not key:  # " =3": no key once its blanks go
      raise DataError(None, f"--option {item!r} is not KEY=VALUE")
    if unique and key in options:
      raise DataError(None, f"--option {key} given twice ({options[key]}, {value}): give it once")
    options[key] = value
  return options


def check_unique_options(items: Sequence[str]) -> None:
  """DataError when a user's `--option` KEY is given more than once (the last would win
  silently), or an item is not KEY=VALUE."""
  split_options(items, unique=True)


def _coerce(key: str, text: str, annotation: Any) -> Any:
  """`text` as the type `annotation` names (Optional and unions tried in order)."""
  from pitta_jax.config_cli import parse_bool, parser_for
  if isinstance(annotation, str) or annotation is inspect.Parameter.empty or annotation is Any:
    annotation = str
  origin = typing.get_origin(annotation)
  if origin in (typing.Union, types.UnionType):
    args = typing.get_args(annotation)
    if type(None) in args and text.lower() == "none":
      return None
    errors = []
    for arg in (a for a in args if a is not type(None)):
      try:
        return _coerce(key, text, arg)
      except DataError as e:
        errors.append(str(e))
    raise DataError(None, errors[0] if errors else f"--option {key}={text!r}: invalid")
  kind, _ = parser_for(annotation) if annotation is not bool else (parse_bool, "")
  if annotation not in (int, float, bool, str) and origin is not tuple:
    kind = str  # paths and other objects are given as text
  try:
    return kind(text)
  except (ValueError, TypeError, Exception) as e:  # argparse.ArgumentTypeError included
    want = getattr(annotation, "__name__", str(annotation))
    raise DataError(None, f"--option {key}={text!r}: expected {want} ({e})") from None


def typed_options(raw: Mapping[str, str], annotations: Mapping[str, Any], target: str
                  ) -> dict[str, Any]:
  """Coerces `raw` option texts with `annotations` (name -> type); DataError on unknown keys."""
  unknown = sorted(set(raw) - set(annotations))
  if unknown:
    raise DataError(None, f"{target} has no option {', '.join(unknown)} (options: "
                          f"{', '.join(sorted(annotations))})")
  return {k: _coerce(k, v, annotations[k]) for k, v in raw.items()}


def function_annotations(fn: Callable, skip: Sequence[str] = ("root",)) -> dict[str, Any]:
  """Keyword parameter name -> resolved annotation of a reader function."""
  hints = typing.get_type_hints(fn)
  return {p: hints.get(p, str) for p in inspect.signature(fn).parameters if p not in skip}


def dataclass_annotations(cls: type) -> dict[str, Any]:
  hints = typing.get_type_hints(cls)
  return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def check_model(model: str | None, architecture: str, weights_dir: str) -> None:
  """DataError unless the --model the user asked for (None: any) is the network the weights
  directory holds (its model.json's `architecture`)."""
  if model and architecture != model:
    raise DataError(None, f"--model {model}, but {weights_dir} holds a {architecture}")


def open_weights(weights_dir: str | None, dataset: str, quiet: bool = False,
                 model: str | None = None) -> Weights:
  """The given weights directory; for the synthetic benchmark without one, the cached source
  model of `model` (default MonoDepth2), trained on first use.

  model: the network the user asked for; a weights directory of another architecture is an
  error.
  """
  if weights_dir:
    weights = load_weights(weights_dir)
    check_model(model, weights.spec.name, weights_dir)
    return weights
  if dataset != "synthetic":
    raise DataError(None, "--weights is required for real datasets (convert a checkpoint with "
                          "`pitta-jax convert NETWORK ...`)")
  from pitta_jax.models.registry import get_spec
  from pitta_jax.source_model import load_or_train_source, network_source_config
  if model and get_spec(model).output != "sigmoid_disparity":  # no synthetic source model
    raise DataError(None, f"--model {model} needs --weights: the synthetic benchmark trains "
                          f"source models of the MonoDepth2 family only (convert a checkpoint "
                          f"with `pitta-jax convert ...`)")
  return load_or_train_source(network_source_config(model or "monodepth2"), quiet=quiet)[0]


SOURCE_BATCH = 4  # images per forward pass when a method computes source statistics
SYNTHETIC_SOURCE_SEEDS = (0, 1)  # clear training streets used as source data on synthetic
SYNTHETIC_SOURCE_FRAMES = 8      # frames per street


class SourceImages(Sequence[np.ndarray]):
  """Source-domain images (H, W, 3) at the network size, read on access, so that a large source
  set (thousands of files, a KITTI raw root) never sits in memory; slicing gives a list."""

  def __init__(self, loaders: Sequence[Callable[[], np.ndarray]]):
    self.loaders = tuple(loaders)

  @classmethod
  def from_files(cls, paths: Sequence[Path], height: int, width: int) -> SourceImages:
    return cls([functools.partial(_read_resized, p, height, width) for p in paths])

  @classmethod
  def from_sequences(cls, sequences: Sequence[Sequence[Frame]]) -> SourceImages:
    return cls([functools.partial(_frame_image, seq, i)
                for seq in sequences for i in range(len(seq))])

  def __len__(self) -> int:
    return len(self.loaders)

  def __getitem__(self, index):
    if isinstance(index, slice):
      return [load() for load in self.loaders[index]]
    return self.loaders[index]()


def _read_resized(path: Path, height: int, width: int) -> np.ndarray:
  from pitta_jax.data.image_io import read_image
  from pitta_jax.data.resize import resize_image
  return resize_image(read_image(path), height, width)


def _frame_image(frames: Sequence[Frame], index: int) -> np.ndarray:
  return frames[index].image


def read_source_images(spec: str, height: int, width: int) -> SourceImages:
  """The images of `spec` (a file, a directory or a glob), lazily resized to (height, width)."""
  from pitta_jax.predict import expand_images
  return SourceImages.from_files(expand_images(spec, unique_stems=False), height, width)


def replay_sequences(replay_root: str, height: int, width: int) -> list:
  """The KITTI raw drives of `replay_root` as lazy sequences resized to (height, width)."""
  from pitta_jax.data.kitti import open_raw_sequences
  from pitta_jax.data.resize import resize_frame
  resize = functools.partial(resize_frame, height=height, width=width)
  return [seq.map(resize) for seq in open_raw_sequences(replay_root)]


def method_resources(method, weights: Weights, dataset: str, source_images: str | None = None,
                     replay_root: str | None = None, source_stats: str | None = None,
                     quiet: bool = False) -> dict[str, Any]:
  """The method's host-side inputs: the weights' pose network when the method needs one, and
  `Method.prepare` on source-domain data: the files of `source_images` (a file, a directory
  or a glob), consecutive frames of `replay_root` (a KITTI raw-data root), or on the synthetic
  benchmark the clear-weather training streets (seeds 0, 1). {} for methods that need none.

  source_stats: an ActMAD statistics file (`pitta-jax source-stats`), used instead of
  computing them; on the synthetic benchmark without any source flag, ActMAD's statistics are
  cached (`source_stats.cached_stats`), so a second run does not recompute them.
  quiet: no progress bar while `prepare` reads the source images.
  """
  from pitta_jax.methods.base import POSE, PoseNet, SourceData
  resources: dict[str, Any] = {}
  if weights.spec.keep_aspect and (method.prepare is not None or source_stats):
    # its source data (e.g. ActMAD's per-location statistics) would be at the trained size,
    # while runs feed each dataset's aspect ratio (run.input_size)
    raise DataError(None, f"--method {method.name} prepares source-domain data at one input "
                          f"size, but {weights.spec.name} takes each dataset's aspect ratio: "
                          f"not supported")
  if "pose" in method.needs:
    if weights.pose is None or weights.spec.build_pose is None:
      raise no_pose_error(method)
    resources[POSE] = PoseNet(weights.spec.build_pose(weights.config), weights.pose)
  if source_stats:
    from pitta_jax.methods import actmad
    from pitta_jax.source_stats import load_source_stats
    check_stats_method(method, source_stats)
    resources[actmad.RESOURCE] = load_source_stats(source_stats, weights, method.config.layers)
    return resources
  if method.prepare is None:
    return resources
  if method.name == "actmad":  # its layers before any source data is read, as source-stats
    from pitta_jax.source_stats import matched_layers
    matched_layers(weights, method.config.layers, "--actmad.layers")
  h, w = weights.height, weights.width
  images = read_source_images(source_images, h, w) if source_images else None
  sequences = replay_sequences(replay_root, h, w) if replay_root else None
  synthetic_default = images is None and sequences is None
  if synthetic_default and dataset != "synthetic":
    raise no_source_error(method)

  def prepare() -> tuple[dict[str, Any], int]:
    """The method's resources and how many source images they come from."""
    seqs = synthetic_streets(h, w) if synthetic_default else (sequences or [])
    imgs = images if images is not None else SourceImages.from_sequences(seqs)
    source = SourceData(imgs, tuple(seqs), None if quiet else f"{method.name}: source data")
    return method.prepare(weights.network(), weights.depth, source), len(imgs)

  if synthetic_default and method.name == "actmad":
    from pitta_jax.methods import actmad
    from pitta_jax.source_stats import cached_stats

    def compute():
      prepared, count = prepare()
      return prepared[actmad.RESOURCE], count

    data = {"synthetic": {"seeds": SYNTHETIC_SOURCE_SEEDS, "frames": SYNTHETIC_SOURCE_FRAMES}}
    resources[actmad.RESOURCE] = cached_stats(data, weights, method.config.layers, compute)
    return resources
  resources.update(prepare()[0])
  return resources


def no_source_error(method, who: str | None = None, stats_flag: bool = True) -> DataError:
  """A method with `prepare` on a real dataset and no source flag; `who` names it in the
  message (default `--method NAME`), `stats_flag` offers --source-stats (ActMAD's; the
  experiment commands have no such flag)."""
  stats = ", --source-stats FILE" if method.name == "actmad" and stats_flag else ""
  return DataError(None, f"{who or f'--method {method.name}'} needs source-domain data: "
                         f"--source-images PATH{stats} or --replay-root DIR")


def check_stats_method(method, source_stats: str) -> None:
  """A statistics file (`pitta-jax source-stats`) serves ActMAD only."""
  if method.name != "actmad":
    raise DataError(source_stats, f"holds ActMAD's source statistics; --method {method.name} "
                                  f"does not use them (drop --source-stats)")


def synthetic_streets(height: int, width: int) -> list[list[Frame]]:
  """The synthetic benchmark's source data: clear streets of SYNTHETIC_SOURCE_SEEDS."""
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  return [list(generate_sequence(SyntheticConfig(
      height=height, width=width, num_frames=SYNTHETIC_SOURCE_FRAMES, seed=seed, domain="clear")))
      for seed in SYNTHETIC_SOURCE_SEEDS]


def parse_segmentation(segmentation: str) -> tuple[str, str]:
  """`gt`, `png:DIR`, `mask2former:DIR` -> (kind, argument); DataError otherwise."""
  kind, _, arg = segmentation.partition(":")
  if kind not in SEGMENTATIONS:
    raise DataError(None, f"--segmentation {segmentation!r}: use gt, png:DIR or mask2former:DIR")
  if kind != "gt" and not arg:
    raise DataError(None, f"--segmentation {kind}:DIR needs a directory")
  if kind == "gt" and segmentation != "gt":  # (`gt:DIR` would read no DIR: a mistyped png:)
    raise DataError(None, f"--segmentation {segmentation!r}: gt takes no directory (the "
                          f"dataset's own panoptic maps); png:DIR reads maps from DIR")
  return kind, arg


def check_dataset_args(dataset: str, root: str | None, option_items: Sequence[str],
                       segmentation: str) -> dict[str, Any]:
  """Validates the dataset flags before any work (no file is read): the typed options."""
  raw = split_options(option_items)
  kind, _ = parse_segmentation(segmentation)
  if dataset == "synthetic":
    if root:
      raise DataError(None, f"--root {root}: for real datasets (the synthetic benchmark is "
                            "generated); drop it or name the dataset with --dataset")
    if kind != "gt":
      raise DataError(None, "the synthetic benchmark carries exact panoptic maps: use "
                            "--segmentation gt")
    sized = [k for k in ("height", "width") if k in raw]
    if sized:
      raise DataError(None, f"--option {sized[0]}: the synthetic frames are rendered at the "
                            "weights' input size (their model.json height and width)")
    from pitta_jax.data.synthetic import SyntheticConfig
    fields = {k: v for k, v in dataclass_annotations(SyntheticConfig).items()
              if k not in ("height", "width")}
    return typed_options(raw, fields, "synthetic")
  if not root:
    raise DataError(None, f"--root is required for dataset {dataset}")
  from pitta_jax.data.readers import READERS
  if dataset not in READERS:
    raise DataError(None, f"unknown dataset {dataset!r}; choose from {', '.join(READERS)}")
  annotations = function_annotations(READERS[dataset])
  options = typed_options(raw, annotations, dataset)
  empty = next((k for k, v in options.items() if v == "" and _names_a_path(annotations[k])), None)
  if empty is not None:  # (Path("") is the working directory)
    raise DataError(None, f"--option {empty}= names no file or directory")
  # the maps come from one place: --segmentation png:DIR is the panoptic directory (beside
  # --option panoptic_json, its annotation file), mask2former:DIR computes them
  taken = ("panoptic_dir",) if kind == "png" else ("panoptic_dir", "panoptic_json") \
      if kind == "mask2former" else ()
  both = next((k for k in taken if k in options), None)
  if both is not None:
    raise DataError(None, f"--option {both} and --segmentation {segmentation} both say where the "
                          f"panoptic maps come from: give one")
  return options


def _names_a_path(annotation: Any) -> bool:
  """Whether a reader parameter's annotation takes a path (`PathLike`, optional or not)."""
  return any(a is os.PathLike or typing.get_origin(a) is os.PathLike
             for a in typing.get_args(annotation))


def lacks_panoptic_maps(config, segmentation: str, readers: Sequence[FrameSequence]) -> bool:
  """Whether a method config's loss holds L_d (`depth_refining.uses_instances`) while, under
  `--segmentation gt`, no frame of `readers` (at least one) has a panoptic map: its L_d is 0
  on them. What `pitta-jax adapt` and the tables say in a note."""
  from pitta_jax.methods.depth_refining import uses_instances
  return (segmentation == "gt" and len(readers) > 0 and uses_instances(config)
          and all(f.panoptic is None for reader in readers for f in reader.files))


def open_reader(dataset: str, root: str | None, option_items: Sequence[str], segmentation: str
                ) -> FrameSequence:
  """The reader's frames of a real dataset (files listed, none read), with `png:DIR` panoptic
  maps; Mask2Former segmentation is added by `open_frames`."""
  options = check_dataset_args(dataset, root, option_items, segmentation)
  kind, arg = parse_segmentation(segmentation)
  from pitta_jax.data.readers import open_dataset
  if kind == "png":
    options["panoptic_dir"] = arg
  return open_dataset(dataset, root, **options)


def open_frames(dataset: str, root: str | None, option_items: Sequence[str], segmentation: str,
                height: int, width: int, reader: FrameSequence | None = None) -> Sequence[Frame]:
  """The frame sequence of a dataset with its panoptic maps chosen by `segmentation`.

  reader: the `open_reader` result when the caller already has it (real datasets).
  """
  options = check_dataset_args(dataset, root, option_items, segmentation)
  kind, arg = parse_segmentation(segmentation)
  if dataset == "synthetic":  # rendered as the run reads it, as a dataset's files are
    from pitta_jax.data.synthetic import SyntheticSequence
    return SyntheticSequence(synthetic_config(options, height, width))
  frames = reader if reader is not None else open_reader(dataset, root, option_items, segmentation)
  if kind == "mask2former":
    from pitta_jax.segment import segmented_frames
    frames = segmented_frames(frames, arg)
  return frames


def synthetic_config(options: Mapping[str, Any], height: int, width: int):
  """The benchmark's SyntheticConfig from typed `--option`s (seed 100: the target streets)."""
  from pitta_jax.data.synthetic import SyntheticConfig
  try:
    return SyntheticConfig(**{"height": height, "width": width, "seed": 100, **options})
  except (TypeError, ValueError) as e:
    raise DataError(None, f"synthetic options: {e}") from None


# ------------------------------------------------------------------ what a method needs, checked


def _needs_error(method, need: str, problem: str, remedy: str | None) -> DataError:
  what = {"intrinsics": "camera intrinsics K for every frame",
          "previous_frame": "consecutive frames (each frame's previous one)"}[need]
  return DataError(None, f"--method {method.name} needs {what}, and {problem}"
                         + (f": provide {remedy}" if remedy else ""))


def check_needs(method, frames: Sequence[Frame], what: str = "the sequence") -> None:
  """Refuses, before any work, frames that lack what `method.needs` asks for (one-line
  DataError naming the missing thing and the flag or file that provides it).

  A `FrameSequence` is checked from its metadata (nothing is read): every frame's K, the
  temporal order, at least 2 frames. Another sequence (in-memory frames in the caller's order)
  is checked for its length only; its frames' K is checked as they stream (`run_sequence`).
  what: how to name the frames in the message (e.g. "dataset folder").
  """
  needs = set(method.needs)
  remedies = frames.remedies if isinstance(frames, FrameSequence) else {}
  if "previous_frame" in needs:
    if len(frames) < 2:
      raise _needs_error(method, "previous_frame", f"{what} has {len(frames)} frame(s)",
                         "at least 2 frames")
    if isinstance(frames, FrameSequence) and not frames.temporal:
      raise _needs_error(method, "previous_frame", f"the order of {what} is not known to be "
                                                   f"capture order", remedies.get("previous_frame"))
  if "intrinsics" in needs and isinstance(frames, FrameSequence):
    lacking = next((f for f in frames.files if f.intrinsics is None), None)
    if lacking is not None:
      raise _needs_error(method, "intrinsics", f"frame {lacking.name} of {what} has none",
                         remedies.get("intrinsics"))


def check_frame_needs(method, frame: Frame) -> None:
  """`check_needs` for one loaded frame (its K), for sequences without metadata."""
  if "intrinsics" in method.needs and frame.intrinsics is None:
    raise _needs_error(method, "intrinsics", f"frame {frame.name or '?'} has none", None)


def no_pose_error(method, who: str | None = None, weights: str | None = None) -> DataError:
  """A method that needs a pose network on weights without one; `who` names the method in the
  message (default `--method NAME`), `weights` the weights directory."""
  return DataError(weights, f"{who or f'--method {method.name}'} needs a pose network, and the "
                            f"weights have none (convert with --pose-encoder/--pose, or "
                            f"train-source)")


def check_replay_root(methods: Sequence, replay_root: str, notes: list[str] | None = None
                      ) -> None:
  """Each drive of the KITTI raw root `replay_root` as the `methods` with `prepare` need their
  source frames (`check_needs`); the drives' notes (e.g. a drive split at missing frames) are
  appended to `notes`, once each, when given."""
  from pitta_jax.data.kitti import open_raw_sequences
  replaying = [m for m in methods if m.prepare is not None]
  if not replaying:
    return
  for seq in open_raw_sequences(replay_root):
    for method in replaying:
      check_needs(method, seq, f"--replay-root {replay_root}")
    if notes is not None:
      notes += [f"--replay-root: {n}" for n in seq.notes
                if f"--replay-root: {n}" not in notes]  # once per drive, not per run


def check_run_needs(method, dataset: str, root: str | None, option_items: Sequence[str],
                    segmentation: str, replay_root: str | None = None,
                    weights_config: Mapping[str, Any] | None = None,
                    source_given: bool = False, notes: list[str] | None = None
                    ) -> FrameSequence | None:
  """The CLI's before-work check of a method's data needs: opens the reader (files listed,
  nothing read) or, on the synthetic benchmark, reads the options (every synthetic frame has K
  and the order is temporal), and the replay root; with `weights_config` (a model.json) also
  the pose network; a method with `prepare` on a real dataset needs a source flag
  (`source_given`). Returns the reader for `open_frames`; the replay root's notes (e.g. a drive
  split at missing frames) are appended to `notes` when given."""
  if "pose" in method.needs and weights_config is not None and not weights_config.get("has_pose"):
    raise no_pose_error(method)
  if method.prepare is not None and dataset != "synthetic" and not source_given:
    raise no_source_error(method)
  reader = None
  if dataset == "synthetic":
    options = check_dataset_args(dataset, root, option_items, segmentation)
    if isinstance(options.get("num_frames"), int) and options["num_frames"] < 1:
      raise DataError(None, f"--option num_frames={options['num_frames']}: the synthetic "
                            f"sequence has no frames")
    n = synthetic_config(options, 8, 8).num_frames
    if "previous_frame" in method.needs and n < 2:
      raise _needs_error(method, "previous_frame", f"the synthetic sequence has {n} frame(s)",
                         "--option num_frames=N with N >= 2")
  else:
    reader = open_reader(dataset, root, option_items, segmentation)
    if len(reader) == 0:  # e.g. an option selecting nothing; found before the weights load
      raise DataError(root, f"dataset {dataset} with {' '.join(option_items) or 'no options'}: "
                            "no frames to adapt on")
    check_needs(method, reader, f"dataset {dataset}")
  if replay_root:
    check_replay_root([method], replay_root, notes)
  return reader
