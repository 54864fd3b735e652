"""The source model of the embedded benchmark: a depth network trained on clear synthetic frames.

MonoDepth2 ResNet-18 by default; `--source.model` trains any registered network whose output is
a sigmoid disparity (the MonoDepth2 family: SGDepth, HR-Depth, Lite-Mono, MonoViT). Depth
Anything V2 is a ViT trained on millions of images: it runs from a user's checkpoint only.


No pretrained weights can be downloaded, so `pitta-jax demo` trains its own source network once
(from scratch, no ImageNet initialisation) with a supervised depth loss on the `clear` domain of
the synthetic driving benchmark, at a reduced size, and caches it under the user cache dir keyed
by a hash of the config. This stands in for "MonoDepth2 pretrained on KITTI" of the paper.

Loss: mean |log D_s - log D_gt| over valid ground-truth pixels, for the 4 output scales each
upsampled (nearest) to the input size, D_s = disp_to_depth(disp_s) — a supervised version of
MonoDepth2's multi-scale training. BatchNorm runs in train mode and updates its running
statistics (momentum 0.1), as MonoDepth2's training does.

The pose network (`pitta_jax.models.pose.PoseNet`, for the pose-based baselines CoMoDa and
Ada-Depth) is trained beside it, supervised by the generator's exact camera motion: the camera
of frame n sits at world (x0, h, speed * n / fps), axes aligned with the straight road, so from
frame a to frame b the camera translates by (b - a) * speed / fps metres along its optical axis
and never rotates (`camera_motion`). MonoDepth2's convention (`trainer.predict_poses`) is kept:
for a pair stacked (first, second) the net's `transformation_from_parameters(axisangle[:, 0],
translation[:, 0], invert=False)` is the motion T mapping points of the first camera to the
second (upstream passes frames in temporal order and inverts for frame -1, so T maps target to
source as `pitta_jax.sfm.project` expects). Loss: sum over the 12 entries of the top 3x4 block
of |T_pred - T_true|, batch mean. Pairs are 1..pose_max_gap frames apart, in temporal order,
with the depth net's flips (a flip conjugates T by diag(-1, 1, 1, 1)) and brightness jitter
shared by both frames. On this benchmark every adjacent pair has the same motion (0.8 m
forward by default), so with the default gap of 1 the net mostly learns that motion; larger
gaps make it read the magnitude from the images.

A model trained with the default `SourceConfig` ships with the package (`assets/`, float16
parameters, written by `pitta-jax train-source --ship`): `load_or_train_source` copies it into
the cache on first use instead of training; without the file it trains, as for any config.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import hashlib
import io
import json
import math
import os
import re
import sys
import time
import warnings
from functools import partial
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from pitta_jax.checkpoint import Weights, load_weights, save_weights
from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
from pitta_jax.configs import check, check_seed, check_types, finite, option
from pitta_jax.models.depth_decoder import disp_to_depth
from pitta_jax.models.pose import transformation_from_parameters
from pitta_jax.outputs import atomic_write_files, atomic_write_text
from pitta_jax.models.random_init import jit_init
from pitta_jax.nonsmooth import absolute
from pitta_jax.prng import seed_key

CACHE_ENV = "PITTA_JAX_CACHE"
# Bump when the training recipe changes, so old caches are not reused. 2: the pose network is
# trained too (a format-1 cache holds the depth network alone; its key is never looked up again).
FORMAT_VERSION = 2
ASSETS = Path(__file__).resolve().parent / "assets"  # shipped source models (package data)
FLIP = np.diag([-1.0, 1.0, 1.0, 1.0])  # a horizontal image flip in camera coordinates (x -> -x)


# the learning rate where SourceConfig's default (1e-3) does not train the network: Lite-Mono
# stalls at loss 1.86 after 250 steps at 1e-3 (AbsRel 0.56 on All), reaches 0.26 at 1e-4 and
# 0.20 at 3e-4 (upstream Lite-Mono trains with AdamW at 1e-4..5e-4)
NETWORK_LR = {"litemono": 3e-4}


@dataclasses.dataclass(frozen=True)
class SourceConfig:
  """How the source model is trained (the defaults are the shipped model's recipe)."""
  model: str = option("monodepth2", "network to train (a registered sigmoid-disparity model)")
  num_layers: int = option(18, "ResNet depth for ResNet-encoder networks (paper: ResNet-18)")
  height: int = option(96, "training size: half of 640x192 for the CPU budget")
  width: int = option(320, "training width")
  sequences: int = option(8, "clear-domain training sequences (seeds 0..sequences-1)")
  frames_per_sequence: int = option(120, "frames per training sequence")
  steps: int = option(600, "optimiser steps of the depth network (shipped model: clear AbsRel "
                           "0.147; 250 steps of batch 4: 0.216)")
  batch_size: int = option(8, "frames (pose net: frame pairs) per step")
  lr: float = option(1e-3, "Adam: 5% linear warm-up, cosine decay to 0.01 * lr")
  pose_fraction: float = option(0.2, "pose-net optimiser steps as a fraction of steps, rounded "
                                     "up (0: no pose net; networks without one train none)")
  pose_max_gap: int = option(1, "pose-net training pairs are 1..pose_max_gap frames apart "
                                "(in temporal order)")
  seed: int = option(0, "initialisation and sampling seed")

  def __post_init__(self):
    from pitta_jax.models.registry import get_spec
    from pitta_jax.models.resnet import RESNET_SPECS
    check_types(self)
    check_seed(self.seed)
    check(self.num_layers in RESNET_SPECS,
          f"num_layers must be one of {sorted(RESNET_SPECS)}, got {self.num_layers}")
    spec = get_spec(self.model)
    check(spec.output == "sigmoid_disparity",
          f"train-source cannot train {self.model} ({spec.output} output); it runs from a "
          f"converted checkpoint (`pitta-jax convert ...`, then --weights)")
    spec.check_size(self.height, self.width)
    # a ResNet depth for a network without a ResNet encoder would be ignored, under a cache
    # name (`name()`) that says otherwise and a training of its own: refused (18, the default,
    # stands for "not given")
    check(self.num_layers == 18 or self.resnet_encoder(),
          f"num_layers {self.num_layers} does not apply to model {self.model}: it has no ResNet "
          f"encoder")
    for name in ("sequences", "frames_per_sequence", "steps", "batch_size", "pose_max_gap"):
      check(getattr(self, name) >= 1, f"{name} must be >= 1, got {getattr(self, name)}")
    finite(self.lr, "lr", 0.0)
    check(self.lr > 0, f"lr must be > 0 (training needs steps), got {self.lr}")
    finite(self.pose_fraction, "pose_fraction", 0.0)
    check(self.pose_fraction <= 1.0, f"pose_fraction must be in [0, 1], got {self.pose_fraction}")
    check(self.pose_steps == 0 or self.frames_per_sequence > self.pose_max_gap,
          f"frames_per_sequence ({self.frames_per_sequence}) must exceed pose_max_gap "
          f"({self.pose_max_gap}) to make pose-net training pairs (or set pose_fraction 0)")

  @property
  def pose_steps(self) -> int:
    """Optimiser steps of the pose network (0 when the network has none)."""
    from pitta_jax.models.registry import get_spec
    if get_spec(self.model).build_pose is None:
      return 0
    return math.ceil(self.pose_fraction * self.steps)

  def key(self) -> str:
    fields = dataclasses.asdict(self)
    if fields["model"] == "monodepth2":  # keys of caches made before `model` existed stay valid
      del fields["model"]
    text = json.dumps({**fields, "format": FORMAT_VERSION}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]

  def name(self) -> str:
    """The cache directory's (and a shipped model's file) name."""
    return f"{self.model}_r{self.num_layers}_{self.width}x{self.height}_{self.key()}"

  def _base_config(self) -> dict:
    """The model.json fields of the network to train, but for the ResNet depth."""
    from pitta_jax.models.registry import get_spec
    spec = get_spec(self.model)
    return (spec.source_config(self.height, self.width) if spec.source_config
            else {"height": self.height, "width": self.width})

  def resnet_encoder(self) -> bool:
    """Whether the network's encoder is a ResNet whose depth `num_layers` sets (MonoDepth2,
    SGDepth, HR-Depth; not Lite-Mono or MonoViT)."""
    from pitta_jax.models.registry import get_spec
    module = get_spec(self.model).build(self._base_config())
    return isinstance(getattr(module, "num_layers", None), int)

  def network_config(self) -> dict:
    """The model.json fields of the network to train."""
    config = self._base_config()
    if self.resnet_encoder():
      config["num_layers"] = self.num_layers
    return config


# where `cache_root` is, in the words of the commands' --help
CACHE_ROOT_TEXT = "$PITTA_JAX_CACHE, else $XDG_CACHE_HOME/pitta-jax, else ~/.cache/pitta-jax"


def cache_root() -> Path:
  """$PITTA_JAX_CACHE, else $XDG_CACHE_HOME/pitta-jax, else ~/.cache/pitta-jax."""
  if os.environ.get(CACHE_ENV):
    return Path(os.environ[CACHE_ENV])
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return Path(base) / "pitta-jax"


def writable_cache_dir(path: Path, probe: bool = True) -> Path:
  """`path` (a folder under the cache root), created and (`probe`) checked writable with a probe
  file: DataError naming it and the fix, in one line, otherwise (e.g. $PITTA_JAX_CACHE pointing
  nowhere writable), before any work whose result would go there. Without `probe` a folder that
  exists is taken as it is (a read-only compilation cache is still read)."""
  import tempfile
  try:
    path.mkdir(parents=True, exist_ok=True)
    if probe:
      with tempfile.TemporaryFile(dir=path):
        pass
  except OSError as e:
    from pitta_jax.data.errors import DataError
    raise DataError(path, f"cannot write the cache directory ({e.strerror or e}); set "
                          f"${CACHE_ENV} to a writable directory") from None
  return path


def enable_compilation_cache() -> None:
  """Persist XLA executables under the cache root, so a second run skips the compiles
  (tens of seconds per network on a CPU). Safe to call more than once."""
  # created if need be, not probed: a read-only cache that holds the compiled programs (and the
  # source models) serves them; JAX only warns where it cannot add one
  path = writable_cache_dir(cache_root() / "xla", probe=False)
  jax.config.update("jax_compilation_cache_dir", str(path))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


# JAX's warning for a persistent-cache entry it cannot read (names the program or the key)
_UNREADABLE_ENTRY = re.compile(r"Error reading persistent compilation cache entry for '([^']+)'")


def remove_damaged_entries(name: str) -> list[Path]:
  """Removes the compiled programs of the persistent cache that cannot be decompressed, among
  the entries of `name` (a cache key, or a program name: its keys `<name>-<hash>`); returns
  them. JAX writes an entry in place and never replaces one, so an entry cut short (a kill or a
  full disk while it was written) made every later run warn and compile again."""
  try:  # JAX's own decoder of its entries (zstandard or zlib, as it wrote them)
    from jax._src.compilation_cache import decompress_executable
  except ImportError:  # another JAX: its warning is shown as it is
    return []
  if not jax.config.jax_compilation_cache_dir:
    return []
  folder = Path(jax.config.jax_compilation_cache_dir)
  if not folder.is_dir():
    return []
  removed = []
  for entry in sorted({*folder.glob(f"{glob.escape(name)}-cache"),
                       *folder.glob(f"{glob.escape(name)}-*-cache")}):
    try:
      decompress_executable(entry.read_bytes())
    except Exception:  # noqa: BLE001 (any decoder's error: the entry is unreadable)
      with contextlib.suppress(OSError):
        entry.unlink()
        removed.append(entry)
        entry.with_name(entry.name.removesuffix("-cache") + "-atime").unlink(missing_ok=True)
  return removed


@contextlib.contextmanager
def repairing_compilation_cache():
  """While a command runs: JAX's warning that it cannot read a cached program (it then compiles
  it, but cannot store it again while the damaged entry is there) removes that entry, so that
  this run's compile is stored in its place, with one line instead of JAX's two. The
  command's choice (warning hooks are the process's); any other warning is shown as before."""
  with warnings.catch_warnings():
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
      found = _UNREADABLE_ENTRY.match(str(message))
      removed = remove_damaged_entries(found.group(1)) if found else []
      if not removed:
        shown(message, category, filename, lineno, file, line)
      for entry in removed:
        print(f"warning: {entry}: a damaged compiled program in the cache (written by a run "
              f"that was killed or ran out of disk) was removed; this run stores it again",
              file=sys.stderr)
    warnings.showwarning = show
    yield


def cached_dir(cfg: SourceConfig) -> Path:
  return cache_root() / "source" / cfg.name()


def shipped_path(cfg: SourceConfig) -> Path:
  """The package's shipped model for `cfg` (`<name>.npz` + `<name>.json`), present or not."""
  return ASSETS / f"{cfg.name()}.npz"


# ----------------------------------------------------------------------------- training data


def training_streets(cfg: SourceConfig) -> list[SyntheticConfig]:
  """The clear-domain sequences the source model is trained on (seeds 0..sequences-1)."""
  return [SyntheticConfig(height=cfg.height, width=cfg.width, num_frames=cfg.frames_per_sequence,
                          seed=seed, domain="clear") for seed in range(cfg.sequences)]


def training_frames(cfg: SourceConfig) -> tuple[np.ndarray, np.ndarray]:
  """Clear-domain images (N, H, W, 3) and depths (N, H, W), N = sequences * frames_per_sequence:
  the frames of `training_streets`, sequence after sequence, in temporal order."""
  images, depths = [], []
  for street in training_streets(cfg):
    for f in generate_sequence(street):
      images.append(f.image)
      depths.append(f.depth)
  return np.stack(images).astype(np.float32), np.stack(depths).astype(np.float32)


def camera_motion(synth: SyntheticConfig, first: int, second: int) -> np.ndarray:
  """(4, 4) float64 T mapping camera-`first` points to camera-`second` points of a synthetic
  sequence (MonoDepth2's cam_T_cam from target `first` to source `second`).

  The generator (`data.synthetic.scene.Street.frame`) puts the camera of frame n at world
  (ego_x, camera_height, speed * n / fps) with its axes along the world's (x right, y down,
  z forward along the straight road): no rotation, so a static point p in camera `first` is
  p - (0, 0, (second - first) * speed / fps) in camera `second`.
  """
  motion = np.eye(4)
  motion[2, 3] = -(second - first) * synth.speed / synth.fps
  return motion


def sample_pairs(rng: np.random.Generator, cfg: SourceConfig, count: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """`count` random pose-training pairs: indices (first, second) into `training_frames`'
  arrays, second = first + 1..pose_max_gap frames within one sequence (temporal order, as
  MonoDepth2 feeds its pose net), and their true motions T (count, 4, 4) from the first
  camera to the second."""
  seq = rng.integers(0, cfg.sequences, count)
  gap = rng.integers(1, cfg.pose_max_gap + 1, count)
  first = rng.integers(0, cfg.frames_per_sequence - gap)  # (count,), each below its own bound
  second = first + gap
  street = training_streets(cfg)[0]  # every training street has the same speed and fps
  motions = np.stack([camera_motion(street, a, b) for a, b in zip(first, second)])
  base = seq * cfg.frames_per_sequence
  return base + first, base + second, motions


def _augment(rng: np.random.Generator, images: np.ndarray, depths: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
  """Horizontal flips (geometry-preserving for a centred camera) and mild brightness jitter.

  images: (B, H, W, C), C = 6 for stacked frame pairs (both frames get the same flip and
  gain); depths: (B, H, W) or None. Returns the images, the depths flipped alike, and the flip
  mask (B,).
  """
  flip = rng.random(len(images)) < 0.5
  images = np.where(flip[:, None, None, None], images[:, :, ::-1], images)
  if depths is not None:
    depths = np.where(flip[:, None, None], depths[:, :, ::-1], depths)
  gain = rng.uniform(0.9, 1.1, (len(images), 1, 1, 1)).astype(np.float32)
  return np.clip(images * gain, 0.0, 1.0), depths, flip


def augment_pose_pairs(rng: np.random.Generator, pairs: np.ndarray, motions: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """The depth net's augmentation (`_augment`) on stacked frame pairs, with each flipped pair's
  true motion mirrored to match its images.

  pairs: (B, H, W, 6) (first, second) stacked; motions: (B, 4, 4) T from the first camera to
  the second. A horizontal flip maps camera points (x, y, z) to (-x, y, z) (FLIP, for a centred
  principal point), so the flipped pair's motion is FLIP T FLIP: its sideways translation and
  its yaw and roll change sign. (The synthetic streets' motion is straight ahead, which the flip
  leaves as it is; a pair that turns or drifts sideways would otherwise teach the pose net the
  mirror image of its motion.) Returns the pairs, the motions and the flip mask (B,).
  """
  pairs, _, flip = _augment(rng, pairs)
  motions = np.where(flip[:, None, None], FLIP @ motions @ FLIP, motions)
  return pairs, motions, flip


# ----------------------------------------------------------------------------- losses


def supervised_loss(disps: tuple[jax.Array, ...], gt: jax.Array, to_depth=disp_to_depth
                    ) -> jax.Array:
  """Multi-scale mean |log D - log gt| on valid pixels (gt > 0). gt: (B, H, W); scale s is
  upsampled (nearest) by the factor between its size and gt's."""
  valid = gt > 0
  log_gt = jnp.log(jnp.where(valid, gt, 1.0))
  total = 0.0
  for s, disp in enumerate(disps):
    d = disp[..., 0]
    f = gt.shape[1] // d.shape[1]
    if f > 1:
      d = jnp.repeat(jnp.repeat(d, f, axis=1), f, axis=2)
    err = absolute(jnp.log(to_depth(d)) - log_gt)
    total = total + jnp.sum(jnp.where(valid, err, 0.0)) / jnp.maximum(jnp.sum(valid), 1)
  return total / len(disps)


def pose_loss(outputs: tuple[jax.Array, jax.Array], motion: jax.Array) -> jax.Array:
  """Batch mean of sum |T_pred - T_true| over the top 3x4 block of the camera motion.

  outputs: the PoseNet's (axisangle, translation), each (B, F, 1, 3); its first prediction
  (upstream uses `[:, 0]`) gives T_pred = transformation_from_parameters(axisangle,
  translation, invert=False), the motion from the first input frame's camera to the second's.
  motion: (B, 4, 4) the true T.
  """
  axisangle, translation = outputs
  pred = transformation_from_parameters(axisangle[:, 0], translation[:, 0])  # (B, 4, 4)
  return jnp.mean(jnp.sum(absolute(pred[:, :3] - motion[:, :3]), axis=(1, 2)))


def make_train_step(net, tx: optax.GradientTransformation,
                    loss: Callable[[object, jax.Array], jax.Array]):
  """Jitted (params, batch_stats, opt_state, inputs, targets) -> (params, batch_stats,
  opt_state, loss): one Adam step on loss(net(inputs) in train mode, targets)."""
  @jax.jit
  def step(params, batch_stats, opt_state, inputs, targets):
    def loss_fn(p):
      outputs, new_vars = net.apply({"params": p, "batch_stats": batch_stats}, inputs,
                                    train=True, mutable=["batch_stats"])
      return loss(outputs, targets), new_vars["batch_stats"]
    (value, new_stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), new_stats, opt_state, value
  return step


def _fit(net, example: np.ndarray, loss, batches: Callable[[], tuple[np.ndarray, np.ndarray]],
         steps: int, lr: float, key: jax.Array, desc: str, quiet: bool
         ) -> tuple[dict, list[float]]:
  """Initialises `net` from `key` and runs `steps` Adam steps (5% warm-up, cosine decay to
  0.01 lr) on `batches()`; returns the Flax variables and the per-step losses."""
  variables = dict(jit_init(net, key, jnp.zeros((1,) + example.shape[1:], jnp.float32)))
  variables.setdefault("batch_stats", {})
  warmup = min(max(1, steps // 20), steps - 1)  # a single step has no warm-up
  schedule = optax.warmup_cosine_decay_schedule(0.0, lr, warmup, steps, lr * 0.01)
  tx = optax.adam(schedule)
  params, batch_stats = variables["params"], variables["batch_stats"]
  opt_state = tx.init(params)
  step = make_train_step(net, tx, loss)
  losses: list[float] = []
  bar = tqdm(range(steps), desc=desc, unit="step", disable=quiet)
  for _ in bar:
    x, y = batches()
    params, batch_stats, opt_state, value = step(params, batch_stats, opt_state, x, y)
    losses.append(float(value))
    bar.set_postfix(loss=f"{np.mean(losses[-20:]):.3f}")
  return {"params": params, "batch_stats": batch_stats}, losses


def train_source(cfg: SourceConfig = SourceConfig(), quiet: bool = False
                 ) -> tuple[dict, dict | None, dict]:
  """Trains from scratch; returns (depth-net variables, pose-net variables or None when
  cfg.pose_steps is 0, report dict with losses and timing)."""
  t0 = time.perf_counter()
  images, depths = training_frames(cfg)
  t_data = time.perf_counter() - t0
  from pitta_jax.models.registry import get_spec
  spec = get_spec(cfg.model)
  rng = np.random.default_rng(cfg.seed)

  def depth_batch():
    idx = rng.integers(0, len(images), cfg.batch_size)
    x, y, _ = _augment(rng, images[idx], depths[idx])
    return x, y

  variables, losses = _fit(spec.build(cfg.network_config()), images[:1],
                           partial(supervised_loss, to_depth=spec.to_depth), depth_batch,
                           cfg.steps, cfg.lr, seed_key(cfg.seed),
                           f"train source {cfg.model} (clear)", quiet)
  t_depth = time.perf_counter() - t0 - t_data
  report = {"config": dataclasses.asdict(cfg), "train_frames": int(len(images)),
            "data_seconds": round(t_data, 1), "train_seconds": round(t_depth, 1),
            "loss_first_20": float(np.mean(losses[:20])),
            "loss_last_20": float(np.mean(losses[-20:])), "pose_steps": cfg.pose_steps}
  pose_variables = None
  if cfg.pose_steps:
    pose_rng = np.random.default_rng([cfg.seed, 1])

    def pose_batch():
      first, second, motions = sample_pairs(pose_rng, cfg, cfg.batch_size)
      pairs = np.concatenate([images[first], images[second]], axis=-1)  # (B, H, W, 6)
      pairs, motions, _ = augment_pose_pairs(pose_rng, pairs, motions)
      return pairs, motions.astype(np.float32)

    t1 = time.perf_counter()
    pose_variables, pose_losses = _fit(
        spec.build_pose(cfg.network_config()), np.zeros((1, cfg.height, cfg.width, 6)),
        pose_loss, pose_batch, cfg.pose_steps, cfg.lr,
        jax.random.fold_in(seed_key(cfg.seed), 1), f"train pose net {cfg.model}",
        quiet)
    report.update({"pose_train_seconds": round(time.perf_counter() - t1, 1),
                   "pose_loss_first_20": float(np.mean(pose_losses[:20])),
                   "pose_loss_last_20": float(np.mean(pose_losses[-20:]))})
  return variables, pose_variables, report


# ----------------------------------------------------------------------------- evaluation


def evaluation_frames(cfg: SourceConfig, seed: int, num_frames: int) -> tuple[SyntheticConfig,
                                                                              list]:
  """A held-out clear street at the training size: its SyntheticConfig and frames."""
  street = SyntheticConfig(height=cfg.height, width=cfg.width, num_frames=num_frames, seed=seed,
                           domain="clear")
  return street, generate_sequence(street)


def evaluate_depth(weights: Weights, frames) -> list[dict[str, float]]:
  """The 7 metrics of each frame exactly as the demo's "No adaptation" row scores them
  (`run.run_sequence`: running BN statistics, no update, `EvalConfig`'s protocol, i.e. per-frame
  median scaling for MonoDepth2-family nets); frames without valid ground truth are left out."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.demo import ROWS
  from pitta_jax.methods import build as build_method, method_setting
  from pitta_jax.run import run_sequence
  _, name, changes = ROWS["none"]
  cfg = dataclasses.replace(AdaptConfig(method=name), **{**method_setting(name), **changes})
  return run_sequence(weights, frames, cfg, build_method(name), quiet=True).per_frame


def predict_motions(weights: Weights, firsts: np.ndarray, seconds: np.ndarray,
                    invert: bool = False) -> np.ndarray:
  """(B, 4, 4) the pose net's T for frames (B, H, W, 3) stacked (first, second), eval mode:
  `transformation_from_parameters(axisangle[:, 0], translation[:, 0], invert)`."""
  module = weights.spec.build_pose(weights.config)
  aa, t = module.apply(weights.pose, np.concatenate([firsts, seconds], -1).astype(np.float32))
  return np.asarray(transformation_from_parameters(aa[:, 0], t[:, 0], invert))


def evaluate_pose(weights: Weights, street: SyntheticConfig, frames) -> dict[str, float]:
  """Errors of the pose net on the adjacent pairs (n, n + 1) of `frames` (consecutive frames of
  `street` from its `start`), against `camera_motion`: mean and max translation error (metres,
  Euclidean) and mean rotation angle (degrees)."""
  images = np.stack([f.image for f in frames]).astype(np.float32)
  pred = predict_motions(weights, images[:-1], images[1:])
  true = np.stack([camera_motion(street, street.start + n, street.start + n + 1)
                   for n in range(len(frames) - 1)])
  t_err = np.linalg.norm(pred[:, :3, 3] - true[:, :3, 3], axis=-1)
  rel = np.swapaxes(true[:, :3, :3], 1, 2) @ pred[:, :3, :3]
  cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
  return {"translation_error_m": float(np.mean(t_err)),
          "max_translation_error_m": float(np.max(t_err)),
          "rotation_error_deg": float(np.degrees(np.mean(np.arccos(cos)))),
          "pairs": int(len(t_err))}


# ----------------------------------------------------------------------------- cache, shipping


def _save(directory: Path, cfg: SourceConfig, depth: dict, pose: dict | None, report: dict,
          source: dict) -> tuple[Weights, dict]:
  save_weights(directory, cfg.model, cfg.network_config(),
               jax.tree_util.tree_map(np.asarray, depth),
               None if pose is None else jax.tree_util.tree_map(np.asarray, pose),
               source={"key": cfg.key(), **source})
  report = {**report, "weights_dir": str(directory)}
  # atomic: the report marks a finished cache entry
  atomic_write_text(directory / "train_report.json", json.dumps(report, indent=2) + "\n")
  return load_weights(directory), report


def _read_shipped(path: Path) -> tuple[dict, dict | None, dict]:
  """(depth variables, pose variables or None, record) of a shipped model, float32."""
  from flax.traverse_util import unflatten_dict
  record = json.loads(path.with_suffix(".json").read_text())
  trees: dict[str, dict] = {}
  with np.load(path) as arrays:
    for name in arrays.files:
      net, *rest = name.split("/")
      trees.setdefault(net, {})[tuple(rest)] = arrays[name].astype(np.float32)
  return (unflatten_dict(trees["depth"]),
          unflatten_dict(trees["pose"]) if "pose" in trees else None, record)


def network_defaults(model: str) -> dict[str, Any]:
  """SourceConfig values of `model` that differ from the defaults (`NETWORK_LR`)."""
  return {"lr": NETWORK_LR[model]} if model in NETWORK_LR else {}


def network_source_config(model: str, **changes: Any) -> SourceConfig:
  """SourceConfig of `model` with its own values (`network_defaults`), then `changes`."""
  return SourceConfig(model=model, **{**network_defaults(model), **changes})


def load_or_train_source(cfg: SourceConfig = SourceConfig(), quiet: bool = False,
                         retrain: bool = False) -> tuple[Weights, dict]:
  """The cached source model for `cfg`; on the first call the shipped model of `cfg` when the
  package has one (copied into the cache), else trained (and cached). retrain: train anyway."""
  directory = cached_dir(cfg)
  report_path = directory / "train_report.json"
  shipped = shipped_path(cfg)
  if not retrain and report_path.is_file():
    try:
      return load_weights(directory), json.loads(report_path.read_text())
    except (OSError, ValueError) as e:  # a broken cache is rebuilt, not fatal
      # on stderr: train-source's stdout is its JSON report
      print(f"warning: cached source model at {directory} unreadable ({e}); "
            + ("copying the shipped model again" if shipped.is_file() else "retraining"),
            file=sys.stderr)
  writable_cache_dir(directory.parent)  # before a training of minutes, not after it
  if not retrain and shipped.is_file():
    depth, pose, record = _read_shipped(shipped)
    return _save(directory, cfg, depth, pose, {**record["report"], "shipped": str(shipped)},
                 {"trained_by": record["command"], "shipped": shipped.name})
  variables, pose_variables, report = train_source(cfg, quiet)
  return _save(directory, cfg, variables, pose_variables, report,
               {"trained_by": "pitta-jax train-source"})


def to_float16(variables: dict) -> dict:
  """The shipped precision: parameters rounded to float16, BatchNorm statistics kept float32
  (a few thousand numbers; running variances can fall below float16's normal range)."""
  return {"params": jax.tree_util.tree_map(lambda a: np.asarray(a, np.float16),
                                           variables["params"]),
          "batch_stats": jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32),
                                                variables["batch_stats"])}


def ship_source(cfg: SourceConfig, quiet: bool = False) -> Path:
  """Writes `cfg`'s model (trained or cached) as a shipped model: `<name>.npz` (float16
  parameters, `to_float16`, compressed) and `<name>.json` (the training report, the command that
  reproduces it, and the clear-domain metrics of the float16 model as loaded, on the demo's
  clear street (`DemoConfig` target_seed and num_frames: its "No adaptation" clear row): per
  frame, their mean, and the pose net's errors on the street's adjacent pairs)."""
  from flax.traverse_util import flatten_dict
  from pitta_jax.demo import DemoConfig
  from pitta_jax.metrics import mean_metrics
  eval_seed, eval_frames = DemoConfig().target_seed, DemoConfig().num_frames
  weights, report = load_or_train_source(cfg, quiet)
  trees = {"depth": to_float16(weights.depth)}
  if weights.pose is not None:
    trees["pose"] = to_float16(weights.pose)
  rounded = Weights(weights.spec, weights.config,
                    *(jax.tree_util.tree_map(lambda a: a.astype(np.float32), trees.get(k))
                      for k in ("depth", "pose")))
  street, frames = evaluation_frames(cfg, eval_seed, eval_frames)
  per_frame = evaluate_depth(rounded, frames)
  record = {
      "command": "pitta-jax train-source --retrain --ship"
                 + "".join(f" --source.{k.replace('_', '-')} {v}"
                           for k, v in dataclasses.asdict(cfg).items()
                           if v != getattr(SourceConfig, k)),
      "config": dataclasses.asdict(cfg), "model": {"architecture": cfg.model, **weights.config},
      "report": {k: v for k, v in report.items() if k not in ("weights_dir", "shipped")},
      "evaluation": {"domain": "clear", "seed": eval_seed, "frames": eval_frames,
                     "size": [cfg.height, cfg.width], "mean": mean_metrics(per_frame),
                     "per_frame": per_frame,
                     **({"pose": evaluate_pose(rounded, street, frames)}
                        if rounded.pose is not None else {})}}
  path = shipped_path(cfg)
  path.parent.mkdir(parents=True, exist_ok=True)
  buffer = io.BytesIO()
  np.savez_compressed(buffer, **{"/".join((net,) + k): v for net, tree in trees.items()
                                 for k, v in flatten_dict(tree).items()})
  # both files synced before either is renamed: a kill leaves the old pair or the new one
  atomic_write_files(path.parent, {path.name: buffer.getvalue(),
                                   path.with_suffix(".json").name: json.dumps(record, indent=2)
                                   + "\n"})
  return path
