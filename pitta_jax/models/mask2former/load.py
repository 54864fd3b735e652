"""A converted Mask2Former on disk (`pitta-jax convert mask2former`): config.json + orbax params."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

CONFIG_JSON = "config.json"
PARAMS_DIR = "params"


def load_mask2former(weights_dir: str | os.PathLike):
  """Loads a directory written by `weights_convert.mask2former.save_mask2former` ->
  (Mask2Former module, variables).

  The variables are float32 device arrays {"params": ...}, ready for
  `pitta_jax.models.mask2former.segment(module, variables, image)`.
  """
  import jax
  from pitta_jax.checkpoint import load_tree, read_json_object
  from pitta_jax.models.mask2former.model import Mask2Former, Mask2FormerConfig
  root = Path(weights_dir)
  meta_path = root / CONFIG_JSON
  if not meta_path.is_file():
    raise FileNotFoundError(f"{meta_path}: not found; a Mask2Former weights directory is made by "
                            f"`pitta-jax convert mask2former --from ... CKPT --out DIR`")
  meta = read_json_object(meta_path)
  if meta.get("architecture") != "mask2former":
    raise ValueError(f"{meta_path}: not a Mask2Former description (architecture "
                     f"{meta.get('architecture')!r})")
  cfg = Mask2FormerConfig.from_dict(meta["config"])
  variables = load_tree(root / PARAMS_DIR)
  # on the device once, so that every `segment` call does not copy the weights again
  variables = jax.device_put(jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), variables))
  return Mask2Former(cfg), variables
