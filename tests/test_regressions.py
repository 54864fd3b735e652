"""Regressions of changes, each test failing without its fix."""
import errno
import json
import math
import tempfile

from experiments.common import Entry
from experiments.render import write_table


def _non_finite_values(tmp_path, name, series):
  out = tmp_path / name
  write_table(out, "table2", [Entry("Waymo", "PITTA", {"abs_rel": 0.1, "a1": 0.9},
                                    extra={"abs_rel_per_frame": series})],
              layout="rows", caption="c", group_title="Dataset", row_title="Method",
              seconds=1.0, meta={})
  return json.loads((out / "results.json").read_text())["non_finite_values"]


def test_an_unscored_frame_is_not_counted_as_a_non_finite_value(tmp_path):
  """A row's per-frame series holds NaN for a frame not scored (a fresh run) or null (the same
  row served from the row cache): results.json counts neither as a diverged value, and a rerun
  from the cache writes the same count as the run that computed the rows."""
  fresh = _non_finite_values(tmp_path, "fresh", [float("nan"), 0.1])
  cached = _non_finite_values(tmp_path, "cached", [None, 0.1])
  assert fresh == cached == 0


def test_a_read_only_cache_still_serves_compiled_programs(tmp_path, monkeypatch):
  """enable_compilation_cache on a cache folder that exists but takes no new file (a read-only
  mount holding the compiled programs and source models): the run goes on, as it did."""
  from pitta_jax import source_model
  (tmp_path / "xla").mkdir()
  monkeypatch.setenv(source_model.CACHE_ENV, str(tmp_path))
  real = tempfile.TemporaryFile

  def read_only(*args, dir=None, **kwargs):
    if dir is not None and str(dir).startswith(str(tmp_path)):
      raise PermissionError(errno.EROFS, "Read-only file system")
    return real(*args, dir=dir, **kwargs)
  monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
  updates = {}
  monkeypatch.setattr(source_model.jax.config, "update", lambda k, v: updates.__setitem__(k, v))
  source_model.enable_compilation_cache()  # DataError "cannot write the cache directory" before
  assert updates["jax_compilation_cache_dir"] == str(tmp_path / "xla")


def test_an_unhashable_global_is_held_by_the_runners_key():
  """`run.code_key` keys an unhashable module-level value a function reads by identity and holds
  it: by its id alone, a value freed and replaced by a new object at the same address (a
  notebook rebinding the name) could be served the old compiled step."""
  import gc
  import weakref
  from pitta_jax.run import code_key

  class Unhashable:
    __hash__ = None

  namespace = {"TABLE": Unhashable()}
  exec("def f():\n  return TABLE", namespace)
  first = code_key(namespace["f"])
  assert first == code_key(namespace["f"])  # the same binding: the same key (no recompile)
  held = weakref.ref(namespace["TABLE"])
  namespace["TABLE"] = Unhashable()  # rebound
  gc.collect()
  assert held() is not None  # the key keeps the old value alive, so its id is not reused
  assert code_key(namespace["f"]) != first


def test_a_helper_redefined_two_calls_below_changes_the_runners_key():
  """A notebook that redefines a helper which the loss's helper calls (two calls below the
  loss) must not be served the compiled step of the old helper: `run.code_key` keyed the
  loss's helper by identity, unchanged. A function that calls itself still has a key."""
  from pitta_jax.run import code_key
  namespace = {}
  exec("def scale(x):\n  return 2 * x\n"
       "def helper(x):\n  return scale(x) + 1\n"
       "def loss(x):\n  return helper(x)\n"
       "def countdown(n):\n  return countdown(n - 1) if n else 0\n", namespace)
  first = code_key(namespace["loss"])
  assert first == code_key(namespace["loss"]) and hash(first) == hash(code_key(namespace["loss"]))
  exec("def scale(x):\n  return 3 * x\n", namespace)   # the cell of `scale` edited, run again
  assert namespace["loss"](1) == 4 and code_key(namespace["loss"]) != first
  exec("def scale(x):\n  return 2 * x\n", namespace)   # and put back: the first key again
  assert code_key(namespace["loss"]) == first
  assert code_key(namespace["countdown"]) == code_key(namespace["countdown"])


def test_code_key_walks_each_helper_once(monkeypatch):
  """Helpers that several functions read are keyed once per `code_key` call: a chain of 16
  functions each reading the next two (`f0` reads `f1` and `f2`, ...) was walked once per path
  to each (15,501 calls for 18 functions, growing like Fibonacci's numbers with the chain).
  Counted calls, and keys that still follow a change at the end of the chain."""
  from pitta_jax import run
  namespace = {}
  source = "".join(f"def f{i}(x):\n  return f{i + 1}(x) + f{i + 2}(x)\n" for i in range(16))
  exec(source + "def f16(x):\n  return x\ndef f17(x):\n  return 2 * x\n", namespace)
  calls = []
  real = run.code_key
  monkeypatch.setattr(run, "code_key", lambda *a: calls.append(1) or real(*a))
  first = run.code_key(namespace["f0"])
  print(f"code_key calls for 18 functions: {len(calls)}")
  assert len(calls) < 200
  exec("def f17(x):\n  return 3 * x\n", namespace)
  assert run.code_key(namespace["f0"]) != first


def test_configs_take_numpy_scalars_and_check_nested_configs_and_selectors():
  """A NumPy scalar that fits a number field is taken as its Python value (np.float32(0.25)
  was refused as 'lam must be >= 0'); a nested config field holds its config (ld=None was
  taken and failed when the step was traced); dynamic_classes must be a tuple (3 was a
  TypeError without the field, 'car' was read letter by letter); a selector percentage like
  1.2.3 is the selector's own one-line error (it was float()'s)."""
  import numpy as np
  import pytest
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.methods.adadepth import AdadepthConfig
  from pitta_jax.methods.comoda import ComodaConfig
  from pitta_jax.methods.cotta import CottaConfig
  from pitta_jax.methods.depth_refining import DepthRefiningConfig
  from pitta_jax.methods.pitta import PittaConfig
  from pitta_jax.run import EvalConfig
  for config, field, value in [(PittaConfig(lam=np.float32(0.25)), "lam", 0.25),
                               (CottaConfig(brightness=np.float32(0.25)), "brightness", 0.25),
                               (AdadepthConfig(variance_focus=np.float64(0.5)),
                                "variance_focus", 0.5),
                               (EvalConfig(max_depth=np.float32(80)), "max_depth", 80.0),
                               (AdaptConfig(chunk_size=np.int64(4)), "chunk_size", 4)]:
    got = getattr(config, field)
    assert got == value and type(got) is type(value), (field, got)
  for make, message in [(lambda: PittaConfig(ld=None), "ld must be a DepthRefiningConfig"),
                        (lambda: ComodaConfig(sfm="x"), "sfm must be a SfmLossConfig"),
                        (lambda: DepthRefiningConfig(dynamic_classes=3),
                         "dynamic_classes must be a tuple of COCO ids or names, got 3"),
                        (lambda: DepthRefiningConfig(dynamic_classes="car"),
                         "dynamic_classes must be a tuple of COCO ids or names, got 'car'"),
                        (lambda: AdaptConfig(selector="fraction(cnn=1.2.3,bn=5)"),
                         "cannot parse selector")]:
    with pytest.raises(ValueError, match=message):
      make()
