"""Result files that survive: the output directory checked and locked before any work, atomic
writes, and JSON that is always valid.

- `open_output_dir(path)`: creates the directory, proves it writable (a probe file), and takes
  an exclusive lock (`.pitta-jax.lock`, `fcntl.flock`), so a second run on the same `--out`
  is refused with one line instead of racing; the lock goes with the process, also on a kill.
  Used as a context manager, a command that fails leaves no directory it created behind.
- `atomic_write_text` / `atomic_write_bytes`: a temporary file in the same directory, fsync,
  then `os.replace` and an fsync of the directory: a reader (or a crash) sees the old file or
  the new one, never half of one.
  `atomic_write_files`: the files of one result (a table's .md/.csv/.tex/results.json), every
  one written and synced before the first rename, so a failure while writing replaces none.
- `json_safe`: NaN/Inf become `null` (the JSON standard has no such numbers) and are counted.
"""

from __future__ import annotations

import fcntl
import math
import os
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

LOCK_NAME = ".pitta-jax.lock"


class OutputError(ValueError):
  """An output location that cannot be used (one line, names the path)."""


class OutputDir:
  """A checked, locked output directory; release with `close()` (or let the process end)."""

  def __init__(self, path: Path, lock_fd: int, created: list[Path], what: str = "--out"):
    self.path = path
    self._fd = lock_fd
    self._created = created  # directories this call made (removed again if left empty)
    self._what = what

  def check(self) -> None:
    """OutputError when the directory (or its lock file) was removed or replaced since it was
    locked: what the command would write now would re-make it without the lock, where a second
    run could take it."""
    _check_still_open(self._fd, self.path / LOCK_NAME, self.path, self._what)

  def close(self) -> None:
    """Releases the lock and removes the lock file (a killed run leaves the file, unlocked)."""
    if self._fd >= 0:
      if self._holds_lock_file():  # not another run's, in a directory made again meanwhile
        (self.path / LOCK_NAME).unlink(missing_ok=True)
      os.close(self._fd)  # releases the flock
      self._fd = -1

  def _holds_lock_file(self) -> bool:
    """Whether DIR/.pitta-jax.lock is still the file this object locked."""
    return _is_open_file(self._fd, self.path / LOCK_NAME)

  def __enter__(self) -> "OutputDir":
    return self

  def __exit__(self, exc_type, *exc) -> None:
    ours = self._fd >= 0 and self._holds_lock_file()  # (not a directory made again meanwhile)
    self.close()
    if exc_type is not None and ours:  # a failed command leaves no empty directories behind
      for d in reversed(self._created):
        try:
          d.rmdir()
        except OSError:
          break


class WatchedDirectory:
  """`path` as it is when watched, to tell later whether that name still is this directory: an
  open descriptor of it keeps its inode in use, so a directory removed and made again under the
  same name (whose new inode could otherwise take the freed number) is told apart, as
  `OutputDir.check` tells its lock file apart. For library calls that write into a directory
  given to them without its `OutputDir` (a run's checkpoints, the demo's figures)."""

  def __init__(self, path: str | os.PathLike, what: str = "--out"):
    self.path = Path(path)
    self._what = what
    try:
      self._fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY)
    except (FileNotFoundError, NotADirectoryError):
      raise removed_while_running(self.path, what) from None

  def check(self) -> None:
    """OutputError when `path` was removed or replaced since it was watched (or closed)."""
    _check_still_open(self._fd, self.path, self.path, self._what)

  def close(self) -> None:
    if self._fd >= 0:
      os.close(self._fd)
      self._fd = -1

  def __enter__(self) -> "WatchedDirectory":
    return self

  def __exit__(self, *exc) -> None:
    self.close()


def check_passes(check: Callable[[], Any] | None) -> bool:
  """Whether an output directory's check (`OutputDir.check`, `WatchedDirectory.check`; None:
  none) passes: an interrupted run saves or clears files only in a directory still its own."""
  if check is None:
    return True
  try:
    check()
  except OutputError:
    return False
  return True


