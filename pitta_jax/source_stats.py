"""ActMAD's source statistics on disk: computed once, validated when loaded, cached.

ActMAD (methods/actmad.py) aligns test-time activation moments with the per-location mean and
variance of the source domain's BatchNorm outputs. Those are computed over many source images
(`actmad.source_statistics`), which is slow for a real source set, so `pitta-jax source-stats`
writes them to an `.npz` once and `adapt --method actmad --source-stats FILE` reads them.

File format (NumPy `.npz`, no pickle): per layer path P (e.g. `encoder/layer1/0/bn1`) the arrays
`mean:P` and `var:P` (h, w, c) float32, and the 0-d metadata arrays `meta:format` (FORMAT),
`meta:architecture`, `meta:height`, `meta:width` (the weights' network and input size),
`meta:layers` (the layer regex), `meta:images` (how many source images) and `meta:weights`
(`weights_identity`, provenance only). Loading checks the format, the network, the size and
that the layer paths and shapes are exactly those `--actmad.layers` selects in the network.

On the synthetic benchmark without a file, the statistics of the clear training streets are
cached under `source_model.cache_root()/actmad_stats/<key>.npz`, the key hashing the weights'
identity (architecture, model.json, every variable's bytes), the layers and the source data.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pitta_jax.checkpoint import Weights
from pitta_jax.data.errors import DataError

FORMAT = "pitta-jax actmad source statistics v1"
CACHE_VERSION = 1  # bump when the synthetic source data or the statistics change
Stats = dict[str, tuple[np.ndarray, np.ndarray]]


def weights_identity(weights: Weights) -> str:
  """sha256 of the architecture, model.json and every depth-network variable (path, dtype,
  shape, bytes): equal exactly for the same network with the same values."""
  digest = hashlib.sha256()
  digest.update(json.dumps([weights.spec.name, weights.config], sort_keys=True,
                           default=str).encode())
  update_with_tree(digest, weights.depth)
  return digest.hexdigest()


def update_with_tree(digest, tree) -> None:
  """Feeds every leaf of a variables tree (path, dtype, shape, bytes; sorted by path) to a
  hashlib `digest`."""
  from flax.traverse_util import flatten_dict
  for path, leaf in sorted(flatten_dict(tree, sep="/").items()):
    array = np.ascontiguousarray(np.asarray(leaf))
    digest.update(f"{path}|{array.dtype.str}|{array.shape}".encode())
    digest.update(array.tobytes())


def layer_shapes(weights: Weights, layers: str) -> dict[str, tuple[int, ...]]:
  """{path: (h, w, c)} of the modules `layers` matches, at the weights' input size (abstract
  evaluation: nothing is computed)."""
  import jax
  import jax.numpy as jnp
  model = weights.network()
  x = jax.ShapeDtypeStruct((1, weights.height, weights.width, 3), jnp.float32)
  acts = jax.eval_shape(lambda v, images: model.capture(v, images, False, layers)[1],
                        weights.depth, x)
  return {k: tuple(a.shape[1:]) for k, a in acts.items()}


def matched_layers(weights: Weights, layers: str, flag: str) -> dict[str, tuple[int, ...]]:
  """`layer_shapes`, checked before any source image is read: DataError naming `flag` (the
  command's option that set `layers`) when the regex matches no module."""
  shapes = layer_shapes(weights, layers)
  if not shapes:
    raise DataError(None, f"{flag} {layers!r} matches no module of {weights.spec.name} whose "
                          f"output is one feature map")
  return shapes


def save_source_stats(path: str | Path, stats: Stats, weights: Weights, layers: str,
                      n_images: int) -> Path:
  """Writes `stats` ({path: (mean, var)}) with its metadata atomically (module docstring)."""
  from pitta_jax.outputs import atomic_write_bytes
  path = Path(path)
  if path.is_dir():
    raise DataError(path, "is a directory; --out names the .npz file to write")
  arrays: dict[str, np.ndarray] = {
      "meta:format": np.asarray(FORMAT), "meta:architecture": np.asarray(weights.spec.name),
      "meta:height": np.asarray(weights.height), "meta:width": np.asarray(weights.width),
      "meta:layers": np.asarray(layers), "meta:images": np.asarray(n_images),
      "meta:weights": np.asarray(weights_identity(weights))}
  for layer, (mean, var) in stats.items():
    arrays[f"mean:{layer}"] = np.asarray(mean)
    arrays[f"var:{layer}"] = np.asarray(var)
  buffer = io.BytesIO()
  np.savez(buffer, **arrays)
  try:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buffer.getvalue())
  except OSError as e:
    raise DataError(path, f"cannot write ({e.strerror or e})") from None
  return path


