"""Runs that survive: bad output locations refused before work, one writer per --out, valid JSON
always, frames without ground truth excluded, and resume after a kill -9.

References: hand-built fault fixtures (a file in place of a directory, since the tests run as
root and permissions do not stop root; a second process holding the lock); the uninterrupted run
for the resumed one.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from interrupts import interrupt_a_wait

from pitta_jax.cli import main
from pitta_jax.outputs import (OutputError, atomic_write_files, atomic_write_text, json_safe,
                               open_output_dir)
from pitta_jax.report import Row, write_results


def test_a_lock_taken_as_its_holder_ends_counts_only_on_the_current_file(tmp_path,
                                                                         monkeypatch):
  """Run A ends (unlinks its lock file, then unlocks) between run B's open of that file and B's
  lock, and run C starts on a new lock file: B locked the unlinked file and wrote alongside C.
  B now finds its file gone, takes the current one, and is refused while C holds it."""
  import fcntl
  out = tmp_path / "out"
  a, real, later = open_output_dir(out), fcntl.flock, {}

  def flock(fd, op):
    if not later:
      later["c"] = None
      a.close()                          # A ends: unlink, unlock
      later["c"] = open_output_dir(out)  # C starts on a new lock file
    return real(fd, op)

  monkeypatch.setattr(fcntl, "flock", flock)
  with pytest.raises(OutputError, match="another pitta-jax run is writing there"):
    open_output_dir(out)                 # B
  later["c"].close()
  open_output_dir(out).close()


def test_output_dir_checked_and_locked(tmp_path):
  blocker = tmp_path / "file"
  blocker.write_text("x")
  with pytest.raises(OutputError, match="exists and is not a directory"):
    open_output_dir(blocker)
  with pytest.raises(OutputError, match="cannot write there"):
    open_output_dir(blocker / "sub")  # a file in place of a parent directory
  long = tmp_path / ("a" * 300)  # one name past the file system's 255 bytes
  with pytest.raises(OutputError, match=rf"^--out {re.escape(str(long))}: cannot write there "
                                        rf"\(File name too long\)$"):
    open_output_dir(long)
  first = open_output_dir(tmp_path / "out")
  with pytest.raises(OutputError, match="another pitta-jax run is writing there"):
    open_output_dir(tmp_path / "out")
  first.close()
  open_output_dir(tmp_path / "out").close()  # free again


def test_an_existing_directory_nothing_can_be_written_to_is_refused_by_name():
  """An existing --out directory in which no file can be made (/proc here: the tests run as
  root, whom permissions do not stop) is one line naming --out, found by the probe file before
  any work, not an OSError of the lock file's path."""
  with pytest.raises(OutputError, match=r"^--out /proc: cannot write there \("):
    open_output_dir("/proc")


def test_second_writer_on_one_out_is_refused_with_one_line(tmp_path, capsys):
  out = tmp_path / "out"
  holder = subprocess.Popen(
      [sys.executable, "-c", "import sys, time; from pitta_jax.outputs import open_output_dir;"
       f"d = open_output_dir({str(out)!r}); print('locked', flush=True); time.sleep(60)"],
      stdout=subprocess.PIPE, text=True)
  try:
    assert holder.stdout.readline().strip() == "locked"
    rc = main(["adapt", "--dataset", "synthetic", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: ") and err.count("\n") == 1
    assert "another pitta-jax run" in err
  finally:
    holder.kill()
    holder.wait()


def test_bad_out_fails_before_any_work(tmp_path, capsys):
  blocker = tmp_path / "file"
  blocker.write_text("x")
  # no kitti data and no weights exist under the root: the output check comes before reading
  rc = main(["adapt", "--dataset", "kitti", "--root", str(tmp_path), "--out", str(blocker)])
  err = capsys.readouterr().err
  assert rc == 2 and "--out" in err and "not a directory" in err and err.count("\n") == 1
  for bad, match in ((["--lr", "inf"], "lr must be a finite"),
                     (["--momentum", "-5"], "momentum must be a finite"),
                     (["--checkpoint-every", "-1"], "checkpoint-every must be >= 0"),
                     (["--min-depth", "50", "--max-depth", "10"], "min_depth < max_depth"),
                     (["--resume"], "--resume needs --checkpoint-every")):
    rc = main(["adapt", "--dataset", "synthetic", "--out", str(tmp_path / "o"), *bad])
    err = capsys.readouterr().err
    assert rc == 2 and match in err and err.count("\n") == 1, (bad, err)
  with pytest.raises(SystemExit) as e:  # argparse: one error line (no usage), exit 2
    main(["adapt", "--dataset", "synthetic", "--out", str(tmp_path / "o"),
          "--pitta.ld.dynamic-classes", "car,unicorn"])
  err = capsys.readouterr().err
  assert e.value.code == 2 and "unicorn" in err and err.count("\n") == 1, err
  assert err.startswith("error: argument --pitta.ld.dynamic-classes") and err.endswith(
      "(see pitta-jax adapt --help)\n")
  # the short name several methods share: the selected method's field, parsed as it
  rc = main(["adapt", "--dataset", "synthetic", "--out", str(tmp_path / "o"),
             "--dynamic-classes", "car,unicorn"])
  err = capsys.readouterr().err
  assert rc == 2 and err.count("\n") == 1 and err.startswith("error: --dynamic-classes: ") and (
      "'unicorn' is neither an integer nor a COCO class name" in err), err
  rc = main(["adapt", "--dataset", "synthetic", "--out", str(tmp_path / "o"), "--option",
             "num_frames=3.5"])
  err = capsys.readouterr().err
  assert rc == 2 and "expected int" in err


def test_results_json_is_valid_with_nan(tmp_path):
  metrics = {"abs_rel": float("nan"), "sq_rel": 1.0, "rmse": float("inf"), "rmse_log": 0.1,
             "a1": 0.9, "a2": 0.95, "a3": 0.99}
  write_results(tmp_path, [Row("fog", "PITTA", metrics)], {"logs": {"loss": [1.0, np.nan]}})
  text = (tmp_path / "results.json").read_text()
  def refuse(name):
    raise ValueError(name)
  data = json.loads(text, parse_constant=refuse)  # strict JSON: no NaN / Infinity tokens
  assert data["rows"][0]["metrics"]["abs_rel"] is None and data["logs"]["loss"] == [1.0, None]
  assert data["non_finite_values"] == 3
  assert not list(tmp_path.glob(".*.tmp-*"))  # atomic writes leave no temp file
  assert json_safe({"a": [np.float32(np.nan), 2]}) == ({"a": [None, 2]}, 1)


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
  path = tmp_path / "table.md"
  atomic_write_text(path, "old")
  class Boom(str):
    def encode(self, *a, **k):
      raise OSError(28, "No space left on device")
  with pytest.raises(OSError):
    atomic_write_text(path, Boom("new"))
  assert path.read_text() == "old" and not list(tmp_path.glob(".*.tmp-*"))


def test_files_of_one_result_are_replaced_together_or_not_at_all(tmp_path):
  """The disk fills while the third of a table's files is written: none of the earlier run's
  files is replaced (each was, one by one, until the first two had been renamed)."""
  names = ("t.md", "t.csv", "results.json")
  for name in names:
    (tmp_path / name).write_text("old")

  class Boom(str):
    def encode(self, *a, **k):
      raise OSError(28, "No space left on device")
  with pytest.raises(OSError) as caught:
    atomic_write_files(tmp_path, {"t.md": "new", "t.csv": "new", "results.json": Boom("new")})
  # the error names the file (a command prints "error: DIR/results.json: No space left ...")
  assert (caught.value.errno, caught.value.filename) == (28, str(tmp_path / "results.json"))
  assert [(tmp_path / n).read_text() for n in names] == ["old"] * 3
  assert not list(tmp_path.glob(".*.tmp-*"))
  atomic_write_files(tmp_path, {"t.md": "new", "t.csv": b"new"})
  assert [(tmp_path / n).read_text() for n in names] == ["new", "new", "old"]


def test_a_refused_rename_names_the_file_not_its_temporary(tmp_path):
  """A result file whose name is taken by a directory: the rename's error named the temporary
  file it had just removed (".results.json.tmp-PID: Is a directory"); it names the file."""
  (tmp_path / "results.json").mkdir()
  with pytest.raises(OSError) as caught:
    atomic_write_files(tmp_path, {"t.md": "new", "results.json": b"{}"})
  assert caught.value.filename == str(tmp_path / "results.json")
  assert not list(tmp_path.glob(".*.tmp-*"))


def test_every_file_of_a_result_is_synced_before_the_first_rename(tmp_path, monkeypatch):
  """The write's durability (the module's promise: temporary file, fsync, then rename): each
  temporary file is fsynced, every one before the first `os.replace`, so that a crash after a
  rename cannot find a renamed file whose data never reached the disk; then the directory."""
  events = []
  real_fsync, real_replace = os.fsync, os.replace
  monkeypatch.setattr(os, "fsync", lambda fd: events.append(
      ("fsync", os.path.basename(os.readlink(f"/proc/self/fd/{fd}")))) or real_fsync(fd))
  monkeypatch.setattr(os, "replace", lambda src, dst: events.append(
      ("replace", os.path.basename(dst))) or real_replace(src, dst))
  atomic_write_files(tmp_path, {"t.md": "new", "results.json": b"{}"})
  pid = os.getpid()
  assert events == [("fsync", f".t.md.tmp-{pid}"), ("fsync", f".results.json.tmp-{pid}"),
                    ("replace", "t.md"), ("replace", "results.json"),
                    ("fsync", tmp_path.name)]  # the directory: its renames reach the disk too
  assert (tmp_path / "t.md").read_text() == "new"


def _dead_pid() -> int:
  """The pid of a process that has ended (a killed writer's)."""
  return int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                            capture_output=True, text=True, check=True).stdout)


