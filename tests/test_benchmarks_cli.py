"""The benchmark scripts' command lines: a bad count or list is one usage error (exit 2) before
any work, and --help is help, as for the project's commands."""

from __future__ import annotations

import importlib.util
import runpy
import sys
import types
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _script(name: str):
  """benchmarks/<name>.py as a module (its own imports find bench_common beside it)."""
  spec = importlib.util.spec_from_file_location(f"bench_script_{name}", BENCHMARKS / f"{name}.py")
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def _no_work(*args, **kwargs):
  raise AssertionError("the benchmark started work before checking its arguments")


def test_memory_refuses_lengths_that_are_not_counts(capsys):
  """`--lengths abc` ended in a ValueError traceback (exit 1)."""
  memory = _script("memory")
  with pytest.raises(SystemExit) as e:
    memory.main(["--lengths", "abc"])
  assert e.value.code == 2
  assert "--lengths" in capsys.readouterr().err


def test_streams_refuses_zero_streams_before_any_compile(monkeypatch, capsys):
  """`--ks 0` compiled and timed a full-size stream, then failed with a traceback ("no stream
  to stack")."""
  streams = _script("streams")
  monkeypatch.setattr(streams.bc, "depth_network", _no_work)
  with pytest.raises(SystemExit) as e:
    streams.main(["--ks", "0"])
  assert e.value.code == 2
  assert "--ks" in capsys.readouterr().err


def test_step_refuses_zero_frames_before_any_work(monkeypatch, capsys):
  """`--frames 0` built both networks and timed a JAX chunk, then divided by zero."""
  step = _script("step")
  monkeypatch.setattr(step.bc, "torch_and_jax_weights", _no_work)
  for flags in (["--frames", "0"], ["--reps", "0"]):
    with pytest.raises(SystemExit) as e:
      step.main(flags)
    assert e.value.code == 2, flags
    assert "must be >= 1" in capsys.readouterr().err


def test_dav2_full_parity_help_is_help(monkeypatch, capsys):
  """`python benchmarks/dav2_full_parity.py --help` ran the minute-long parity check."""
  monkeypatch.setitem(sys.modules, "test_depth_anything_v2",
                      types.SimpleNamespace(full_size_vits_matches_torch=_no_work))
  monkeypatch.setattr(sys, "argv", [str(BENCHMARKS / "dav2_full_parity.py"), "--help"])
  with pytest.raises(SystemExit) as e:
    runpy.run_path(str(BENCHMARKS / "dav2_full_parity.py"), run_name="__main__")
  assert e.value.code == 0
  assert "usage:" in capsys.readouterr().out
