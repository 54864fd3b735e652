"""What every table command shares: test cases, rows, cached runs, and the command line.

A table is a list of `Entry`s (a row of the paper's table: its group, e.g. the test case, its
label, e.g. the method, and our metrics or the reason it has none), computed by `run_row` for
each (`RowSpec`, `Case`) pair. Each computed row is cached under `OUT/rows/<key>.json`, the key
a hash of everything that determines it (row, test case, dataset and options, weights, size,
frame count, the resolved AdaptConfig, method config and evaluation protocol, `FORMAT`), so a
re-run only computes what changed (a changed library default included) and an
interrupted table resumes: finished rows are read back, and the row that was running resumes
from its last checkpoint (`run_sequence(..., resume=True)`).

Datasets. `--dataset synthetic` (the default) maps the paper's test cases onto the embedded
synthetic driving benchmark (`SYNTHETIC`): DrivingStereo's weather subsets become the
generator's domains on unseen streets; Waymo becomes another camera (mounted higher), faster
and denser traffic, other streets, in moderate rain (`WAYMO_LIKE`). With `--dataset
drivingstereo|waymo --root DIR` the tables run on the real data (`REAL`), read by the project's
readers with the `--option`s and `--segmentation` given.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

# bump when a row's meaning changes: cached rows of another format are recomputed (2: the
# prediction's disparity is resized onto the ground truth; CoMoDa's and Ada-Depth's warp,
# CoTTA's blur as upstream computes them; 3: ActMAD evaluated after its update, Ada-Depth and
# CoMoDa never pair frames of two recordings; 4: a row's per-frame AbsRel holds every frame, a gap
# where one was not scored, and a sweep's lambda that diverges is its own row's status)
FORMAT = 4

# The embedded stand-ins of the paper's datasets (SyntheticConfig fields per part of a case).
TARGET_SEED = 200          # DrivingStereo-like streets (training uses seeds 0..7, the demo 100)
WAYMO_LIKE = dict(seed=300, camera_height=2.1, speed=11.0, n_cars=12.0, n_pedestrians=10.0,
                  domain="rain", severity=0.5)
SYNTHETIC = {
    "Foggy": ({"domain": "fog", "seed": TARGET_SEED},),
    "Rainy": ({"domain": "rain", "seed": TARGET_SEED},),
    "Sunny": ({"domain": "clear", "seed": TARGET_SEED + 1},),
    # "All": cloudy, foggy, rainy, sunny in turn (the paper's order); cloudy = clear street 202
    "All": ({"domain": "clear", "seed": TARGET_SEED + 2}, {"domain": "fog", "seed": TARGET_SEED},
            {"domain": "rain", "seed": TARGET_SEED}, {"domain": "clear", "seed": TARGET_SEED + 1}),
    "Waymo": (WAYMO_LIKE,),
}
SYNTHETIC_CAPTION = {
    "drivingstereo": "synthetic benchmark standing in for DrivingStereo: Foggy = fog, Rainy = rain "
                     "(severity 0.7), Sunny = clear, All = clear, fog, rain, clear in turn (one "
                     "continual run), on unseen streets (seeds 200-202)",
    "waymo": "synthetic benchmark standing in for Waymo: camera 2.1 m high (KITTI: 1.65 m), "
             "11 m/s, denser traffic (12 vehicles, 10 pedestrians per 100 m), rain at "
             "severity 0.5, street seed 300",
}
# The real datasets: the reader options of each part of a case.
REAL = {
    "drivingstereo": {
        "Foggy": ({"weather": "foggy"},), "Rainy": ({"weather": "rainy"},),
        "Sunny": ({"weather": "sunny"},),
        "All": ({"weather": "cloudy"}, {"weather": "foggy"}, {"weather": "rainy"},
                {"weather": "sunny"}),
    },
    "waymo": {"Waymo": ({},)},
}
FRAMES = 50        # frames per part of a case on synthetic (All: 4 parts)
QUICK_FRAMES = 2   # --quick: frames per part (one compile serves every case: same chunk)
QUICK_SIZE = (64, 96)
# frames between a running row's checkpoints (its resume points): a multiple of the chunk size
# (AdaptConfig's 32), which run_sequence would otherwise shrink to gcd(32, K) frames
CHECKPOINT_EVERY = 32
# Table 3's other networks on synthetic: train-source with a shorter recipe than MonoDepth2's
# shipped model (whose 600 x 8 recipe takes about an hour per network on a 2-core CPU)
# (and each network's own learning rate: source_model.NETWORK_LR)
OTHER_NETWORK_SOURCE = dict(steps=250, batch_size=4)


@dataclasses.dataclass(frozen=True)
class RowSpec:
  """One row of a table: a method on a network, with AdaptConfig / method-config changes."""
  label: str                                       # as printed in our table
  method: str = "none"                             # registry name (pitta_jax.methods)
  model: str = "monodepth2"                        # registry name (pitta_jax.models)
  adapt: tuple[tuple[str, Any], ...] = ()          # AdaptConfig changes after the method's own
  method_config: tuple[tuple[str, Any], ...] = ()  # its config's changes
  paper: str | None = None                         # the paper's label of the row (None: ours only)


@dataclasses.dataclass
class Entry:
  """A computed (or not computable) row of a table."""
  group: str
  label: str
  metrics: dict[str, float]
  status: str = "ok"            # ok | needs weights: --weights MODEL=DIR | diverged: ...
  extra: dict[str, Any] = dataclasses.field(default_factory=dict)
  paper: dict[str, float] | None = None
  spec: RowSpec | None = None   # the row's configuration (None for derived rows)
  paper_marks: dict[str, list[str]] | None = None  # the paper's bold / underline metrics


@dataclasses.dataclass
class Context:
  """The table command's arguments, resolved."""
  dataset: str
  root: str | None
  options: list[str]
  segmentation: str
  weights: dict[str, str]       # model -> weights directory ("monodepth2" for a bare --weights)
  out: Path
  quick: bool
  frames: int
  quiet: bool
  source_images: str | None = None
  replay_root: str | None = None
  runners: Any = None           # a `run.Runners` compile cache shared by the rows (None: fresh)
  rows: tuple[str, ...] = ()    # --rows: compute only rows whose labels contain one of these
  eval_cfg: Any = None          # --eval.* flags: the `run.EvalConfig` every row is scored with
  name: str = ""                # the table's name (table1, ..., sensitivity): its files' stem
  # the weights of each model, read once per command (`weights_for`): reading and checking a
  # directory traces the network's init, ~3 s a row at 64x96 on 2 cores, for every row
  loaded: dict[str, Any] = dataclasses.field(default_factory=dict)
  # each model's weights identity (`weights_identity`), hashed once per command, not per row
  identities: dict[str, dict] = dataclasses.field(default_factory=dict)
  files_id: str | None = None   # `files_identity`, once per command
  notes: list[str] = dataclasses.field(default_factory=list)  # for the caption (`check_rows`)
  # raises when --out was removed or replaced since the command locked it (its
  # `OutputDir.check`); None (a Context built by hand): `check_out` tests that it exists
  out_check: Callable[[], Any] | None = None

  def wants(self, label: str, *names: str) -> bool:
    """Whether --rows selects the row `label` (no --rows: every row): a --rows entry that is a
    part of the label, or the whole of one of its other `names` (its method, network, test
    case);
    only a label is matched by parts ('depth' once selected every MonoDepth2 row)."""
    return not self.rows or any(_selects(r, label, names) for r in self.rows)

  def evaluation(self):
    """The protocol the rows are scored with (`run.EvalConfig`; its defaults without flags)."""
    from pitta_jax.run import EvalConfig
    return self.eval_cfg if self.eval_cfg is not None else EvalConfig()

  def cases(self, names: Sequence[str]) -> list[tuple[str, tuple[dict, ...]]]:
    table = SYNTHETIC if self.dataset == "synthetic" else REAL[self.dataset]
    return [(n, table[n]) for n in names]