def test_a_killed_writers_temporaries_go_when_the_directory_is_next_opened(tmp_path):
  """SIGKILL between an atomic write's temporary file and its rename leaves
  `.<name>.tmp-<pid>`: the next command that opens the directory removes it, once its writer is
  gone (a live writer's stays; other dot-files are not touched)."""
  stale = tmp_path / f".results.json.tmp-{_dead_pid()}"
  live = tmp_path / f".results.csv.tmp-{os.getpid()}"
  other = tmp_path / ".notes.tmp-draft"
  for path in (stale, live, other):
    path.write_text("x")
  open_output_dir(tmp_path).close()
  assert not stale.exists() and live.exists() and other.exists()


def test_a_killed_writers_temporaries_go_when_the_file_is_next_written(tmp_path):
  """Outside a locked output directory (a cache entry, `source-stats --out FILE`) nothing else
  cleans a killed writer's `.<name>.tmp-<pid>`: the next atomic write of that file removes the
  dead writers' (a 2.4 MB one stayed beside its statistics file); another file's and other
  dot-files stay (a live writer's: the test above)."""
  from pitta_jax.outputs import atomic_write_bytes
  dead = _dead_pid()
  stale, other_file = tmp_path / f".stats[1].npz.tmp-{dead}", tmp_path / f".other.npz.tmp-{dead}"
  other = tmp_path / ".stats[1].npz.tmp-draft"
  for path in (stale, other_file, other):
    path.write_text("x")
  atomic_write_bytes(tmp_path / "stats[1].npz", b"new")
  assert (tmp_path / "stats[1].npz").read_bytes() == b"new"
  assert not stale.exists() and other_file.exists() and other.exists()


def test_non_utf8_file_names_are_read(tmp_path):
  from pitta_jax.data.image_io import read_image, write_image
  name = os.fsdecode(b"frame_\xff\xfe.png")  # surrogate-escaped: not valid UTF-8
  img = np.random.default_rng(0).uniform(size=(8, 10, 3)).astype(np.float32)
  write_image(tmp_path / name, img)
  back = read_image(tmp_path / name)
  np.testing.assert_allclose(back, np.round(img * 255) / 255, atol=1e-6)


def test_predict_refuses_inputs_sharing_a_stem(tmp_path):
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.image_io import write_image
  from pitta_jax.predict import expand_images
  for d in ("a", "b"):
    write_image(tmp_path / d / "000001.png", np.zeros((4, 4, 3)))
  with pytest.raises(DataError, match="same file stem"):
    expand_images(str(tmp_path / "*" / "*.png"))


def test_dangling_symlink_is_an_error(tmp_path):
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.image_io import list_images
  (tmp_path / "000001.png").symlink_to(tmp_path / "missing.png")
  with pytest.raises(DataError, match="dangling symbolic link"):
    list_images(tmp_path)
  (tmp_path / "000001.png").unlink()
  (tmp_path / "000002.png").mkdir()  # was skipped: the sequence lost a frame without a word
  with pytest.raises(DataError, match="000002.png: has an image's name but is not a file"):
    list_images(tmp_path)


# ---------------------------------------------------------------------- resume after kill -9

H, W, N, K = 64, 96, 6, 2


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory):
  """Weights of the tiny MonoDepth2-shaped network (`tiny_net`), registered for this module as a
  user registers a network (`MODELS[spec.name] = spec`): the runs below test how the engine and
  the commands survive faults, which does not depend on the network's size, and an in-process
  `adapt` of N frames takes ~1.8 s on it against ~4.3 s on ResNet-18 (64x96, compiled step in
  the cache). The subprocesses run `tiny_cli`, the command with the same registration."""
  from pitta_jax.checkpoint import save_weights
  from tiny_net import SPEC, registered, tiny_variables
  with registered():
    root = tmp_path_factory.mktemp("w") / "tiny"
    save_weights(root, SPEC.name, {"height": H, "width": W}, tiny_variables(0))
    yield root


@pytest.fixture(scope="module")
def r18_weights(tmp_path_factory):
  """Random MonoDepth2 ResNet-18 weights at 64x96, for the tests about MonoDepth2's weights."""
  from pitta_jax.checkpoint import save_weights
  from pitta_jax.models.random_init import random_monodepth2_variables
  root = tmp_path_factory.mktemp("w") / "r18"
  save_weights(root, "monodepth2", {"num_layers": 18, "height": H, "width": W},
               random_monodepth2_variables(0))
  return root


@pytest.fixture(scope="module")
def uninterrupted(tiny_weights, tmp_path_factory) -> dict:
  """results.json of `_adapt_args`' run without a fault, from the start: what the tests of
  interrupted and resumed runs compare theirs with (run once for the module)."""
  out = tmp_path_factory.mktemp("uninterrupted") / "full"
  assert main(_adapt_args(tiny_weights, out)) == 0
  return json.loads((out / "results.json").read_text())


def _adapt_args(weights, out, *extra, frames: int = N):
  """The default PITTA configuration at 64x96 in chunks of K frames (the killed subprocess finds
  the step compiled in the suite's shared XLA cache)."""
  return ["adapt", "--dataset", "synthetic", "--weights", str(weights), "--option",
          f"num_frames={frames}", "--option", "domain=fog", "--checkpoint-every", str(K),
          "--quiet", "--out", str(out), *extra]


def _run_until_first_checkpoint(weights, out, *extra, frames: int = N) -> subprocess.Popen:
  """`pitta-jax adapt` (`tiny_cli`) in a subprocess, returned once its first checkpoint is
  complete; each scored frame takes at least 0.5 s, so that the run is still going then."""
  proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("tiny_cli.py")),
                           *_adapt_args(weights, out, *extra, frames=frames)],
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          env={**os.environ, "PITTA_JAX_TEST_SECONDS_PER_FRAME": "0.5"})
  sidecar = out / "checkpoints" / f"state_{K:06d}.json"
  deadline = time.time() + 300
  while not sidecar.exists() and proc.poll() is None and time.time() < deadline:
    time.sleep(0.05)
  assert sidecar.exists(), proc.stderr.read().decode()[-2000:] if proc.poll() else "timeout"
  return proc


def _rate_of(frames: int, seconds: float, fps: float) -> bool:
  """Whether `fps` (results.json's, to 0.01) is `frames` over a time that `seconds` (to 0.01 s)
  rounds: a run of a second or so moves the rate by more than 0.01 within that rounding."""
  return frames / (seconds + 0.005) - 0.005 <= fps <= frames / (seconds - 0.005) + 0.005


def test_kill_then_resume_equals_an_uninterrupted_run(tiny_weights, uninterrupted, tmp_path):
  killed = tmp_path / "killed"
  proc = _run_until_first_checkpoint(tiny_weights, killed)
  proc.send_signal(signal.SIGKILL)
  proc.wait()
  assert not (killed / "results.json").exists()  # killed before the end
  assert main(_adapt_args(tiny_weights, killed, "--resume")) == 0
  resumed, full = json.loads((killed / "results.json").read_text()), uninterrupted
  assert resumed["resumed_at_frame"] >= K and full["resumed_at_frame"] == 0
  assert resumed["per_frame"] == full["per_frame"] and len(full["per_frame"]) == N
  assert resumed["logs"] == full["logs"]
  assert resumed["rows"][0]["metrics"] == full["rows"][0]["metrics"]
  # time and speed cover every frame: the killed call's time up to its checkpoint counts
  seconds = resumed["seconds"]
  assert seconds["total"] > seconds["this_call"] > 0
  assert _rate_of(N, seconds["total"], resumed["rows"][0]["extra"]["fps"])


def test_ctrl_c_while_a_chunk_is_scored_loses_no_frame(tiny_weights, uninterrupted, tmp_path,
                                                       monkeypatch, capfd):
  """Ctrl-C between a chunk's steps and the end of its scoring: the checkpoint is the last
  chunk whose frames were all scored (the interrupted chunk's state would skip its unscored
  frames on --resume), and the resumed run equals an uninterrupted one, frame for frame."""
  from pitta_jax import run as run_lib
  real, calls = run_lib.frame_metrics, []

  def interrupting(*args, **kwargs):
    calls.append(1)
    if len(calls) == 2 * K + 2:   # the second frame of the third chunk
      raise KeyboardInterrupt
    return real(*args, **kwargs)

  out = tmp_path / "cut"
  out.mkdir()
  for name in ("results.json", "results.csv", "table.md", "notes.txt"):  # an earlier run's
    (out / name).write_text("earlier")
  monkeypatch.setattr(run_lib, "frame_metrics", interrupting)
  assert main(_adapt_args(tiny_weights, out)) == 130
  err = capfd.readouterr().err
  # no earlier results beside this run's checkpoints; the user's own file stays
  assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
      "checkpoints", "notes.txt"]
  assert (f"warning: {out}: removed an earlier run's results (results.json, results.csv, "
          f"table.md)") in err
  assert f"interrupted; its first {2 * K} frames are checkpointed" in err
  assert f"--checkpoint-every {K} runs chunks of {K} frames, not --chunk-size 32" in err
  monkeypatch.setattr(run_lib, "frame_metrics", real)
  saved = sorted(p.name for p in (out / "checkpoints").glob("state_??????.json"))
  assert saved[-1] == f"state_{2 * K:06d}.json"          # not the half-scored third chunk's
  assert main(_adapt_args(tiny_weights, out, "--resume")) == 0
  resumed, full = json.loads((out / "results.json").read_text()), uninterrupted
  assert resumed["resumed_at_frame"] == 2 * K and len(full["per_frame"]) == N
  assert resumed["per_frame"] == full["per_frame"] and resumed["logs"] == full["logs"]


