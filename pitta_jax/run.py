"""One adaptation run, evaluated: a method over a frame sequence -> per-frame metrics and logs.

This is what `pitta-jax adapt`, `pitta-jax evaluate`, the demo and the experiments call. A
caller running many sequences passes one `Runners` (its own cache of compiled chunk runners,
keyed by network, method and config), so the same compile serves every sequence of a sweep (e.g.
the four weather shifts of the demo); nothing is cached at module level.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
import time
import types
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from tqdm import tqdm

from pitta_jax import metrics as metrics_lib
from pitta_jax.adapt import (AdaptConfig, adapt_stream, init_state, load_state,
                             make_method_runner, make_optimizer, save_state)
from pitta_jax.adapt.inputs import chunks
from pitta_jax.checkpoint import Weights, saves_running
from pitta_jax.configs import check, check_types, is_number, option
from pitta_jax.methods import Method, build as build_method
from pitta_jax.methods.base import INPUT_SIZE, METRIC_FACTOR
from pitta_jax.methods.depth_refining import dynamic_classes
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame, aspect_mismatch
from pitta_jax.data.sequence import FrameSequence
from pitta_jax.outputs import remove_stale_temps


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """The evaluation protocol (paper Sec. 4.1; its Appendix D is not public): MonoDepth2's
  `evaluate_depth.py` as it scores its Eigen split, without the crop unless asked (`valid_gt`
  positive is its rule on other splits; `metrics` says where they differ)."""
  # ground truth outside (min_depth, max_depth) is left out, not clipped (MonoDepth2's mask),
  # and with valid_gt positive scored whatever its depth; the prediction is clamped either way
  min_depth: float = option(metrics_lib.MIN_DEPTH, "ground truth at or below this is not scored "
                                                   "(valid_gt range), and the prediction is "
                                                   "clamped up to it (metres)")
  max_depth: float = option(metrics_lib.MAX_DEPTH, "ground truth at or beyond this is not scored "
                                                   "(valid_gt range; not capped), and the "
                                                   "prediction is clamped down to it (metres)")
  alignment: str = option("model", "per-frame alignment of the prediction: model (the "
                                   "weights' own: median for self-supervised monocular nets, "
                                   "stereo (x5.4) for weights trained with stereo pairs "
                                   "(model.json use_stereo), scale_shift for relative depth) | "
                                   "median | scale_shift | stereo | none")
  garg_crop: bool = option(False, "score inside the Garg/Eigen crop; a KITTI split file under "
                                  "splits/eigen/ turns it on unless given (MonoDepth2's "
                                  "evaluate_depth.py --eval_split eigen)")
  resize: str = option("disparity", "the map resized onto the ground truth's size: disparity "
                                    "(MonoDepth2's evaluate_depth.py: resize 1 / depth, then "
                                    "invert) | depth")
  valid_gt: str = option("range", "ground-truth pixels scored: range (min_depth < gt < "
                                  "max_depth) | positive (gt > 0; a KITTI split under "
                                  "splits/eigen_benchmark/ turns it on unless given, as "
                                  "MonoDepth2's evaluate_depth.py)")

  def __post_init__(self):
    check_types(self)
    check(is_number(self.min_depth) and is_number(self.max_depth)
          and 0 < self.min_depth < self.max_depth < float("inf"),
          # (> 0: the prediction is clamped up to min_depth before log and division)
          f"need 0 < min_depth < max_depth < inf, got min_depth={self.min_depth} "
          f"max_depth={self.max_depth}")
    check(self.alignment in ("model", "median", "scale_shift", "stereo", "none"),
          f"alignment must be model, median, scale_shift, stereo or none, got "
          f"{self.alignment!r}")
    check(self.resize in metrics_lib.RESIZE_DOMAINS,
          f"resize must be {' or '.join(metrics_lib.RESIZE_DOMAINS)}, got {self.resize!r}")
    check(self.valid_gt in metrics_lib.VALID_GT,
          f"valid_gt must be {' or '.join(metrics_lib.VALID_GT)}, got {self.valid_gt!r}")


def run_status(nonfinite_indices: Sequence[int], n_frames: int, n_scored: int) -> str:
  """A run's status: "ok"; "diverged: ..." from the first frame whose depth is not finite
  (`nonfinite_indices`, ascending, of `n_frames`); "not scored: ..." when none of its frames
  could be scored. What a results table shows instead of a row's means (`RunResult.status`,
  and each lambda of Table 4's sweep)."""
  if nonfinite_indices:
    return (f"diverged: non-finite depth from frame {nonfinite_indices[0]} of {n_frames} "
            f"({len(nonfinite_indices)} frames not scored)")
  if not n_scored:
    return "not scored: no frame has valid ground truth"
  return "ok"


