"""`pitta-jax source-stats` and ActMAD's statistics files: written once, checked when loaded.

Reference: tests/torch_tta.py's `pooled_source_stats` (ActMAD's forward hooks on the PyTorch
MonoDepth2 of torch_monodepth2, torch.mean / torch.var over all the images) on the same random
weights, converted with `pitta-jax convert`; the file is read back with plain `np.load`. Our
statistics are the whole set's; upstream averages per-batch ones (`upstream_source_stats`): the
file is checked against those through the exact relation between the two. The synthetic cache
is checked by counting the computations.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

import torch_monodepth2 as tm
import torch_tta
from pitta_jax import source_model, sources
from pitta_jax.checkpoint import Weights, load_weights
from pitta_jax.cli import main
from pitta_jax.data.errors import DataError
from pitta_jax.methods import actmad, build
from pitta_jax.methods.actmad import ActmadConfig
from pitta_jax.methods.base import SourceData
from pitta_jax.source_stats import FORMAT, load_source_stats, read_source_stats
from test_readers import _write_rgb

H, W, N = 64, 96, 4


@pytest.fixture(scope="module")
def written(tmp_path_factory):
  """Random torch MonoDepth2 converted to a weights dir, N source images, `source-stats` run."""
  root = tmp_path_factory.mktemp("stats")
  enc, dec = tm.ResnetEncoder(18), tm.DepthDecoder(tm.num_ch_enc(18))
  tm.randomize_(enc, 5), tm.randomize_(dec, 6)
  torch.save({**enc.state_dict(), "height": H, "width": W}, root / "encoder.pth")
  torch.save(dec.state_dict(), root / "depth.pth")
  assert main(["convert", "monodepth2", "--encoder", str(root / "encoder.pth"), "--depth",
               str(root / "depth.pth"), "--out", str(root / "weights")]) == 0
  rng = np.random.default_rng(0)
  yy, xx = np.mgrid[0:H, 0:W]
  images = []
  for k in range(N):  # smooth images, so that the statistics are those of image-like inputs
    base = 0.5 + 0.4 * np.sin(xx / (5 + k) + yy / (9 + k) + rng.uniform(0, 6))[..., None]
    rgb = np.clip(np.rint(255 * base * np.array([1, 0.8, 0.6])), 0, 255).astype(np.uint8)
    _write_rgb(root / "src" / f"{k}" / "0000000000.png", rgb)  # one stem in several folders
    images.append(rgb.astype(np.float32) / np.float32(255))
  out = root / "stats" / "mono.npz"
  assert main(["source-stats", "--weights", str(root / "weights"), "--images",
               str(root / "src" / "*" / "*.png"), "--out", str(out)]) == 0
  return root, out, np.stack(images), enc.double().eval(), dec.double().eval()


def test_file_equals_torch_reference(written):
  root, out, images, enc, dec = written
  with np.load(out, allow_pickle=False) as data:
    arrays = {k: data[k] for k in data.files}
  assert arrays["meta:format"].item() == FORMAT
  assert (arrays["meta:architecture"].item(), arrays["meta:height"].item(),
          arrays["meta:width"].item(), arrays["meta:images"].item()) == ("monodepth2", H, W, N)
  assert arrays["meta:layers"].item() == ActmadConfig().layers
  ref = torch_tta.pooled_source_stats(enc, dec, images)
  names = {torch_tta.flax_path(f"{n}.weight").rsplit("/", 1)[0]: n for n in ref}
  layers = sorted(k[len("mean:"):] for k in arrays if k.startswith("mean:"))
  assert len(layers) == len(ref) == 20
  worst = 0.0
  for layer in layers:
    t_mean, t_var = (x.permute(1, 2, 0).numpy() for x in ref[names[layer.split("/", 1)[1]]])
    mean, var = arrays[f"mean:{layer}"], arrays[f"var:{layer}"]
    assert mean.dtype == var.dtype == np.float32 and mean.shape == t_mean.shape
    worst = max(worst, np.max(np.abs(mean - t_mean)) / np.max(np.abs(t_mean)),
                np.max(np.abs(var - t_var)) / np.max(np.abs(t_var)))
  print(f"source-stats file vs torch ActMAD statistics (float32, {N} images): worst max diff / "
        f"max {worst:.1e}")
  assert worst < 1e-5


def test_round_trip_and_mismatches(written):
  root, out, _, _, _ = written
  weights = load_weights(root / "weights")
  meta, raw = read_source_stats(out)
  stats = load_source_stats(out, weights, ActmadConfig().layers)
  assert set(stats) == set(raw) and meta["images"] == N
  for layer, (mean, var) in stats.items():
    np.testing.assert_array_equal(mean, raw[layer][0])
    np.testing.assert_array_equal(var, raw[layer][1])
  # through the CLI's resources: the file, not a computation
  got = sources.method_resources(build("actmad"), weights, "folder", source_stats=str(out))
  assert set(got) == {actmad.RESOURCE} and got[actmad.RESOURCE].keys() == stats.keys()
  cases = [
      (dict(layers=r"encoder/bn1"), r"mono\.npz: has layer encoder/layer1_0/bn1, which layers "
                                    r"'encoder/bn1' does not select in this network \(0 missing, "
                                    r"19 extra"),
      (dict(weights=Weights(weights.spec, {**weights.config, "height": 32, "width": 64},
                            weights.depth)),
       r"mono\.npz: statistics of a monodepth2 at 96x64, but the weights are a monodepth2 at "
       r"64x32"),
  ]
  for change, pattern in cases:
    with pytest.raises(DataError, match=pattern) as info:
      load_source_stats(out, change.get("weights", weights), change.get("layers",
                                                                        ActmadConfig().layers))
    assert "\n" not in str(info.value)
  bad = root / "bad.npz"
  with np.load(out) as data:
    arrays = {k: data[k] for k in data.files}
  arrays["var:encoder/bn1"] = arrays["var:encoder/bn1"][:, :-1]
  np.savez(bad, **arrays)
  with pytest.raises(DataError, match=r"bad\.npz: var of layer encoder/bn1 is \(32, 47, 64\), the "
                                      r"network gives \(32, 48, 64\)"):
    load_source_stats(bad, weights, ActmadConfig().layers)
  # a negative variance (ActMAD would pull the frame's variance towards it), and a NaN mean
  for key, value in (("var:encoder/bn1", -1.0), ("mean:encoder/bn1", np.nan)):
    with np.load(out) as data:
      corrupt = {k: np.array(data[k]) for k in data.files}
    corrupt[key][0, 0, 0] = value
    np.savez(bad, **corrupt)
    with pytest.raises(DataError, match=rf"bad\.npz: {key.split(':')[0]} of layer encoder/bn1 "
                                        rf"holds non-finite or negative values"):
      load_source_stats(bad, weights, ActmadConfig().layers)
  # arrays of another kind than floats (a complex one failed inside the step's trace, a bool
  # one ran), and an input size written as text
  for dtype in (np.complex64, bool, np.int64, "U3"):
    with np.load(out) as data:
      other = {k: np.array(data[k]) for k in data.files}
    other["mean:encoder/bn1"] = other["mean:encoder/bn1"].astype(dtype)
    np.savez(bad, **other)
    with pytest.raises(DataError, match=rf"bad\.npz: mean of layer encoder/bn1 is "
                                        rf"{re.escape(str(np.dtype(dtype)))}, not floating point"):
      load_source_stats(bad, weights, ActmadConfig().layers)
  with np.load(out) as data:
    other = {k: np.array(data[k]) for k in data.files}
  other["meta:height"] = np.asarray(str(other["meta:height"]))
  np.savez(bad, **other)
  with pytest.raises(DataError, match=r"bad\.npz: meta:height '\d+': the input size must be "
                                      r"integers"):
    load_source_stats(bad, weights, ActmadConfig().layers)
  np.savez(bad, data=np.zeros(3))
  with pytest.raises(DataError, match=r"bad\.npz: not a source statistics file"):
    read_source_stats(bad)


def test_adapt_with_mismatching_file_fails_in_one_line(written, tmp_path, capsys):
  root, out, _, _, _ = written
  rc = main(["adapt", "--method", "actmad", "--bn-stats", "running", "--selector",
             "fraction(cnn=100,bn=100)", "--actmad.layers", "encoder/bn1", "--dataset", "folder", "--root", str(root / "src" / "0"),
             "--weights", str(root / "weights"), "--source-stats", str(out), "--out",
             str(tmp_path / "o"), "--quiet"])
  err = capsys.readouterr().err
  *notes, error = err.splitlines()  # the folder has no ground truth: a note says so first
  assert rc == 2 and error.startswith(f"error: {out}: has layer ")
  assert all(n.startswith("note: ") for n in notes)
  assert not (tmp_path / "o").exists()
  assert main(["source-stats", "--weights", str(root / "weights"), "--images",
               str(root / "src" / "0"), "--out", str(tmp_path / "x.npz")]) == 2
  assert "1 image(s); the variance needs at least 2" in capsys.readouterr().err
  assert not (tmp_path / "x.npz").exists()


def test_layers_matching_only_modules_with_several_outputs_fail_in_one_line(written, tmp_path,
                                                                            capsys):
  """`encoder` and `decoder` return several maps (no statistics of their own) and a pattern
  matching only them is refused before any work, as a pattern matching nothing."""
  root, _, _, _, _ = written
  for layers in ("decoder", "encoder", "nothing"):
    assert main(["source-stats", "--weights", str(root / "weights"), "--images",
                 str(root / "src" / "*" / "*.png"), "--layers", layers, "--out",
                 str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--layers {layers!r} matches no module" in err, err
  assert not (tmp_path / "x.npz").exists()
  (tmp_path / "f").write_text("")
  assert main(["source-stats", "--weights", str(root / "weights"), "--images",
               str(root / "src" / "*" / "*.png"), "--out", str(tmp_path / "f" / "x.npz")]) == 2
  assert f"{tmp_path / 'f'} is a file, not a directory" in capsys.readouterr().err
  # a folder nothing can be written to (root writes anywhere on disk; not in /proc): refused
  # before the images are read, with the statistics left uncomputed
  assert main(["source-stats", "--weights", str(root / "weights"), "--images",
               str(tmp_path / "no-images-here"), "--out", "/proc/pitta-jax-test/x.npz"]) == 2
  assert "--out /proc/pitta-jax-test/x.npz: cannot write there" in capsys.readouterr().err
  # an existing file that is not a statistics file (the weights' model.json) is not replaced
  before = (root / "weights" / "model.json").read_bytes()
  assert main(["source-stats", "--weights", str(root / "weights"), "--images",
               str(root / "src" / "*" / "*.png"), "--out",
               str(root / "weights" / "model.json")]) == 2
  assert "exists and is not a statistics file" in capsys.readouterr().err
  assert (root / "weights" / "model.json").read_bytes() == before


def test_an_out_that_is_a_directory_is_named_as_one(tmp_path, capsys):
  """--out naming a directory (the folder meant to hold the file) is one line saying to name
  the .npz file, before the weights (here none) or the images are read (not "exists and is
  not a statistics file", which would send the user looking for a file that is not there)."""
  folder = tmp_path / "stats"
  folder.mkdir()
  assert main(["source-stats", "--weights", str(tmp_path / "none"), "--images",
               str(tmp_path / "none"), "--out", str(folder)]) == 2
  assert capsys.readouterr().err == (f"error: --out {folder}: is a directory; name the .npz "
                                     f"file to write\n")
  assert list(folder.iterdir()) == []


def test_synthetic_statistics_are_cached(written, tmp_path, monkeypatch):
  root = written[0]
  weights = load_weights(root / "weights")
  monkeypatch.setenv(source_model.CACHE_ENV, str(tmp_path))
  monkeypatch.setattr(sources, "SYNTHETIC_SOURCE_SEEDS", (0,))
  monkeypatch.setattr(sources, "SYNTHETIC_SOURCE_FRAMES", 2)
  calls = []
  compute = actmad.source_statistics

  def counted(*args, **kwargs):
    calls.append(kwargs.get("layers", args[3] if len(args) > 3 else None))
    return compute(*args, **kwargs)

  monkeypatch.setattr(actmad, "source_statistics", counted)
  method = build("actmad")
  first = sources.method_resources(method, weights, "synthetic")[actmad.RESOURCE]
  second = sources.method_resources(method, weights, "synthetic")[actmad.RESOURCE]
  assert len(calls) == 1 and len(list((tmp_path / "actmad_stats").glob("*.npz"))) == 1
  for layer, (mean, var) in first.items():
    np.testing.assert_array_equal(second[layer][0], mean)
    np.testing.assert_array_equal(second[layer][1], var)
  # other layers, other weights: other keys, computed again
  sources.method_resources(build("actmad", ActmadConfig(layers=r"encoder/bn1")), weights,
                           "synthetic")
  changed = Weights(weights.spec, weights.config, {
      "params": weights.depth["params"],
      "batch_stats": {**weights.depth["batch_stats"], "encoder": {
          **weights.depth["batch_stats"]["encoder"],
          "bn1": {k: np.asarray(v) + 1 for k, v in
                  weights.depth["batch_stats"]["encoder"]["bn1"].items()}}}})
  sources.method_resources(method, changed, "synthetic")
  assert len(calls) == 3 and len(list((tmp_path / "actmad_stats").glob("*.npz"))) == 3


def test_help_renders(capsys):
  with pytest.raises(SystemExit) as e:
    main(["source-stats", "--help"])
  out = capsys.readouterr().out
  assert e.value.code == 0 and "--layers REGEX" in out and "every encoder BN" in out


def test_source_batches_read_lazily_with_a_progress_bar(capsys):
  images = tuple(np.full((2, 3, 3), k, np.float32) for k in range(5))
  batches = SourceData(images, progress="source statistics").batches(2)
  assert capsys.readouterr().err == ""  # nothing read before the first batch is asked for
  out = list(batches)
  assert [b.shape for b in out] == [(2, 2, 3, 3), (2, 2, 3, 3), (1, 2, 3, 3)]
  assert [b[:, 0, 0, 0].tolist() for b in out] == [[0, 1], [2, 3], [4]]
  assert "source statistics" in capsys.readouterr().err
  assert len(list(SourceData(images).batches(4))) == 2
  assert capsys.readouterr().err == ""  # no title: no bar


def test_file_against_upstreams_averaged_batches(written):
  """Upstream's statistics are the mean over loader batches of each batch's torch.mean and
  torch.var (unbiased, per batch). With two batches of 2 images: our mean equals theirs, and
  our variance is theirs plus the spread between the batches, exactly
  (N - 1) var = sum_b (n_b - 1) var_b + sum_b n_b (mean_b - mean)^2."""
  root, out, images, enc, dec = written
  (avg, per_batch) = torch_tta.upstream_source_stats(enc, dec, [images[:2], images[2:]])
  names = {torch_tta.flax_path(f"{n}.weight").rsplit("/", 1)[0]: n for n in avg}
  with np.load(out, allow_pickle=False) as data:
    arrays = {k: data[k] for k in data.files}
  worst_mean = worst_var = gap = 0.0
  for layer in sorted(k[len("mean:"):] for k in arrays if k.startswith("mean:")):
    name = names[layer.split("/", 1)[1]]
    hwc = lambda t: t.permute(1, 2, 0).numpy()
    mean, var = arrays[f"mean:{layer}"], arrays[f"var:{layer}"]
    u_mean, u_var = hwc(avg[name][0]), hwc(avg[name][1])
    within = sum((2 - 1) * hwc(b[name][1]) for b in per_batch)
    between = sum(2 * (hwc(b[name][0]) - u_mean) ** 2 for b in per_batch)
    worst_mean = max(worst_mean, np.max(np.abs(mean - u_mean)) / np.max(np.abs(u_mean)))
    worst_var = max(worst_var, np.max(np.abs((N - 1) * var - (within + between)))
                    / np.max(np.abs(within + between)))
    gap = max(gap, np.max(np.abs(var - u_var)) / np.max(u_var))
  print(f"vs upstream's averaged batches (2 + 2): mean {worst_mean:.1e}, variance through the "
        f"relation {worst_var:.1e}; our variance differs from theirs by up to {gap:.2f} x max")
  assert worst_mean < 1e-5 and worst_var < 1e-5


def test_weights_identity_tells_networks_apart(written):
  """The cache key's `weights_identity` (module docstring: architecture, model.json, every
  variable's path, dtype, shape and bytes) is equal for equal weights and differs when only
  model.json changes (another input size, same arrays), or when one leaf keeps its bytes but
  not its dtype (float32 read as int32) or its shape (reshaped): each of those is another
  network, whose cached statistics would not fit."""
  from flax.traverse_util import flatten_dict, unflatten_dict
  from pitta_jax.source_stats import weights_identity
  weights = load_weights(written[0] / "weights")
  base = weights_identity(weights)
  copy = Weights(weights.spec, dict(weights.config),
                 unflatten_dict({k: np.array(v) for k, v in flatten_dict(weights.depth).items()}))
  assert weights_identity(copy) == base
  assert weights_identity(Weights(weights.spec, {**weights.config, "height": 32},
                                  weights.depth)) != base
  path = ("params", "encoder", "conv1", "kernel")
  flat = flatten_dict(weights.depth)
  leaf = np.asarray(flat[path])
  for changed in (leaf.view(np.int32), leaf.reshape(-1)):
    assert changed.tobytes() == leaf.tobytes()
    other = Weights(weights.spec, weights.config, unflatten_dict({**flat, path: changed}))
    assert weights_identity(other) != base