def test_a_ctrl_c_while_a_chunk_runs_keeps_that_chunk(tiny_weights, uninterrupted, tmp_path,
                                                      monkeypatch, capfd):
  """XLA cannot stop a running chunk, so a Ctrl-C during its run waited for it all the same and
  then dropped its frames (checkpointing the chunk before): it is said at once, the chunk's
  frames are recorded and checkpointed, and the run stops there; --resume goes on after it and
  equals an uninterrupted run."""
  out = tmp_path / "cut"
  interrupt_a_wait(monkeypatch, 3)
  assert main(_adapt_args(tiny_weights, out)) == 130
  err = capfd.readouterr().err
  assert "interrupted while a chunk runs: it cannot be cut short" in err
  assert f"interrupted; its first {3 * K} frames are checkpointed" in err
  monkeypatch.undo()
  assert main(_adapt_args(tiny_weights, out, "--resume")) == 0
  resumed, full = json.loads((out / "results.json").read_text()), uninterrupted
  assert resumed["resumed_at_frame"] == 3 * K
  assert resumed["per_frame"] == full["per_frame"] and resumed["logs"] == full["logs"]


def test_a_second_ctrl_c_stops_the_wait_for_a_chunk(capfd):
  """Hand case of the wait: the first interrupt is held and returned once the arrays are ready
  (a line on stderr at once), a second one raises."""
  from pitta_jax.adapt import engine
  polls = []

  class Pending:  # a chunk's array: interrupted on the 2nd poll, ready from the 4th on
    def __init__(self, cuts):
      self.cuts = cuts

  def all_ready(leaves):
    polls.append(1)
    if len(polls) in leaves[0].cuts:
      raise KeyboardInterrupt
    return len(polls) >= 4
  import unittest.mock
  with unittest.mock.patch.object(engine, "_all_ready", all_ready), \
      unittest.mock.patch.object(engine, "POLL_SECONDS", 0.0):
    held = engine.wait_for_chunk([Pending({2})])
    assert isinstance(held, KeyboardInterrupt) and len(polls) == 4
    assert "interrupted while a chunk runs" in capfd.readouterr().err
    polls.clear()
    with pytest.raises(KeyboardInterrupt):
      engine.wait_for_chunk([Pending({1, 2})])
    assert engine.wait_for_chunk([Pending(set())]) is None


def test_a_record_is_cut_back_to_its_marks():
  """Hand case: what a chunk added to a run record after its marks were taken goes (frames,
  per-lambda results, log entries, a log first written by that chunk); the rest stays."""
  from pitta_jax.run import record_marks, truncate_record
  record = {"names": ["a"], "per_frame": [[{"abs_rel": 1.0}], []], "logs": {"loss": [0.5]},
            "fingerprint": "f", "seconds": 2.0}
  marks = record_marks(record)
  record["names"].append("b")
  record["per_frame"][0].append({"abs_rel": 2.0})
  record["per_frame"][1].extend([{"abs_rel": 3.0}, {"abs_rel": 4.0}])
  record["logs"]["loss"].append(0.25)
  record["logs"]["l_d"] = [0.1]
  truncate_record(record, marks)
  assert record == {"names": ["a"], "per_frame": [[{"abs_rel": 1.0}], []],
                    "logs": {"loss": [0.5]}, "fingerprint": "f", "seconds": 2.0}


def test_sigterm_stops_like_ctrl_c(tiny_weights, tmp_path):
  """SIGTERM (a scheduler's stop): the run stops as on Ctrl-C, with the last completed chunk
  checkpointed, the output directory unlocked, exit 143 and a line saying how to resume."""
  out = tmp_path / "term"
  proc = _run_until_first_checkpoint(tiny_weights, out, frames=400)
  proc.send_signal(signal.SIGTERM)
  assert proc.wait(timeout=120) == 143
  err = proc.stderr.read().decode()
  assert re.search(r"^interrupted; its first \d+ frames are checkpointed: run the same command "
                   r"with --resume to continue$", err, re.M)
  assert not (out / ".pitta-jax.lock").exists() and not (out / "results.json").exists()
  assert sorted(out.glob("checkpoints/state_??????.json"))


def test_a_cache_resume_starts_afresh_over_another_runs_checkpoints(tiny_weights, tmp_path,
                                                                    capsys):
  """resume=RESUME_OWN (an experiment row's checkpoints, a cache): another run's checkpoints
  are removed with a warning and the run starts from its first frame, where resume=True
  refuses them (the test below)."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  from pitta_jax.run import RESUME_OWN, run_sequence
  out = tmp_path / "out"
  assert main(_adapt_args(tiny_weights, out)) == 0  # an N-frame run's checkpoints
  capsys.readouterr()
  frames = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=N - K, domain="fog"))
  result = run_sequence(load_weights(tiny_weights), frames, AdaptConfig(), quiet=True,
                        checkpoint_dir=out / "checkpoints", checkpoint_every=K, resume=RESUME_OWN)
  err = capsys.readouterr().err
  assert f"warning: {out / 'checkpoints'}: its checkpoints are not this run's" in err
  assert result.resumed_at == 0 and result.status == "ok" and len(result.per_frame) == N - K


def test_ctrl_c_between_checkpoints_saves_the_last_chunk_without_the_cut_ones_frames(
    tiny_weights, uninterrupted, tmp_path, monkeypatch, capfd):
  """--checkpoint-every 2K in chunks of K: Ctrl-C while the second chunk is scored, before any
  checkpoint, saves the first chunk's state with the first chunk's frames only (the cut chunk's
  scored frame is dropped from the record, else a resume would score it twice), and the resumed
  run equals an uninterrupted one, frame for frame. The checkpoint's time is the first chunk's
  too: the cut chunk's (here an hour on the run's clock) is not counted, as a resume runs that
  chunk again and counts it then."""
  import types
  from pitta_jax import run as run_lib
  real, calls = run_lib.frame_metrics, []
  hour = [0.0]  # added to the run's clock once the cut chunk has taken its hour
  monkeypatch.setattr(run_lib, "time", types.SimpleNamespace(
      perf_counter=lambda: time.perf_counter() + hour[0]))

  def interrupting(*args, **kwargs):
    calls.append(1)
    if len(calls) == K + 2:   # the second frame of the second chunk
      hour[0] = 3600.0
      raise KeyboardInterrupt
    return real(*args, **kwargs)

  every = ("--checkpoint-every", str(2 * K), "--chunk-size", str(K))
  out = tmp_path / "cut"
  monkeypatch.setattr(run_lib, "frame_metrics", interrupting)
  assert main(_adapt_args(tiny_weights, out, *every)) == 130
  assert f"interrupted; its first {K} frames are checkpointed" in capfd.readouterr().err
  monkeypatch.setattr(run_lib, "frame_metrics", real)
  monkeypatch.setattr(run_lib, "time", time)
  saved = sorted(p.name for p in (out / "checkpoints").glob("state_??????.json"))
  assert saved == [f"state_{K:06d}.json"]
  sidecar = json.loads((out / "checkpoints" / saved[0]).read_text())
  assert len(sidecar["names"]) == len(sidecar["per_frame"]) == K
  assert 0 < sidecar["seconds"] < 3600
  assert all(len(v) == K for v in sidecar["logs"].values())
  assert main(_adapt_args(tiny_weights, out, *every, "--resume")) == 0
  # the uninterrupted run also runs chunks of K (checkpointing every K)
  resumed, full = json.loads((out / "results.json").read_text()), uninterrupted
  assert resumed["resumed_at_frame"] == K and len(full["per_frame"]) == N
  assert resumed["per_frame"] == full["per_frame"] and resumed["logs"] == full["logs"]


def test_a_resume_with_other_dataset_options_is_refused_naming_them(tiny_weights, tmp_path,
                                                                    capsys):
  """A synthetic frame's name holds its domain and seed, not --option severity (nor the
  traffic; a folder's names hold no depth_dir or --segmentation maps): a --resume with another
  severity continued the old run's checkpoint and wrote its numbers under the new options, exit
  0. It is refused with one line naming the option, and so is another --adapt.lr, by name."""
  out = tmp_path / "out"
  assert main(_adapt_args(tiny_weights, out, frames=K)) == 0   # its checkpoint at K frames
  for flags, named in ((("--option", "severity=0.1"), "severity=0.1"),
                       (("--adapt.lr", "0.001"), "adapt.lr")):
    capsys.readouterr()
    assert main(_adapt_args(tiny_weights, out, "--resume", *flags, frames=K)) == 2, flags
    err = [line for line in capsys.readouterr().err.splitlines()
           if not line.startswith("note: ")]
    assert len(err) == 1 and "none of this run" in err[0] and named in err[0], (flags, err)
  assert json.loads((out / "results.json").read_text())["options"] == [
      f"num_frames={K}", "domain=fog"]   # a refused --resume leaves the results as they were


def test_ctrl_c_as_a_checkpoint_save_ends_keeps_the_chunk_it_saved(tiny_weights, tmp_path,
                                                                   monkeypatch, capfd):
  """Ctrl-C (or SIGTERM) landing while the first checkpoint is saved, after its state is
  written: the save removed what it wrote, the run saved nothing else (its last completed
  chunk was the one being saved), said "no checkpoint was saved yet" and removed --out, so the
  chunk's frames were lost. The completed chunk is saved, and --resume continues after it."""
  from pitta_jax import run as run_lib
  real, calls = run_lib.save_state, []

  def interrupted(path, state):
    real(path, state)
    calls.append(path)
    if len(calls) == 1:   # the Ctrl-C lands as orbax's save returns
      raise KeyboardInterrupt

  out = tmp_path / "cut"
  monkeypatch.setattr(run_lib, "save_state", interrupted)
  assert main(_adapt_args(tiny_weights, out, frames=2 * K)) == 130
  assert f"interrupted; its first {K} frames are checkpointed" in capfd.readouterr().err
  monkeypatch.setattr(run_lib, "save_state", real)
  saved = sorted(p.name for p in (out / "checkpoints").glob("state_??????.json"))
  assert saved == [f"state_{K:06d}.json"]
  assert main(_adapt_args(tiny_weights, out, "--resume", frames=2 * K)) == 0
  resumed = json.loads((out / "results.json").read_text())
  assert resumed["resumed_at_frame"] == K and len(resumed["per_frame"]) == 2 * K