@dataclasses.dataclass
class RunResult:
  """Everything one run produced (host NumPy)."""
  name: str
  per_frame: list[dict]                # {"name", "index", 7 metrics} per scored frame (valid GT)
  mean: dict[str, float]               # averaged over frames
  logs: dict[str, np.ndarray]          # per frame: loss, loss_d, loss_e, n_instances, skipped...
  frame_names: list[str]
  seconds: float
  kept_depths: dict[int, np.ndarray]   # frame index -> predicted depth (network size)
  n_skipped: int = 0
  excluded: list[str] = dataclasses.field(default_factory=list)  # frames without valid GT
  resumed_at: int = 0                  # frames taken from a checkpoint (--resume)
  # wall time the checkpoint's frames took in the call(s) that ran them (up to its save)
  seconds_before: float = 0.0
  # indices of the frames whose predicted depth has a non-finite value (a diverged method):
  # not scored
  nonfinite_indices: list[int] = dataclasses.field(default_factory=list)
  # of `seconds`: the chunks during which the step compiled (or loaded from the compilation
  # cache), and their frames: `steady_fps` leaves them out
  compile_seconds: float = 0.0
  compiled_frames: int = 0

  def per_frame_series(self, metric: str = "abs_rel") -> list[float]:
    """`metric` of every frame in frame order, NaN where the frame was not scored (its depth
    not finite, its ground truth without a valid pixel or absent): a curve over the frames
    whose x is the frame index, where `per_frame` holds the scored frames only."""
    out = [float("nan")] * len(self.frame_names)
    if all(isinstance(e.get("index"), int) for e in self.per_frame):
      for entry in self.per_frame:  # each scored frame knows its place
        if 0 <= entry["index"] < len(out):
          out[entry["index"]] = entry[metric]
      return out
    # entries without their index (a result built by hand): matched by name, in order
    bad, scored = set(self.nonfinite_indices), iter(self.per_frame)
    entry = next(scored, None)
    for i, name in enumerate(self.frame_names):
      if entry is not None and i not in bad and entry.get("name") == name:
        out[i] = entry[metric]
        entry = next(scored, None)
    return out

  @property
  def nonfinite(self) -> list[str]:
    """The names of the frames whose prediction is not finite."""
    return [self.frame_names[i] for i in self.nonfinite_indices]

  @property
  def diverged_at(self) -> int | None:
    """Index of the first frame whose prediction is not finite (None: the run never diverged)."""
    return self.nonfinite_indices[0] if self.nonfinite_indices else None

  @property
  def status(self) -> str:
    """"ok", where the method diverged, or that no frame could be scored: what a results
    table shows instead of its means (`run_status`)."""
    return run_status(self.nonfinite_indices, len(self.frame_names), len(self.per_frame))

  @property
  def fps(self) -> float:
    """Frames per second of the frames this call ran (not those taken from a checkpoint), in
    wall time: the step's compile included."""
    ran = len(self.frame_names) - self.resumed_at
    return ran / self.seconds if ran > 0 and self.seconds > 0 else float("nan")

  @property
  def steady_fps(self) -> float:
    """Frames per second of the chunks after the step was compiled (what a longer run
    approaches; NaN when every chunk this call ran compiled, e.g. a one-chunk run)."""
    ran = len(self.frame_names) - self.resumed_at - self.compiled_frames
    rest = self.seconds - self.compile_seconds
    return ran / rest if ran > 0 and rest > 0 else float("nan")

  @property
  def total_seconds(self) -> float:
    """Wall time of every frame: this call's and, after a resume, the earlier calls' up to the
    checkpoint (time spent after it, on frames run again here, is not counted twice)."""
    return self.seconds_before + self.seconds

  @property
  def total_fps(self) -> float:
    """Frames per second over the whole sequence, resumed or not (`total_seconds`)."""
    n = len(self.frame_names)
    return n / self.total_seconds if n and self.total_seconds > 0 else float("nan")


class Runners:
  """A caller-owned cache of compiled chunk runners, keyed by (network, method, config).

  Pass one instance to every `run_sequence` of a sweep so that sequences with the same network
  and configs share one compile.
  """

  def __init__(self):
    self._cache: dict = {}

  def custom(self, key, build):
    """Any other compiled callable under a caller-chosen hashable `key` (e.g. a vmapped
    sweep), built by `build()` once."""
    if ("custom", key) not in self._cache:
      self._cache[("custom", key)] = build()
    return self._cache[("custom", key)]

  def get(self, weights: Weights, method: Method, cfg: AdaptConfig):
    """The (model, optimiser, runner) of this network, method and config, compiled once.

    The network and the method are keyed by what they compute (`code_key`: their functions'
    code and captured values, their configs), not by their names: methods rebuilt from the
    same config share a compile, while two methods of one name whose functions differ (an
    ablation's variants, a notebook's redefined loss) do not."""
    key = (code_key(weights.spec), tuple(sorted((k, str(v)) for k, v in weights.config.items()
                                                if k != "source")), code_key(method), cfg)
    if key not in self._cache:
      model = weights.network()
      tx = make_optimizer(cfg, method)
      # the entry keeps `method` and the spec alive: ids in its key stay unique meanwhile
      self._cache[key] = (model, tx, make_method_runner(model, method, cfg, tx), method,
                          weights.spec)
    return self._cache[key][:3]


def code_key(obj: Any, _path: frozenset = frozenset(), _memo: dict | None = None) -> Any:
  """A hashable key equal for objects that compute the same thing: a function by its code,
  captured values and defaults (two closures of one `def` capturing equal values are equal,
  capturing different ones are not), a `functools.partial` by its function and arguments, a
  dataclass by its type and fields, tuples/lists/dicts by their items; any other hashable
  value by its type and value, an unhashable one by identity."""
  if id(obj) in _path:  # a cycle (a closure that refers to itself)
    return ("cycle", id(obj))
  path = _path | {id(obj)}
  memo = {} if _memo is None else _memo  # one call's keys of the functions met by name
  if isinstance(obj, functools.partial):
    return ("partial", code_key(obj.func, path, memo), code_key(obj.args, path, memo),
            code_key(obj.keywords, path, memo))
  code = getattr(obj, "__code__", None)
  if isinstance(code, types.CodeType):
    cells = []
    for cell in getattr(obj, "__closure__", None) or ():
      try:
        cells.append(code_key(cell.cell_contents, path, memo))
      except ValueError:  # a cell not yet filled
        cells.append(("empty",))
    return ("function", code, tuple(cells),
            code_key(getattr(obj, "__defaults__", None), path, memo),
            code_key(getattr(obj, "__kwdefaults__", None), path, memo),
            _globals_key(code, getattr(obj, "__globals__", {}), path, memo))
  if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
    return (type(obj), tuple(code_key(getattr(obj, f.name), path, memo)
                             for f in dataclasses.fields(obj)))
  if isinstance(obj, (tuple, list)):
    return (type(obj), tuple(code_key(v, path, memo) for v in obj))
  if isinstance(obj, dict):
    return (dict, tuple((code_key(k, path, memo), code_key(v, path, memo)) for k, v in obj.items()))
  try:
    hash(obj)
  except TypeError:
    return ("id", id(obj))
  return (type(obj), obj)