def adapt_config(method: str, changes: Sequence[tuple[str, Any]] = (), quick: bool = False):
  """AdaptConfig of a row: the method's own setting (`methods.method_setting`), then `changes`
  (--quick: chunks of QUICK_FRAMES frames, so that every test case reuses one compile)."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.methods import method_setting
  extra = {"chunk_size": QUICK_FRAMES} if quick else {}
  return dataclasses.replace(AdaptConfig(method=method),
                             **{**method_setting(method), **dict(changes), **extra})


def method_of(row: RowSpec):
  from pitta_jax.methods import build, method_config_class
  cls = method_config_class(row.method)
  return build(row.method, dataclasses.replace(cls(), **dict(row.method_config)))


# ----------------------------------------------------------------------------- weights


def weights_for(ctx: Context, model: str):
  """The weights of `model`: the user's directory, else on synthetic the cached source model
  (--quick: a seeded random network at QUICK_SIZE, no training); None when only a user
  checkpoint can provide them (a network train-source cannot train, on real data any). Read
  once per command: the rows of a table share them (`Context.loaded`)."""
  if model not in ctx.loaded:
    ctx.loaded[model] = _read_weights(ctx, model)
  return ctx.loaded[model]


def _read_weights(ctx: Context, model: str):
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.models.registry import get_spec
  if model in ctx.weights:
    return load_weights(ctx.weights[model])
  if ctx.dataset != "synthetic" or get_spec(model).output != "sigmoid_disparity":
    return None
  if ctx.quick:
    return _random_weights(ctx.out / "weights" / model, model)
  from pitta_jax.source_model import load_or_train_source, network_source_config
  recipe = {} if model == "monodepth2" else OTHER_NETWORK_SOURCE
  return load_or_train_source(network_source_config(model, **recipe), quiet=ctx.quiet)[0]


def _random_weights(directory: Path, model: str):
  """A seeded random `model` at QUICK_SIZE (with a pose net when it has one), saved once."""
  import jax
  import jax.numpy as jnp
  from pitta_jax.checkpoint import load_weights, save_weights
  from pitta_jax.models.random_init import init_variables
  from pitta_jax.models.registry import get_spec
  if not (directory / "model.json").is_file():
    spec = get_spec(model)
    h, w = QUICK_SIZE
    config = dict(spec.source_config(h, w)) if spec.source_config else {"height": h, "width": w}
    # jitted (op by op, an init compiles each of its hundreds of small ops) from an RBG key
    depth = init_variables(spec.build(config), 0, jnp.zeros((1, h, w, 3)))
    pose = (init_variables(spec.build_pose(config), 1, jnp.zeros((1, h, w, 6)))
            if spec.build_pose else None)
    save_weights(directory, model, config, jax.device_get(depth),
                 None if pose is None else jax.device_get(pose),
                 source={"random_init": 0, "prng": "rbg"})
  return load_weights(directory)


def weights_identity(ctx: Context, model: str, weights) -> dict:
  """What identifies the weights in a row's cache key: where they are, and their model.json
  and values (`source_stats.weights_identity`: the depth network; and the pose network), so
  that weights re-converted or retrained into the same directory are not served the old rows.
  `weights` is `weights_for(ctx, model)`; hashed once per command (`Context.identities`)."""
  if model not in ctx.identities:
    from pitta_jax.source_stats import update_with_tree, weights_identity as depth_identity
    where = (str(Path(ctx.weights[model]).resolve()) if model in ctx.weights
             else "synthetic-source")
    pose = hashlib.sha256()
    if weights.pose is not None:
      update_with_tree(pose, weights.pose)
    ctx.identities[model] = {"model": model, "where": where,
                             "values": depth_identity(weights)[:16],
                             "pose": pose.hexdigest()[:16]}
  return ctx.identities[model]


# ----------------------------------------------------------------------------- frames


def case_frames(ctx: Context, parts: Sequence[dict], height: int, width: int) -> Sequence:
  """The frames of a test case: its parts one after another (one continual run), each part's
  first frame marked as starting a recording (a method never pairs frames of two parts). A real
  dataset's frames stay on disk until the run reaches them (a `FrameSequence`: a case of
  thousands of frames is never decoded at once), the synthetic benchmark's are rendered then."""
  if ctx.dataset == "synthetic":
    from pitta_jax.data.sequence import JoinedFrames
    from pitta_jax.data.synthetic import SyntheticConfig, SyntheticSequence
    return JoinedFrames([SyntheticSequence(SyntheticConfig(height=height, width=width,
                                                           num_frames=ctx.frames, **part))
                         for part in parts])
  from pitta_jax.sources import open_frames
  joined = None
  for part in parts:
    seq = open_frames(ctx.dataset, ctx.root, [*ctx.options, *(f"{k}={v}" for k, v in
                                                             part.items())],
                      ctx.segmentation, height, width)
    seq = seq[:ctx.frames] if ctx.frames else seq
    joined = seq if joined is None else joined + seq  # (+: the part starts a recording)
  return joined if joined is not None else []