def test_a_run_of_another_evaluation_protocol_is_another_run(r18_weights):
  """The fingerprint a checkpoint carries holds the evaluation's config: a --resume with other
  --eval.* flags does not continue frames scored under the old protocol."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.methods import build
  from pitta_jax.run import EvalConfig, run_fingerprint
  weights, method, cfg = load_weights(r18_weights), build("pitta"), AdaptConfig()
  names = ["a", "b"]
  prints = {run_fingerprint(weights, method, cfg, ev, names)
            for ev in (EvalConfig(), EvalConfig(max_depth=50.0), EvalConfig(garg_crop=True))}
  assert len(prints) == 3


def test_a_run_with_other_pose_weights_is_another_run(r18_weights):
  """A method that runs the pose network (CoMoDa) continues only a run of the same pose
  weights: the fingerprint held the depth network's values alone. A method without a pose
  network keeps its fingerprint whatever the pose weights."""
  import dataclasses
  import jax
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.methods import build
  from pitta_jax.run import EvalConfig, run_fingerprint
  weights = load_weights(r18_weights)
  pose = {"params": {"pose_conv": {"kernel": np.zeros((3, 3, 6, 4), np.float32)}}}
  moved = jax.tree_util.tree_map(lambda a: a + 1, pose)
  names = ["a", "b"]
  for method, differ in ((build("comoda"), True), (build("pitta"), False)):
    prints = {run_fingerprint(dataclasses.replace(weights, pose=p), method, AdaptConfig(),
                              EvalConfig(), names) for p in (pose, moved)}
    assert (len(prints) == 2) == differ, method.name
    assert "pose" in method.needs or not differ


def test_an_interrupt_before_the_first_frame_claims_no_checkpoint(tiny_weights, tmp_path,
                                                                   monkeypatch, capfd):
  """Ctrl-C while a run loads, before its first frame: the checkpoints in --out are still an
  earlier run's (other settings), not yet removed. The stopped line says the run had not begun;
  it had said "its first 4 frames are checkpointed: run the same command with --resume", which
  the --resume then refused."""
  from pitta_jax import run as run_lib
  out = tmp_path / "out"
  earlier = out / "checkpoints"
  earlier.mkdir(parents=True)
  (earlier / "state_000004").mkdir()
  (earlier / "state_000004.json").write_text("{}")

  def interrupted(directory):
    raise KeyboardInterrupt
  monkeypatch.setattr(run_lib, "_clear_checkpoints", interrupted)
  capfd.readouterr()
  assert main(_adapt_args(tiny_weights, out)) == 130
  assert capfd.readouterr().err.splitlines()[-1] == "interrupted before its first frame"


@pytest.mark.parametrize("replaced", [False, True])
@pytest.mark.parametrize("checkpointing", [True, False])
def test_an_out_removed_while_a_run_goes_on_is_not_made_again(tiny_weights, tmp_path,
                                                              monkeypatch, capsys, checkpointing,
                                                              replaced):
  """--out removed (rm -rf), or removed and made again (by hand, or by a second run that locks
  it), while adapt runs: the run stops with one line at its next write (a checkpoint, or its
  results). It had re-made a removed directory without its lock, and went on saving into one
  made again, where its pruning of old checkpoints removed the second run's."""
  import shutil
  from pitta_jax import run as run_lib
  real, calls = run_lib.frame_metrics, []
  out = tmp_path / "out"

  def removing(*args, **kwargs):
    calls.append(1)
    if len(calls) == K + 1:  # a frame of the second chunk, after the first checkpoint
      shutil.rmtree(out)
      if replaced:  # a second run's directory: its lock and a checkpoint of its own
        (out / "checkpoints" / "state_000002").mkdir(parents=True)
        (out / "checkpoints" / "state_000002.json").write_text("{}")
        (out / ".pitta-jax.lock").write_text("")
    return real(*args, **kwargs)

  monkeypatch.setattr(run_lib, "frame_metrics", removing)
  args = _adapt_args(tiny_weights, out)
  if not checkpointing:
    at = args.index("--checkpoint-every")
    args = args[:at] + args[at + 2:]
  capsys.readouterr()
  assert main(args) == 2
  err = capsys.readouterr().err.splitlines()
  assert err[-1] == (f"error: --out {out}: removed while the command ran; its results are not "
                     f"written (run it again)"), err
  if replaced:  # the second run's files as they were, nothing of the first run's beside them
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        ".pitta-jax.lock", "checkpoints", "checkpoints/state_000002",
        "checkpoints/state_000002.json"]
  else:
    assert not out.exists()


def test_a_checkpoint_folder_replaced_under_a_library_run_stops_it(tiny_weights, tmp_path,
                                                                   monkeypatch):
  """run_sequence called without a command's check watches its checkpoint folder itself: a
  folder removed and made again under the same name stops the run at its next save."""
  import shutil
  from pitta_jax import run as run_lib
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  from pitta_jax.outputs import OutputError
  real, calls = run_lib.frame_metrics, []
  folder = tmp_path / "runs"

  def replacing(*args, **kwargs):
    calls.append(1)
    if len(calls) == K + 1:
      shutil.rmtree(folder)
      folder.mkdir()
    return real(*args, **kwargs)

  monkeypatch.setattr(run_lib, "frame_metrics", replacing)
  weights = load_weights(tiny_weights)
  frames = list(generate_sequence(SyntheticConfig(height=weights.height, width=weights.width,
                                                  num_frames=N, domain="fog")))
  with pytest.raises(OutputError, match=f"^checkpoint_dir's folder {folder}: removed while"):
    run_lib.run_sequence(weights, frames, AdaptConfig(chunk_size=K), quiet=True,
                         checkpoint_dir=folder / "ckpt", checkpoint_every=K)
  assert list(folder.iterdir()) == []


def test_a_held_output_directory_knows_when_it_was_removed(tmp_path):
  import shutil
  held = open_output_dir(tmp_path / "out")
  held.check()
  shutil.rmtree(tmp_path / "out")
  with pytest.raises(OutputError, match=r"^--out .*out: removed while the command ran"):
    held.check()
  (tmp_path / "out").mkdir()  # made again, by hand or by another run: not this one's lock
  (tmp_path / "out" / ".pitta-jax.lock").write_text("")
  with pytest.raises(OutputError, match="removed while the command ran"):
    held.check()
  held.close()
  assert (tmp_path / "out" / ".pitta-jax.lock").exists()  # close() leaves a lock not its own


def test_fps_after_a_resume_counts_this_calls_frames():
  """8 frames, 4 of them from a checkpoint, this call 2 s: fps 2.0 (this call's 4 frames), and
  total_fps over all 8 frames and both calls' time."""
  from pitta_jax.run import RunResult
  r = RunResult(name="x", per_frame=[], mean={}, logs={}, frame_names=[str(i) for i in range(8)],
                seconds=2.0, kept_depths={}, n_skipped=0, excluded=[], resumed_at=4,
                seconds_before=6.0)
  assert r.fps == 2.0 and r.total_fps == 1.0


def test_resume_takes_only_its_own_runs_checkpoints(tiny_weights, tmp_path, capsys):
  """A checkpoint carries its run's fingerprint (frames, weights, settings): --resume refuses
  another run's with one line (exit 2), and a fresh run clears the checkpoints it finds."""
  out = tmp_path / "out"
  ckpt = out / "checkpoints"
  capsys.readouterr()
  assert main(_adapt_args(tiny_weights, out, "--resume")) == 0  # N frames: checkpoints at 2, 4, 6
  assert (f"note: --resume: no checkpoint in {ckpt}; the run starts at its first frame"
          in capsys.readouterr().err.splitlines())
  assert sorted(p.name for p in ckpt.glob("state_*")) == [  # the newest two are kept
      f"state_{k:06d}{ext}" for k in range(N - K, N + 1, K) for ext in ("", ".json")]
  fewer = N - K  # the same first frames, another sequence
  capsys.readouterr()
  earlier = (out / "results.json").read_text()
  assert main(_adapt_args(tiny_weights, out, "--resume", frames=fewer)) == 2
  err = [line for line in capsys.readouterr().err.splitlines()
         if not line.startswith("note: ")]   # the run's notes (the chunk size) come first
  assert len(err) == 1 and str(ckpt) in err[0] and "none of this run" in err[0]
  assert (out / "results.json").read_text() == earlier  # a refused --resume removes nothing
  assert main(_adapt_args(tiny_weights, out, frames=fewer)) == 0  # fresh: the old ones go
  assert "removed an earlier run's checkpoints" in capsys.readouterr().err
  assert sorted(p.name for p in ckpt.glob("state_*")) == [
      f"state_{k:06d}{ext}" for k in range(K, N - K + 1, K) for ext in ("", ".json")]
  assert main(_adapt_args(tiny_weights, out, "--resume", frames=fewer)) == 0
  done = json.loads((out / "results.json").read_text())
  assert done["resumed_at_frame"] == N - K
  # the newest state damaged (a kill during its save): the one before it is taken, with a warning
  for f in (ckpt / f"state_{N - K:06d}").rglob("*"):
    if f.is_file() and f.parent.name == "d":  # the OCDBT data files
      f.write_bytes(b"garbage")
  capsys.readouterr()
  assert main(_adapt_args(tiny_weights, out, "--resume", frames=fewer)) == 0
  assert f"resuming from state_{N - 2 * K:06d} instead" in capsys.readouterr().err
  assert json.loads((out / "results.json").read_text())["per_frame"] == done["per_frame"]
  # orbax's _METADATA gone (its FileNotFoundError): the same fallback, one warning line
  (ckpt / f"state_{N - K:06d}" / "_METADATA").unlink()
  assert main(_adapt_args(tiny_weights, out, "--resume", frames=fewer)) == 0
  fallback = [line for line in capsys.readouterr().err.splitlines() if "resuming from" in line]
  assert len(fallback) == 1 and fallback[0].startswith("warning: ")
  assert f"resuming from state_{N - 2 * K:06d} instead" in fallback[0]
  assert json.loads((out / "results.json").read_text())["per_frame"] == done["per_frame"]
  # a sidecar whose frames are not its state's (cut to one): not used; nor is a save a kill
  # left unfinished in the way (orbax warned of its temporary directory)
  newest = json.loads((ckpt / f"state_{N - K:06d}.json").read_text())
  (ckpt / f"state_{N - K:06d}.json").write_text(json.dumps(
      {**newest, "names": newest["names"][:1]}))
  (ckpt / f"state_{N:06d}.orbax-checkpoint-tmp-1").mkdir()
  assert main(_adapt_args(tiny_weights, out, "--resume", frames=fewer)) == 0
  again = json.loads((out / "results.json").read_text())
  assert again["resumed_at_frame"] == K and again["per_frame"] == done["per_frame"]
  assert "orbax-checkpoint-tmp" not in capsys.readouterr().err
  assert not list(ckpt.glob("*.orbax-checkpoint-tmp*"))
  # nothing ran in that call: the speed is the earlier calls' (it was frames / ~0 s once)
  seconds = done["seconds"]
  assert seconds["total"] > seconds["this_call"] >= 0
  assert _rate_of(N - K, seconds["total"], done["rows"][0]["extra"]["fps"])