def read_source_stats(path: str | Path) -> tuple[dict[str, Any], Stats]:
  """(metadata, stats) of a file written by `save_source_stats`, unvalidated against a network;
  DataError naming the file when it is not one."""
  path = Path(path)
  if path.is_dir():
    raise DataError(path, "is a directory; --source-stats names the .npz file that `pitta-jax "
                          "source-stats` wrote")
  if not path.is_file():
    raise DataError(path, "source statistics file not found (write one with `pitta-jax "
                          "source-stats`)")
  if not zipfile.is_zipfile(path):  # np.load would take it for a pickle
    raise DataError(path, "not an .npz file (write one with `pitta-jax source-stats`)")
  try:
    with np.load(path, allow_pickle=False) as data:
      arrays = {k: data[k] for k in data.files}
  except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
    raise DataError(path, f"not a readable .npz file ({type(e).__name__}: {e})") from None
  meta = {k.split(":", 1)[1]: v.item() for k, v in arrays.items()
          if k.startswith("meta:") and v.ndim == 0}
  if meta.get("format") != FORMAT:
    raise DataError(path, "not a source statistics file of `pitta-jax source-stats` (no "
                          f"meta:format {FORMAT!r})")
  stats = {}
  for key, mean in arrays.items():
    if key.startswith("mean:"):
      layer = key[len("mean:"):]
      if f"var:{layer}" not in arrays:
        raise DataError(path, f"layer {layer} has a mean but no variance")
      stats[layer] = (mean, arrays[f"var:{layer}"])
  return meta, stats


def load_source_stats(path: str | Path, weights: Weights, layers: str) -> Stats:
  """The statistics of `path`, checked against the network of `weights` and the layer regex
  the method uses (one-line DataError naming the file and the mismatch)."""
  path = Path(path)
  meta, stats = read_source_stats(path)
  network = (meta.get("architecture"), meta.get("width"), meta.get("height"))
  bad = [f"meta:{k} {v!r}" for k, v in zip(("width", "height"), network[1:])
         if not isinstance(v, int) or isinstance(v, bool)]
  if bad:
    raise DataError(path, f"{', '.join(bad)}: the input size must be integers")
  if network != (weights.spec.name, weights.width, weights.height):
    raise DataError(path, f"statistics of a {network[0]} at {network[1]}x{network[2]}, but the "
                          f"weights are a {weights.spec.name} at {weights.width}x{weights.height}")
  expected = layer_shapes(weights, layers)
  missing = [k for k in expected if k not in stats]
  extra = [k for k in stats if k not in expected]
  if missing or extra:
    what = (f"lacks layer {missing[0]}, which layers {layers!r} selects" if missing else
            f"has layer {extra[0]}, which layers {layers!r} does not select")
    raise DataError(path, f"{what} in this network ({len(missing)} missing, {len(extra)} extra; "
                          f"the file was computed with layers {meta.get('layers')!r})")
  for layer, (mean, var) in stats.items():
    for name, array in (("mean", mean), ("var", var)):
      if array.dtype.kind != "f":
        raise DataError(path, f"{name} of layer {layer} is {array.dtype}, not floating point")
      if tuple(array.shape) != expected[layer]:
        raise DataError(path, f"{name} of layer {layer} is {tuple(array.shape)}, the network "
                              f"gives {expected[layer]}")
      if not np.all(np.isfinite(array)) or (name == "var" and np.any(array < 0)):
        raise DataError(path, f"{name} of layer {layer} holds non-finite or negative values")
  return stats


def cached_stats(key_parts: dict[str, Any], weights: Weights, layers: str,
                 compute: Callable[[], tuple[Stats, int]]) -> Stats:
  """The statistics cached under `cache_root()/actmad_stats/`, computed (and cached) when absent
  or unreadable. key_parts: what defines the source data (e.g. the synthetic seeds)."""
  from pitta_jax.source_model import cache_root
  key = hashlib.sha256(json.dumps(
      {"version": CACHE_VERSION, "weights": weights_identity(weights), "layers": layers,
       "data": key_parts}, sort_keys=True).encode()).hexdigest()[:24]
  path = cache_root() / "actmad_stats" / f"{key}.npz"
  if path.is_file():
    try:
      return load_source_stats(path, weights, layers)
    except DataError:
      pass  # a stale or damaged cache entry is recomputed and overwritten
  stats, n_images = compute()
  save_source_stats(path, stats, weights, layers, n_images)
  return stats
