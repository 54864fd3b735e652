"""The source model of the synthetic benchmark: its pose-net supervision and the shipped model.

References: the generator's own camera positions (`scene.Street.frame`) and its rendered images
(a frame warped into its neighbour with the ground-truth depth), MonoDepth2's
`transformation_from_parameters` in PyTorch (tests/torch_sfm.py), and the metrics recorded when
the shipped model was written (`pitta-jax train-source --ship`).
"""

from __future__ import annotations

import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

from pitta_jax import sfm, source_model
from pitta_jax.data.synthetic import STUFF_CATEGORY, SyntheticConfig, generate_sequence
from pitta_jax.data.synthetic.scene import Street
from pitta_jax.source_model import SourceConfig, camera_motion
import torch_sfm

SHAPE = (96, 320)  # the shipped model's size; the renderer's textures need some resolution
EVAL_FRAMES = 4    # of the recorded evaluation street: enough to check, cheap to render
BOUND = 0.01       # pose net: max |T_pred - T_true| per matrix entry (see the pose test)


@pytest.fixture(scope="module")
def street_frames():
  """Frames 10..12 of an unseen clear street (seed 100), with their SyntheticConfig."""
  street = SyntheticConfig(height=SHAPE[0], width=SHAPE[1], num_frames=3, start=10, seed=100)
  return street, generate_sequence(street)


def test_camera_motion_is_the_generators(street_frames):
  """T = camera_motion(a, b) maps a point's camera-a coordinates to its camera-b coordinates,
  computed from the world positions of the generator's cameras (world X right, height up, Z
  forward; camera x right, y down, z forward; no rotation)."""
  street = street_frames[0]
  scene = Street(street)
  to_camera = np.diag([1.0, -1.0, 1.0])  # world (X, height, Z) -> camera (x, y, z) axes
  rng = np.random.default_rng(0)
  world = rng.uniform(-20, 20, (5, 3))  # static points
  for a, b in [(10, 11), (11, 10), (3, 7), (12, 12)]:
    ca, cb = scene.frame(a).camera, scene.frame(b).camera
    in_a = (world - ca) @ to_camera.T
    in_b = (world - cb) @ to_camera.T
    T = camera_motion(street, a, b)
    np.testing.assert_allclose(in_a @ T[:3, :3].T + T[:3, 3], in_b, atol=1e-12)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def _warp_errors(target, source, motions: dict[str, np.ndarray]) -> dict[str, float]:
  """Median |warped source - target| (channel mean) over static pixels (stuff classes with
  valid depth) that every motion projects inside the source image."""
  h, w = SHAPE
  K = np.eye(4, dtype=np.float32)
  K[:3, :3] = target.intrinsics
  points = sfm.backproject(jnp.asarray(target.depth[None]), jnp.asarray(np.linalg.inv(K)[None]))
  mask = np.isin(target.panoptic, list(STUFF_CATEGORY)) & (target.depth > 0)
  warped = {}
  for name, T in motions.items():
    coords = sfm.project(points, jnp.asarray(K[None]), jnp.asarray(T[None], jnp.float32), h, w)
    mask &= np.asarray(jnp.all(jnp.abs(coords) <= 1, axis=-1))[0]
    warped[name] = np.asarray(sfm.warp(jnp.asarray(source.image[None]), coords))[0]
  assert mask.mean() > 0.5, mask.mean()  # most of the frame is compared
  return {name: float(np.median(np.abs(im - target.image).mean(-1)[mask]))
          for name, im in warped.items()}


@pytest.mark.parametrize("source_offset", [1, -1])  # MonoDepth2's frame ids +1 and -1
def test_target_motion_warps_the_next_frame_onto_the_target(street_frames, source_offset):
  """The supervised target is the geometry `pitta_jax.sfm` expects: warping the source frame
  with the target frame's ground-truth depth and T = camera_motion(target, source) reproduces the
  target on static pixels, and does so better than the inverse motion (the other convention),
  no motion, or the motion scaled by 0.9 / 1.1.
  Measured medians (frame 11, seed 100, 96x320): +1: 0.0025 vs inverse 0.023, identity 0.014,
  x0.9 0.0037, x1.1 0.0036; -1: 0.0030 vs 0.020, 0.013."""
  street, frames = street_frames
  target, source = frames[1], frames[1 + source_offset]
  T = camera_motion(street, 11, 11 + source_offset)
  scaled = {f"x{s}": np.where(np.eye(4, dtype=bool), T, T * s) for s in (0.9, 1.1)}
  errors = _warp_errors(target, source, {"true": T, "inverse": np.linalg.inv(T),
                                         "identity": np.eye(4), **scaled})
  print(errors)
  assert errors["true"] < 0.005
  assert errors["true"] < 0.5 * min(errors["inverse"], errors["identity"])
  assert errors["true"] < min(errors["x0.9"], errors["x1.1"])