def test_garbage_in_readers_is_refused(tmp_path):
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.folder import open_folder
  from pitta_jax.data.image_io import write_image
  from pitta_jax.data.panoptic_io import parse_segments
  write_image(tmp_path / "img" / "a.png", np.zeros((8, 16, 3)))
  for scale in (0, -256, float("inf")):
    with pytest.raises(DataError, match="depth_scale"):
      open_folder(tmp_path / "img", depth_scale=scale)
  # a JSON boolean is not a segment id (True == 1 in Python)
  with pytest.raises(DataError, match="invalid id True"):
    parse_segments([{"id": True, "category_id": 3}], tmp_path / "x.json")


def test_ground_truth_with_another_aspect_ratio_is_refused():
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.frame import Frame
  from pitta_jax.run import check_aspect
  check_aspect(Frame(np.zeros((400, 881, 3)), np.zeros((800, 1762))))  # half-size image, full GT
  with pytest.raises(DataError, match="another aspect ratio"):
    check_aspect(Frame(np.zeros((16, 16, 3)), np.zeros((6, 8)), name="f1"))


def test_nonfinite_checkpoint_values_and_bad_demo_shifts_fail_before_work(tmp_path, capsys):
  from weights_convert import rules as R
  from weights_convert.pth import CheckpointError
  state = {"w.weight": np.full((2, 3), np.nan, np.float32)}
  rules: R.Rules = []
  R.linear(rules, ("params", "w"), "w", bias=False)
  with pytest.raises(CheckpointError, match="w.weight holds 6 non-finite"):
    R.apply_rules(state, rules, lambda k: False, "x.pth", {("params", "w", "kernel"): (3, 2)})
  t0 = time.time()
  rc = main(["demo", "--retrain", "--shifts", "hail", "--out", str(tmp_path / "d")])
  assert rc == 2 and "hail" in capsys.readouterr().err and time.time() - t0 < 5
  assert not (tmp_path / "d").exists()


def test_frames_without_valid_ground_truth_are_excluded_not_fatal(tiny_weights):
  """A frame whose ground truth has no valid pixel (e.g. LiDAR outside the image) is named and
  left out of the means; the others are scored as usual (reference: the metrics of the two
  good frames computed directly)."""
  import dataclasses
  from pitta_jax import metrics
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  from pitta_jax.run import run_sequence
  frames = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=3, seed=100))
  frames[1] = dataclasses.replace(frames[1], depth=np.zeros_like(frames[1].depth),
                                  name=frames[2].name)  # names need not be unique
  res = run_sequence(load_weights(tiny_weights), frames, AdaptConfig(method="none",
                     bn_stats="running"), quiet=True, keep=(0, 2))
  assert res.excluded == [frames[1].name] and len(res.per_frame) == 2
  want = [metrics.depth_metrics(res.kept_depths[i], frames[i].depth)["abs_rel"] for i in (0, 2)]
  np.testing.assert_allclose(res.mean["abs_rel"], np.mean(want), rtol=1e-12)
  # the per-frame curve keeps frame 2's value at frame 2, not at frame 1 of the same name
  series = res.per_frame_series("abs_rel")
  assert np.isnan(series[1])
  np.testing.assert_allclose([series[0], series[2]], want, rtol=1e-12)
  assert res.status == "ok"
  # no frame with valid ground truth: reported as not scored, not as an "ok" row without means
  none_valid = [dataclasses.replace(f, depth=np.zeros_like(f.depth)) for f in frames]
  res = run_sequence(load_weights(tiny_weights), none_valid, AdaptConfig(
      method="none", bn_stats="running"), quiet=True)
  assert res.mean == {} and res.status == "not scored: no frame has valid ground truth"


def test_a_diverged_method_finishes_and_is_reported_not_scored(r18_weights):
  """A method whose parameters stay finite but make the network overflow (here SGD at lr 1e30
  on the BN scales) predicts non-finite depths: those frames are named, not scored, and the
  run says where it diverged; the frames before are scored as usual (reference: frame 0's
  metrics computed directly). A results table shows the status instead of numbers."""
  from pitta_jax import metrics
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  from pitta_jax.report import Row, markdown_table
  from pitta_jax.run import run_sequence
  import dataclasses
  # one name for every frame (names need not be unique): the divergence point is an index
  frames = [dataclasses.replace(f, name="same") for f in
            generate_sequence(SyntheticConfig(height=H, width=W, num_frames=3, seed=100))]
  res = run_sequence(load_weights(r18_weights), frames, AdaptConfig(optimizer="sgd", lr=1e30),
                     quiet=True, keep=(0,))
  assert res.nonfinite == [f.name for f in frames[1:]] and res.diverged_at == 1
  assert [m["name"] for m in res.per_frame] == [frames[0].name]
  assert res.mean["abs_rel"] == metrics.depth_metrics(res.kept_depths[0], frames[0].depth)["abs_rel"]
  assert res.status.startswith("diverged: non-finite depth from frame 1 of 3")
  table = markdown_table([Row("fog", "A", {"abs_rel": 0.3}), Row("fog", "B", {"abs_rel": 0.4}),
                          Row("fog", "C", {}, status=res.status)])
  assert "| fog | C | diverged: non-finite depth from frame 1" in table and "**0.300**" in table


def test_method_requirements_are_checked_before_work(tmp_path, capsys):
  for method in ("actmad", "cotta"):
    t0 = time.time()
    rc = main(["adapt", "--dataset", "synthetic", "--method", method, "--out", str(tmp_path / method)])
    err = capsys.readouterr().err
    assert rc == 2 and "--bn-stats running" in err and err.count("\n") == 1
    assert time.time() - t0 < 5 and not (tmp_path / method).exists()


def _png_sequence(directory, n: int) -> list:
  """n 64x96 PNG frames 000.png.. written with OpenCV (smooth, distinct)."""
  import cv2
  directory.mkdir(parents=True)
  paths = []
  for k in range(n):
    ramp = np.linspace(0, 255, W, dtype=np.float32)[None, :, None]
    image = np.broadcast_to(ramp, (H, W, 3)) * (0.5 + 0.1 * k)
    paths.append(directory / f"{k:03d}.png")
    assert cv2.imwrite(str(paths[-1]), np.clip(image, 0, 255).astype(np.uint8))
  return paths


