"""Which parameters adapt: the `trainable` / `frozen` / `batch_stats` split (paper eq. 11, Table 5).

PITTA adapts theta = the gamma and beta of every BatchNorm in the *encoder* (paper Sec. 4.1) and
nothing else. The split keeps the adapted leaves in their own pytree, so that the gradient, the
optimiser state and the update touch only them (an `optax.masked` optimiser would still see the
frozen leaves). `merge` puts the three parts back into Flax variables.

Selectors (parameter paths are `/`-joined, e.g. `encoder/layer1_0/bn1/scale`):
  encoder_bn           every encoder BN scale/bias (default; 20 layers, 9,600 values in ResNet-18)
  encoder_ln           every encoder LayerNorm scale/bias (transformer encoders)
  all                  every parameter of the network
  no_bn                every parameter except the scale/bias of BatchNorm layers, anywhere in
                       the network (CoMoDa: BN frozen, everything else adapts)
  fraction(cnn=a,bn=b) kernels of the last a% of encoder conv layers + scale/bias of the last
                       b% of encoder BN layers (LN where the encoder has no BN), in forward
                       order (Table 5: "CNN a% + BN b%")
A BatchNorm is a layer with running statistics in `batch_stats`; a LayerNorm has none.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, NamedTuple

from flax.traverse_util import flatten_dict, unflatten_dict

Tree = dict[str, Any]

SELECTOR_KINDS = ("encoder_bn", "encoder_ln", "all", "no_bn", "fraction")


@dataclasses.dataclass(frozen=True)
class Selector:
  """Which parameters adapt. kind: one of SELECTOR_KINDS; cnn/bn: percentages (fraction)."""
  kind: str = "encoder_bn"  # paper Sec. 4.1: BN gamma/beta of the encoder
  cnn: float = 0.0
  bn: float = 100.0

  def __post_init__(self):
    if self.kind not in SELECTOR_KINDS:
      raise ValueError(f"unknown selector kind {self.kind!r}; use {', '.join(SELECTOR_KINDS)}")
    for name, v in (("cnn", self.cnn), ("bn", self.bn)):
      if not 0.0 <= v <= 100.0:
        raise ValueError(f"selector {name}={v} is not a percentage in [0, 100]")

  def __str__(self) -> str:
    if self.kind == "fraction":
      return f"fraction(cnn={self.cnn:g},bn={self.bn:g})"
    return self.kind


def parse_selector(text: str) -> Selector:
  """Parses `encoder_bn`, `encoder_ln`, `all`, `no_bn`, or `fraction(cnn=20,bn=80)` (also
  `cnn20_bn80`)."""
  text = text.strip().replace(" ", "")
  if text in ("encoder_bn", "encoder_ln", "all", "no_bn"):
    return Selector(text)
  number = r"(\d+(?:\.\d*)?|\.\d+)"  # a percentage: 20, 12.5, .5 (not 1.2.3)
  m = re.fullmatch(rf"fraction\(cnn={number},bn={number}\)|cnn{number}_bn{number}", text)
  if not m:
    raise ValueError(f"cannot parse selector {text!r}; use encoder_bn, encoder_ln, all, no_bn, "
                     f"or fraction(cnn=A,bn=B) with percentages A, B")
  a, b = (m.group(1), m.group(2)) if m.group(1) is not None else (m.group(3), m.group(4))
  selector = Selector("fraction", float(a), float(b))
  if selector.cnn == 0 and selector.bn == 0:  # on any network: refused with the flags, not
    # once the weights are loaded (`selected_paths`)
    raise ValueError(f"selector {text!r} selects no parameter (0% of the convolutions and 0% "
                     f"of the norm layers)")
  return selector


def _natural_key(path: str) -> list:
  """Sort key that orders `layer2_10` after `layer2_9`."""
  return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path)]


def encoder_layers(variables: Tree, kind: str, encoder: str = "encoder",
                   order: list[str] | None = None) -> list[str]:
  """Module paths of the encoder's layers of one kind, in forward order.

  kind: "conv" (a 4-D `kernel`), "bn" (scale/bias with BatchNorm running statistics in
  `batch_stats`), "ln" (scale/bias without running statistics: LayerNorm/GroupNorm).
  order: module paths in forward order (`registry.Network.forward_order()`); without it, a
  natural sort of the paths, which is the forward order for ResNet names (stem, then
  layer{stage}_{block} with conv1, conv2, [conv3], downsample).
  """
  params = flatten_dict(variables["params"], sep="/")
  stats = {k.rsplit("/", 1)[0] for k in flatten_dict(variables.get("batch_stats", {}), sep="/")}
  prefix = encoder + "/"
  if kind == "conv":
    mods = {k[: -len("/kernel")] for k, v in params.items()
            if k.startswith(prefix) and k.endswith("/kernel") and getattr(v, "ndim", 0) == 4}
  elif kind in ("bn", "ln"):
    mods = {k[: -len("/scale")] for k in params if k.startswith(prefix) and k.endswith("/scale")}
    mods = {m for m in mods if (m in stats) == (kind == "bn")}
  else:
    raise ValueError(f"layer kind must be conv, bn or ln, got {kind!r}")
  if order is None:
    return sorted(mods, key=_natural_key)
  rank = {m: i for i, m in enumerate(order)}
  missing = sorted(m for m in mods if m not in rank)
  if missing:
    raise ValueError(f"forward order lacks layers {missing[:3]}")
  return sorted(mods, key=rank.__getitem__)


def _last_percent(layers: list[str], percent: float) -> list[str]:
  """The last `percent` % of `layers` (encoder order), rounded to whole layers by Python's
  round (a half to even: 50% of 5 layers is 2); ResNet's 20 make every multiple of 5% whole."""
  n = int(round(len(layers) * percent / 100.0))
  return layers[len(layers) - n:] if n else []