def check_cases(ctx: Context, cases: Sequence[tuple[str, Sequence[dict]]]
                ) -> dict[str, list[tuple[str, Any]]]:
  """Opens the reader of every part of `cases` once (paths only, no frame is read): a missing
  or empty part of a real dataset fails before the first row is computed, not after it.
  Returns each case's parts as (how to name it, its reader), for `check_rows`'s needs ({} on
  the synthetic benchmark, whose frames all have K, in capture order)."""
  if ctx.dataset == "synthetic":
    return {}
  from pitta_jax.data.errors import DataError
  from pitta_jax.sources import open_reader
  readers: dict[str, list[tuple[str, Any]]] = {}
  for case, parts in cases:
    for part in parts:
      options = [*ctx.options, *(f"{k}={v}" for k, v in part.items())]
      reader = open_reader(ctx.dataset, ctx.root, options, ctx.segmentation)
      if len(reader) == 0:
        raise DataError(ctx.root, f"test case {case} ({', '.join(options)}): no frames")
      readers.setdefault(case, []).append((f"test case {case} ({', '.join(options)})", reader))
  return readers


def check_flags_used(ctx: Context, rows: Sequence[RowSpec],
                     selected: Sequence[RowSpec] | None = None) -> None:
  """Flags the table's rows cannot use are refused, not ignored: --weights of a network none
  of `rows` runs, and the source-domain flags when no `selected` row's method (default: no
  row's) takes source data."""
  from pitta_jax.data.errors import DataError
  models = list(dict.fromkeys(row.model for row in rows))
  for model, directory in ctx.weights.items():
    if model not in models:
      raise DataError(None, f"--weights {model}={directory}: this table has no {model} row "
                            f"(its networks: {', '.join(models)})")
  given = [flag for flag, value in (("--source-images", ctx.source_images),
                                    ("--replay-root", ctx.replay_root)) if value]
  if given and not any(method_of(row).prepare is not None
                       for row in (rows if selected is None else selected)):
    which = "of this table" if selected is None else "selected"
    raise DataError(None, f"{' and '.join(given)}: no row {which} uses source-domain data "
                          f"(only CoMoDa's and ActMAD's rows do)")


def check_rows(ctx: Context, selected: Sequence[tuple[str, Sequence[dict], RowSpec]]) -> None:
  """Before the first row runs, what the selected (test case, parts, row)s need: no --option
  that a test case sets itself, each test case's frames (`check_cases`), weights for at least
  one row (a table of 'needs weights' only is not a result), each method's pose network and
  source-domain data, a --replay-root that is a KITTI raw root, and each test case's frames as
  its methods need them (K, capture order; from the readers `check_cases` opened). Without this
  a missing need stopped the table at its row, after the rows before."""
  from pitta_jax.data.errors import DataError
  from pitta_jax.sources import check_needs, check_replay_root, no_pose_error, no_source_error
  own = {k for _, parts, _ in selected for part in parts for k in part}
  for item in ctx.options:
    if item.split("=", 1)[0] in own:
      raise DataError(None, f"--option {item}: each test case sets {item.split('=', 1)[0]} "
                            f"itself")
  readers = check_cases(ctx, list({case: parts for case, parts, _ in selected}.items()))
  models = list(dict.fromkeys(row.model for _, _, row in selected))
  if all(weights_for(ctx, model) is None for model in models):
    raise DataError(None, f"no weights for the selected rows: --weights "
                          f"{models[0]}=DIR (on {ctx.dataset} no network is trained for you)")
  methods: dict[tuple[str, str], Any] = {}  # (method, network) -> (its first row, the Method)
  for _, _, row in selected:
    if weights_for(ctx, row.model) is not None and (row.method, row.model) not in methods:
      methods[(row.method, row.model)] = (row, method_of(row))
  for (_, model), (row, method) in methods.items():
    who = f"row {row.label}: {method.name}"
    if "pose" in method.needs and weights_for(ctx, model).pose is None:
      raise no_pose_error(method, who, ctx.weights.get(model))
    if (method.prepare is not None and ctx.dataset != "synthetic"
            and not (ctx.source_images or ctx.replay_root)):
      raise no_source_error(method, who, stats_flag=False)
  if ctx.replay_root:
    check_replay_root([m for _, m in methods.values()], ctx.replay_root)
  no_instances(ctx, selected, readers)
  for case, _, row in selected:  # each test case's frames, as its methods need them
    entry = methods.get((row.method, row.model))
    if entry is not None and entry[1].needs:
      if ctx.frames:  # --frames N (synthetic: always) frames per part, each its own recording
        check_needs(entry[1], [None] * ctx.frames,
                    f"each part of test case {case} (--frames {ctx.frames})")
      for what, reader in readers.get(case, ()):
        check_needs(entry[1], reader, what)
  clear_earlier_table(ctx)


