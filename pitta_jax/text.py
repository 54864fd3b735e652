"""Wording shared by messages: a long list named in part, the rest counted."""

from __future__ import annotations

from typing import Iterable


def first_and_count(items: Iterable[object], shown: int, sep: str = ", ") -> str:
  """The first `shown` of `items` joined by `sep`, then how many are left unnamed.

  `first_and_count("abcdefg", 3)` is "a, b, c, ... and 4 more": a message names what the reader
  can act on and still says how many there are in all.
  """
  names = [str(x) for x in items]
  more = len(names) - shown
  return sep.join(names[:shown]) + (f"{sep}... and {more} more" if more > 0 else "")