def _globals_key(code: types.CodeType, namespace: dict, path: frozenset, memo: dict) -> tuple:
  """What the module-level names a function's code reads are bound to: a Python function by
  its own `code_key` (its code and, in turn, the names it reads: a notebook that redefines a
  helper that the loss's helper calls gets a new key, where keying the loss's helper by
  identity served the old compiled step), a class or any other callable itself, which compares
  by identity (a notebook cell run again with an edited `class Net` binds the name to a new
  object, where the code of `lambda config: Net()` stays equal; held by the key, so that its id
  is never reused meanwhile), another hashable value (a constant) by its value, an unhashable
  one by identity; modules are left out. `path` and `memo` are `code_key`'s (the objects above
  this one, the functions keyed so far in this call)."""
  names, codes = set(), [code]
  while codes:  # the function's code and that of its nested functions and comprehensions
    c = codes.pop()
    names |= set(c.co_names)
    codes += [const for const in c.co_consts if isinstance(const, types.CodeType)]
  key = []
  for name in sorted(names):
    if name not in namespace or isinstance(namespace[name], types.ModuleType):
      continue
    value = namespace[name]
    if isinstance(value, types.FunctionType):  # keyed once per `code_key` call: a helper
      if id(value) not in memo:                 # several functions read is walked once
        memo[id(value)] = code_key(value, path, memo)
      key.append((name, memo[id(value)]))
      continue
    try:
      hash(value)
    except TypeError:
      key.append((name, _ByIdentity(value)))
      continue
    key.append((name, type(value), value))
  return tuple(key)


class _ByIdentity:
  """An unhashable value in a cache key, equal only to itself and held alive by the key (an id
  alone could be reused by a later object once the value is gone)."""
  __slots__ = ("obj",)

  def __init__(self, obj: Any):
    self.obj = obj

  def __hash__(self) -> int:
    return id(self.obj)

  def __eq__(self, other: Any) -> bool:
    return isinstance(other, _ByIdentity) and other.obj is self.obj


def model_alignment(weights: Weights) -> str:
  """The evaluation alignment the weights need: the network's (`ModelSpec.alignment`), except
  that a median-scaled network trained with stereo pairs (model.json `use_stereo`, as
  MonoDepth2's `stereo_*` and `mono+stereo_*` releases) is scaled by 5.4 as MonoDepth2's
  `evaluate_depth.py` does (`metrics.STEREO_SCALE_FACTOR`)."""
  return "stereo" if _stereo_trained(weights.spec, weights.config) else weights.spec.alignment


def _stereo_trained(spec, config: Mapping[str, Any]) -> bool:
  """A median-scaled network whose weights were trained with stereo pairs (`use_stereo`)."""
  return spec.alignment == "median" and config.get("use_stereo") is True


def metric_factor(spec, config: Mapping[str, Any]) -> float | None:
  """The fixed factor from a network's depth to metres, where its weights (`spec`, model.json
  `config`) give one: 1 for a network that predicts metres (`ModelSpec.output` "metric_depth",
  and the source models `pitta-jax train-source` trains, supervised in metres on the synthetic
  benchmark: model.json `source.trained_by`), MonoDepth2's 5.4 for weights trained with stereo
  pairs (`use_stereo`, a baseline of 0.1 units for KITTI's 54 cm), None for weights up to scale
  (monocular training)."""
  source = config.get("source")
  if spec.output == "metric_depth" or (isinstance(source, Mapping) and "trained_by" in source):
    return 1.0
  if _stereo_trained(spec, config):
    return metrics_lib.STEREO_SCALE_FACTOR
  return None


def frame_metrics(depth: np.ndarray, gt: np.ndarray, eval_cfg: EvalConfig, alignment: str
                  ) -> dict[str, float]:
  """The 7 metrics of one frame's predicted depth (h, w) against its ground truth (H, W) under
  `eval_cfg`, with the alignment resolved (`model_alignment` for "model"). Raises
  `metrics.NoValidPixels` when the ground truth has no valid pixel."""
  return metrics_lib.depth_metrics(depth, gt, min_depth=eval_cfg.min_depth,
                                   max_depth=eval_cfg.max_depth, alignment=alignment,
                                   garg_crop=eval_cfg.garg_crop, resize=eval_cfg.resize,
                                   valid_gt=eval_cfg.valid_gt)


def checkpoint_chunk_size(chunk_size: int, checkpoint_every: int) -> int:
  """The chunk size of a run that checkpoints every `checkpoint_every` frames (0: none): it
  saves after exact frames at chunk ends, so chunks of gcd(chunk_size, checkpoint_every)."""
  return math.gcd(chunk_size, checkpoint_every) if checkpoint_every > 0 else chunk_size