def no_instances(ctx: Context, selected: Sequence[tuple[str, Sequence[dict], RowSpec]],
                 readers: dict[str, list[tuple[str, Any]]]) -> None:
  """A note (stderr and the caption) where a selected row's loss takes the frames' dynamic
  instances but its test case's frames have no panoptic maps under `--segmentation gt`: L_d is
  0 there, PITTA's row is L_e alone (as `pitta-jax adapt` notes), and a method's own use of
  them (CoMoDa's moving-object mask) has none."""
  from pitta_jax.methods.depth_refining import LD_IS_ZERO, instance_uses
  from pitta_jax.sources import lacks_panoptic_maps
  lacking = [(case, row) for case, _, row in selected
             if lacks_panoptic_maps(method_of(row).config, ctx.segmentation,
                                    [reader for _, reader in readers.get(case, ())])]
  if lacking:
    cases = list(dict.fromkeys(case for case, _ in lacking))
    uses = dict.fromkeys(use for _, row in lacking for use in instance_uses(method_of(row).config))
    said = [f"{LD_IS_ZERO} in PITTA's and the '+ L_d' rows" if use == LD_IS_ZERO else use
            for use in uses]
    note = (f"{ctx.dataset} has no panoptic maps in test case {', '.join(cases)}: no frame has "
            f"instances, so {' and '.join(said)} (--segmentation png:DIR or mask2former:DIR).")
    print(f"note: {note}", file=sys.stderr)
    ctx.notes.append(note)


def clear_earlier_table(ctx: Context) -> None:
  """Once the table's checks passed, before its first row: the earlier NAME.md/.csv/.tex,
  results.json and figures in --out go (with a warning), so that a rerun interrupted on the way
  leaves no earlier table that could pass for its own; its cached rows (rows/) stay and are
  reused."""
  from pitta_jax.report import TABLE_SUFFIXES, clear_earlier_results
  clear_earlier_results(ctx.out, (f"figures/{ctx.name}_*.png",),
                        files=tuple(f"{ctx.name}{s}" for s in TABLE_SUFFIXES) + ("results.json",))


def _selects(entry: str, label: str, names: Sequence[str]) -> bool:
  """Whether the --rows entry selects the row `label` with its other `names` (`Context.wants`)."""
  return entry.lower() in label.lower() or any(entry.lower() == n.lower() for n in names)


def check_selection(ctx: Context, selected: Sequence, labels: Sequence[str],
                    candidates: Sequence[Sequence[str]]) -> None:
  """--rows that selects nothing is an error (an empty table is not a result), and so is each
  entry that selects none of `candidates` (every row's label and other names, as given to
  `Context.wants`): a misspelt name beside a good one would leave its rows out unsaid."""
  from pitta_jax.data.errors import DataError
  unmatched = [r for r in ctx.rows if not any(_selects(r, c[0], c[1:]) for c in candidates)]
  if ctx.rows and (not selected or unmatched):
    raise DataError(None, f"--rows {','.join(unmatched or ctx.rows)}: matches none of this "
                          f"table's rows ({', '.join(dict.fromkeys(labels))})")


# ----------------------------------------------------------------------------- rows


def row_key(ctx: Context, row: RowSpec, case: str, parts, weights_id: dict) -> str:
  """The cache key of a row's result: a hash of the row, the test case, the data, the weights,
  the frame count, the configurations it resolves to (the AdaptConfig with the method's
  setting, the method's config, the evaluation protocol) and a preparing method's source data,
  so that a changed library default or --source-images recomputes the rows it changes instead
  of serving them from the cache."""
  from pitta_jax.methods import method_config_class
  # the method config's defaults (the row's changes are in `row`; a sweep's are not one config)
  resolved = {"adapt": dataclasses.asdict(adapt_config(row.method, row.adapt, ctx.quick)),
              "method": dataclasses.asdict(method_config_class(row.method)()),
              "eval": dataclasses.asdict(ctx.evaluation())}
  # the source-domain data of a method that prepares from it (ActMAD's statistics, CoMoDa's
  # replay): another --source-images or --replay-root is another row (only there, so that the
  # other rows stay cached); the method by its name, with its default config: a sweep's row
  # holds all its values in one field (Table 4's 12 lambdas), which no single config takes
  from pitta_jax.methods import build
  if build(row.method).prepare is not None:
    resolved["source"] = [str(Path(p).resolve()) if p else None
                          for p in (ctx.source_images, ctx.replay_root)]
  text = json.dumps({"format": FORMAT, "row": dataclasses.asdict(row), "case": case,
                     "parts": parts, "dataset": ctx.dataset,
                     "root": str(Path(ctx.root).resolve()) if ctx.root else None,
                     "options": sorted(ctx.options), "segmentation": ctx.segmentation,
                     "files": files_identity(ctx), "weights": weights_id, "frames": ctx.frames,
                     "resolved": resolved},
                    sort_keys=True, default=str)
  return hashlib.sha256(text.encode()).hexdigest()[:20]


def files_identity(ctx: Context) -> str:
  """What the rows read besides the depth weights, as a digest of every file's path, size and
  modification time under --root and the --segmentation directory (png:DIR's maps,
  mask2former:DIR's weights; --out left out): re-segmented maps, re-exported ground truth or
  added images under the same paths are not served the old rows. Once per command."""
  if ctx.files_id is None:
    from pitta_jax.sources import parse_segmentation
    kind, arg = parse_segmentation(ctx.segmentation)
    roots = [r for r in (ctx.root if ctx.dataset != "synthetic" else None,
                         arg if kind != "gt" else None) if r]
    out = ctx.out.resolve() if ctx.out else None
    digest = hashlib.sha256()
    for root in roots:
      root = Path(root).resolve()
      for directory, dirs, files in os.walk(root):
        here = Path(directory)
        dirs[:] = sorted(d for d in dirs if out is None or (here / d).resolve() != out)
        for name in sorted(files):
          try:
            st = (here / name).stat()
          except OSError:  # a dangling link: its name is all there is
            st = None
          digest.update(f"{(here / name).relative_to(root)}\0"
                        f"{st and st.st_size}\0{st and st.st_mtime_ns}\n".encode())
      digest.update(f"{root}\n".encode())
    ctx.files_id = digest.hexdigest()[:16]
  return ctx.files_id


def _metric_values(x: Any) -> bool:
  """A stored row's metrics: none, or every metric's name -> a number (None for a non-finite
  one)."""
  from pitta_jax.metrics import METRIC_NAMES
  from pitta_jax.outputs import json_number
  return isinstance(x, dict) and (not x or set(x) == set(METRIC_NAMES)) and all(
      map(json_number, x.values()))


def _per_frame_values(x: Any) -> bool:
  from pitta_jax.outputs import json_number
  return isinstance(x, list) and all(map(json_number, x))


