"""Command-line overrides for every field of a frozen config dataclass (`--lr 1e-4 --lam 0.2`).

Each field `foo_bar` becomes `--foo-bar`, typed from its default: int, float (`inf` allowed),
str, bool (`--skip-nonfinite true|false`), tuples of str or int (comma-separated; for
`dynamic_classes` COCO names are accepted too: `--dynamic-classes person,car`). Only the flags a
user gives override the dataclass defaults; the resolved config is saved with the results.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
from typing import Any, TypeVar

T = TypeVar("T")


def _parse_bool(text: str) -> bool:
  low = text.lower()
  if low in ("1", "true", "yes", "on"):
    return True
  if low in ("0", "false", "no", "off"):
    return False
  raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _parse_str_tuple(text: str) -> tuple[str, ...]:
  return tuple(t.strip() for t in text.split(",") if t.strip())


def _parse_int_tuple(text: str) -> tuple[int, ...]:
  from pitta_jax.data import coco
  out = []
  for item in (t.strip() for t in text.split(",") if t.strip()):
    out.append(int(item) if item.lstrip("-").isdigit() else coco.name_to_id(item))
  return tuple(out)


def field_comments(cls: type) -> dict[str, str]:
  """The trailing `# comment` of each field line in the dataclass source (its help text)."""
  try:
    source = inspect.getsource(cls)
  except (OSError, TypeError):
    return {}
  found = {}
  for match in re.finditer(r"^\s+(\w+): [^=\n]+=[^#\n]*#\s*(.+)$", source, re.MULTILINE):
    found[match.group(1)] = match.group(2).strip()
  return found


def add_dataclass_arguments(parser: argparse.ArgumentParser, cls: type, title: str) -> None:
  """Adds one optional flag per field of `cls` (default None = keep the dataclass default)."""
  group = parser.add_argument_group(title)
  comments = field_comments(cls)
  for field in dataclasses.fields(cls):
    default = field.default
    if isinstance(default, bool):
      kind, meta = _parse_bool, "{true,false}"
    elif isinstance(default, int):
      kind, meta = int, "INT"
    elif isinstance(default, float):
      kind, meta = float, "FLOAT"
    elif isinstance(default, tuple) and all(isinstance(x, str) for x in default):
      kind, meta = _parse_str_tuple, "A,B,..."
    elif isinstance(default, tuple):
      kind, meta = _parse_int_tuple, "A,B,..."
    else:
      kind, meta = str, "STR"
    shown = ",".join(map(str, default)) if isinstance(default, tuple) else default
    group.add_argument(f"--{field.name.replace('_', '-')}", dest=f"cfg_{field.name}", type=kind,
                       default=None, metavar=meta,
                       help=f"{comments.get(field.name, '')} (default: {shown})".lstrip())


def dataclass_from_args(cls: type[T], args: argparse.Namespace, **fixed: Any) -> T:
  """Builds `cls` from the defaults, the given flags, then `fixed` values."""
  values = {f.name: getattr(args, f"cfg_{f.name}") for f in dataclasses.fields(cls)
            if getattr(args, f"cfg_{f.name}", None) is not None}
  values.update(fixed)
  return cls(**values)
