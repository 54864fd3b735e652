"""Config dataclasses: one default per field, in one place, with its help text beside it.

A field is declared with `option(default, help)`; the help travels in the field's metadata, so
the CLI (`pitta_jax.config_cli`) shows exactly what the code documents. Configs are frozen
dataclasses validated in `__post_init__` (one line naming the field on failure).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any


def option(default: Any, help: str) -> Any:  # noqa: A002 (argparse's word)
  """A dataclass field with `default` and its help text."""
  if isinstance(default, (list, dict, set)):
    raise TypeError("mutable defaults are not allowed in configs; use a tuple")
  return dataclasses.field(default=default, metadata={"help": help})


def help_of(field: dataclasses.Field) -> str:
  return field.metadata.get("help", "")


def check(ok: bool, message: str) -> None:
  """Raises ValueError(message) unless ok."""
  if not ok:
    raise ValueError(message)


def finite(value: float, name: str, low: float = -math.inf) -> None:
  """`value` must be a finite number >= low."""
  check(isinstance(value, (int, float)) and math.isfinite(value) and value >= low,
        f"{name} must be a finite number >= {low:g}, got {value!r}")
