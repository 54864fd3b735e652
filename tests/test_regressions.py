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