def removed_while_running(path: Path, what: str = "--out") -> OutputError:
  """The error of a command whose output directory was removed while it ran: what it would
  write now would make the directory again without the command's lock."""
  return OutputError(f"{what} {path}: removed while the command ran; its results are not "
                     f"written (run it again)")


def open_output_dir(path: str | os.PathLike, what: str = "--out") -> OutputDir:
  """Creates/checks/locks `path` before any work (see the module docstring)."""
  if not str(path).strip():  # Path("") is the working directory: never meant
    raise OutputError(f"{what}: an empty path")
  p = Path(path)
  try:  # (exists() itself raises for a name too long)
    if p.exists() and not p.is_dir():
      raise OutputError(f"{what} {p}: exists and is not a directory")
    created = [a for a in reversed((p, *p.parents)) if not a.exists()]
    p.mkdir(parents=True, exist_ok=True)
    _write_probe(p)
  except OSError as e:
    raise OutputError(f"{what} {p}: cannot write there ({e.strerror or e})") from None
  fd = _lock(p / LOCK_NAME)
  if fd < 0:
    raise OutputError(f"{what} {p}: another pitta-jax run is writing there; wait for it or "
                      f"choose another directory")
  remove_stale_temps(p)  # a killed run's half-written files (its results' temporaries)
  return OutputDir(p, fd, created, what)


def _lock(path: Path) -> int:
  """An open descriptor of `path` holding its exclusive flock, or -1 when another process holds
  it. The lock counts only while `path` is still the locked file: a run that ends unlinks the
  file and then unlocks it, so a run that opened the old file in between would lock a file
  that is gone while a third locks the new one; such a lock is dropped and taken again."""
  while True:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
      fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
      os.close(fd)
      return -1
    if _is_open_file(fd, path):
      return fd
    os.close(fd)  # the file was replaced or removed since it was opened: try again


def _check_still_open(fd: int, path: Path, out: Path, what: str) -> None:
  """OutputError naming `out` unless `path` still is the file (or directory) open as `fd`
  (-1: closed)."""
  if fd < 0 or not _is_open_file(fd, path):
    raise removed_while_running(out, what)


def _is_open_file(fd: int, path: Path) -> bool:
  """Whether `path` names the file (or directory) open as `fd` (not removed, not replaced by
  another)."""
  try:
    now = os.stat(path)
  except OSError:
    return False
  held = os.fstat(fd)
  return (now.st_ino, now.st_dev) == (held.st_ino, held.st_dev)


def _write_probe(folder: Path) -> None:
  """Writes and removes a small file in `folder` (OSError where that is not possible): the one
  proof that outputs can be written there (permissions do not stop root, a read-only mount
  does)."""
  probe = folder / f".pitta-jax-probe-{os.getpid()}"
  probe.write_bytes(b"ok")
  probe.unlink()


def check_writable_file(path: str | os.PathLike, what: str = "--out") -> None:
  """OutputError (one line) unless a file can be written at `path`: a probe file is written and
  removed in its nearest existing folder (the folders below it are made when the file is
  written), so that a command that writes one file at its end fails before its work."""
  p = Path(path)
  folder = next(a for a in p.parents if a.exists())
  if not folder.is_dir():
    raise OutputError(f"{what} {p}: {folder} is a file, not a directory")
  try:
    _write_probe(folder)
  except OSError as e:
    raise OutputError(f"{what} {p}: cannot write there ({e.strerror or e})") from None


def _temp_path(directory: Path, name: str) -> Path:
  """Where `atomic_write_files` writes `name` before its rename (named after the writer's pid)."""
  return directory / f".{name}.tmp-{os.getpid()}"