def test_pose_loss_is_monodepth2s_transformation_error():
  """pose_loss = batch mean of sum |T(axisangle, translation) - T_true| over the top 3x4 block,
  with T from PyTorch MonoDepth2's transformation_from_parameters (float64)."""
  rng = np.random.default_rng(1)
  aa = rng.normal(0, 0.1, (3, 2, 1, 3))
  t = rng.normal(0, 1.0, (3, 2, 1, 3))
  true = np.stack([camera_motion(SyntheticConfig(), 0, g) for g in (1, 2, -1)])
  want_T = torch_sfm.transformation_from_parameters(torch.tensor(aa[:, 0]), torch.tensor(t[:, 0]))
  want = (want_T - torch.tensor(true))[:, :3].abs().sum(dim=(1, 2)).mean().item()
  with jax.enable_x64(True):
    got = float(source_model.pose_loss((jnp.asarray(aa), jnp.asarray(t)), jnp.asarray(true)))
    zero = float(source_model.pose_loss((jnp.zeros((3, 2, 1, 3)), jnp.asarray(
        true[:, None, None, :3, 3])), jnp.asarray(true)))
  np.testing.assert_allclose(got, want, rtol=1e-12)
  assert zero == 0.0  # no rotation, the true translation: no loss


def test_pose_pairs_follow_the_sequences():
  """Pose-training pairs lie within one sequence, second = first + 1..pose_max_gap, and carry
  camera_motion of their frame numbers."""
  cfg = SourceConfig(sequences=3, frames_per_sequence=5, pose_max_gap=2)
  first, second, motions = source_model.sample_pairs(np.random.default_rng(0), cfg, 200)
  n = cfg.frames_per_sequence
  np.testing.assert_array_equal(first // n, second // n)
  assert set((second - first).tolist()) == {1, 2}
  street = source_model.training_streets(cfg)[0]
  for a, b, T in zip(first, second, motions):
    np.testing.assert_array_equal(T, camera_motion(street, a % n, b % n))


def test_a_flipped_pose_pair_is_given_the_mirrored_motion():
  """A pair that turns and drifts sideways: where the augmentation flips its images, its target
  is the motion of the mirrored scene, sideways translation and yaw negated (written out by
  hand), and for any 3-D point the flipped motion maps the mirrored point to the mirror of the
  moved one; an unflipped pair keeps its images (up to the gain) and its motion."""
  c, s = np.cos(0.1), np.sin(0.1)
  turn = np.array([[c, 0, s, 0.3], [0, 1, 0, 0.02], [-s, 0, c, -0.8], [0, 0, 0, 1]])  # yaw, x drift
  mirrored = np.array([[c, 0, -s, -0.3], [0, 1, 0, 0.02], [s, 0, c, -0.8], [0, 0, 0, 1]])
  rng = np.random.default_rng(3)
  pairs = rng.uniform(0.2, 0.6, (16, 4, 5, 6))  # no value clipped by the gain of 0.9..1.1
  got_pairs, got, flip = source_model.augment_pose_pairs(
      np.random.default_rng(0), pairs, np.repeat(turn[None], 16, axis=0))
  assert 0 < flip.sum() < 16
  mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
  points = np.concatenate([rng.normal(size=(3, 7)), np.ones((1, 7))])  # homogeneous (4, 7)
  for i in range(16):
    seen = pairs[i, :, ::-1] if flip[i] else pairs[i]
    ratio = got_pairs[i] / seen
    np.testing.assert_allclose(ratio, ratio.flat[0], rtol=1e-6)  # one gain for both frames
    np.testing.assert_allclose(got[i], mirrored if flip[i] else turn, atol=1e-15)
    if flip[i]:
      np.testing.assert_allclose(got[i] @ (mirror @ points), mirror @ (turn @ points),
                                 atol=1e-12)


# ----------------------------------------------------------------------------- shipped model


@pytest.fixture(scope="module")
def shipped(tmp_path_factory):
  """The default config's model, loaded twice into a fresh cache (copied from the package, then
  read back from the cache), and the file's record."""
  mp = pytest.MonkeyPatch()
  mp.setenv(source_model.CACHE_ENV, str(tmp_path_factory.mktemp("cache")))
  cfg = SourceConfig()
  path = source_model.shipped_path(cfg)
  assert path.is_file(), f"{path} is missing: run `pitta-jax train-source --ship`"
  first, report = source_model.load_or_train_source(cfg, quiet=True)
  again, _ = source_model.load_or_train_source(cfg, quiet=True)
  mp.undo()
  return path, json.loads(path.with_suffix(".json").read_text()), first, again, report


def test_a_damaged_cache_entry_is_rebuilt_with_a_warning_on_stderr(tmp_path, monkeypatch,
                                                                   capsys):
  """A cache entry a killed --retrain left without its model.json: rebuilt from the shipped
  model, said on stderr (train-source's stdout is its JSON report; the warning went there and
  said 'retraining' where the shipped model is copied)."""
  monkeypatch.setenv(source_model.CACHE_ENV, str(tmp_path))
  cfg = SourceConfig()
  first, _ = source_model.load_or_train_source(cfg, quiet=True)
  (source_model.cached_dir(cfg) / "model.json").unlink()
  again, report = source_model.load_or_train_source(cfg, quiet=True)
  out, err = capsys.readouterr()
  assert out == "" and err.startswith("warning: cached source model at ")
  assert err.rstrip().endswith("copying the shipped model again")
  assert report["shipped"] == str(source_model.shipped_path(cfg))
  jax.tree_util.tree_map(np.testing.assert_array_equal, again.depth, first.depth)


_CACHED_PROGRAM = """
import jax, jax.numpy as jnp
from pitta_jax.source_model import enable_compilation_cache, repairing_compilation_cache
enable_compilation_cache()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # store even this one
with repairing_compilation_cache():
  print(float(jax.jit(lambda x: jnp.sin(x) * 3 + 1)(jnp.float32(2.0))))
"""


def test_a_compiled_program_cut_short_in_the_cache_is_removed_and_stored_again(tmp_path):
  """JAX writes a cache entry in place and never replaces one: an entry cut short by a kill or
  a full disk made every later command warn (two lines) and compile again. The command removes
  it, says so in one line, and stores its own compile: the entry is whole again."""
  import subprocess
  env = {**os.environ, source_model.CACHE_ENV: str(tmp_path), "JAX_PLATFORMS": "cpu"}
  run = lambda: subprocess.run([sys.executable, "-c", _CACHED_PROGRAM], env=env,
                               capture_output=True, text=True, timeout=120)
  first = run()
  assert first.returncode == 0, first.stderr
  entries = list((tmp_path / "xla").glob("jit__lambda-*-cache"))
  assert len(entries) == 1
  whole = entries[0].read_bytes()
  entries[0].write_bytes(whole[:len(whole) // 2])
  second = run()
  assert second.returncode == 0 and second.stdout == first.stdout
  assert "Error reading persistent compilation cache" not in second.stderr
  assert f"warning: {entries[0]}: a damaged compiled program in the cache" in second.stderr
  assert entries[0].read_bytes() == whole  # whole again: the next command loads it


def test_retrain_trains_over_a_cache_and_a_shipped_model(tmp_path, monkeypatch):
  """`retrain=True` (`train-source --retrain`) trains even when the config has a cache entry
  and a shipped model, and its result replaces the cache entry, which the next plain call
  reads. Training is stood in for by a function returning the shipped variables with a marker
  in its report."""
  monkeypatch.setenv(source_model.CACHE_ENV, str(tmp_path))
  cfg = SourceConfig()
  first, _ = source_model.load_or_train_source(cfg, quiet=True)  # cache entry from the package
  calls = []

  def fake_train(c, quiet=False):
    calls.append(c)
    return first.depth, first.pose, {"trained": "fake"}

  monkeypatch.setattr(source_model, "train_source", fake_train)
  _, report = source_model.load_or_train_source(cfg, quiet=True, retrain=True)
  assert calls == [cfg] and report["trained"] == "fake" and "shipped" not in report
  _, again = source_model.load_or_train_source(cfg, quiet=True)
  assert calls == [cfg] and again["trained"] == "fake"


def test_shipped_model_loads_bitwise(shipped):
  """The default config finds the shipped file; its float16 parameters come back as exactly
  their float32 values (first from the package, then from the cache), BN statistics as stored,
  the pose net included; the file stays compact."""
  path, record, first, again, report = shipped
  assert report["shipped"] == str(path) and record["config"] == report["config"]
  assert path.stat().st_size < 60e6
  with np.load(path) as arrays:
    assert len(arrays.files) > 100
    for name in arrays.files:
      net, collection, *rest = name.split("/")
      stored = arrays[name]
      assert stored.dtype == (np.float16 if collection == "params" else np.float32), name
      for weights in (first, again):
        tree = weights.depth if net == "depth" else weights.pose
        leaf = tree[collection]
        for k in rest:
          leaf = leaf[k]
        assert leaf.dtype == np.float32
        np.testing.assert_array_equal(leaf, stored.astype(np.float32), err_msg=name)
  assert first.pose is not None and first.config["has_pose"]


@pytest.fixture(scope="module")
def evaluation(shipped):
  """The first EVAL_FRAMES frames of the shipped model's recorded evaluation street."""
  record = shipped[1]["evaluation"]
  street, frames = source_model.evaluation_frames(SourceConfig(), record["seed"], EVAL_FRAMES)
  return street, frames


def test_shipped_model_matches_its_recorded_metrics(shipped, evaluation):
  """Clear-domain AbsRel and delta < 1.25 of the loaded model equal the values recorded when
  the file was written, frame by frame. Tolerance: the recomputation runs the same float32
  network on the same rendered frames, so only XLA's summation order on another CPU can differ
  (~1e-6 relative in depth, i.e. ~1e-6 in AbsRel, and a few pixels of a1 at the 1.25 threshold
  out of ~20,000); a changed weight or renderer moves AbsRel by far more than 1e-4."""
  _, record, weights, _, _ = shipped
  got = source_model.evaluate_depth(weights, evaluation[1])
  want = record["evaluation"]["per_frame"][:EVAL_FRAMES]
  assert [g["name"] for g in got] == [w["name"] for w in want]
  for g, w in zip(got, want):
    print(g["name"], g["abs_rel"], w["abs_rel"], g["a1"], w["a1"])
    np.testing.assert_allclose(g["abs_rel"], w["abs_rel"], atol=1e-4)
    np.testing.assert_allclose(g["a1"], w["a1"], atol=2e-4)


def test_shipped_pose_net_recovers_the_motion(shipped, evaluation):
  """On an unseen street the pose net's T is the true camera motion within a measured bound,
  used as MonoDepth2 uses it: frames in temporal order, T(0 -> +1) = T(axisangle, translation),
  T(0 -> -1) = the inverted T of the pair (-1, 0). Bound: 0.01 per matrix entry (1 cm of the
  0.8 m step, 0.6 degrees); measured on the street's 39 pairs when shipped: translation error
  mean 1.2 mm, max 3.0 mm, rotation 0.03 degrees."""
  _, _, weights, _, _ = shipped
  street, frames = evaluation
  images = np.stack([f.image for f in frames])
  forward = source_model.predict_motions(weights, images[:-1], images[1:])
  backward = source_model.predict_motions(weights, images[:-1], images[1:], invert=True)
  for n in range(len(frames) - 1):
    print(n, np.abs(forward[n] - camera_motion(street, n, n + 1)).max(),
          np.abs(backward[n] - camera_motion(street, n + 1, n)).max())
    np.testing.assert_allclose(forward[n], camera_motion(street, n, n + 1), atol=BOUND)
    np.testing.assert_allclose(backward[n], camera_motion(street, n + 1, n), atol=BOUND)


def test_networks_train_at_their_own_learning_rate(monkeypatch, capsys):
  """`adapt --model litemono` and `train-source --source.model litemono` train Lite-Mono at
  3e-4 (at the default 1e-3 it stalls: loss 1.86 after 250 steps), as Table 3 does; a given
  --source.lr and other networks keep theirs. (Before, only the experiments used 3e-4.)"""
  from pitta_jax import sources
  from pitta_jax.cli import main
  seen = []

  def fake(cfg, quiet=False, retrain=False):
    seen.append(cfg)
    raise SystemExit(0)               # stop before any training

  monkeypatch.setattr(source_model, "load_or_train_source", fake)
  for call in (lambda: sources.open_weights(None, "synthetic", True, "litemono"),
               lambda: sources.open_weights(None, "synthetic", True, "hrdepth"),
               lambda: main(["train-source", "--source.model", "litemono", "--quiet"]),
               lambda: main(["train-source", "--source.model", "litemono", "--source.lr",
                             "1e-4", "--quiet"])):
    with pytest.raises(SystemExit):
      call()
  assert [(c.model, c.lr) for c in seen] == [("litemono", 3e-4), ("hrdepth", 1e-3),
                                             ("litemono", 3e-4), ("litemono", 1e-4)]
  assert "litemono trains at --source.lr 0.0003" in capsys.readouterr().err
