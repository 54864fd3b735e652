"""Config dataclasses: one default per field, in one place, with its help text beside it.

A field is declared with `option(default, help)`; the help travels in the field's metadata, so
the CLI (`pitta_jax.config_cli`) shows exactly what the code documents. Configs are frozen
dataclasses validated in `__post_init__` (one line naming the field on failure).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from typing import Any

import numpy as np


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
  check(is_number(value) and _is_finite(value) and value >= low,
        f"{name} must be a finite number >= {low:g}, got {value!r}")


def _is_finite(value: Any) -> bool:
  """math.isfinite, False for an int too large for a float (10**400 was an OverflowError)."""
  try:
    return math.isfinite(value)
  except OverflowError:
    return False


def check_seed(seed: int) -> None:
  """A PRNG seed: `jax.random.PRNGKey` takes a signed 64-bit one; negative ones are refused as
  the readers do."""
  check(0 <= seed < 2**63, f"seed must be in [0, 2^63), got {seed}")


def is_int(value: Any) -> bool:
  return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def is_number(value: Any) -> bool:
  return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


# annotation -> (does a value fit it, what the message asks for)
_SIMPLE_TYPES = {int: (is_int, "an integer"), float: (is_number, "a number"),
                 bool: (lambda v: isinstance(v, (bool, np.bool_)), "true or false"),
                 str: (lambda v: isinstance(v, str), "a string")}


def check_types(config: Any) -> None:
  """Each field annotated with a simple type (int, float, bool, str, or one of them | None)
  holds one (ValueError naming the field): `chunk_size=2.5` or `skip_nonfinite="no"` (truthy:
  the guard stayed on) were taken before. A float field takes an int; a bool is not a
  number here. A NumPy scalar that fits becomes the Python value. Other annotations are the
  config's own to check."""
  hints = typing.get_type_hints(type(config))
  for field in dataclasses.fields(config):
    want, value = hints.get(field.name), getattr(config, field.name)
    if isinstance(want, type) and dataclasses.is_dataclass(want):  # a nested config (ld, sfm)
      check(isinstance(value, want), f"{field.name} must be a {want.__name__}, got {value!r}")
      continue
    union = isinstance(want, types.UnionType) or typing.get_origin(want) is typing.Union
    allowed = typing.get_args(want) if union else (want,)
    if value is None and type(None) in allowed:
      continue
    kinds = [a for a in allowed if a is not type(None)]
    if not kinds or any(a not in _SIMPLE_TYPES for a in kinds):
      continue
    check(any(_SIMPLE_TYPES[a][0](value) for a in kinds),
          f"{field.name} must be {' or '.join(_SIMPLE_TYPES[a][1] for a in kinds)}"
          f"{' or unset' if type(None) in allowed else ''}, got {value!r}")
    if isinstance(value, np.generic):  # np.float32(0.25) -> 0.25: the config's later checks,
      object.__setattr__(config, field.name, value.item())  # its hash and its JSON as given
