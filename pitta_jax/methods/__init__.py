"""Test-time adaptation methods: one module each, with its own config, and this registry.

`METHODS[name] = (ConfigClass, build)`; `build(config) -> Method` (see `methods.base`). Adding a
method is one module plus one line here.
"""

from __future__ import annotations

from typing import Any, Callable

from pitta_jax.methods import actmad, adadepth, comoda, cotta, none, pitta
from pitta_jax.methods.base import Aux, Method
from pitta_jax.methods.depth_refining import DepthRefiningConfig

METHODS: dict[str, tuple[type, Callable[[Any], Method]]] = {
    "pitta": (pitta.PittaConfig, pitta.build),
    "none": (none.NoneConfig, none.build),
    "comoda": (comoda.ComodaConfig, comoda.build),
    "adadepth": (adadepth.AdadepthConfig, adadepth.build),
    "actmad": (actmad.ActmadConfig, actmad.build),
    "cotta": (cotta.CottaConfig, cotta.build),
}


def method_config_class(name: str) -> type:
  """The config dataclass of method `name`."""
  _check(name)
  return METHODS[name][0]


def build(name: str, config: Any | None = None) -> Method:
  """Method `name` with `config` (default: its paper defaults)."""
  _check(name)
  cls, make = METHODS[name]
  if config is None:
    config = cls()
  if not isinstance(config, cls):
    raise TypeError(f"method {name} takes a {cls.__name__}, got {type(config).__name__}")
  method = make(config)
  if method.name != name:  # runs, flags (--<name>.*) and records go by Method.name
    raise ValueError(f"METHODS[{name!r}] builds a method named {method.name!r}: register it "
                     f"under its own name, METHODS[{method.name!r}]")
  return method


def method_setting(name: str) -> dict[str, Any]:
  """The AdaptConfig values of method `name`'s own setting: its `requires` and its `setting`
  (e.g. ActMAD: BN in eval mode, every encoder conv and BN adapts); `method` itself is not
  among them: `AdaptConfig(method=name, **method_setting(name))`."""
  method = build(name)
  return {**{field: value for field, value, _ in method.requires}, **dict(method.setting)}


def _check(name: str) -> None:
  if name not in METHODS:
    raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(METHODS))}")


__all__ = ["METHODS", "Aux", "Method", "DepthRefiningConfig", "build", "method_config_class", "method_setting"]