# a stored result's counts and times (numbers or None where present; a sweep's entries need
# "frames", which the table shows)
NUMBER_FIELDS = ("frames", "seconds", "fps", "steady_fps", "compile_seconds", "n_skipped")


def stored_result(stored: Any, field: str, length: int | None = None) -> bool:
  """Whether a row file's content is a result of its kind: a row's ("metrics": its metrics,
  all of them where its status is ok, its per-frame AbsRel, metrics before divergence, counts
  and times where present) or a lambda sweep's ("sweep": one such result per lambda, `length`
  of them, each with its frame count). A hand-edited file of the wrong kinds was served to the
  table: cells left blank under an ok status, a sweep cut short shown as complete, or a failure
  at its rendering naming no file."""
  from pitta_jax.outputs import json_number
  if not isinstance(stored, dict):
    return False
  results = stored.get(field)
  if field == "metrics":
    results = [stored]
  if not isinstance(results, list) or not results or (
      length is not None and len(results) != length):
    return False
  return all(isinstance(r, dict) and _metric_values(r.get("metrics"))
             and (r.get("status", "ok") != "ok" or bool(r["metrics"]))
             and (r.get("metrics_before_divergence") is None
                  or _metric_values(r["metrics_before_divergence"]))
             and _per_frame_values(r.get("abs_rel_per_frame", []))
             and isinstance(r.get("status", ""), str)
             and all(json_number(r[k]) for k in NUMBER_FIELDS if k in r)
             and (field != "sweep" or (isinstance(r.get("frames"), int)
                                       and "abs_rel_per_frame" in r)) for r in results)


def check_out(ctx: Context) -> None:
  """OutputError when --out was removed or replaced while the command ran: a row written now
  (or its checkpoints) would go to a directory without the command's lock."""
  from pitta_jax.outputs import removed_while_running
  if ctx.out_check is not None:
    ctx.out_check()
  elif not ctx.out.is_dir():
    raise removed_while_running(ctx.out)


def cached(ctx: Context, key: str, compute: Callable[[], dict], field: str = "metrics",
           length: int | None = None) -> dict:
  """The row result stored under `key`, computed (and stored atomically) when absent or not a
  result (`stored_result`: a row's "metrics", a lambda sweep's "sweep" of `length` entries),
  with a warning then."""
  from pitta_jax.outputs import atomic_write_text, json_safe
  path = ctx.out / "rows" / f"{key}.json"
  if path.is_file():
    try:
      stored = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
      stored = None  # a torn file cannot exist (atomic writes); a hand-edited one is recomputed
    if stored_result(stored, field, length):
      return stored
    print(f"warning: {path}: not a stored row result (edited or damaged); computing the row "
          f"again", file=sys.stderr)
  check_out(ctx)
  result = compute()
  check_out(ctx)
  path.parent.mkdir(exist_ok=True)
  atomic_write_text(path, json.dumps(json_safe(result)[0], indent=1) + "\n")
  return result


def run_row(ctx: Context, row: RowSpec, case: str, parts, runners, resources: dict) -> Entry:
  """One row on one test case (cached): the method adapting online over the case's frames."""
  from pitta_jax.outputs import rounded_or_none
  from pitta_jax.run import RESUME_OWN, run_sequence
  from pitta_jax.sources import method_resources
  weights = weights_for(ctx, row.model)
  if weights is None:
    return Entry(case, row.label, {}, status=f"needs weights: --weights {row.model}=DIR",
                 spec=row)
  key = row_key(ctx, row, case, parts, weights_identity(ctx, row.model, weights))

  def compute() -> dict:
    method = method_of(row)
    cfg = adapt_config(row.method, row.adapt, ctx.quick)
    frames = case_frames(ctx, parts, weights.height, weights.width)
    res_key = (row.model, row.method, method.config)
    if res_key not in resources:
      resources[res_key] = method_resources(method, weights, ctx.dataset, ctx.source_images,
                                            ctx.replay_root, quiet=ctx.quiet)
    ckpt = checkpoints(ctx, key, f"{case}: {row.label}")
    res = run_sequence(weights, frames, cfg, method, ctx.evaluation(),
                       name=f"{case}: {row.label}", quiet=ctx.quiet, runners=runners,
                       resources=resources[res_key], checkpoint_dir=ckpt,
                       checkpoint_every=CHECKPOINT_EVERY if ckpt else 0, resume=RESUME_OWN,
                       check_out=lambda: check_out(ctx))
    return {"metrics": res.mean if res.status == "ok" else {}, "status": res.status,
            "metrics_before_divergence": res.mean if res.status != "ok" else None,
            "frames": len(frames), "seconds": round(res.total_seconds, 2),
            "fps": rounded_or_none(res.total_fps, 3),
            "steady_fps": rounded_or_none(res.steady_fps, 3),
            "compile_seconds": round(res.compile_seconds, 2), "n_skipped": res.n_skipped,
            "abs_rel_per_frame": res.per_frame_series("abs_rel"),  # NaN: a frame not scored
            "adapt": dataclasses.asdict(cfg), "method_config": dataclasses.asdict(method.config)}

  result = cached(ctx, key, compute)
  remove_checkpoints(ctx, key)
  return Entry(case, row.label, result["metrics"], spec=row, status=result.get("status", "ok"),
               extra={**{k: result.get(k) for k in (
                   "frames", "seconds", "fps", "steady_fps", "compile_seconds", "n_skipped",
                   "abs_rel_per_frame",
                   "metrics_before_divergence", "adapt", "method_config")}, "row_key": key})


ROW_OF_CHECKPOINTS = "row.txt"  # in a row's checkpoint folder: which table row it is


def checkpoints(ctx: Context, key: str, row: str) -> Path | None:
  """Where the row (or sweep) `key` keeps its checkpoints while it runs (None with --quick:
  none), made now with `row` (the row's case and label) written in it: the checkpoints of a
  run whose settings (--frames, the weights, ...) gave the same row another key are then known
  for that row's, and go when it is stored (`remove_checkpoints`)."""
  if ctx.quick:
    return None
  from pitta_jax.outputs import atomic_write_text
  directory = _checkpoint_dir(ctx, key)
  check_out(ctx)  # not under an --out removed meanwhile (no parents made)
  directory.parent.mkdir(exist_ok=True)
  directory.mkdir(exist_ok=True)
  atomic_write_text(directory / ROW_OF_CHECKPOINTS, f"{ctx.name}/{row}\n")
  return directory


