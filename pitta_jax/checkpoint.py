"""A network's weights on disk: orbax variables + model.json, loaded and validated with one call.

Layout of a weights directory (written by `pitta-jax convert ...` or `train-source`):

  DIR/model.json   {"architecture": "monodepth2", "height": 192, "width": 640, ...network
                    fields (e.g. "num_layers": 18)..., "has_pose": false, "source": {...}}
  DIR/depth/       orbax checkpoint of the depth network's Flax variables
  DIR/pose/        (optional) orbax checkpoint of its pose network's variables

`load_weights` checks everything before returning: model.json is a JSON object naming a
registered architecture with positive integer sizes the network accepts; the restored trees have
exactly the leaves and shapes of the network that model.json describes; every value is finite.
Each problem is a `WeightsError` naming the file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Collection

import numpy as np

MODEL_JSON = "model.json"
# beside weights being written, from before their description goes until after the new one is
# written: a directory a kill left half-written says so, and a rerun may replace it
INCOMPLETE = ".pitta-jax-incomplete"


class WeightsError(ValueError):
  """A weights directory that cannot be used (one line, names the file)."""


@dataclasses.dataclass
class Weights:
  """A loaded weights directory: its network spec, model.json, and Flax variables."""
  spec: Any                  # pitta_jax.models.spec.ModelSpec
  config: dict[str, Any]     # model.json (without "architecture")
  depth: dict                # {"params": ..., "batch_stats": ...} of the depth network
  pose: dict | None = None   # same for its pose network

  @property
  def height(self) -> int:
    return int(self.config["height"])

  @property
  def width(self) -> int:
    return int(self.config["width"])

  def network(self):
    """The depth network (`pitta_jax.models.registry.Network`) these weights are for."""
    from pitta_jax.models.registry import network
    return network(self.spec, self.config)


@contextlib.contextmanager
def _root_logging_kept():
  """The root logger's handlers as they were after the block: orbax logs through absl, whose
  every call runs `logging.basicConfig()` while the root logger has no handler, so a save or a
  load left a stderr handler on the root logger and made a caller's own
  `logging.basicConfig(...)` afterwards silently do nothing. Handlers the block added go."""
  import logging
  before = list(logging.root.handlers)
  try:
    yield
  finally:
    for handler in [h for h in logging.root.handlers if h not in before]:
      logging.root.removeHandler(handler)


def _checkpointer():
  with _root_logging_kept():
    import orbax.checkpoint as ocp  # imported lazily: orbax start-up is slow
    return ocp.StandardCheckpointer()


# orbax's threads of one save (orbax 0.11's names): its commit thread and the threads it starts
ORBAX_SAVE_THREADS = ("async_save", "write_metadata_after_commits", "np_type_handler")


def _wait_for_save_threads(before: set, timeout: float = 60.0) -> None:
  """Waits until the orbax save threads started since `before` have ended. By their presence
  in `threading.enumerate()`, not `join()`: on Python 3.11 a Ctrl-C that interrupts
  `Thread.join` marks the thread stopped while it runs on, so orbax's own wait returned at once
  and its commit thread re-created the temporary directory removed after it."""
  import time
  deadline = time.monotonic() + timeout
  while time.monotonic() < deadline and saves_running(before):
    time.sleep(0.02)


def saves_running(before: Collection = frozenset()) -> bool:
  """Whether orbax's save threads (those not in `before`) are still writing: a save whose wait a
  second Ctrl-C cut short (`save_tree`) goes on in them, and nothing should be saved at its path
  meanwhile."""
  import threading
  return any(t.name in ORBAX_SAVE_THREADS for t in threading.enumerate() if t not in before)


def save_tree(path: str | os.PathLike, tree: Any) -> None:
  """Writes a pytree of arrays as an orbax checkpoint at `path` (overwrites)."""
  import threading
  ckpt = _checkpointer()
  before = set(threading.enumerate())
  try:
    with _root_logging_kept():
      ckpt.save(os.path.abspath(path), tree, force=True)
      ckpt.wait_until_finished()
  except BaseException as e:  # a full disk, Ctrl-C: no half-written temporary directory stays
    if isinstance(e, KeyboardInterrupt):
      # orbax writes from its own threads: let them end first (deleting their files under
      # them printed hundreds of lines of their tracebacks, and the commit thread re-created
      # the directory); a second Ctrl-C stops the wait
      try:
        try:
          ckpt.wait_until_finished()
        except Exception:  # the interrupted save's own error (e.g. arrays missing)
          pass
        _wait_for_save_threads(before)
      except KeyboardInterrupt:
        pass
    import shutil
    for tmp in Path(path).parent.glob(f"{Path(path).name}.orbax-checkpoint-tmp*"):
      shutil.rmtree(tmp, ignore_errors=True)
    code = _os_error_code(e)
    if code is not None:  # named after the checkpoint, not a temporary file just removed
      raise OSError(code, f"checkpoint not saved: {os.strerror(code)}",
                    os.path.abspath(path)) from e
    raise


def _os_error_code(error: BaseException) -> int | None:
  """The errno of a file-system failure during a save: tensorstore reports it inside a
  ValueError ("... No space left on device [os_error_code='28']"), orbax's own writes as an
  OSError; None for any other error."""
  import re
  if isinstance(error, OSError):
    return error.errno
  found = isinstance(error, ValueError) and re.search(r"\[os_error_code='(\d+)'\]", str(error))
  return int(found.group(1)) if found else None


def load_tree(path: str | os.PathLike) -> Any:
  """Reads an orbax checkpoint written by `save_tree` (arrays come back as NumPy); its values
  are read once synchronously first (`_check_readable`). WeightsError naming the directory when
  it is missing or unreadable (orbax raises many kinds for a damaged one: a missing _METADATA
  is a FileNotFoundError, a truncated array a ValueError)."""
  path = Path(path)
  if not path.is_dir():
    raise WeightsError(f"{path}: the checkpoint is missing")
  try:
    _check_readable(path)
    with _root_logging_kept():
      return _checkpointer().restore(os.path.abspath(path))
  except WeightsError:
    raise
  except Exception as e:
    raise _unreadable(path, e) from None


def save_weights(out_dir: str | os.PathLike, architecture: str, config: dict[str, Any],
                 depth: Any, pose: Any | None = None, source: dict | None = None) -> Path:
  """Writes a weights directory for any registered network.

  model.json = {"architecture": NAME, **config, "has_pose": ..., "source": {...}}; `config` holds
  the JSON fields the network's `ModelSpec.build` reads (with "height"/"width", the input size
  the weights were trained at); depth/ (and pose/) are orbax checkpoints of Flax variables.
  """
  from pitta_jax.models.registry import MODELS, REGISTER_HINT
  from pitta_jax.outputs import atomic_write_text
  if architecture not in MODELS:  # weights the loader would refuse are not written
    raise WeightsError(f"{out_dir}: not written: architecture {architecture!r} is not one of "
                       f"{', '.join(sorted(MODELS))} ({REGISTER_HINT})")
  spec = MODELS[architecture]
  spec.check_size(config.get("height", spec.default_size[0]),
                  config.get("width", spec.default_size[1]))
  with writing_weights(out_dir, MODEL_JSON) as out:
    save_tree(out / "depth", depth)
    if pose is not None:
      save_tree(out / "pose", pose)
    elif (out / "pose").is_dir():  # an earlier conversion's pose network is not these weights'
      import shutil
      shutil.rmtree(out / "pose")
    meta = {"architecture": architecture, **config, "has_pose": pose is not None,
            "source": source or {}}
    # last and atomic: a directory with a model.json is complete (a kill leaves none)
    atomic_write_text(out / MODEL_JSON, json.dumps(meta, indent=2) + "\n")
  return out


@contextlib.contextmanager
def writing_weights(out_dir: str | os.PathLike, description: str):
  """Writes weights into `out_dir` (yielded as a Path) that `description` (model.json, or
  Mask2Former's config.json), written last by the body, completes. Before the body the
  directory is marked `INCOMPLETE` and the old description removed, so that a kill midway
  leaves a directory without a description (never the old one beside new arrays) and with the
  mark, which a rerun of the conversion may replace; the mark goes once the body is done."""
  from pitta_jax.outputs import atomic_write_text
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  atomic_write_text(out / INCOMPLETE, "weights being written by pitta-jax: a conversion into "
                                      "this directory replaces them\n")
  (out / description).unlink(missing_ok=True)
  yield out
  (out / INCOMPLETE).unlink(missing_ok=True)


def read_json_object(path: Path) -> dict[str, Any]:
  """A JSON file holding an object; WeightsError naming the file otherwise."""
  try:
    meta = json.loads(path.read_text())
  except (json.JSONDecodeError, UnicodeDecodeError) as e:
    raise WeightsError(f"{path}: not valid JSON ({e})") from None
  if not isinstance(meta, dict):
    raise WeightsError(f"{path}: expected a JSON object, found {type(meta).__name__}")
  return meta


def read_model_json(weights_dir: str | os.PathLike) -> tuple[Any, dict[str, Any]]:
  """(spec, config) from DIR/model.json, validated (see the module docstring)."""
  from pitta_jax.models.registry import MODELS, REGISTER_HINT
  path = Path(weights_dir) / MODEL_JSON
  if not Path(weights_dir).is_dir():
    raise WeightsError(f"{weights_dir}: not a weights directory with a {MODEL_JSON} (make one "
                       f"with `pitta-jax convert ...` or `pitta-jax train-source`)")
  if not path.is_file() and (Path(weights_dir) / INCOMPLETE).is_file():
    raise WeightsError(f"{weights_dir}: its weights were being written when that stopped (a "
                       f"conversion or train-source interrupted: {INCOMPLETE}); run it again")
  if not path.is_file():
    pth = sorted(p.name for p in Path(weights_dir).glob("*.pth"))
    hint = (f"; this folder holds PyTorch files ({', '.join(pth[:4])}): convert them first, e.g. "
            f"`pitta-jax convert monodepth2 --encoder {Path(weights_dir) / 'encoder.pth'} --depth "
            f"{Path(weights_dir) / 'depth.pth'} --out DIR`" if pth else "")
    raise WeightsError(f"{path}: not found; a weights directory is made by `pitta-jax convert "
                       f"...` or `pitta-jax train-source`{hint}")
  meta = read_json_object(path)
  arch = meta.get("architecture")
  if not isinstance(arch, str) or arch not in MODELS:
    raise WeightsError(f"{path}: architecture {arch!r} is not one of {', '.join(sorted(MODELS))} "
                       f"({REGISTER_HINT})")
  spec = MODELS[arch]
  config = {k: v for k, v in meta.items() if k != "architecture"}
  config.setdefault("height", spec.default_size[0])
  config.setdefault("width", spec.default_size[1])
  for key in ("height", "width"):
    v = config[key]
    if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
      raise WeightsError(f"{path}: {key} must be a positive integer, got {v!r}")
  for key in ("has_pose", "use_stereo"):  # ("no" would read as true)
    if not isinstance(config.get(key, False), bool):
      raise WeightsError(f"{path}: {key} must be true or false, got {config[key]!r}")
  try:
    spec.check_size(config["height"], config["width"])
    spec.build(dict(config))  # the network's own fields (e.g. num_layers), checked here
    if config.get("has_pose") and spec.build_pose is not None:
      spec.build_pose(dict(config))  # and the pose network's (pose_num_layers)
  except BUILD_ERRORS as e:
    raise WeightsError(f"{path}: {e}") from None
  return spec, config


# what building a network from model.json's fields raises where a field is out of its range
# (MonoViT's num_heads 0 divides by zero, a per-stage list too short indexes past its end)
BUILD_ERRORS = (ValueError, TypeError, KeyError, IndexError, ArithmeticError)


def _check_tree(tree: Any, module, config: dict, path: Path, channels: int) -> Any:
  """The restored variables as float32, checked against the module's abstract variables."""
  import jax
  import jax.numpy as jnp
  from flax.traverse_util import flatten_dict, unflatten_dict
  h, w = config["height"], config["width"]
  try:
    abstract = jax.eval_shape(lambda: module.init(jax.random.PRNGKey(0),
                                                  jnp.zeros((1, h, w, channels), jnp.float32)))
  except BUILD_ERRORS as e:  # a field the module's own checks let through (num_heads 0, ...)
    raise WeightsError(f"{path.parent / MODEL_JSON}: cannot build the network it describes "
                       f"({type(e).__name__}: {e})") from None
  want = {k: tuple(v.shape) for k, v in flatten_dict(abstract).items()}
  got = flatten_dict(tree) if isinstance(tree, dict) else {}
  missing = sorted("/".join(k) for k in want if k not in got)
  extra = sorted("/".join(k) for k in got if k not in want)
  if missing or extra:
    raise WeightsError(
        f"{path}: does not match the network in model.json ({len(missing)} missing, "
        f"{len(extra)} unexpected arrays, e.g. {(missing + extra)[:3]}); was it written for "
        f"another architecture or num_layers?")
  out = {}
  for k, shape in want.items():
    arr = np.asarray(got[k], np.float32)
    if arr.shape != shape:
      raise WeightsError(f"{path}: {'/'.join(k)} has shape {arr.shape}, the network in "
                         f"model.json expects {shape}")
    if not np.all(np.isfinite(arr)):
      raise WeightsError(f"{path}: {'/'.join(k)} holds non-finite values (NaN/Inf)")
    out[k] = arr
  return unflatten_dict(out)


def _unreadable(path: Path, error: Exception) -> WeightsError:
  """The one-line error of a checkpoint that cannot be read."""
  return WeightsError(f"{path}: cannot read the checkpoint ({type(error).__name__}: "
                      f"{str(error).splitlines()[0] if str(error) else ''})")


def _check_readable(path: Path) -> None:
  """Reads every value of the checkpoint's OCDBT store once, synchronously (~0.1 s for 37 MB):
  a truncated or corrupt data file is a WeightsError here. Orbax's own asynchronous restore
  reports it too, but its reads still in flight then print tracebacks from tensorstore's
  threads ("Event loop is closed"). A directory without OCDBT's manifest is left to orbax; one
  with it whose index does not even list is corrupt too."""
  import tensorstore as ts
  try:
    store = ts.KvStore.open({"driver": "ocdbt", "base": f"{path.resolve().as_uri()}/"}).result()
    keys = store.list().result()
  except Exception as e:
    if (path / "manifest.ocdbt").is_file():  # an OCDBT checkpoint whose index is damaged
      raise _unreadable(path, e) from None
    return  # not an OCDBT checkpoint: orbax reads (and judges) it
  for key in keys:
    try:
      store.read(key).result()
    except Exception as e:
      raise _unreadable(path, e) from None


def load_weights(weights_dir: str | os.PathLike) -> Weights:
  """Loads and validates a weights directory written by `save_weights`."""
  root = Path(weights_dir)
  spec, config = read_model_json(root)
  depth = _check_tree(load_tree(root / "depth"), spec.build(config), config, root / "depth", 3)
  pose = None
  if config.get("has_pose"):
    if spec.build_pose is None:
      raise WeightsError(f"{root / MODEL_JSON}: has_pose is set, but {spec.name} has no pose net")
    pose = _check_tree(load_tree(root / "pose"), spec.build_pose(config), config, root / "pose", 6)
  return Weights(spec, config, depth, pose)
