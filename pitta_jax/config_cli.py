"""Command-line flags for every field of the config dataclasses, one namespace per config.

Field `foo_bar` of the config in namespace `adapt` becomes `--adapt.foo-bar`, and also
`--foo-bar` when no other config of the command has that field (a short alias). A nested config
field (`PittaConfig.ld`) continues the namespace: `--pitta.ld.window` (alias `--window`). Types
come from the field annotations: int, float (`inf` allowed), str, bool (`true|false`), tuples of
str or int (comma-separated; for `dynamic_classes` COCO names are accepted too:
`person,car`). Help texts come from the fields' metadata (`configs.option`). Only the flags a
user gives override the defaults; the resolved configs are saved with the results.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from typing import Any, TypeVar

from pitta_jax.configs import help_of

T = TypeVar("T")


class ArgumentParser(argparse.ArgumentParser):
  """argparse's parser with a one-line error, `error: MESSAGE (see PROG --help)`, exit 2:
  argparse prints the usage first, dozens of lines for a command with every config field as a
  flag, which bury the one line that matters. Subcommand parsers inherit it."""

  def error(self, message: str):
    self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def parse_bool(text: str) -> bool:
  low = text.strip().lower()
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
    if item.lstrip("-").isdigit():
      out.append(int(item))
    else:
      try:
        out.append(coco.name_to_id(item))
      except (KeyError, ValueError):
        raise argparse.ArgumentTypeError(f"{item!r} is neither an integer nor a COCO class "
                                         f"name") from None
  return tuple(out)


def parser_for(annotation: Any) -> tuple[Any, str]:
  """(argparse type, metavar) for a field annotation."""
  origin = typing.get_origin(annotation)
  if annotation is bool:
    return parse_bool, "{true,false}"
  if annotation is int:
    return int, "INT"
  if annotation is float:
    return float, "FLOAT"
  if origin is tuple:
    args = typing.get_args(annotation)
    return (_parse_int_tuple if args and args[0] is int else _parse_str_tuple), "A,B,..."
  return str, "STR"


def _fields(cls: type) -> list[tuple[dataclasses.Field, Any]]:
  hints = typing.get_type_hints(cls)
  return [(f, hints[f.name]) for f in dataclasses.fields(cls)]


def add_config_arguments(parser: argparse.ArgumentParser, cls: type, namespace: str,
                         title: str, _group=None) -> None:
  """Adds `--{namespace}.{field}` (and a unique short alias) for every field of `cls`."""
  group = _group or parser.add_argument_group(title)
  for field, annotation in _fields(cls):
    if dataclasses.is_dataclass(annotation):
      add_config_arguments(parser, annotation, f"{namespace}.{field.name}", title, group)
      continue
    kind, meta = parser_for(annotation)
    default = field.default
    shown = ",".join(map(str, default)) if isinstance(default, tuple) else default
    flags = [f"--{namespace}.{field.name.replace('_', '-')}"]
    alias = f"--{field.name.replace('_', '-')}"
    if alias not in parser._option_string_actions:  # argparse's own registry of flags
      flags.append(alias)
    text = f"{help_of(field)} (default: {shown})".lstrip().replace("%", "%%")  # argparse formats
    group.add_argument(*flags, dest=_dest(namespace, field.name), type=kind, default=None,
                       metavar=meta, help=text)


def _dest(namespace: str, name: str) -> str:
  return f"cfg__{namespace.replace('.', '__')}__{name}"


def given_fields(cls: type, args: argparse.Namespace, namespace: str) -> set[str]:
  """The (top-level) fields of `cls` whose flags were given on the command line."""
  return {f.name for f, _ in _fields(cls) if getattr(args, _dest(namespace, f.name), None)
          is not None}


def apply_unless_given(cfg: T, values: Any, args: argparse.Namespace, namespace: str
                       ) -> tuple[T, dict[str, Any]]:
  """`cfg` (a config dataclass built from `namespace`'s flags) with `values` ((field, value)
  pairs or a mapping) applied where no flag gave the field, and the values that changed it."""
  given = given_fields(type(cfg), args, namespace)
  own = {k: v for k, v in dict(values).items() if k not in given and getattr(cfg, k) != v}
  return (dataclasses.replace(cfg, **own) if own else cfg), own


def config_from_args(cls: type[T], args: argparse.Namespace, namespace: str,
                     **fixed: Any) -> T:
  """Builds `cls` from its defaults, the flags given in `namespace`, then `fixed` values."""
  values = {}
  for field, annotation in _fields(cls):
    if dataclasses.is_dataclass(annotation):
      values[field.name] = config_from_args(annotation, args, f"{namespace}.{field.name}")
      continue
    value = getattr(args, _dest(namespace, field.name), None)
    if value is not None:
      values[field.name] = value
  values.update(fixed)
  return cls(**values)