def selected_paths(variables: Tree, selector: Selector, encoder: str = "encoder",
                   order: list[str] | None = None) -> list[str]:
  """The `/`-joined parameter leaf paths the selector adapts (asserts each rule matched).

  variables: {"params": ..., "batch_stats": ...} (BatchNorm layers are the ones with running
  statistics; a LayerNorm is never taken for a BatchNorm). encoder, order: see `encoder_layers`.
  """
  flat = flatten_dict(variables["params"], sep="/")
  if selector.kind == "all":
    return sorted(flat)
  if selector.kind == "no_bn":  # a BatchNorm is a module with running statistics
    bn = {k.rsplit("/", 1)[0] for k in flatten_dict(variables.get("batch_stats", {}), sep="/")}
    paths = sorted(p for p in flat if p.rsplit("/", 1)[0] not in bn)
    if not paths:
      raise ValueError(f"selector {selector} selects no parameter")
    return paths
  norm_kind = "ln" if selector.kind == "encoder_ln" else "bn"
  norms = encoder_layers(variables, norm_kind, encoder, order)
  if not norms and selector.kind != "fraction":
    name = "LayerNorm" if norm_kind == "ln" else "BatchNorm"
    tops = sorted({p.split("/", 1)[0] for p in flat})
    if encoder not in tops:  # e.g. a network of one's own whose encoder has another name
      raise ValueError(f"selector {selector} found no {name} layer: the network has no "
                       f"top-level module {encoder!r} (its ModelSpec.encoder), its top-level "
                       f"modules are {', '.join(tops)}: set ModelSpec(encoder=...) to its "
                       f"encoder's name")
    other = "encoder_bn" if norm_kind == "ln" else "encoder_ln"
    raise ValueError(f"selector {selector} found no {name} layer under {encoder}/ "
                     f"(try {other}, all or fraction(cnn=..., bn=...))")
  if selector.kind in ("encoder_bn", "encoder_ln"):
    convs = []
  else:
    if not norms:
      norms = encoder_layers(variables, "ln", encoder, order)  # fraction over LN networks
    norms = _last_percent(norms, selector.bn)
    convs = _last_percent(encoder_layers(variables, "conv", encoder, order), selector.cnn)
  paths = [f"{m}/{leaf}" for m in norms for leaf in ("scale", "bias")]
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


def split(variables: Tree, selector: Selector = Selector(), encoder: str = "encoder",
          order: list[str] | None = None) -> Split:
  """Splits Flax variables {"params", "batch_stats"} into trainable / frozen / batch_stats."""
  params = variables["params"]
  chosen = set(selected_paths(variables, selector, encoder, order))
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
