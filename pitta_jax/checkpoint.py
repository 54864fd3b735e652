"""A converted MonoDepth2 on disk: orbax variables + a small JSON, loaded with one call.

Layout of a weights directory (written by `weights_convert monodepth2` or `train-source`):

  DIR/model.json        {"architecture": "monodepth2", "num_layers": 18, "height": 192,
                         "width": 640, "use_stereo": false, "has_pose": true, "source": {...}}
  DIR/depth/            orbax checkpoint of DepthNet variables {"params", "batch_stats"}
  DIR/pose/             (optional) orbax checkpoint of PoseNet variables
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

MODEL_JSON = "model.json"


@dataclasses.dataclass(frozen=True)
class ModelConfig:
  """What a weights directory holds. height/width: the input size the network was trained at."""
  architecture: str = "monodepth2"
  num_layers: int = 18
  height: int = 192  # MonoDepth2 mono_640x192
  width: int = 640
  use_stereo: bool = False
  has_pose: bool = False
  source: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class MonoDepth2Weights:
  config: ModelConfig
  depth: dict  # {"params": ..., "batch_stats": ...} for DepthNet
  pose: dict | None = None  # same for PoseNet


def _checkpointer():
  import orbax.checkpoint as ocp  # imported lazily: orbax start-up is slow
  return ocp.StandardCheckpointer()


def save_tree(path: str | os.PathLike, tree: Any) -> None:
  """Writes a pytree of arrays as an orbax checkpoint at `path` (overwrites)."""
  ckpt = _checkpointer()
  ckpt.save(os.path.abspath(path), tree, force=True)
  ckpt.wait_until_finished()


def load_tree(path: str | os.PathLike) -> Any:
  """Reads an orbax checkpoint written by `save_tree` (arrays come back as NumPy)."""
  return _checkpointer().restore(os.path.abspath(path))


def save_weights(out_dir: str | os.PathLike, architecture: str, config: dict[str, Any],
                 depth: Any, pose: Any | None = None, source: dict | None = None) -> Path:
  """Writes a weights directory for any registered network.

  model.json = {"architecture": NAME, **config, "has_pose": ..., "source": {...}}; `config` holds
  the JSON fields the network's `ModelSpec.build` reads (with "height"/"width", the input size
  the weights were trained at); depth/ (and pose/) are orbax checkpoints of Flax variables.
  """
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  save_tree(out / "depth", depth)
  if pose is not None:
    save_tree(out / "pose", pose)
  meta = {"architecture": architecture, **config, "has_pose": pose is not None,
          "source": source or {}}
  (out / MODEL_JSON).write_text(json.dumps(meta, indent=2) + "\n")
  return out


def save_monodepth2(out_dir: str | os.PathLike, config: ModelConfig, depth: dict,
                    pose: dict | None = None) -> Path:
  """Writes a MonoDepth2 weights directory (see the module docstring)."""
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  config = dataclasses.replace(config, has_pose=pose is not None)
  save_tree(out / "depth", depth)
  if pose is not None:
    save_tree(out / "pose", pose)
  (out / MODEL_JSON).write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
  return out


def load_monodepth2(weights_dir: str | os.PathLike) -> MonoDepth2Weights:
  """Loads a weights directory written by `save_monodepth2`.

  Raises:
    FileNotFoundError: the directory or its model.json / depth checkpoint is missing.
    ValueError: model.json is not a MonoDepth2 description.
  """
  root = Path(weights_dir)
  meta_path = root / MODEL_JSON
  if not meta_path.is_file():
    raise FileNotFoundError(
        f"{meta_path}: not found; a weights directory is made by "
        f"`pitta-jax convert monodepth2 ...` or `pitta-jax train-source`")
  try:
    meta = json.loads(meta_path.read_text())
  except json.JSONDecodeError as e:
    raise ValueError(f"{meta_path}: not valid JSON ({e})") from e
  if meta.get("architecture") != "monodepth2":
    raise ValueError(f"{meta_path}: architecture {meta.get('architecture')!r} is not 'monodepth2'")
  known = {f.name for f in dataclasses.fields(ModelConfig)}
  config = ModelConfig(**{k: v for k, v in meta.items() if k in known})
  if not (root / "depth").is_dir():
    raise FileNotFoundError(f"{root / 'depth'}: the depth network checkpoint is missing")
  depth = _as_float32(load_tree(root / "depth"))
  pose = _as_float32(load_tree(root / "pose")) if config.has_pose else None
  return MonoDepth2Weights(config, depth, pose)


def _as_float32(tree: Any) -> Any:
  import jax
  return jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), tree)
