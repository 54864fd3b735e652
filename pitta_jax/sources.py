"""Resolving the CLI's `--dataset/--root/--option/--segmentation/--weights` into frames and weights.

`--option KEY=VALUE` values are typed from the target's annotations (the reader function's
parameters, or `SyntheticConfig`'s fields): `sequences=0001` stays the string "0001" for a str
option, `num_frames=3.5` is refused for an int one, and an unknown key lists the valid ones.
"""

from __future__ import annotations

import dataclasses
import inspect
import types
import typing
from typing import Any, Callable, Mapping, Sequence

from pitta_jax.checkpoint import Weights, load_weights
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame

SEGMENTATIONS = ("gt", "png", "mask2former")


def split_options(items: Sequence[str]) -> dict[str, str]:
  """["weather=foggy", "num_frames=100"] -> {"weather": "foggy", "num_frames": "100"} (text)."""
  options: dict[str, str] = {}
  for item in items:
    key, sep, value = item.partition("=")
    if not sep or not key:
      raise DataError(None, f"--option {item!r} is not KEY=VALUE")
    options[key.strip()] = value.strip()
  return options


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


def open_weights(weights_dir: str | None, dataset: str, quiet: bool = False,
                 model: str | None = None) -> Weights:
  """The given weights directory; for the synthetic benchmark without one, the cached source
  model of `model` (default MonoDepth2), trained on first use.

  model: the network the user asked for; a weights directory of another architecture is an
  error.
  """
  if weights_dir:
    weights = load_weights(weights_dir)
    if model and weights.spec.name != model:
      raise DataError(None, f"--model {model}, but {weights_dir} holds a {weights.spec.name}")
    return weights
  if dataset != "synthetic":
    raise DataError(None, "--weights is required for real datasets (convert a checkpoint with "
                          "`pitta-jax convert NETWORK ...`)")
  from pitta_jax.source_model import SourceConfig, load_or_train_source
  return load_or_train_source(SourceConfig(model=model or "monodepth2"), quiet=quiet)[0]


SOURCE_BATCH = 4  # images per forward pass when a method computes source statistics
SYNTHETIC_SOURCE_SEEDS = (0, 1)  # clear training streets used as source data on synthetic
SYNTHETIC_SOURCE_FRAMES = 8      # frames per street


def method_resources(method, weights: Weights, dataset: str, source_images: str | None = None,
                     replay_root: str | None = None) -> dict[str, Any]:
  """The method's host-side inputs: the weights' pose network when the method needs one, and
  `Method.prepare` on source-domain data: the files of `source_images` (a file, a directory or
  a glob), consecutive frames of `replay_root` (a KITTI raw-data root), or on the synthetic
  benchmark the clear-weather training streets (seeds 0, 1). {} for methods that need none."""
  from pitta_jax.methods.base import POSE, PoseNet, SourceData
  resources: dict[str, Any] = {}
  if "pose" in method.needs:
    if weights.pose is None or weights.spec.build_pose is None:
      raise DataError(None, f"--method {method.name} needs a pose network, and the weights have "
                            f"none (convert with --pose-encoder/--pose, or train-source)")
    resources[POSE] = PoseNet(weights.spec.build_pose(weights.config), weights.pose)
  if method.prepare is None:
    return resources
  from pitta_jax.data.resize import resize_frame, resize_image
  h, w = weights.height, weights.width
  images: list = []
  sequences: list = []
  if source_images:
    from pitta_jax.data.image_io import read_image
    from pitta_jax.predict import expand_images
    images = [resize_image(read_image(p), h, w) for p in expand_images(source_images)]
  if replay_root:
    from pitta_jax.data.kitti import open_raw_sequences
    sequences = [[resize_frame(f, h, w) for f in seq] for seq in open_raw_sequences(replay_root)]
  if not images and not sequences:
    if dataset != "synthetic":
      raise DataError(None, f"--method {method.name} needs source-domain data: "
                            f"--source-images PATH or --replay-root DIR")
    from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
    sequences = [list(generate_sequence(SyntheticConfig(
        height=h, width=w, num_frames=SYNTHETIC_SOURCE_FRAMES, seed=seed, domain="clear")))
        for seed in SYNTHETIC_SOURCE_SEEDS]
  if not images:
    images = [f.image for seq in sequences for f in seq]
  source = SourceData(tuple(images), tuple(tuple(seq) for seq in sequences))
  resources.update(method.prepare(weights.network(), weights.depth, source))
  return resources


def parse_segmentation(segmentation: str) -> tuple[str, str]:
  """`gt`, `png:DIR`, `mask2former:DIR` -> (kind, argument); DataError otherwise."""
  kind, _, arg = segmentation.partition(":")
  if kind not in SEGMENTATIONS:
    raise DataError(None, f"--segmentation {segmentation!r}: use gt, png:DIR or mask2former:DIR")
  if kind != "gt" and not arg:
    raise DataError(None, f"--segmentation {kind}:DIR needs a directory")
  return kind, arg


def check_dataset_args(dataset: str, root: str | None, option_items: Sequence[str],
                       segmentation: str) -> dict[str, Any]:
  """Validates the dataset flags before any work (no file is read): the typed options."""
  raw = split_options(option_items)
  kind, _ = parse_segmentation(segmentation)
  if dataset == "synthetic":
    if kind != "gt":
      raise DataError(None, "the synthetic benchmark carries exact panoptic maps: use "
                            "--segmentation gt")
    from pitta_jax.data.synthetic import SyntheticConfig
    return typed_options(raw, dataclass_annotations(SyntheticConfig), "synthetic")
  if not root:
    raise DataError(None, f"--root is required for dataset {dataset}")
  from pitta_jax.data.readers import READERS
  if dataset not in READERS:
    raise DataError(None, f"unknown dataset {dataset!r}; choose from {', '.join(READERS)}")
  return typed_options(raw, function_annotations(READERS[dataset]), dataset)


def open_frames(dataset: str, root: str | None, option_items: Sequence[str], segmentation: str,
                height: int, width: int) -> Sequence[Frame]:
  """The frame sequence of a dataset with its panoptic maps chosen by `segmentation`."""
  options = check_dataset_args(dataset, root, option_items, segmentation)
  kind, arg = parse_segmentation(segmentation)
  if dataset == "synthetic":
    from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
    try:
      cfg = SyntheticConfig(**{"height": height, "width": width, "seed": 100, **options})
    except (TypeError, ValueError) as e:
      raise DataError(None, f"synthetic options: {e}") from None
    return generate_sequence(cfg)
  from pitta_jax.data.readers import open_dataset
  if kind == "png":
    options["panoptic_dir"] = arg
  frames = open_dataset(dataset, root, **options)
  if kind == "mask2former":
    from pitta_jax.segment import segmented_frames
    frames = segmented_frames(frames, arg)
  return frames