def input_size(weights: Weights, frames: Sequence[Frame]) -> tuple[int, int]:
  """The (H, W) a run feeds the network: the size its weights were trained at, or for a network
  that keeps the aspect ratio (Depth Anything V2, as its upstream `infer_image`) the first
  frame's size brought to it (`ModelSpec.inference_size`: 518 x 1722 for KITTI's 375 x 1242)."""
  trained = (weights.height, weights.width)
  if not weights.spec.keep_aspect:
    return trained
  return weights.spec.inference_size(frames[0].image.shape[:2], trained)


def check_aspect(frame: Frame) -> None:
  """The prediction is resized onto the ground truth: their aspect ratios must agree (1%).
  DataError naming the frame's ground-truth file and its image (a reader's frame), else the
  frame."""
  if frame.depth is None:
    return
  why = aspect_mismatch(frame.image.shape, np.shape(frame.depth))
  if why is not None:
    if frame.depth_file and frame.image_file:
      why += f" (image {frame.image_file})"
    raise DataError(frame.depth_file or frame.image_file or frame.name or "frame", why)


CHECKPOINT_PATTERN = "state_[0-9][0-9][0-9][0-9][0-9][0-9]"
UNFINISHED_PATTERN = CHECKPOINT_PATTERN + ".orbax-checkpoint-tmp*"  # a save cut short by a kill
KEEP_CHECKPOINTS = 2  # a run keeps its newest two (the older one if the newest is cut short)
RESUME_OWN = "own"  # run_sequence(resume=...): resume this run's checkpoint, else start afresh


def run_fingerprint(weights: Weights, method: Method, cfg: AdaptConfig, eval_cfg: EvalConfig,
                    names: Sequence[str], data: dict | None = None) -> str:
  """A digest of everything that decides a run's results: the network (spec, model.json, the
  parameter values; the pose network's values for a method that needs it), the method and its
  config, the run's and the evaluation's configs, the frames' names in order and, where given,
  `data`: what the frames are beyond their names (the dataset flags: a synthetic frame's name
  holds its domain and seed, not its severity or traffic; a folder's names not its ground-truth
  or panoptic directory; nor do they hold the method's source data). A checkpoint carries it,
  so that a resume continues only its own run."""
  import hashlib
  from pitta_jax.source_stats import update_with_tree, weights_identity
  parts = {"weights": weights_identity(weights), "method": method.name,
           "method_config": repr(method.config), "adapt": repr(cfg), "eval": repr(eval_cfg),
           "frames": list(names)}
  if "pose" in method.needs and weights.pose is not None:  # the pose network it runs too
    pose = hashlib.sha256()
    update_with_tree(pose, weights.pose)
    parts["pose"] = pose.hexdigest()
  if data is not None:  # absent (not null) without it: earlier fingerprints stay as they were
    parts["data"] = data
  text = json.dumps(parts, sort_keys=True, default=str)
  return hashlib.sha256(text.encode()).hexdigest()[:32]


def run_settings(method: Method, cfg: AdaptConfig, eval_cfg: EvalConfig,
                 data: dict | None = None) -> dict[str, Any]:
  """The readable settings of a run, as JSON values ({"method", "method_config", "adapt",
  "eval", "data"}): a checkpoint's sidecar carries them, so that a --resume refused for another
  run's checkpoints names the flags that differ (`setting_differences`), not only that some do."""
  from pitta_jax.outputs import json_safe

  def fields(config) -> Any:
    return dataclasses.asdict(config) if dataclasses.is_dataclass(config) else repr(config)

  settings = {"method": method.name, "method_config": fields(method.config),
              "adapt": fields(cfg), "eval": fields(eval_cfg), "data": data or {}}
  return json.loads(json.dumps(json_safe(settings)[0], default=str))  # tuples as lists, as read


def setting_differences(saved: Any, now: dict[str, Any], prefix: str = "") -> list[str]:
  """`saved.KEY was A, now B` for each setting (nested keys joined with dots, e.g.
  adapt.lr) in which a checkpoint's `run_settings` differ from this run's."""
  if not isinstance(saved, dict):
    return []
  out = []
  for key in sorted(set(saved) | set(now)):
    a, b = saved.get(key), now.get(key)
    if isinstance(a, dict) and isinstance(b, dict):
      out += setting_differences(a, b, f"{prefix}{key}.")
    elif a != b:
      out.append(f"{prefix}{key} was {a!r}, now {b!r}")
  return out


def frame_names(frames: Sequence[Frame]) -> list[str]:
  """The frames' names, without reading a lazily loaded sequence."""
  names = getattr(frames, "names", None)
  return list(names) if names is not None else [frame.name for frame in frames]


# sidecar keys a record may lack (sidecars written before they were added; a resumed run
# takes the fresh record's)
RECORD_OPTIONAL = ("nonfinite_indices", "seconds", "settings")


