"""The one exception type for problems with the user's data files.

A `DataError` message is a single line "<file or directory>: <problem>", so that the CLI can
print it without a traceback (and exit with status 2) and the user knows which file to fix.
Programming errors (wrong argument types, bugs) stay ordinary Python exceptions.
"""

from __future__ import annotations

import os


class DataError(Exception):
  """A missing, malformed or inconsistent data file.

  Args:
    path: the file or directory concerned (None when no single file is to blame).
    problem: what is wrong with it, one sentence without a trailing period.
  """

  def __init__(self, path: str | os.PathLike[str] | None, problem: str):
    self.path = None if path is None else os.fspath(path)
    self.problem = " ".join(str(problem).split())  # one line, whatever the caller passed
    super().__init__(self.problem if self.path is None else f"{self.path}: {self.problem}")

  def __reduce__(self):  # picklable across processes despite the two-argument constructor
    return type(self), (self.path, self.problem)
