"""Resolving the CLI's `--dataset/--root/--option/--segmentation/--weights` into frames and weights."""

from __future__ import annotations

import dataclasses
from typing import Sequence

from pitta_jax.checkpoint import MonoDepth2Weights, load_monodepth2
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame


def parse_options(items: Sequence[str]) -> dict[str, object]:
  """["weather=foggy", "num_frames=100"] -> {"weather": "foggy", "num_frames": 100}."""
  options: dict[str, object] = {}
  for item in items:
    key, sep, value = item.partition("=")
    if not sep or not key:
      raise DataError(None, f"--option {item!r} is not KEY=VALUE")
    for cast in (int, float):
      try:
        options[key] = cast(value)
        break
      except ValueError:
        continue
    else:
      options[key] = {"true": True, "false": False, "none": None}.get(value.lower(), value)
  return options


def open_weights(weights_dir: str | None, dataset: str, quiet: bool = False) -> MonoDepth2Weights:
  """The given weights directory; for the synthetic benchmark, the cached source model."""
  if weights_dir:
    return load_monodepth2(weights_dir)
  if dataset != "synthetic":
    raise DataError(None, "--weights is required for real datasets (convert a checkpoint with "
                          "`pitta-jax convert monodepth2 ...`)")
  from pitta_jax.source_model import SourceConfig, load_or_train_source
  return load_or_train_source(SourceConfig(), quiet=quiet)[0]


def open_frames(dataset: str, root: str | None, option_items: Sequence[str], segmentation: str,
                height: int, width: int) -> Sequence[Frame]:
  """The frame sequence of a dataset with its panoptic maps chosen by `segmentation`."""
  options = parse_options(option_items)
  kind, _, arg = segmentation.partition(":")
  if kind not in ("gt", "png", "mask2former"):
    raise DataError(None, f"--segmentation {segmentation!r}: use gt, png:DIR or mask2former:DIR")
  if dataset == "synthetic":
    if kind != "gt":
      raise DataError(None, "the synthetic benchmark carries exact panoptic maps: use "
                            "--segmentation gt")
    from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
    known = {f.name for f in dataclasses.fields(SyntheticConfig)}
    unknown = sorted(set(options) - known)
    if unknown:
      raise DataError(None, f"synthetic has no option {', '.join(unknown)} "
                            f"(options: {', '.join(sorted(known))})")
    cfg = SyntheticConfig(**{"height": height, "width": width, "seed": 100, **options})
    return generate_sequence(cfg)
  if not root:
    raise DataError(None, f"--root is required for dataset {dataset}")
  from pitta_jax.data.readers import open_dataset
  if kind == "png":
    if not arg:
      raise DataError(None, "--segmentation png:DIR needs a directory")
    options["panoptic_dir"] = arg
  frames = open_dataset(dataset, root, **options)
  if kind == "mask2former":
    from pitta_jax.segment import segmented_frames
    frames = segmented_frames(frames, arg)
  return frames