def _sidecar_problem(record: dict, template: dict) -> str | None:
  """What is wrong with a sidecar `record` whose run is this one, against the fresh record
  `template` of its run (its keys and their kinds: a list of per-lambda lists in a sweep), or
  None: a hand-edited or damaged sidecar is refused here, not met as a KeyError later."""
  from pitta_jax.outputs import json_number

  def numbers(x) -> bool:  # a log's per-frame values: numbers or flags (or lists of them)
    return json_number(x) or isinstance(x, bool) or (isinstance(x, list) and all(map(numbers, x)))

  for key, fresh in template.items():
    if key not in record:
      if key in RECORD_OPTIONAL:
        continue
      return f"no {key!r}"
    value = record[key]
    if not isinstance(value, type(fresh)) and not (isinstance(fresh, float) and value is not None
                                                   and json_number(value)):
      return f"{key!r} is not a {type(fresh).__name__}"
    if isinstance(fresh, list) and fresh and isinstance(fresh[0], list) and (
        len(value) != len(fresh) or not all(isinstance(v, list) for v in value)):
      return f"{key!r} is not {len(fresh)} lists"
  items = {key: [v for x in record.get(key, []) for v in (x if isinstance(x, list) else [x])]
           if key in template else []
           for key in ("per_frame", "names", "excluded", "nonfinite_indices")}
  if not all(isinstance(m, dict) and all(isinstance(v, str) if k == "name" else json_number(v)
                                         for k, v in m.items()) for m in items["per_frame"]):
    return "'per_frame' holds an entry that is not a frame's metrics"
  if not all(isinstance(v, str) for v in items["names"] + items["excluded"]):
    return "'names' or 'excluded' holds a value that is not a frame name"
  if not all(isinstance(v, int) and not isinstance(v, bool) for v in items["nonfinite_indices"]):
    return "'nonfinite_indices' holds a value that is not a frame index"
  logs = record.get("logs", {}) if "logs" in template else {}
  if not all(isinstance(v, list) and numbers(v) for v in logs.values()):
    return "'logs' holds a value that is not a list of numbers"
  seconds = record.get("seconds", 0.0) if "seconds" in template else 0.0
  if not 0 <= seconds < float("inf"):  # a run's wall time so far (its kind checked above)
    return "'seconds' is not a time (a number >= 0)"
  return None


