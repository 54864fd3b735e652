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
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from pitta_jax.checkpoint import Weights, load_weights, save_weights
from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
from pitta_jax.configs import check, finite, option
from pitta_jax.models.depth_decoder import disp_to_depth
from pitta_jax.nonsmooth import absolute

CACHE_ENV = "PITTA_JAX_CACHE"
FORMAT_VERSION = 1  # bump when the training recipe changes, so old caches are not reused


@dataclasses.dataclass(frozen=True)
class SourceConfig:
  """How the source model is trained (defaults: about 5 minutes on a quiet 2-core CPU)."""
  model: str = option("monodepth2", "network to train (a registered sigmoid-disparity model)")
  num_layers: int = option(18, "ResNet depth for ResNet-encoder networks (paper: ResNet-18)")
  height: int = option(96, "training size: half of 640x192 for the CPU budget")
  width: int = option(320, "training width")
  sequences: int = option(8, "clear-domain training sequences (seeds 0..sequences-1)")
  frames_per_sequence: int = option(60, "frames per training sequence")
  steps: int = option(250, "optimiser steps (measured: clear AbsRel 0.139; ~5 min on a quiet "
                           "2-core CPU for MonoDepth2)")
  batch_size: int = option(4, "frames per step")
  lr: float = option(1e-3, "Adam: 5% linear warm-up, cosine decay to 0.01 * lr")
  seed: int = option(0, "initialisation and sampling seed")

  def __post_init__(self):
    from pitta_jax.models.registry import get_spec
    spec = get_spec(self.model)
    check(spec.output == "sigmoid_disparity",
          f"train-source cannot train {self.model} ({spec.output} output); it runs from a "
          f"converted checkpoint (`pitta-jax convert ...`, then --weights)")
    spec.check_size(self.height, self.width)
    check(min(self.sequences, self.frames_per_sequence, self.steps, self.batch_size) >= 1,
          "sequences, frames_per_sequence, steps and batch_size must be >= 1")
    finite(self.lr, "lr", 0.0)

  def key(self) -> str:
    fields = dataclasses.asdict(self)
    if fields["model"] == "monodepth2":  # keys of caches made before `model` existed stay valid
      del fields["model"]
    text = json.dumps({**fields, "format": FORMAT_VERSION}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]

  def network_config(self) -> dict:
    """The model.json fields of the network to train."""
    from pitta_jax.models.registry import get_spec
    spec = get_spec(self.model)
    config = (spec.source_config(self.height, self.width) if spec.source_config
              else {"height": self.height, "width": self.width})
    module = spec.build(config)
    if isinstance(getattr(module, "num_layers", None), int):  # ResNet-encoder networks
      config["num_layers"] = self.num_layers
    return config


def cache_root() -> Path:
  """$PITTA_JAX_CACHE, else $XDG_CACHE_HOME/pitta-jax, else ~/.cache/pitta-jax."""
  if os.environ.get(CACHE_ENV):
    return Path(os.environ[CACHE_ENV])
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return Path(base) / "pitta-jax"


def enable_compilation_cache() -> None:
  """Persist XLA executables under the cache root, so a second run skips the compiles
  (tens of seconds per network on a CPU). Safe to call more than once."""
  path = cache_root() / "xla"
  path.mkdir(parents=True, exist_ok=True)
  jax.config.update("jax_compilation_cache_dir", str(path))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def cached_dir(cfg: SourceConfig) -> Path:
  return cache_root() / "source" / f"{cfg.model}_r{cfg.num_layers}_{cfg.width}x{cfg.height}_{cfg.key()}"


def training_frames(cfg: SourceConfig) -> tuple[np.ndarray, np.ndarray]:
  """Clear-domain images (N, H, W, 3) and depths (N, H, W) of seeds 0..sequences-1."""
  images, depths = [], []
  for seed in range(cfg.sequences):
    for f in generate_sequence(SyntheticConfig(height=cfg.height, width=cfg.width,
                                               num_frames=cfg.frames_per_sequence, seed=seed,
                                               domain="clear")):
      images.append(f.image)
      depths.append(f.depth)
  return np.stack(images).astype(np.float32), np.stack(depths).astype(np.float32)


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


