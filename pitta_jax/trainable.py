"""Which parameters adapt: the `trainable` / `frozen` / `batch_stats` split (paper eq. 11, Table 5).

PITTA adapts theta = the gamma and beta of every BatchNorm in the *encoder* (paper Sec. 4.1) and
nothing else. The split keeps the adapted leaves in their own pytree, so that the gradient, the
optimiser state and the update touch only them (an `optax.masked` optimiser would still see the
frozen leaves). `merge` puts the three parts back into Flax variables.

Selectors (parameter paths are `/`-joined, e.g. `encoder/layer1_0/bn1/scale`):
  encoder_bn           every encoder BN scale/bias (default; 20 layers, 9,600 values in ResNet-18)
  all                  every parameter of the network
  fraction(cnn=a,bn=b) kernels of the last a% of encoder conv layers + scale/bias of the last
                       b% of encoder BN layers, in forward order (Table 5: "CNN a% + BN b%")
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, NamedTuple

from flax.traverse_util import flatten_dict, unflatten_dict

Tree = dict[str, Any]

_BLOCK_RE = re.compile(r"^encoder/layer(\d+)_(\d+)/([a-z_]+?)(\d*)/")
# order of a block's layers in PyTorch's forward: convs/BNs by index, then the downsample branch
_POSITION = {"conv": 0, "bn": 0, "downsample_conv": 10, "downsample_bn": 10}


@dataclasses.dataclass(frozen=True)
class Selector:
  """Which parameters adapt. kind: "encoder_bn" | "all" | "fraction"; cnn/bn: percentages."""
  kind: str = "encoder_bn"  # paper Sec. 4.1: BN gamma/beta of the encoder
  cnn: float = 0.0
  bn: float = 100.0

  def __post_init__(self):
    if self.kind not in ("encoder_bn", "all", "fraction"):
      raise ValueError(f"unknown selector kind {self.kind!r}; use encoder_bn, all or fraction")
    for name, v in (("cnn", self.cnn), ("bn", self.bn)):
      if not 0.0 <= v <= 100.0:
        raise ValueError(f"selector {name}={v} is not a percentage in [0, 100]")

  def __str__(self) -> str:
    if self.kind == "fraction":
      return f"fraction(cnn={self.cnn:g},bn={self.bn:g})"
    return self.kind


def parse_selector(text: str) -> Selector:
  """Parses `encoder_bn`, `all`, or `fraction(cnn=20,bn=80)` (also `cnn20_bn80`)."""
  text = text.strip().replace(" ", "")
  if text in ("encoder_bn", "all"):
    return Selector(text)
  m = re.fullmatch(r"fraction\(cnn=([\d.]+),bn=([\d.]+)\)|cnn([\d.]+)_bn([\d.]+)", text)
  if not m:
    raise ValueError(f"cannot parse selector {text!r}; use encoder_bn, all, "
                     f"or fraction(cnn=A,bn=B) with percentages A, B")
  a, b = (m.group(1), m.group(2)) if m.group(1) is not None else (m.group(3), m.group(4))
  return Selector("fraction", float(a), float(b))


def _forward_key(module_path: str) -> tuple:
  """Sort key giving the forward order of an encoder conv/BN module path."""
  if module_path.startswith("encoder/conv1") or module_path.startswith("encoder/bn1"):
    return (0, 0, 0)
  m = _BLOCK_RE.match(module_path + "/")
  if not m:
    raise ValueError(f"not an encoder layer path: {module_path}")
  stage, block, kind, idx = int(m.group(1)), int(m.group(2)), m.group(3), m.group(4)
  return (stage, block, _POSITION[kind] + (int(idx) if idx else 0))


def encoder_layers(params: Tree, kind: str) -> list[str]:
  """Module paths of the encoder's conv ("conv") or BN ("bn") layers, in forward order."""
  flat = flatten_dict(params, sep="/")
  if kind == "conv":
    mods = {k[: -len("/kernel")] for k in flat if k.startswith("encoder/") and k.endswith("/kernel")}
  elif kind == "bn":
    mods = {k[: -len("/scale")] for k in flat if k.startswith("encoder/") and k.endswith("/scale")}
  else:
    raise ValueError(kind)
  return sorted(mods, key=_forward_key)


def _last_percent(layers: list[str], percent: float) -> list[str]:
  n = int(round(len(layers) * percent / 100.0))
  return layers[len(layers) - n:] if n else []


def selected_paths(params: Tree, selector: Selector) -> list[str]:
  """The `/`-joined parameter leaf paths the selector adapts (asserts each rule matched)."""
  flat = flatten_dict(params, sep="/")
  if selector.kind == "all":
    return sorted(flat)
  bn_layers = encoder_layers(params, "bn")
  if not bn_layers:
    raise ValueError("selector found no BatchNorm layer under encoder/; is this a MonoDepth2?")
  if selector.kind == "encoder_bn":
    bns, convs = bn_layers, []
  else:
    bns = _last_percent(bn_layers, selector.bn)
    convs = _last_percent(encoder_layers(params, "conv"), selector.cnn)
  paths = [f"{m}/{leaf}" for m in bns for leaf in ("scale", "bias")]
  paths += [f"{m}/kernel" for m in convs]
  for p in paths:
    assert p in flat, p
  if not paths:
    raise ValueError(f"selector {selector} selects no parameter")
  return paths


class Split(NamedTuple):
  trainable: Tree   # the adapted leaves (nested dict, a subset of params)
  frozen: Tree      # the remaining params
  batch_stats: Tree


def split(variables: Tree, selector: Selector = Selector()) -> Split:
  """Splits Flax variables {"params", "batch_stats"} into trainable / frozen / batch_stats."""
  params = variables["params"]
  chosen = set(selected_paths(params, selector))
  flat = flatten_dict(params, sep="/")
  trainable = unflatten_dict({k: v for k, v in flat.items() if k in chosen}, sep="/")
  frozen = unflatten_dict({k: v for k, v in flat.items() if k not in chosen}, sep="/")
  return Split(trainable, frozen, variables.get("batch_stats", {}))


def merge(trainable: Tree, frozen: Tree, batch_stats: Tree) -> Tree:
  """Inverse of `split`: Flax variables {"params": ..., "batch_stats": ...}."""
  flat = flatten_dict(frozen, sep="/")
  flat.update(flatten_dict(trainable, sep="/"))
  return {"params": unflatten_dict(flat, sep="/"), "batch_stats": batch_stats}


def describe(trainable: Tree) -> str:
  """One line for logs: how many leaves/values adapt."""
  flat = flatten_dict(trainable, sep="/")
  n_values = sum(int(getattr(v, "size", 0)) for v in flat.values())
  return f"{len(flat)} trainable leaves, {n_values:,} values"
