"""Command-line flags for every field of the config dataclasses, one namespace per config.

Field `foo_bar` of the config in namespace `adapt` becomes `--adapt.foo-bar`, and also
`--foo-bar` when no other config of the command has that field (a short alias). A nested config
field (`PittaConfig.ld`) continues the namespace: `--pitta.ld.window`. A name several configs
share (`--lr`, `--window`, `--ld-weight` among the methods) is a shared alias
(`add_shared_aliases`): `route_aliases` gives it to the selected method's field, else to
`--adapt.*`'s, and refuses it where neither has one. Types
come from the field annotations: int, float (`inf` allowed), str, bool (`true|false`), tuples of
str or int (comma-separated; for `dynamic_classes` COCO names are accepted too:
`person,car`). Help texts come from the fields' metadata (`configs.option`). Only the flags a
user gives override the defaults; the resolved configs are saved with the results.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import types
import typing
from typing import Any, Collection, Sequence, TypeVar

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
    try:
      out.append(int(item))  # "--5" passed an isdigit test, then int() raised a bare ValueError
    except ValueError:
      try:
        out.append(coco.name_to_id(item))
      except (KeyError, ValueError):
        raise argparse.ArgumentTypeError(f"{item!r} is neither an integer nor a COCO class "
                                         f"name") from None
  return tuple(out)


def parser_for(annotation: Any) -> tuple[Any, str]:
  """(argparse type, metavar) for a field annotation (`X | None`: X's, the flag sets X)."""
  origin = typing.get_origin(annotation)
  if origin in (typing.Union, types.UnionType):
    given = [a for a in typing.get_args(annotation) if a is not type(None)]
    if len(given) == 1:
      return parser_for(given[0])
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
                         title: str, _group=None, shared: Collection[str] = (),
                         hidden: Collection[str] = ()) -> None:
  """Adds `--{namespace}.{field}` (and a short alias, unless another flag has it or the name is
  in `shared`) for every field of `cls`; those of the (top-level) fields in `hidden` are parsed
  but not shown in --help (a command that refuses them, with a one-line pointer)."""
  group = _group or parser.add_argument_group(title)
  for field, annotation in _fields(cls):
    if dataclasses.is_dataclass(annotation):
      add_config_arguments(parser, annotation, f"{namespace}.{field.name}", title, group, shared)
      continue
    kind, meta = parser_for(annotation)
    default = field.default
    shown = (",".join(map(str, default)) if isinstance(default, tuple)
             else "unset" if default is None else default)
    flags = [f"--{namespace}.{field.name.replace('_', '-')}"]
    alias = f"--{field.name.replace('_', '-')}"
    # argparse's own registry of flags: the first config to claim a name outside `shared` keeps it
    if alias not in parser._option_string_actions and field.name not in shared:
      flags.append(alias)
    text = f"{help_of(field)} (default: {shown})".lstrip().replace("%", "%%")  # argparse formats
    group.add_argument(*flags, dest=flag_dest(namespace, field.name), type=kind, default=None,
                       metavar=meta, help=argparse.SUPPRESS if field.name in hidden else text,
                       action=_StoreSpelled, path=f"{namespace}.{field.name}")


class _StoreSpelled(argparse.Action):
  """argparse's store, recording which spelling of the field's flags the command line used
  (`--adapt.lr` or its short alias), for `typed_flag`."""

  def __init__(self, *args, path: str, **kwargs):
    super().__init__(*args, **kwargs)
    self.path = path  # "adapt.lr"

  def __call__(self, parser, namespace, values, option_string=None):
    setattr(namespace, self.dest, values)
    if option_string:
      vars(namespace).setdefault(SPELLED, {})[self.path] = option_string


def flag_dest(namespace: str, name: str) -> str:
  return f"cfg__{namespace.replace('.', '__')}__{name}"


def given_flags(args: argparse.Namespace, namespace: str) -> list[str]:
  """The `--{namespace}.*` flags given on the command line (nested ones included), sorted."""
  prefix = flag_dest(namespace, "")
  return sorted("--" + k[len("cfg__"):].replace("__", ".").replace("_", "-")
                for k, v in vars(args).items() if v is not None and k.startswith(prefix))