@pytest.mark.parametrize("damage", ["cut short", "empty"])
def test_a_damaged_frame_deep_in_a_folder_stops_the_run_before_any_work(tiny_weights, tmp_path,
                                                                       capsys, damage):
  """A PNG cut short (its IEND chunk lost, as a copy interrupted part-way leaves it) or an
  empty file at frame 5 of 6 is reported before the run starts: an earlier run's results in
  --out, which a starting run removes, are still there. The line is the one reading that frame
  gives (`decode_file`'s)."""
  paths = _png_sequence(tmp_path / "seq", 6)
  data = paths[4].read_bytes()
  paths[4].write_bytes(data[:len(data) // 2] if damage == "cut short" else b"")
  out = tmp_path / "out"
  out.mkdir()
  (out / "results.json").write_text("{}")  # an earlier run's
  rc = main(["adapt", "--dataset", "folder", "--root", str(tmp_path / "seq"), "--weights",
             str(tiny_weights), "--method", "none", "--out", str(out), "--quiet"])
  err = capsys.readouterr().err
  reason = "a PNG file cut short: no IEND chunk" if damage == "cut short" else \
      "not a PNG/JPEG file, or truncated"
  assert rc == 2 and err.count("error") == 1
  assert err.splitlines()[-1] == f"error: {paths[4]}: cannot decode image ({reason})"
  assert (out / "results.json").read_text() == "{}"  # the run did not start
  # the same message as when the frame is read
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.image_io import read_image
  with pytest.raises(DataError) as info:
    read_image(paths[4])
  assert f"error: {info.value}" == err.splitlines()[-1]
  if damage == "empty":  # the file replaced: the same command runs through
    paths[4].write_bytes(data)
    assert main(["adapt", "--dataset", "folder", "--root", str(tmp_path / "seq"), "--weights",
                 str(tiny_weights), "--method", "none", "--out", str(out), "--quiet"]) == 0
    assert len(json.loads((out / "results.json").read_text())["logs"]["loss"]) == 6


def test_a_png_with_data_after_its_iend_chunk_is_not_damaged(tmp_path):
  """IEND need not end the file (some writers append data): the check reads the whole file
  then, and takes it, as decoding does."""
  from pitta_jax.data.image_io import check_image_file, read_image
  from pitta_jax.data.readers import open_dataset
  path = _png_sequence(tmp_path / "seq", 2)[1]
  path.write_bytes(path.read_bytes() + b"trailing bytes after IEND")
  assert check_image_file(path) == path
  assert read_image(path).shape == (H, W, 3)
  open_dataset("folder", tmp_path / "seq").check_files()  # no error


def test_a_binary_split_file_and_a_bad_network_field_name_their_file(tmp_path):
  from pitta_jax.checkpoint import WeightsError, read_model_json
  from pitta_jax.data.errors import DataError
  from pitta_jax.data.kitti import read_split
  split = tmp_path / "test_files.txt"
  split.write_bytes(b"\xff\xfe2011_09_26 0000000000 l\n")
  with pytest.raises(DataError, match=f"^{split}: not a text split file"):
    read_split(split)
  split.write_text("9 0 l\n")  # MonoDepth2's splits/odom/test_files_09.txt
  with pytest.raises(DataError, match=f"^{split}: line 1 is '9 0 l': a KITTI odometry split"):
    read_split(split)
  (tmp_path / "w").mkdir()
  (tmp_path / "w" / "model.json").write_text(json.dumps(
      {"architecture": "monodepth2", "num_layers": "18", "height": 64, "width": 96}))
  with pytest.raises(WeightsError, match=f"^{tmp_path / 'w' / 'model.json'}: num_layers"):
    read_model_json(tmp_path / "w")


def test_sigterm_inside_a_finaliser_still_stops_the_command():
  """A SIGTERM whose handler runs inside a finaliser or a gc callback (JAX frees buffers from
  one): Python prints and drops the exception raised there, and the command ran to its end with
  exit 0 (about 1 kill in 15). terminate_as_interrupt sends it again; it lands outside."""
  from pitta_jax.cli import Terminated, terminate_as_interrupt

  class Finaliser:
    def __del__(self):
      os.kill(os.getpid(), signal.SIGTERM)
      for _ in range(10_000):   # the handler runs here, where Python swallows its exception
        pass

  ran_on, hooks = False, (signal.getsignal(signal.SIGTERM), sys.unraisablehook)
  with pytest.raises(Terminated):
    with terminate_as_interrupt():
      Finaliser()                # collected at once: __del__ runs now
      deadline = time.time() + 5  # the command's work (the signal is sent again within ~10 ms)
      while time.time() < deadline:
        pass
      ran_on = True
  assert not ran_on
  assert (signal.getsignal(signal.SIGTERM), sys.unraisablehook) == hooks  # both restored


def test_ctrl_c_during_a_checkpoint_save_waits_for_its_writers(tmp_path, monkeypatch):
  """Ctrl-C while orbax's threads write a checkpoint: save_tree lets them finish before it
  removes the half-written directory (it removed it under them: hundreds of lines of their
  tracebacks), then re-raises; a second Ctrl-C during that wait still stops."""
  from pitta_jax import checkpoint
  events = []

  class Writer:                           # orbax's checkpointer: save() starts threads
    def __init__(self, interrupts):
      self.interrupts = interrupts

    def save(self, path, tree, force):
      (tmp_path / "state.orbax-checkpoint-tmp-1").mkdir()
      events.append("save")

    def wait_until_finished(self):
      events.append("wait")
      if self.interrupts:
        self.interrupts -= 1
        raise KeyboardInterrupt

  for interrupts, waits in ((1, 2), (2, 2)):
    events.clear()
    monkeypatch.setattr(checkpoint, "_checkpointer", lambda n=interrupts: Writer(n))
    with pytest.raises(KeyboardInterrupt):
      checkpoint.save_tree(tmp_path / "state", {"a": np.zeros(2)})
    assert events == ["save"] + ["wait"] * waits
    assert not list(tmp_path.glob("state.orbax-checkpoint-tmp*"))


def test_ctrl_c_during_a_save_waits_for_orbax_threads_its_wait_lost(tmp_path, monkeypatch):
  """On Python 3.11 a Ctrl-C that interrupts `Thread.join` marks the thread stopped while it runs
  on: orbax's wait returned at once and its commit thread re-created the temporary directory
  after save_tree removed it (an audit: left after SIGINT and SIGTERM in adapt and convert).
  save_tree waits for orbax's named save threads themselves."""
  import threading
  from pitta_jax import checkpoint
  tmp = tmp_path / "state.orbax-checkpoint-tmp-1"

  class Writer:                           # its commit thread writes on after the wait returned
    waits = 0

    def save(self, path, tree, force):
      def commit():
        time.sleep(0.3)
        tmp.mkdir(exist_ok=True)
      threading.Thread(target=commit, name="async_save").start()

    def wait_until_finished(self):       # Ctrl-C, then the lost wait returns at once
      self.waits += 1
      if self.waits == 1:
        raise KeyboardInterrupt

  monkeypatch.setattr(checkpoint, "_checkpointer", Writer)
  with pytest.raises(KeyboardInterrupt):
    checkpoint.save_tree(tmp_path / "state", {"a": np.zeros(2)})
  time.sleep(0.5)                         # past the commit thread's write
  assert not list(tmp_path.glob("state.orbax-checkpoint-tmp*"))


def test_a_signal_dropped_as_the_command_ends_still_stops_it():
  """The command returns before the signal sent again arrives: the block raises it on the way
  out (before: the timer fired after the handlers were restored, killing the process without
  a message, or a traceback after main returned)."""
  from pitta_jax.cli import Terminated, terminate_as_interrupt

  class Finaliser:
    def __del__(self):
      os.kill(os.getpid(), signal.SIGTERM)
      for _ in range(10_000):
        pass

  hooks = (signal.getsignal(signal.SIGTERM), sys.unraisablehook)
  with pytest.raises(Terminated):
    with terminate_as_interrupt():
      Finaliser()                 # and the block ends at once
  assert (signal.getsignal(signal.SIGTERM), sys.unraisablehook) == hooks
  time.sleep(0.05)                # nothing fires later


def test_a_signal_while_a_command_starts_stops_it_with_one_line(monkeypatch, capsys):
  """Ctrl-C or SIGTERM while a command still imports and parses: one line, exit 130 / 143 (a
  traceback before), also when its exception lands in a gc callback during the imports (JAX
  frees buffers from one: the signal was dropped and the whole run went on to exit 0)."""
  from pitta_jax import cli

  def interrupted_parser():
    raise KeyboardInterrupt

  monkeypatch.setattr(cli, "build_parser", interrupted_parser)
  assert cli.main(["adapt"]) == 130
  assert capsys.readouterr().err == "interrupted\n"

  class Finaliser:
    def __del__(self):
      os.kill(os.getpid(), signal.SIGTERM)
      for _ in range(10_000):   # the handler runs here, where Python swallows its exception
        pass

  def importing():              # a signal dropped in a finaliser, then the imports go on
    Finaliser()
    deadline = time.time() + 5
    while time.time() < deadline:
      pass
    raise AssertionError("the command started after the signal")

  monkeypatch.setattr(cli, "build_parser", importing)
  hooks = (signal.getsignal(signal.SIGTERM), sys.unraisablehook)
  assert cli.main(["adapt", "--debug"]) == 143
  assert capsys.readouterr().err.endswith("interrupted\n")
  assert (signal.getsignal(signal.SIGTERM), sys.unraisablehook) == hooks
  # python -m weights_convert / experiments run their main the same way
  assert cli.interruptible(interrupted_parser, debug=True) == 130


def test_a_commands_stderr_holds_no_log_lines_of_orbax_threads(capsys, caplog):
  """A full disk during a checkpoint save: orbax's threads log their tracebacks through absl
  (an audit: 778 lines before the command's one-line error); a command silences them unless
  --debug, and its own error line stays."""
  import logging
  from pitta_jax import cli
  absl = logging.getLogger("absl")
  level = absl.level

  def failing_save():
    try:
      raise OSError(28, "No space left on device")
    except OSError:
      absl.error("Failed to run 2 Handler Commit operations", exc_info=True)  # a save thread
    print("error: No space left on device", file=sys.stderr)
    return 2

  try:
    assert cli.interruptible(failing_save, debug=False) == 2
    assert capsys.readouterr().err == "error: No space left on device\n"
    assert not [r for r in caplog.records if r.name == "absl"]
    absl.setLevel(logging.NOTSET)
    assert cli.interruptible(failing_save, debug=True) == 2
    assert [r.levelname for r in caplog.records if r.name == "absl"] == ["ERROR"]  # --debug
  finally:
    absl.setLevel(level)


def test_the_interrupted_line_offers_resume_only_for_a_run_that_checkpoints(tmp_path,
                                                                           monkeypatch, capsys):
  """Ctrl-C (exit 130): the line says that the last chunk is checkpointed, with --resume to
  continue, only for `adapt --checkpoint-every K` with a complete checkpoint; the same run
  before its first one says none was saved; a run without --checkpoint-every says nothing of
  checkpoints, even over an earlier run's (which --resume, needing the flag, would not take).
  The command and the checkpoints found are stubbed: only the line is checked (a run stopped
  after its frames started; before, see test_an_interrupt_before_the_first_frame_claims_no_
  checkpoint)."""
  from pitta_jax import cli, run

  def stop(args):
    args.frames_started = True  # as run_sequence's on_start marks it
    raise KeyboardInterrupt
  monkeypatch.setattr(cli, "_run_adapt", stop)
  found = [tmp_path / "state_000004.json", tmp_path / "state_000008.json"]
  monkeypatch.setattr(run, "complete_checkpoints", lambda directory: found)
  argv = ["adapt", "--dataset", "synthetic", "--quiet", "--out", str(tmp_path / "o")]
  assert main(argv) == 130
  assert capsys.readouterr().err == "interrupted\n"
  assert main([*argv, "--checkpoint-every", "4"]) == 130
  assert capsys.readouterr().err == ("interrupted; its first 8 frames are checkpointed: run the "
                                     "same command with --resume to continue\n")
  # evaluate checkpoints and resumes alike (it said only "interrupted")
  assert main(["evaluate", *argv[1:], "--checkpoint-every", "4"]) == 130
  assert capsys.readouterr().err == ("interrupted; its first 8 frames are checkpointed: run the "
                                     "same command with --resume to continue\n")
  found.clear()
  assert main([*argv, "--checkpoint-every", "4"]) == 130
  assert capsys.readouterr().err == "interrupted; no checkpoint was saved yet\n"


def test_a_closed_terminal_stops_a_command_as_sigterm_does(capsys):
  """SIGHUP (the ssh session or terminal closed) ended a run at once, without the last chunk's
  checkpoint; it now stops the command where it runs, as SIGTERM, with the shell's status
  128 + 1 (and 143 / 130 for SIGTERM / Ctrl-C)."""
  from pitta_jax import cli

  def signalled(signum):
    def body():
      os.kill(os.getpid(), signum)
      time.sleep(5)  # the command's work: the signal stops it here
      raise AssertionError("the command ran on")
    return body

  hooks = (signal.getsignal(signal.SIGHUP), signal.getsignal(signal.SIGTERM))
  # a background job (nohup, CI) may start with SIGINT ignored: Python's own handler here
  previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
  try:
    for signum, status in ((signal.SIGHUP, 129), (signal.SIGTERM, 143), (signal.SIGINT, 130)):
      assert cli.interruptible(signalled(signum), debug=True) == status
      assert capsys.readouterr().err == "interrupted\n"
  finally:
    signal.signal(signal.SIGINT, previous_int)
  assert (signal.getsignal(signal.SIGHUP), signal.getsignal(signal.SIGTERM)) == hooks


def test_out_of_memory_is_one_line():
  """XLA's RESOURCE_EXHAUSTED (an input size within the flags' limits that the device cannot
  hold) is one line naming what to shrink; other runtime errors are not taken for it."""
  import jax
  from pitta_jax.cli import out_of_memory
  error = jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 51560967936 "
                                     "bytes.\nmore")
  assert out_of_memory(error) == (
      f"out of {jax.default_backend().upper()} memory: Out of memory allocating 51560967936 "
      f"bytes. (a smaller --height/--width, --chunk-size or image?)")
  assert out_of_memory(jax.errors.JaxRuntimeError("INTERNAL: something else")) is None
  assert out_of_memory(ValueError("RESOURCE_EXHAUSTED")) is None


def test_host_out_of_memory_is_one_line_too():
  """NumPy's MemoryError and OpenCV's failed allocation (a weights' model.json edited to a
  huge size ended in a 40-line traceback from cv2.resize) are the same one line."""
  import cv2
  from pitta_jax.cli import out_of_memory
  hint = "(a smaller --height/--width, --chunk-size or image?)"
  try:
    np.empty((10 ** 7, 10 ** 7))
  except MemoryError as e:
    assert out_of_memory(e) == f"out of memory: {e} {hint}"
  try:
    cv2.resize(np.zeros((4, 4, 3), np.uint8), (200000, 200000))
  except cv2.error as e:
    assert out_of_memory(e) == f"out of memory: Failed to allocate 120000000000 bytes {hint}"
  assert out_of_memory(cv2.error("(-215:Assertion failed) !ssize.empty()")) is None
  assert out_of_memory(cv2.error("Insufficient memory to decode")) is None  # not OpenCV's form


def test_weights_of_another_network_than_model_are_refused_before_work(r18_weights, tmp_path,
                                                                       capsys, monkeypatch):
  """--model names the network the user means; weights of another architecture are one line
  naming both, found from model.json before the arrays are read, and nothing runs (the --out
  directory the command made is removed again)."""
  from pitta_jax import sources
  loads = []
  monkeypatch.setattr(sources, "load_weights", lambda d: loads.append(d))
  out = tmp_path / "o"
  assert main(["adapt", "--dataset", "synthetic", "--weights", str(r18_weights), "--model",
               "litemono", "--option", "num_frames=1", "--quiet", "--out", str(out)]) == 2
  assert capsys.readouterr().err == (f"error: --model litemono, but {r18_weights} holds a "
                                     f"monodepth2\n")
  assert not out.exists() and loads == []


def test_weights_of_a_size_no_image_has_are_refused(r18_weights, tmp_path):
  """A model.json whose size is beyond any camera (10^9 rows, a multiple of 32) is refused
  where the weights load, naming the file, and a converter does not write one (it was written,
  and a run on it failed after 40 s with a traceback from an allocation)."""
  import shutil
  from pitta_jax.checkpoint import WeightsError, load_weights, save_weights
  weights = load_weights(r18_weights)
  huge = {"num_layers": 18, "height": 32 * 10 ** 8, "width": W}
  with pytest.raises(ValueError, match="more than 16384 pixels on a side"):
    save_weights(tmp_path / "w", "monodepth2", huge, weights.depth)
  assert not (tmp_path / "w" / "model.json").exists()
  edited = tmp_path / "edited"
  shutil.copytree(r18_weights, edited)
  meta = json.loads((edited / "model.json").read_text())
  (edited / "model.json").write_text(json.dumps({**meta, "height": huge["height"]}))
  with pytest.raises(WeightsError, match=r"model\.json: input size 96x3200000000 .* more than"):
    load_weights(edited)


def test_report_error_is_one_line_for_what_a_user_can_act_on(capsys):
  """The commands' shared handler (pitta-jax, the tables, the converters): one line and exit 2
  for a bad input, flag or file, the command's own kinds and XLA out of memory; anything else
  and everything under --debug raised as it came."""
  import jax
  from pitta_jax.cli import report_error
  from pitta_jax.data.errors import DataError
  from weights_convert.pth import CheckpointError

  def status(error, debug=False, also=()):
    try:
      raise error
    except Exception as e:
      return report_error(e, debug, also)

  for error, line in ((DataError("a.png", "cut short"), str(DataError("a.png", "cut short"))),
                      (ValueError("--lr must be >= 0"), "--lr must be >= 0"),
                      (OSError(28, "No space left on device", "o/x.json"),
                       "o/x.json: No space left on device")):
    assert status(error) == 2 and capsys.readouterr().err == f"error: {line}\n"
  assert status(CheckpointError("enc.pth: not a checkpoint"), also=(CheckpointError,)) == 2
  assert capsys.readouterr().err == "error: enc.pth: not a checkpoint\n"
  with pytest.raises(CheckpointError):  # not a user error unless the command says so
    status(CheckpointError("enc.pth: not a checkpoint"))
  assert status(jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory")) == 2
  assert capsys.readouterr().err.startswith("error: out of ")
  for error in (jax.errors.JaxRuntimeError("INTERNAL: boom"), KeyError("bug")):
    with pytest.raises(type(error)):
      status(error)
  with pytest.raises(ValueError, match="--lr"):
    status(ValueError("--lr must be >= 0"), debug=True)
  assert capsys.readouterr().err == ""


def test_compile_time_is_reported_apart_from_the_steady_rate(tiny_weights):
  """A run's compiling chunks are timed apart (`compile_seconds`, `compiled_frames`) and
  `steady_fps` leaves them out: the demo's ms/frame was the compile's for a method's first
  shift and the step's for the others. A second run on the same compiled runner compiles
  nothing. `none` in chunks of 2 over 6 frames: one compile, in the first chunk."""
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  from pitta_jax.run import Runners, run_sequence
  frames = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=6, seed=100))
  cfg, runners = AdaptConfig(method="none", bn_stats="running", chunk_size=2), Runners()
  first = run_sequence(load_weights(tiny_weights), frames, cfg, quiet=True, runners=runners)
  assert first.compiled_frames == 2 and 0 < first.compile_seconds < first.seconds
  assert first.steady_fps > first.fps
  again = run_sequence(load_weights(tiny_weights), frames, cfg, quiet=True, runners=runners)
  assert again.compiled_frames == 0 and again.compile_seconds == 0.0
  assert again.steady_fps == again.fps