def _checkpoint_dir(ctx: Context, key: str) -> Path:
  return ctx.out / "rows" / f"{key}.ckpt"


def remove_checkpoints(ctx: Context, key: str) -> None:
  """The row's checkpoints, once its result is stored, and those an earlier run left for the
  same row under another key (its settings changed: they would never be resumed)."""
  import shutil
  directory = _checkpoint_dir(ctx, key)
  row = _row_of(directory)
  for other in directory.parent.glob("*.ckpt") if directory.parent.is_dir() else ():
    if other == directory or (row is not None and other.is_dir() and _row_of(other) == row):
      shutil.rmtree(other, ignore_errors=True)


def _row_of(directory: Path) -> str | None:
  """The row a checkpoint folder is for (`checkpoints`), None where it does not say."""
  try:
    return (directory / ROW_OF_CHECKPOINTS).read_text()
  except (OSError, UnicodeDecodeError):
    return None


def attach_paper(entries: Sequence[Entry], table: int,
                 fields_of: Callable[[Entry], dict[str, Any] | None]) -> None:
  """Puts the paper's numbers beside ours: entry `e` gets the values of the one row of the
  paper's Table `table` whose descriptors (`experiments.paper` schema: test_case, method,
  network, lambda, cnn_percent, bn_percent) equal `fields_of(e)` (None: the paper has no such
  row)."""
  from experiments.paper import load_paper_table
  rows = load_paper_table(table)["rows"]
  for e in entries:
    want = fields_of(e)
    if want is None:
      continue
    hits = [r for r in rows if all(r.get(k) == v for k, v in want.items())]
    if len(hits) == 1:
      e.paper = dict(hits[0]["values"])
      e.paper_marks = {"bold": list(hits[0]["bold"]), "underline": list(hits[0]["underline"])}


def paper_fields(e: Entry, with_case: bool = True) -> dict[str, Any] | None:
  """The paper-row descriptors of an entry computed from a `RowSpec` (None for rows the paper
  does not have)."""
  if e.spec is None or not e.spec.paper:
    return None
  fields = {"method": e.spec.method, "network": e.spec.model}
  if with_case:
    fields["test_case"] = e.group.lower()
  return fields


# ----------------------------------------------------------------------------- command line


def parser(name: str, description: str,
           datasets: Sequence[str] = ("synthetic", "drivingstereo"),
           rows: bool = True, frames: int = FRAMES,
           quick_frames: int = QUICK_FRAMES) -> argparse.ArgumentParser:
  """The table command's parser; `rows`: whether it takes --rows (a table of rows); `frames`,
  `quick_frames`: the frames per part it runs on synthetic without --frames (for its --help)."""
  from pitta_jax.config_cli import ArgumentParser
  p = ArgumentParser(prog=command_name(name), description=description)
  add_arguments(p, datasets, rows, frames, quick_frames)
  return p


def command_name(name: str, argv0: str | None = None) -> str:
  """How the user started experiment `name` (`argv0`: sys.argv[0]), for its usage and errors:
  `python -m experiments NAME`, `python -m experiments.NAME`, else `pitta-jax experiment NAME`."""
  path = Path(sys.argv[0] if argv0 is None else argv0)
  if path.parent.name == "experiments" and path.name == "__main__.py":
    return f"python -m experiments {name}"
  if path.parent.name == "experiments" and path.name == f"{name}.py":
    return f"python -m experiments.{name}"
  return f"pitta-jax experiment {name}"


def add_arguments(p: argparse.ArgumentParser, datasets: Sequence[str] = ("synthetic",
                                                                         "drivingstereo"),
                  rows: bool = True, frames: int = FRAMES,
                  quick_frames: int = QUICK_FRAMES) -> None:
  # a command on the synthetic benchmark alone still parses the real-data flags, to refuse them
  # in one line (`context`), but does not offer them in its --help
  real = any(d != "synthetic" for d in datasets)

  def real_only(text: str) -> str:
    return text if real else argparse.SUPPRESS

  p.add_argument("--dataset", default="synthetic", choices=list(datasets),
                 help="synthetic (default: the embedded benchmark, see the caption) or the real "
                      "dataset at --root" if real else "synthetic: the embedded benchmark (the "
                      "only dataset of this study)")
  p.set_defaults(dataset_choices=tuple(datasets))
  p.add_argument("--root", help=real_only("dataset root (real datasets)"))
  p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                 help=real_only("reader option, passed to every part of every test case "
                                "(repeatable)"))
  p.add_argument("--segmentation", default="gt",
                 help=real_only("panoptic input: gt | png:DIR | mask2former:DIR (as `pitta-jax "
                                "adapt`)"))
  p.add_argument("--weights", action="append", default=[], metavar="[MODEL=]DIR",
                 help="converted weights; a bare DIR is MonoDepth2's, MODEL=DIR another network's "
                      "(e.g. depth_anything_v2=DIR, for a table with its rows); repeatable")
  p.add_argument("--source-images", help=real_only("source-domain images for ActMAD's "
                                                    "statistics (real data)"))
  p.add_argument("--replay-root", help=real_only("KITTI raw root for CoMoDa's replay (real data)"))
  p.add_argument("--frames", type=int, default=None,
                 help=f"frames per part of a test case (synthetic default {frames}"
                      + ("; real: all)" if real else ")"))
  p.add_argument("--quick", action="store_true",
                 help=f"a tiny run for trying and testing: {quick_frames} frames per part, "
                      f"random {QUICK_SIZE[1]}x{QUICK_SIZE[0]} networks on synthetic")
  if rows:
    p.add_argument("--rows", default="",
                   help="comma-separated row names (or parts of them, case-insensitive), "
                        "or whole method, network or test case names (e.g. Foggy): compute "
                        "only these rows, e.g. --rows 'No adaptation,PITTA' (default: all); "
                        "an entry that selects no row is an error")
  from pitta_jax.config_cli import add_config_arguments
  from pitta_jax.run import EvalConfig
  add_config_arguments(p, EvalConfig, "eval", "evaluation (every row of the table)")
  p.add_argument("--out", default=None, help="output directory (default experiments_out/NAME)")
  p.add_argument("--quiet", action="store_true",
                 help="no progress bars and no table on the terminal (NAME.md has it)")
  p.add_argument("--debug", action="store_true", help="full tracebacks")