def make_train_step(net, tx: optax.GradientTransformation, to_depth=disp_to_depth):
  @jax.jit
  def step(params, batch_stats, opt_state, images, depths):
    def loss_fn(p):
      disps, new_vars = net.apply({"params": p, "batch_stats": batch_stats}, images, train=True,
                                  mutable=["batch_stats"])
      return supervised_loss(disps, depths, to_depth), new_vars["batch_stats"]
    (loss, new_stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), new_stats, opt_state, loss
  return step


def _augment(rng: np.random.Generator, images: np.ndarray, depths: np.ndarray):
  """Horizontal flips (geometry-preserving for a centred camera) and mild brightness jitter."""
  flip = rng.random(len(images)) < 0.5
  images = np.where(flip[:, None, None, None], images[:, :, ::-1], images)
  depths = np.where(flip[:, None, None], depths[:, :, ::-1], depths)
  gain = rng.uniform(0.9, 1.1, (len(images), 1, 1, 1)).astype(np.float32)
  return np.clip(images * gain, 0.0, 1.0), depths


def train_source(cfg: SourceConfig = SourceConfig(), quiet: bool = False) -> tuple[dict, dict]:
  """Trains from scratch; returns (Flax variables, report dict with losses and timing)."""
  t0 = time.perf_counter()
  images, depths = training_frames(cfg)
  t_data = time.perf_counter() - t0
  from pitta_jax.models.registry import get_spec
  spec = get_spec(cfg.model)
  net = spec.build(cfg.network_config())
  variables = jax.jit(net.init)(jax.random.PRNGKey(cfg.seed),
                                jnp.zeros((1, cfg.height, cfg.width, 3)))
  variables.setdefault("batch_stats", {})
  schedule = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, max(1, cfg.steps // 20), cfg.steps,
                                                cfg.lr * 0.01)
  tx = optax.adam(schedule)
  params, batch_stats = variables["params"], variables["batch_stats"]
  opt_state = tx.init(params)
  step = make_train_step(net, tx, spec.to_depth)
  rng = np.random.default_rng(cfg.seed)
  losses = []
  bar = tqdm(range(cfg.steps), desc=f"train source {cfg.model} (clear)", unit="step",
             disable=quiet)
  for _ in bar:
    idx = rng.integers(0, len(images), cfg.batch_size)
    x, y = _augment(rng, images[idx], depths[idx])
    params, batch_stats, opt_state, loss = step(params, batch_stats, opt_state, x, y)
    losses.append(float(loss))
    bar.set_postfix(loss=f"{np.mean(losses[-20:]):.3f}")
  report = {"config": dataclasses.asdict(cfg), "train_frames": int(len(images)),
            "data_seconds": round(t_data, 1),
            "train_seconds": round(time.perf_counter() - t0 - t_data, 1),
            "loss_first_20": float(np.mean(losses[:20])), "loss_last_20": float(np.mean(losses[-20:]))}
  return {"params": params, "batch_stats": batch_stats}, report


def load_or_train_source(cfg: SourceConfig = SourceConfig(), quiet: bool = False,
                         retrain: bool = False) -> tuple[Weights, dict]:
  """The cached source model for `cfg`, training (and caching) it on the first call."""
  directory = cached_dir(cfg)
  report_path = directory / "train_report.json"
  if not retrain and report_path.is_file():
    try:
      return load_weights(directory), json.loads(report_path.read_text())
    except (OSError, ValueError) as e:  # a broken cache is rebuilt, not fatal
      print(f"warning: cached source model at {directory} unreadable ({e}); retraining")
  variables, report = train_source(cfg, quiet)
  save_weights(directory, cfg.model, cfg.network_config(),
               jax.tree_util.tree_map(np.asarray, variables),
               source={"trained_by": "pitta-jax train-source", "key": cfg.key()})
  report["weights_dir"] = str(directory)
  report_path.write_text(json.dumps(report, indent=2) + "\n")
  return load_weights(directory), report