def _resume_points(directory: Path, fingerprint: str, names: Sequence[str], template: dict
                   ) -> list[tuple[Path, dict]]:
  """This run's checkpoints under `directory`, newest first: the `state_NNNNNN` whose results
  sidecar is readable and says it belongs to this run (`run_fingerprint`, and its frames are the
  first of `names`) and holds what a record of the run holds (`template`,
  `_sidecar_problem`), each with that sidecar; [] when there is no checkpoint. A damaged
  sidecar newer than the one used gets a warning. DataError when there are checkpoints but
  none of this run (another run's: other frames, weights or settings) or none readable."""
  if not directory.is_dir():
    return []
  found, others, damaged, differ = [], 0, [], []
  for path in sorted(directory.glob(CHECKPOINT_PATTERN), reverse=True):
    sidecar = path.parent / f"{path.name}.json"
    if not sidecar.is_file():
      continue  # killed between the state and its sidecar: never used
    try:
      record = json.loads(sidecar.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
      others += 1  # unreadable: an older checkpoint may still be good
      damaged.append(f"{sidecar}: unreadable ({type(e).__name__})")
      continue
    done = record.get("names") if isinstance(record, dict) else None
    if (record.get("fingerprint") if isinstance(record, dict) else None) != fingerprint or \
        not isinstance(done, list) or done != list(names[:len(done)]):
      others += 1
      if not differ and isinstance(record, dict):  # the newest readable one's, for the error
        differ = setting_differences(record.get("settings"), template.get("settings", {}))
      continue
    if len(done) != checkpoint_frames(path):  # a sidecar not of its state's frames
      others += 1
      continue
    problem = _sidecar_problem(record, template)
    if problem is not None:
      others += 1
      damaged.append(f"{sidecar}: {problem}")
      continue
    if damaged and not found:
      print(f"warning: {damaged[0]}; resuming from {path.name} instead", file=sys.stderr)
    found.append((path, record))
  if others and not found:
    why = f"; {damaged[0]}" if damaged else ""
    what = (f"settings differ: {'; '.join(differ[:3])}" + ("; ..." if len(differ) > 3 else "")
            if differ else "another run's frames, weights or settings, or unreadable")
    raise DataError(directory, f"{others} checkpoint(s) here, none of this run ({what}{why}): "
                               f"resume with the interrupted run's command, or run without "
                               f"--resume to start afresh")
  return found


def _load_newest(points: list[tuple[Path, dict]], like) -> tuple[Any, dict] | None:
  """(state, sidecar) of the newest of `points` whose state reads back (a kill during a save
  can leave the newest one damaged: the one before it is used, with a warning); None for no
  points; DataError naming them when none reads."""
  errors = []
  for path, record in points:
    try:
      state = load_state(path, like=like)
    except ValueError as e:  # WeightsError, DataError: unreadable or not this state's shape
      errors.append(str(e))
      continue
    if errors:
      print(f"warning: {errors[0]}; resuming from {path.name} instead", file=sys.stderr)
    return state, record
  if errors:
    raise DataError(points[0][0].parent, f"no checkpoint of this run reads back ({errors[0]}); "
                                         "run without --resume to start afresh")
  return None


def _remove_checkpoint(path: Path) -> None:
  """Removes one checkpoint: its sidecar first (a sidecar without its state is never left)."""
  import shutil
  (path.parent / f"{path.name}.json").unlink(missing_ok=True)
  shutil.rmtree(path) if path.is_dir() else path.unlink()


def record_marks(record):
  """The lengths of every list in a run record (a dict of lists and dicts of lists; a list of
  lists, as a sweep's per-lambda lists, marked item by item): what `truncate_record` cuts back
  to. A list of other items (frame names, metric dicts) is not walked: constant time per call."""
  if isinstance(record, dict):
    return {k: record_marks(v) for k, v in record.items() if isinstance(v, (dict, list))}
  nested = bool(record) and isinstance(record[0], list)
  return len(record), [record_marks(v) for v in record] if nested else []


def truncate_record(record, marks) -> None:
  """Cuts `record` back to `marks` (`record_marks`) in place: what a chunk interrupted while
  being scored added goes, lists and the keys of lists added since (a new log)."""
  if isinstance(record, dict):
    for k in [k for k, v in record.items() if isinstance(v, (dict, list))]:
      if k in marks:
        truncate_record(record[k], marks[k])
      else:
        del record[k]
    return
  n, inner = marks
  del record[n:]
  for v, m in zip(record, inner):  # a list of lists: each cut back too
    truncate_record(v, m)


def complete_checkpoints(directory: str | Path) -> list[Path]:
  """The sidecars of the complete checkpoints under `directory` (a state without its sidecar
  is never used), oldest first."""
  return sorted(Path(directory).glob(CHECKPOINT_PATTERN + ".json"))


def checkpoint_frames(path: Path) -> int:
  """How many frames a checkpoint (`state_NNNNNN`, or its sidecar `state_NNNNNN.json`) has done:
  the number in its name."""
  return int(path.name[len("state_"):len("state_") + 6])


def checkpointed_frames(directory: str | Path) -> int | None:
  """How many frames the newest complete checkpoint under `directory` has done; None without
  one."""
  found = complete_checkpoints(directory)
  return checkpoint_frames(found[-1]) if found else None


def _clear_checkpoints(directory: Path) -> int:
  """Removes the checkpoints a previous run left under `directory` (a fresh run's first step:
  they would otherwise mix with its own), and any save a kill interrupted; returns how many
  complete ones there were."""
  if not directory.is_dir():
    return 0
  complete = len(complete_checkpoints(directory))
  for path in directory.glob(CHECKPOINT_PATTERN):
    _remove_checkpoint(path)
  _remove_leftovers(directory)
  return complete


def _remove_leftovers(directory: Path) -> None:
  """What kills left under `directory`: saves cut short (orbax's temporary directories, in the
  way of the next save of their step) and half-written sidecars."""
  for path in directory.glob(UNFINISHED_PATTERN):
    _remove_checkpoint(path)
  remove_stale_temps(directory)


def load_resume_point(directory: Path, fingerprint: str, names: Sequence[str], like,
                      strict: bool, template: dict) -> tuple[Any, dict] | None:
  """(state, sidecar) of this run's newest checkpoint under `directory` that reads back
  (`fingerprint`, and `names` of the frames from the first: its sidecar's "names" are the
  frames it has done; the sidecar holds what the run's fresh record `template` holds), None
  when there is none. Checkpoints that are not this run's (or none that reads back): DataError
  when `strict`, else removed with a warning (None)."""
  try:
    return _load_newest(_resume_points(directory, fingerprint, names, template), like)
  except DataError:
    if strict:
      raise
    print(f"warning: {directory}: its checkpoints are not this run's (other weights, "
          f"settings or frames, or unreadable); starting afresh", file=sys.stderr)
    _clear_checkpoints(directory)
    return None


def save_checkpoint(directory: Path, state, record: dict,
                    check: Callable[[], Any] | None = None) -> None:
  """The carry (orbax) and every per-frame result so far (JSON sidecar, written last and
  atomically: a state without its sidecar is never used); the record's "names" are the frames
  done, which name the checkpoint (`state_NNNNNN`). check: the caller's test that its folder is
  still its own (`run_sequence`'s check_out), called before anything is written and again once
  both files are, before older checkpoints are pruned: where it raises (the folder was removed
  or replaced during the save), what this save wrote is removed again and nothing is pruned.
  The checkpoint directory itself is made here when missing, never its parent."""
  from pitta_jax.outputs import atomic_write_text, json_safe, removed_while_running
  if check is not None:
    check()
  created = not directory.exists()
  if created and not directory.parent.is_dir():
    raise removed_while_running(directory.parent, "checkpoint_dir's folder")
  directory.mkdir(exist_ok=True)
  path = directory / f"state_{len(record['names']):06d}"
  new = not path.exists()
  try:
    save_state(path, state)
    atomic_write_text(directory / f"{path.name}.json", json.dumps(json_safe(record)[0]))
    if check is not None:
      check()
  except BaseException:  # a full disk, Ctrl-C: the failed save leaves neither a new state
    try:                 # without its sidecar nor, when it was the first, an empty directory
      if new and path.exists():
        _remove_checkpoint(path)
      if created:
        directory.rmdir()  # only when empty: whatever else is there stays
    except OSError:
      pass
    raise
  # the newest KEEP_CHECKPOINTS stay (a full carry each: hundreds of MB for a whole network),
  # and saves a kill interrupted go
  for old in sorted(directory.glob(CHECKPOINT_PATTERN))[:-KEEP_CHECKPOINTS]:
    _remove_checkpoint(old)
  _remove_leftovers(directory)


def run_sequence(weights: Weights, frames: Sequence[Frame], cfg: AdaptConfig,
                 method: Method | None = None, eval_cfg: EvalConfig | None = None,
                 name: str = "", quiet: bool = False, keep: Sequence[int] = (),
                 checkpoint_dir: str | Path | None = None, checkpoint_every: int = 0,
                 runners: Runners | None = None, resume: bool | str = False,
                 resources: dict | None = None,
                 on_start: Callable[[], Any] | None = None,
                 data: dict | None = None,
                 check_out: Callable[[], Any] | None = None) -> RunResult:
  """Runs a method online over `frames` (predict-then-adapt) and evaluates each prediction
  against the frame's ground truth (when it has one).

  A frame whose ground truth has no valid pixel is excluded from the means and named in
  `RunResult.excluded` (the run goes on). A frame whose predicted depth is not finite (the
  method diverged: its parameters are finite but the network overflows) is not scored either; it
  is named in `RunResult.nonfinite` (indices: `nonfinite_indices`), and callers report the run
  as diverged (`RunResult.diverged_at`) rather than its means over the frames that were still
  finite.

  Args:
    weights: the network to adapt (`input_size`: its config's, or for a network that keeps the
      aspect ratio the first frame's).
    frames: the sequence, any length; read lazily chunk by chunk.
    cfg: the run's config; method: the method (default: `cfg.method` with its paper defaults;
      a method given here is what runs, and `cfg.method` is set to its name).
    eval_cfg: how each frame is scored; None: `EvalConfig`'s defaults with the dataset's own
      protocol (a `FrameSequence`'s `evaluation`, e.g. the Garg crop of KITTI's Eigen split, as
      MonoDepth2's evaluate_depth.py scores it), as the commands do where no --eval flag is given.
    keep: frame indices whose predicted depth is returned (for figures).
    checkpoint_dir, checkpoint_every: save the state and the results so far after every K
      frames (exactly: the chunk size becomes a divisor of K), and on Ctrl-C.
    runners: a shared cache of compiled runners (default: a fresh one, compiled for this call).
    resume: continue from the newest checkpoint under `checkpoint_dir` (its frames are not run
      again); the result equals an uninterrupted run's. True: checkpoints of another run (or
      none that reads back) are an error; RESUME_OWN: they are removed, with a warning, and the
      run starts afresh (a cache's checkpoints, e.g. an experiment row's).
    resources: host-side inputs of the method (e.g. ActMAD's source statistics); the input
      size (H, W) is added as `resources["input_size"]`.
    on_start: called once the frames, the method and the checkpoints to resume from are
      checked, before the first step (the CLI removes an earlier run's result files there, so
      that a refused --resume keeps them).
    data: what the frames are beyond their names (JSON values: the dataset flags, the method's
      source data), part of the checkpoints' fingerprint, so that a --resume with other data
      under the same frame names is refused instead of continuing the old run's numbers.
    check_out: with checkpoints, called before `checkpoint_dir` is made and before every save;
      it raises to stop the run when the directory the checkpoints go into was removed or
      replaced meanwhile (a command passes its locked --out's `OutputDir.check`). None: the
      checkpoint directory's folder as it is at the start (`outputs.WatchedDirectory`). A save
      never re-makes a folder removed while the run went on.
  """
  from pitta_jax.outputs import WatchedDirectory
  from pitta_jax.sources import check_frame_needs, check_needs
  if len(frames) == 0:
    raise DataError(name or "sequence", "no frames to adapt on")
  if eval_cfg is None:
    eval_cfg = dataclasses.replace(EvalConfig(), **getattr(frames, "evaluation", {}))
  if method is None:
    method = build_method(cfg.method)
  elif cfg.method != method.name:  # the run, its progress bar and its records name what runs
    cfg = dataclasses.replace(cfg, method=method.name)
  check_needs(method, frames, f"sequence {name!r}" if name else "the sequence")  # before compiling
  if isinstance(frames, FrameSequence):
    frames.check_files()  # a missing or cut-short file found now, not when the run reaches it
  cfg = dataclasses.replace(cfg, chunk_size=checkpoint_chunk_size(cfg.chunk_size,
                                                                  checkpoint_every))
  h, w = input_size(weights, frames)
  model, tx, runner = (runners or Runners()).get(weights, method, cfg)
  alignment = model_alignment(weights) if eval_cfg.alignment == "model" else eval_cfg.alignment
  state, consts = init_state(weights.depth, method, cfg, tx, model,
                             {INPUT_SIZE: (h, w),
                              METRIC_FACTOR: metric_factor(weights.spec, weights.config),
                              **(resources or {})})
  directory = Path(checkpoint_dir) if checkpoint_dir else None
  if directory is not None and checkpoint_every:
    if check_out is not None:
      check_out()  # the caller's folder (a command's locked --out) is never made again here
    # where the checkpoints go is made now: a save re-creates only the checkpoint directory
    # itself, never a parent removed while the run went on (a command's locked --out)
    directory.parent.mkdir(parents=True, exist_ok=True)
  names = None if directory is None else frame_names(frames)
  fingerprint = None if directory is None else run_fingerprint(weights, method, cfg, eval_cfg,
                                                               names, data)
  record = {"per_frame": [], "names": [], "excluded": [], "nonfinite_indices": [],
            "logs": {}, "fingerprint": fingerprint, "seconds": 0.0,
            "settings": run_settings(method, cfg, eval_cfg, data)}
  if directory is not None and resume:
    found = load_resume_point(directory, fingerprint, names, state, strict=resume != RESUME_OWN,
                              template=record)
    if found is not None:
      state, sidecar = found
      record = {**record, **sidecar}  # an older sidecar's missing keys: the fresh record's
      frames = frames[int(state.step):]
    elif resume != RESUME_OWN:  # the user asked to resume: say that there was nothing to resume
      print(f"note: --resume: no checkpoint in {directory}; the run starts at its first frame",
            file=sys.stderr)
    _remove_leftovers(directory)
  elif directory is not None and _clear_checkpoints(directory):
    print(f"warning: {directory}: removed an earlier run's checkpoints (without --resume / "
          f"resume=True a run starts afresh)", file=sys.stderr)
  if on_start is not None:
    on_start()
  watch = None  # opened and closed by the frames' loop below
  start = int(state.step)
  kept: dict[int, np.ndarray] = {}
  keep = set(keep)
  bar = tqdm(total=start + len(frames), initial=start, desc=name or cfg.method, unit="frame",
             disable=quiet)
  t0 = time.perf_counter()
  seconds_before = float(record["seconds"])


  def save(state, elapsed: float) -> None:
    """A checkpoint of `state` with the record, whose time is `elapsed` s of this call."""
    record["seconds"] = seconds_before + elapsed
    save_checkpoint(directory, state, record, check_out)

  # a sequence shorter than a chunk is one chunk of its own length (no padded steps)
  stream = chunks(frames, h, w, min(cfg.chunk_size, max(len(frames), 1)), cfg.max_segments,
                  weights.spec.image_resize, dynamic_classes(method.config))
  chunk_frames: list[list[Frame]] = []

  def inputs():
    for chunk, originals in stream:  # the first chunk is checked before anything compiles
      for frame in originals:
        check_aspect(frame)
        check_frame_needs(method, frame)
      chunk_frames.append(originals)
      yield chunk

  index, last_saved = start, start
  compiles, compile_seconds, compiled_frames = note_compile(bar, runner), 0.0, 0
  chunk_start = time.perf_counter()
  # the newest state whose frames are all in `record`, with the record's lengths then: a
  # Ctrl-C while a chunk is being scored checkpoints this one, not the chunk's half-scored state
  # (and this call's time then: a resumed run does not count the cut chunk's time twice)
  done = (state, record_marks(record), index, 0.0)
  try:
    if directory is not None and checkpoint_every and check_out is None:
      watch = WatchedDirectory(directory.parent, "checkpoint_dir's folder")
      check_out = watch.check
    for state, out in adapt_stream(state, consts, inputs(), runner):
      originals = chunk_frames.pop(0)
      now = _compile_count(runner)
      compiled, compiles = now > compiles, now
      for k, frame in enumerate(originals):
        depth = out.depth[k]
        if index in keep:
          kept[index] = depth
        if not np.isfinite(depth).all():
          record["nonfinite_indices"].append(index)
        elif frame.depth is not None:
          try:
            record["per_frame"].append({"name": frame.name, "index": index, **frame_metrics(
                depth, frame.depth, eval_cfg, alignment)})
          except metrics_lib.NoValidPixels:
            record["excluded"].append(frame.name)
        record["names"].append(frame.name)
        index += 1
      for key, values in [("loss", out.loss), ("skipped", out.skipped),
                          ("grad_norm", out.grad_norm), ("update_norm", out.update_norm),
                          *out.logs.items()]:
        record["logs"].setdefault(key, []).extend(np.asarray(values).tolist())
      # this chunk is complete before its save: a Ctrl-C during the save (which then removes
      # what it wrote) saves it again below, rather than the chunk before or nothing
      done = (state, record_marks(record), index, time.perf_counter() - t0)
      if directory is not None and checkpoint_every and index // checkpoint_every > (
          last_saved // checkpoint_every):
        save(state, done[3])
        last_saved = index
      abs_rels = [m["abs_rel"] for m in record["per_frame"]]
      if compiled:  # this chunk's time (inputs, step, scoring) holds the compile
        compile_seconds += time.perf_counter() - chunk_start
        compiled_frames += len(originals)
      chunk_start = time.perf_counter()
      bar.set_postfix(abs_rel=f"{np.mean(abs_rels) if abs_rels else float('nan'):.4f}",
                      loss=f"{float(np.mean(out.loss)):.3g}", refresh=False)
      bar.update(len(originals))
  except KeyboardInterrupt:
    done_state, marks, done_index, done_elapsed = done
    # the last completed chunk is not lost; unless a second signal cut short the wait for the
    # save it interrupted, whose writer threads go on (a save beside them failed, and its
    # error replaced the interrupt): the checkpoint before it stays the newest then
    if (directory is not None and checkpoint_every and done_index > last_saved
        and not saves_running()):
      truncate_record(record, marks)
      try:
        save(done_state, done_elapsed)
      except Exception:  # the run stops all the same; the command names the newest checkpoint
        pass
    raise
  finally:
    bar.close()
    if watch is not None:
      watch.close()
  seconds = time.perf_counter() - t0
  per_frame = [{k: float("nan") if v is None else v for k, v in m.items()}
               for m in record["per_frame"]]  # {"name", "index", 7 metrics} per scored frame
  logs = {k: np.asarray([np.nan if v is None else v for v in vals])
          for k, vals in record["logs"].items()}
  mean = metrics_lib.mean_metrics(per_frame) if per_frame else {}
  return RunResult(name=name, per_frame=per_frame, mean=mean, logs=logs,
                   frame_names=record["names"], seconds=seconds, kept_depths=kept,
                   n_skipped=int(state.n_skipped), excluded=record["excluded"],
                   resumed_at=start, nonfinite_indices=record["nonfinite_indices"],
                   seconds_before=seconds_before, compile_seconds=compile_seconds,
                   compiled_frames=compiled_frames)


def note_compile(bar, runner) -> int:
  """`_compile_count(runner)`; when it is 0, the progress `bar` says "compiling the step": the
  first chunk waits for the compile (seconds to a minute), with nothing moving before."""
  compiles = _compile_count(runner)
  if not compiles:
    bar.set_postfix_str("compiling the step")
  return compiles


def _compile_count(runner) -> int:
  """How many programs the jitted chunk runner holds (it grows when a call compiles, or loads
  a program from the compilation cache); 0 for a runner that is not a `jax.jit` function."""
  size = getattr(runner, "_cache_size", None)
  return size() if callable(size) else 0