def remove_stale_temps(directory: str | os.PathLike, names: Iterable[str] | None = None
                       ) -> list[Path]:
  """Removes the temporary files `atomic_write_files` left in `directory` when a kill (SIGKILL)
  stopped its writer before the rename: `.<name>.tmp-<pid>` whose process is gone (a live
  writer's are kept), of every name or of `names` only. Returns the removed paths."""
  import glob
  removed = []
  patterns = [".*.tmp-*"] if names is None else [f".{glob.escape(n)}.tmp-*" for n in names]
  for path in (p for pattern in patterns for p in Path(directory).glob(pattern)):
    pid = path.name.rsplit(".tmp-", 1)[1]
    if not (pid.isdigit() and path.is_file()) or _alive(int(pid)):
      continue
    path.unlink(missing_ok=True)
    removed.append(path)
  return removed


def _alive(pid: int) -> bool:
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:  # another user's process
    return True
  return True


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
  """Writes `data` to `path` atomically (temp file in the same directory + fsync + rename)."""
  path = Path(path)
  atomic_write_files(path.parent, {path.name: data})


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
  atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_files(directory: str | os.PathLike, contents: dict[str, str | bytes]) -> None:
  """Writes the files of one result ({name: text or bytes}) into `directory`, each atomically:
  every temporary file is written and synced before the first rename, so a kill can leave two
  runs' files side by side only within the renames themselves (no I/O between them), never
  while a later file is still being written. Text is written as UTF-8."""
  directory = Path(directory)
  temps = {name: _temp_path(directory, name) for name in contents}
  name = ""
  try:
    for name, data in contents.items():
      with open(temps[name], "wb") as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)
        f.flush()
        os.fsync(f.fileno())
    for name, tmp in temps.items():
      os.replace(tmp, directory / name)
    _sync_directory(directory)
  except BaseException as e:
    for tmp in temps.values():
      tmp.unlink(missing_ok=True)
    unnamed = isinstance(e, OSError) and e.errno is not None and (
        e.filename is None or str(e.filename) in {str(t) for t in temps.values()})
    if unnamed:
      # a full disk, a rename refused: name the file, not the temporary one just removed (the
      # commands print "error: FILE: No space left on device")
      raise OSError(e.errno, e.strerror, str(directory / name)) from e
    raise
  # what a killed earlier writer of these files left (a cache entry, `source-stats --out FILE`:
  # places no locked output directory cleans)
  remove_stale_temps(directory, contents)


def _sync_directory(directory: Path) -> None:
  """fsync of `directory` itself, so that its renames reach the disk too (after a power loss
  the files are the new ones, not the old names back). Where a file system or platform refuses a
  directory's fsync, the renames are atomic all the same."""
  try:
    fd = os.open(directory, os.O_RDONLY)
  except OSError:
    return
  try:
    os.fsync(fd)
  except OSError:
    pass
  finally:
    os.close(fd)


def npy_bytes(array: np.ndarray) -> bytes:
  """What `np.save` writes for `array` (no pickles)."""
  import io
  buffer = io.BytesIO()
  np.save(buffer, np.asarray(array), allow_pickle=False)
  return buffer.getvalue()


def rounded_or_none(x: float, digits: int) -> float | None:
  """`round(x, digits)`, or None where `x` is not finite: a rate over no frames (a --resume of a
  finished run) is no value, and written as NaN it counted as a non-finite result."""
  return round(x, digits) if math.isfinite(x) else None


def json_number(x: Any) -> bool:
  """Whether `x` is a number as `json_safe` writes one: an int or float (not a bool), or None
  for a non-finite value. What reading a stored result checks its values against."""
  return x is None or (isinstance(x, (int, float)) and not isinstance(x, bool))


def json_safe(obj: Any) -> tuple[Any, int]:
  """(obj with every non-finite float replaced by None, how many were replaced)."""
  count = 0

  def walk(x):
    nonlocal count
    if isinstance(x, (float, np.floating)):
      if not math.isfinite(float(x)):
        count += 1
        return None
      return float(x)
    if isinstance(x, np.integer):
      return int(x)
    if isinstance(x, np.ndarray):
      return walk(x.tolist())
    if isinstance(x, dict):
      return {k: walk(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
      return [walk(v) for v in x]
    return x

  return walk(obj), count