def _dataset_choices(args: argparse.Namespace) -> tuple[str, ...]:
  """The --dataset values this command's parser offers (`add_arguments`)."""
  return tuple(getattr(args, "dataset_choices", ("synthetic", "drivingstereo")))


def context(args: argparse.Namespace, name: str, runners: Any = None) -> Context:
  """Validates the arguments before any work; DataError / ValueError name the flag.
  runners: a compile cache to share with other tables run in the same process."""
  from pitta_jax.data.errors import DataError
  from pitta_jax.models.registry import MODELS
  from pitta_jax.sources import check_unique_options, parse_segmentation
  if args.dataset != "synthetic" and not args.root:
    raise DataError(None, f"--dataset {args.dataset} needs --root DIR")
  if args.dataset == "synthetic" and args.root:
    real = [c for c in _dataset_choices(args) if c != "synthetic"]
    raise DataError(None, "--root is for real datasets: " + (
        f"add --dataset {'|'.join(real)}" if real else f"{name} runs on the synthetic benchmark "
                                                       f"only"))
  if args.root and not Path(args.root).is_dir():
    raise DataError(args.root, "--root: not a directory")
  parse_segmentation(args.segmentation)
  check_unique_options(args.option)
  if args.dataset == "synthetic":  # flags for real data only: refused, not silently ignored
    given = [f for f, v in (("--source-images", args.source_images),
                            ("--replay-root", args.replay_root)) if v]
    if given:
      raise DataError(None, f"{', '.join(given)}: for real datasets only (the synthetic "
                            "benchmark brings its own source data)")
    if args.option:  # the stand-ins' streets, shifts and sizes are the table's (SYNTHETIC)
      raise DataError(None, f"--option {args.option[0]}: for real datasets' readers only (the "
                            f"synthetic stand-ins of the test cases are fixed: docs/experiments.md)")
    from pitta_jax.sources import check_dataset_args
    check_dataset_args("synthetic", None, list(args.option), args.segmentation)
  else:
    from pitta_jax.predict import expand_images
    if args.source_images:
      try:
        expand_images(args.source_images, unique_stems=False)
      except DataError as e:
        raise DataError(None, f"--source-images {e}") from None
    if args.replay_root and not Path(args.replay_root).is_dir():
      raise DataError(args.replay_root, "--replay-root: not a directory")
  weights: dict[str, str] = {}
  for item in args.weights:
    # NAME=DIR splits at the first '=' (no network's name has one), so that a DIR may hold one
    # (`runs/lam=0.5/w`); an existing directory whose name holds '=' is a bare DIR
    model, sep, directory = item.partition("=")
    if not sep or (model not in MODELS and Path(item).is_dir()):
      model, sep, directory = "", "", item
    if sep and not model:
      raise DataError(None, f"--weights {item}: no network before '=' (NAME=DIR, or DIR alone "
                            f"for a monodepth2)")
    if not directory.strip():
      raise DataError(None, f"--weights {item}: no directory (NAME=DIR, or DIR alone for a "
                            f"monodepth2)")
    model = model or "monodepth2"
    if model in weights:  # (the last one had silently won)
      raise DataError(None, f"--weights {item}: {model} weights given twice ({weights[model]} "
                            f"and {directory}): one directory per network")
    if model not in MODELS:
      raise DataError(None, f"--weights {item}: unknown network {model!r} "
                            f"(use {', '.join(MODELS)})")
    if not (Path(directory) / "model.json").is_file():
      raise DataError(directory, "--weights: no model.json (convert with `pitta-jax convert`)")
    from pitta_jax.checkpoint import read_model_json
    held = read_model_json(directory)[0].name
    if held != model:
      raise DataError(None, f"--weights {item}: the directory holds a {held}, not a "
                                 f"{model}" + ("" if sep else
                                               f" (write --weights {held}=DIR)"))
    weights[model] = directory
  if args.frames is not None and args.frames < 1:
    raise DataError(None, f"--frames must be >= 1, got {args.frames}")
  frames = args.frames or (QUICK_FRAMES if args.quick else (FRAMES if args.dataset == "synthetic"
                                                            else 0))
  if args.dataset == "synthetic":
    check_synthetic_frames(frames)
  if args.out is not None and not str(args.out).strip():  # (Path("") is the working directory)
    raise DataError(None, "--out: an empty path")
  out = Path(args.out if args.out is not None else Path("experiments_out") / name)
  try:  # (exists() itself raises for a name too long)
    if out.exists() and not out.is_dir():
      raise DataError(None, f"--out {out}: exists and is not a directory")  # as open_output_dir
  except OSError as e:
    raise DataError(None, f"--out {out}: cannot write there ({e.strerror or e})") from None
  from pitta_jax.config_cli import config_from_args
  from pitta_jax.run import EvalConfig
  eval_cfg = config_from_args(EvalConfig, args, "eval")
  from pitta_jax.outputs import open_output_dir
  text = getattr(args, "rows", "")
  rows = tuple(r.strip() for r in text.split(",") if r.strip())
  if text.strip() and not rows:
    raise DataError(None, f"--rows {text!r}: no row name in it (comma-separated labels)")
  # created, proved writable and locked before any row runs; `main_wrapper` releases it
  held = open_output_dir(out, "--out")
  vars(args).setdefault("open_outputs", []).append(held)
  from pitta_jax.report import check_results_owner
  check_results_owner(out, f"experiment {name}")
  return Context(args.dataset, args.root, list(args.option), args.segmentation, weights, out,
                 args.quick, frames, args.quiet, args.source_images, args.replay_root,
                 runners, rows, eval_cfg=eval_cfg, name=name, out_check=held.check)