def given_fields(cls: type, args: argparse.Namespace, namespace: str) -> set[str]:
  """The (top-level) fields of `cls` whose flags were given on the command line."""
  return {f.name for f, _ in _fields(cls) if getattr(args, flag_dest(namespace, f.name), None)
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
    value = getattr(args, flag_dest(namespace, field.name), None)
    if value is not None:
      values[field.name] = value
  values.update(fixed)
  try:
    return cls(**values)
  except ValueError as e:  # a field's check: name the flags of the fields it names
    text = str(e)
    named = [f.name for f, _ in _fields(cls) if re.search(rf"\b{f.name}\b", text)]
    if not named or "--" in text:
      raise
    flags = ", ".join(f"--{namespace}.{n.replace('_', '-')}" for n in named)
    if len(named) == 1 and text.startswith(f"{named[0]}: "):  # "field: ..." -> "--flag: ..."
      text = text[len(named[0]) + 2:]
    raise ValueError(f"{flags}: {text}") from None


def leaf_fields(cls: type, namespace: str) -> list[tuple[str, str, Any]]:
  """(field name, namespaced flag, annotation) of every leaf field of `cls`, nested configs
  included: ("window", "pitta.ld.window", int)."""
  out = []
  for field, annotation in _fields(cls):
    path = f"{namespace}.{field.name}"
    out += (leaf_fields(annotation, path) if dataclasses.is_dataclass(annotation)
            else [(field.name, path, annotation)])
  return out


def shared_names(configs: Sequence[tuple[type, str]]) -> set[str]:
  """Field names that more than one of `configs` ((class, namespace) pairs) has."""
  owners: dict[str, set[str]] = {}
  for cls, namespace in configs:
    for name, _, _ in leaf_fields(cls, namespace):
      owners.setdefault(name, set()).add(namespace)
  return {name for name, spaces in owners.items() if len(spaces) > 1}


def ambiguous_names(configs: Sequence[tuple[type, str]]) -> set[str]:
  """Field names that one of `configs` ((class, namespace) pairs) has twice (Ada-Depth's
  `max_depth` and `sfm.max_depth`): a shared alias that sets every config's (`route_aliases`
  with `every`) is refused for them whatever is selected."""
  out = set()
  for cls, namespace in configs:
    names = [name for name, _, _ in leaf_fields(cls, namespace)]
    out |= {name for name in names if names.count(name) > 1}
  return out


def add_shared_aliases(parser: argparse.ArgumentParser, names: Collection[str], title: str,
                       every: bool = False, fallback: tuple[type, str] | None = None,
                       hidden: Collection[str] = ()) -> list[str]:
  """`--name` for each of `names` no other flag has yet (dest `alias__name`), resolved later by
  `route_aliases`; its help says it sets the selected config's field, else `fallback`'s
  ((class, namespace), named where it has the field), or with `every` every config's; those in
  `hidden` are parsed (and refused in one line) but not shown in --help. Returns the names
  added."""
  backup = {n for n, _, _ in leaf_fields(*fallback)} if fallback else set()
  group = parser.add_argument_group(title)
  added = []
  for name in sorted(names):
    flag = f"--{name.replace('_', '-')}"
    if flag in parser._option_string_actions:
      continue
    dashed = name.replace('_', '-')
    if every:
      text = f"every method's {dashed} (each --<namespace>.{dashed} there is)"
    elif name in backup:
      text = f"the selected method's {dashed}, else --{fallback[1]}.{dashed}"
    else:
      text = f"the selected method's {dashed} (refused where it has none)"
    group.add_argument(flag, dest=f"alias__{name}", default=None, metavar="VALUE",
                       help=argparse.SUPPRESS if name in hidden else text)
    added.append(name)
  return added


def route_aliases(args: argparse.Namespace, configs: Sequence[tuple[type, str]],
                  order: Sequence[str], every: bool = False) -> None:
  """Moves each given shared alias (`add_shared_aliases`) onto its namespaced flag, parsed as
  that field: the first namespace of `order` whose config has the name (`every`: each one that
  has it). ValueError (one line, naming the flags) where a config has the name twice, where no
  namespace of `order` has it, or where its namespaced flag was given too."""
  classes = dict((namespace, cls) for cls, namespace in configs)
  for key, text in list(vars(args).items()):
    if not key.startswith("alias__") or text is None:
      continue
    name, flag = key[len("alias__"):], f"--{key[len('alias__'):].replace('_', '-')}"
    targets = []
    for namespace in order:
      found = [(path, a) for n, path, a in leaf_fields(classes[namespace], namespace) if n == name]
      if len(found) > 1:
        raise ValueError(f"{flag} is ambiguous for {namespace}: use "
                         + " or ".join(f"--{p.replace('_', '-')}" for p, _ in found))
      targets += found
      if targets and not every:
        break
    if not targets:
      owners = [path for cls, ns in configs for n, path, _ in leaf_fields(cls, ns) if n == name]
      raise ValueError(f"{flag} is not a flag of "
                       + " or ".join(f"--{namespace}.*" for namespace in order) + "; it is "
                       + ", ".join(f"--{p.replace('_', '-')}" for p in owners))
    for path, annotation in targets:
      dest = flag_dest(*path.rsplit(".", 1))
      if getattr(args, dest, None) is not None:
        raise ValueError(f"both {flag} and --{path.replace('_', '-')} given")
      kind, meta = parser_for(annotation)
      try:
        setattr(args, dest, kind(text))
      except argparse.ArgumentTypeError as e:
        raise ValueError(f"{flag}: {e}") from None
      except ValueError:
        raise ValueError(f"{flag}: expected {meta}, got {text!r}") from None
      vars(args).setdefault(SPELLED, {})[path] = flag
    setattr(args, key, None)


# args' record of how each given config field's flag was spelled: {"adapt.lr": "--lr", ...}
# (`_StoreSpelled`; a shared alias that `route_aliases` moved onto the field)
SPELLED = "flag_spellings"


def typed_flag(args: argparse.Namespace, path: str) -> str:
  """The flag of field `path` ("adapt.lr") as the command line gave it (`--lr`,
  `--steps-per-frame` or `--adapt.lr`; `--adapt.lr` where no flag gave it): what a message
  about the value names, so that it names what the user typed."""
  return getattr(args, SPELLED, {}).get(path, f"--{path.replace('_', '-')}")