def test_a_failed_first_checkpoint_leaves_no_empty_directory(tmp_path, monkeypatch):
  """The disk fills during a run's first checkpoint save: neither an empty OUT/checkpoints/ nor
  the half-written state stays; a directory that held checkpoints before keeps them."""
  from pitta_jax import run as run_lib

  def full_disk(path, state):
    path.mkdir()  # orbax had started the state's directory
    (path / "part").write_bytes(b"x")
    raise OSError(28, "No space left on device")

  monkeypatch.setattr(run_lib, "save_state", full_disk)
  directory = tmp_path / "checkpoints"
  with pytest.raises(OSError, match="No space"):
    run_lib.save_checkpoint(directory, None, {"names": ["f0", "f1"]})
  assert not directory.exists()

  earlier = directory / "state_000001"
  earlier.mkdir(parents=True)
  (directory / "state_000001.json").write_text("{}")
  with pytest.raises(OSError, match="No space"):
    run_lib.save_checkpoint(directory, None, {"names": ["f0", "f1"]})
  assert sorted(p.name for p in directory.iterdir()) == ["state_000001", "state_000001.json"]


def test_a_save_whose_folder_is_replaced_meanwhile_takes_back_what_it_wrote(tmp_path):
  """The folder's check, before a save writes and again once its files are written (before
  older checkpoints are pruned): where --out was made again while the save wrote, the save
  removes its own files and prunes nothing (the run had written a whole checkpoint into the
  new directory and pruned the checkpoints there, another run's); where it was made again
  before the save, nothing is written, not even the checkpoint directory."""
  from pitta_jax import run as run_lib
  from pitta_jax.outputs import OutputError, removed_while_running
  directory = tmp_path / "checkpoints"
  for k in (2, 3):  # with the new one, the oldest would be pruned (the newest two stay)
    (directory / f"state_{k:06d}").mkdir(parents=True)
    (directory / f"state_{k:06d}.json").write_text("{}")
  calls = []

  def replaced_during_the_save():  # passes before the save, fails after it
    calls.append(len(list(directory.iterdir())))
    if len(calls) > 1:
      raise removed_while_running(tmp_path)
  state = {"w": np.zeros(3, np.float32)}
  with pytest.raises(OutputError, match="removed while the command ran"):
    run_lib.save_checkpoint(directory, state, {"names": ["f0", "f1", "f2", "f3"]},
                            replaced_during_the_save)
  assert calls == [4, 6]  # checked before the save wrote and once its two files were written
  assert sorted(p.name for p in directory.iterdir()) == [
      "state_000002", "state_000002.json", "state_000003", "state_000003.json"]

  def replaced():
    raise removed_while_running(tmp_path)
  fresh = tmp_path / "other" / "checkpoints"
  fresh.parent.mkdir()
  with pytest.raises(OutputError, match="removed while the command ran"):
    run_lib.save_checkpoint(fresh, state, {"names": ["f0"]}, replaced)
  assert not fresh.exists()
  gone = tmp_path / "gone"  # without a check: a missing parent is never made again by a save
  with pytest.raises(OutputError, match=f"^checkpoint_dir's folder {gone}: removed while"):
    run_lib.save_checkpoint(gone / "checkpoints", state, {"names": ["f0"]})
  assert not gone.exists()
  run_lib.save_checkpoint(directory, state, {"names": ["f0", "f1", "f2", "f3"]}, lambda: None)
  assert sorted(p.name for p in directory.iterdir()) == [
      "state_000003", "state_000003.json", "state_000004", "state_000004.json"]