def check_synthetic_frames(frames: int) -> None:
  """DataError naming --frames when a synthetic test case's part of `frames` frames drives
  beyond the street the renderer draws exactly (`SyntheticConfig`'s limit), before any work."""
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.synthetic import SyntheticConfig
  for part in {repr(p): p for parts in SYNTHETIC.values() for p in parts}.values():
    try:
      SyntheticConfig(height=QUICK_SIZE[0], width=QUICK_SIZE[1], num_frames=frames, **part)
    except ValueError as e:
      raise DataError(None, f"--frames {frames}: {str(e).removeprefix('num_frames: ')}") from None


def main_wrapper(run: Callable[..., int], p: argparse.ArgumentParser,
                 argv: Sequence[str] | None, runners: Any = None) -> int:
  """Parses, runs, and turns an expected error into one line and exit 2 (tracebacks with
  --debug). Compiled steps persist under the cache root (`source_model.cache_root`, as
  `pitta-jax demo`), so another table or row at the same shapes loads them instead of
  compiling again.
  runners: an in-process compile cache shared with other tables of the same process."""
  from pitta_jax.cli import exit_status, report_error, say_stopped, terminate_as_interrupt
  from pitta_jax.outputs import OutputError
  from pitta_jax.source_model import enable_compilation_cache, repairing_compilation_cache
  args = p.parse_args(argv)
  failed = True
  try:
    enable_compilation_cache()  # the command's choice: a later run skips the step compiles
    # SIGTERM stops as Ctrl-C (also under python -m); a damaged cached program is removed
    with terminate_as_interrupt(), repairing_compilation_cache():
      status = run(args, runners)
    failed = False
    return status
  except Exception as e:
    return report_error(e, args.debug, (OutputError,))
  except KeyboardInterrupt as e:
    say_stopped("interrupted: finished rows are cached; run the same command again to resume")
    return exit_status(e)  # as the pitta-jax commands
  finally:  # the --out lock (`context`); a failed command leaves no directory it created
    for output in vars(args).pop("open_outputs", []):
      output.__exit__(RuntimeError if failed else None, None, None)


def timer() -> Callable[[], float]:
  t0 = time.perf_counter()
  return lambda: time.perf_counter() - t0


def load_average() -> str:
  try:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())
  except OSError:
    return "n/a"


def caption_notes(ctx: Context) -> str:
  """What a table's caption must add about this run: --quick's random networks (not results),
  the user's weights, a --rows subset (the other rows are not in these files)."""
  notes = []
  if ctx.quick:
    nets = ("the networks without --weights: seeded random" if ctx.weights
            else "seeded random")
    notes.append(f"--quick: {nets} {QUICK_SIZE[1]}x{QUICK_SIZE[0]} networks, "
                 f"{ctx.frames} frames per part: a test of the pipeline, not results.")
  if ctx.weights:
    notes.append("Weights: " + ", ".join(f"{m}={d}" for m, d in sorted(ctx.weights.items()))
                 + ".")
  if ctx.rows:
    notes.append(f"Only the rows selected by --rows {','.join(ctx.rows)}.")
  return " ".join(notes + ctx.notes)


# how a prediction is aligned to the ground truth, per `run.EvalConfig.alignment`
ALIGNMENT_NOTES = {
    "model": ("the prediction aligned as its network needs: median scaling (x5.4 instead for "
              "weights trained with stereo pairs); for Depth Anything V2 a least-squares scale "
              "and shift in inverse depth (two numbers fitted per frame, against the median's "
              "one)"),
    "median": "every prediction median-scaled (--eval.alignment median)",
    "scale_shift": ("every prediction aligned by a least-squares scale and shift in inverse "
                    "depth (--eval.alignment scale_shift)"),
    "stereo": "every prediction multiplied by 5.4 (--eval.alignment stereo)",
    "none": "the prediction taken as metres, unaligned (--eval.alignment none)",
}


def evaluation_note(ev) -> str:
  """How every row of a table scores a frame (`run.EvalConfig` `ev`), for its caption."""
  # the mask is open, min < gt < max (MonoDepth2's); the prediction's clamp is closed
  pixels = (f"ground truth in ({ev.min_depth:g}, {ev.max_depth:g}) m, predictions clamped to "
            f"[{ev.min_depth:g}, {ev.max_depth:g}] m" if ev.valid_gt == "range"
            else f"ground truth > 0 (--eval.valid-gt positive; predictions clamped to "
                 f"[{ev.min_depth:g}, {ev.max_depth:g}] m)")
  crop = "inside the Garg crop" if ev.garg_crop else "no crop"
  resize = "" if ev.resize == "disparity" else ", the depth map (not the disparity) resized"
  return f"Scored per frame on {pixels}, {crop}{resize}, {ALIGNMENT_NOTES[ev.alignment]}."


def units_note(ctx: Context, entries: Sequence[Entry]) -> str:
  """Ada-Depth's thresholds are in metres: on weights up to scale (monocular training, no
  factor to metres: `run.metric_factor`) its rows take the depth as metres, which the caption
  must say (`pitta-jax adapt` prints the same as a note)."""
  from pitta_jax.run import metric_factor
  models = {e.spec.model for e in entries if e.spec is not None and e.spec.method == "adadepth"
            and e.status == "ok"}
  scaled = sorted(m for m in models if (w := weights_for(ctx, m)) is not None
                  and metric_factor(w.spec, w.config) is None)
  if not scaled:
    return ""
  return (f"Ada-Depth's thresholds are in metres, and the {', '.join(scaled)} weights are up to "
          f"scale (monocular training): its rows take their depth as metres.")


def meta(ctx: Context) -> dict:
  """What results.json records about the command besides the rows."""
  import platform
  return {"dataset": ctx.dataset, "root": ctx.root, "options": ctx.options,
          "segmentation": ctx.segmentation, "weights": ctx.weights, "quick": ctx.quick,
          "eval": {**dataclasses.asdict(ctx.evaluation()),
                   "note": evaluation_note(ctx.evaluation())},
          "frames_per_part": ctx.frames, "rows_selected": list(ctx.rows),
          "load": f"load average {load_average()}",
          "machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "format": FORMAT}


def runners(ctx: Context):
  """The context's compile cache (a fresh one when none was given)."""
  from pitta_jax.run import Runners
  if ctx.runners is None:
    ctx.runners = Runners()
  return ctx.runners
