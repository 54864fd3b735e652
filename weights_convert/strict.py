"""Strict loading: a checkpoint's keys must be exactly the ones a converter's key table uses."""

from __future__ import annotations

from typing import Callable, Iterable

from weights_convert.pth import CheckpointError


def check_keys(path: str, present: Iterable[str], used: Iterable[str],
               ignorable: Callable[[str], bool]) -> None:
  """Raises CheckpointError listing every unexpected key (in the file, not used, not ignorable)
  and every missing key (used, not in the file); does nothing when they match."""
  present, used = set(present), set(used)
  unexpected = sorted(k for k in present - used if not ignorable(k))
  missing = sorted(used - present)
  problems = []
  if unexpected:
    problems.append(f"{len(unexpected)} unexpected keys: {', '.join(unexpected)}")
  if missing:
    problems.append(f"{len(missing)} missing keys: {', '.join(missing)}")
  if problems:
    raise CheckpointError(f"{path}: " + "; ".join(problems) + f" ({len(used)} keys expected)")