def test_a_failed_command_leaves_a_directory_made_again_alone(tmp_path):
  """open_output_dir made --out; the command fails after --out was removed and made again
  (someone else's now): the failed command's clean-up, which removes the empty directories it
  made, leaves that one (it removed it)."""
  import shutil
  out = tmp_path / "a" / "out"
  with pytest.raises(RuntimeError):
    with open_output_dir(out):
      shutil.rmtree(tmp_path / "a")
      out.mkdir(parents=True)
      raise RuntimeError("the command failed")
  assert out.is_dir()
  with pytest.raises(RuntimeError):  # still its own: removed, with the folder it made above
    with open_output_dir(out / "mine"):
      raise RuntimeError("the command failed")
  assert not (out / "mine").exists() and out.is_dir()


def test_an_early_failure_of_a_run_leaves_no_descriptor_open(tiny_weights, tmp_path):
  """run_sequence watches its checkpoint folder through an open descriptor: a call that fails
  before its frames' loop (here a bad `keep`) leaves none open (one leaked per call)."""
  import os
  from pitta_jax import run as run_lib
  from pitta_jax.adapt import AdaptConfig
  from pitta_jax.checkpoint import load_weights
  from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
  weights = load_weights(tiny_weights)
  frames = list(generate_sequence(SyntheticConfig(height=weights.height, width=weights.width,
                                                  num_frames=2, domain="fog")))
  before = len(os.listdir("/proc/self/fd"))
  for _ in range(3):
    with pytest.raises(TypeError):
      run_lib.run_sequence(weights, frames, AdaptConfig(), quiet=True, keep=5,
                           checkpoint_dir=tmp_path / "ckpt", checkpoint_every=2)
  assert len(os.listdir("/proc/self/fd")) == before


def test_a_commands_stderr_holds_no_closed_event_loop_tracebacks(capsys):
  """A full disk during a checkpoint save: tensorstore's write callbacks then raise
  "RuntimeError: Event loop is closed" as unraisable exceptions (an audit: ~170 tracebacks of 4
  lines around the error line). A command drops those unless --debug; any other unraisable
  exception is still printed."""
  from pitta_jax import cli

  class Raises:
    def __init__(self, error):
      self.error = error

    def __del__(self):
      raise self.error

  def failing_save():
    Raises(RuntimeError("Event loop is closed"))  # dropped at once: an unraisable exception
    Raises(ValueError("something else"))
    print("error: No space left on device", file=sys.stderr)
    return 2

  hook, seen = sys.unraisablehook, []
  try:
    record = sys.unraisablehook = lambda unraisable: seen.append(repr(unraisable.exc_value))
    assert cli.interruptible(failing_save, debug=False) == 2
    assert cli.interruptible(failing_save, debug=False) == 2  # a second command, same process
    assert seen == ["ValueError('something else')"] * 2
    assert sys.unraisablehook is record  # the filter lasts while a command runs
    assert capsys.readouterr().err == "error: No space left on device\n" * 2
    seen.clear()
    sys.unraisablehook = lambda unraisable: seen.append(repr(unraisable.exc_value))
    assert cli.interruptible(failing_save, debug=True) == 2  # --debug: all of it
    assert seen == ["RuntimeError('Event loop is closed')", "ValueError('something else')"]
  finally:
    sys.unraisablehook = hook


def test_a_full_disk_during_a_save_is_one_os_error_naming_the_checkpoint(tmp_path, monkeypatch):
  """tensorstore reports a full disk as a ValueError naming a temporary file the save has just
  removed; save_tree raises it as OSError(28) naming the checkpoint, which the commands print
  as one line. Other errors pass unchanged."""
  from pitta_jax import checkpoint

  class FullDisk:
    def __init__(self, message):
      self.message = message

    def save(self, path, tree, force):
      os.makedirs(f"{path}.orbax-checkpoint-tmp-1/d")
      raise ValueError(self.message)

    def wait_until_finished(self):
      pass

  message = ('RESOURCE_EXHAUSTED: Error writing "00054/0" in OCDBT database at local file '
             '"x.orbax-checkpoint-tmp/ocdbt.process_0/": Failed to write 10326 bytes to file 6: '
             "No space left on device [os_error_code='28']")
  monkeypatch.setattr(checkpoint, "_checkpointer", lambda: FullDisk(message))
  with pytest.raises(OSError) as caught:
    checkpoint.save_tree(tmp_path / "state_000002", {"a": np.zeros(3)})
  assert caught.value.errno == 28 and caught.value.filename == str(tmp_path / "state_000002")
  assert caught.value.strerror == "checkpoint not saved: No space left on device"
  assert os.listdir(tmp_path) == []  # the temporary directory went
  monkeypatch.setattr(checkpoint, "_checkpointer", lambda: FullDisk("bad tree"))
  with pytest.raises(ValueError, match="^bad tree$"):
    checkpoint.save_tree(tmp_path / "state_000002", {"a": np.zeros(3)})

  class PythonWrite(FullDisk):  # orbax's own file writes: an OSError without the file's name
    def save(self, path, tree, force):
      raise OSError(28, "No space left on device")

  monkeypatch.setattr(checkpoint, "_checkpointer", lambda: PythonWrite(""))
  with pytest.raises(OSError) as caught:
    checkpoint.save_tree(tmp_path / "state_000004", {"a": np.zeros(3)})
  assert caught.value.filename == str(tmp_path / "state_000004")


def test_a_damaged_sidecar_is_passed_over_with_a_warning_not_met_as_a_traceback(tmp_path,
                                                                                capsys):
  """A checkpoint's results sidecar with this run's fingerprint and frames but a field missing
  or of the wrong kind (a hand edit, a damaged file): --resume took it and failed frames later
  with KeyError / AttributeError, at every rerun. Now it is passed over like an unreadable one,
  with a warning naming it and what is wrong, and an older good checkpoint is used; with none
  left, one DataError naming it. Sidecars without the keys added later still resume."""
  from pitta_jax.data.errors import DataError
  from pitta_jax.run import _resume_points
  names = ["f0", "f1", "f2", "f3"]
  template = {"per_frame": [], "names": [], "excluded": [], "nonfinite_indices": [],
              "logs": {}, "fingerprint": "fp", "seconds": 0.0}

  def sidecar(done: int, **changes) -> dict:
    record = {"per_frame": [{"name": n, "abs_rel": 0.5, "a1": None} for n in names[:done]],
              "names": names[:done], "excluded": [], "logs": {"loss": [1.0] * done,
                                                              "skipped": [False] * done},
              "fingerprint": "fp", **changes}
    return {k: v for k, v in record.items() if v is not ...}

  def write(directory, done, record):
    (directory / f"state_{done:06d}").mkdir(parents=True, exist_ok=True)
    (directory / f"state_{done:06d}.json").write_text(json.dumps(record))

  good = sidecar(2)  # an older sidecar: no nonfinite_indices, no seconds
  for bad, problem in [(sidecar(4, per_frame=...), "no 'per_frame'"),
                       (sidecar(4, logs="zzz"), "'logs' is not a dict"),
                       (sidecar(4, logs={"loss": ["x"] * 4}), "'logs' holds a value that is not"),
                       (sidecar(4, per_frame=[{"name": "f0", "abs_rel": "garbage"}]),
                        "'per_frame' holds an entry that is not a frame's metrics"),
                       (sidecar(4, seconds="1"), "'seconds' is not a float"),
                       # an edited time: the resumed run reported negative seconds and fps
                       (sidecar(4, seconds=-5.0), "'seconds' is not a time")]:
    directory = tmp_path / problem.replace("'", "").replace(" ", "_")
    write(directory, 2, good)
    write(directory, 4, bad)
    found = _resume_points(directory, "fp", names, template)
    assert [p.name for p, _ in found] == ["state_000002"]
    err = capsys.readouterr().err
    assert err.startswith(f"warning: {directory / 'state_000004.json'}: {problem}")
    assert err.endswith("; resuming from state_000002 instead\n") and err.count("\n") == 1
  directory = tmp_path / "garbage"  # unreadable: passed over as before, now with a warning
  write(directory, 2, good)
  write(directory, 4, good)
  (directory / "state_000004.json").write_text("{garbage")
  assert [p.name for p, _ in _resume_points(directory, "fp", names, template)] == ["state_000002"]
  assert capsys.readouterr().err == (f"warning: {directory / 'state_000004.json'}: unreadable "
                                     f"(JSONDecodeError); resuming from state_000002 instead\n")
  directory = tmp_path / "only_bad"
  write(directory, 4, sidecar(4, excluded=[3]))
  with pytest.raises(DataError, match=r"1 checkpoint\(s\) here, none of this run .*state_000004"
                                      r"\.json: 'names' or 'excluded' holds a value that is not"):
    _resume_points(directory, "fp", names, template)
  sweep = {"names": [], "per_frame": [[], []], "fingerprint": "fp"}  # Table 4: one list per lambda
  write(tmp_path / "sweep", 2, {"names": names[:2], "fingerprint": "fp",
                                "per_frame": [[{"name": "f0", "abs_rel": 1.0}]] * 3})
  with pytest.raises(DataError, match=r"'per_frame' is not 2 lists"):
    _resume_points(tmp_path / "sweep", "fp", names, sweep)
