"""The one key-table engine of every converter: PyTorch state dict -> Flax variables, strictly.

A `Rule` maps one Flax leaf (a path that starts with its collection, "params" or "batch_stats")
to its PyTorch source(s) in PyTorch layout:

* one tensor;
* the row-concatenation of several (e.g. separate q/k/v projections -> one fused `qkv`);
* a row slice of one (e.g. `nn.MultiheadAttention.in_proj_weight` -> `q_proj`/`k_proj`/`v_proj`);

then a layout transform by the rule's declared kind, never guessed from `ndim`:
"linear" (weight transposed), "conv" (OIHW -> HWIO), "param" (as is).

`apply_rules` is strict: every key of the file that no rule uses (and that the converter does
not declare ignorable) and every key a rule needs but the file lacks are listed in one error;
a shape mismatch names the key; a non-finite value names the key. `to_state_dict` inverts the
rules (the tests use it to write checkpoints in the upstream layout).

The helpers (`conv`, `linear`, `batch_norm`, `layer_norm`, ...) append the rules of one PyTorch
module.
"""

from __future__ import annotations

import collections
from typing import Callable, Iterable, NamedTuple

import numpy as np

from weights_convert.pth import CheckpointError
from weights_convert.strict import check_keys

KINDS = ("linear", "conv", "param")
Path = tuple[str, ...]


class Rule(NamedTuple):
  """Flax leaf `flax` (collection first) <- PyTorch `sources`.

  kind: "linear" (weight, transposed), "conv" (OIHW -> HWIO) or "param" (as is).
  rows: (start, stop) row slice of the single source, or None.
  """
  flax: Path
  kind: str
  sources: tuple[str, ...]
  rows: tuple[int, int] | None = None


Rules = list[Rule]


# ------------------------------------------------------------------------------ per-module helpers


def param(rules: Rules, flax: Path, src: str) -> None:
  """A tensor taken as it is (`flax` is the whole leaf path, collection first)."""
  rules.append(Rule(flax, "param", (src,)))


def linear(rules: Rules, flax: Path, src: str, bias: bool = True,
           rows: tuple[int, int] | None = None) -> None:
  """`nn.Linear` `src` -> Dense at `flax` (a module path, collection first)."""
  rules.append(Rule(flax + ("kernel",), "linear", (f"{src}.weight",), rows))
  if bias:
    rules.append(Rule(flax + ("bias",), "param", (f"{src}.bias",), rows))


def fused_linear(rules: Rules, flax: Path, srcs: Iterable[str]) -> None:
  """Several `nn.Linear`s (e.g. query, key, value) -> one Dense with their outputs concatenated."""
  srcs = tuple(srcs)
  rules.append(Rule(flax + ("kernel",), "linear", tuple(f"{s}.weight" for s in srcs)))
  rules.append(Rule(flax + ("bias",), "param", tuple(f"{s}.bias" for s in srcs)))


def in_proj(rules: Rules, flax: Path, src: str, dim: int) -> None:
  """`nn.MultiheadAttention` -> q_proj, k_proj, v_proj (rows of in_proj_*), out_proj."""
  for n, name in enumerate(("q_proj", "k_proj", "v_proj")):
    rows = (n * dim, (n + 1) * dim)
    rules.append(Rule(flax + (name, "kernel"), "linear", (f"{src}.in_proj_weight",), rows))
    rules.append(Rule(flax + (name, "bias"), "param", (f"{src}.in_proj_bias",), rows))
  linear(rules, flax + ("out_proj",), f"{src}.out_proj")


def conv(rules: Rules, flax: Path, src: str, bias: bool = True) -> None:
  """`nn.Conv2d` `src` (`src.weight`, optional `src.bias`) -> Conv at `flax`."""
  rules.append(Rule(flax + ("kernel",), "conv", (f"{src}.weight",)))
  if bias:
    rules.append(Rule(flax + ("bias",), "param", (f"{src}.bias",)))


def layer_norm(rules: Rules, flax: Path, src: str) -> None:
  """`nn.LayerNorm` / `nn.GroupNorm` affine -> scale/bias at `flax`."""
  rules.append(Rule(flax + ("scale",), "param", (f"{src}.weight",)))
  rules.append(Rule(flax + ("bias",), "param", (f"{src}.bias",)))


def batch_norm(rules: Rules, module: Path, src: str) -> None:
  """`nn.BatchNorm2d` `src` -> params scale/bias and batch_stats mean/var of `module`.

  `module` is the module path *without* a collection; `num_batches_tracked` is not used (declare
  it ignorable).
  """
  layer_norm(rules, ("params",) + module, src)
  rules.append(Rule(("batch_stats",) + module + ("mean",), "param", (f"{src}.running_mean",)))
  rules.append(Rule(("batch_stats",) + module + ("var",), "param", (f"{src}.running_var",)))


# ------------------------------------------------------------------------------ the engine


def to_flax(t: np.ndarray, kind: str) -> np.ndarray:
  """PyTorch layout -> Flax layout for a rule kind."""
  if kind == "linear":
    return np.ascontiguousarray(t.T)
  if kind == "conv":
    return np.ascontiguousarray(np.transpose(t, (2, 3, 1, 0)))  # OIHW -> HWIO
  if kind == "param":
    return np.ascontiguousarray(t)
  raise ValueError(f"unknown rule kind {kind!r}; one of {KINDS}")


def to_torch(a: np.ndarray, kind: str) -> np.ndarray:
  """Inverse of `to_flax`."""
  if kind == "linear":
    return np.ascontiguousarray(a.T)
  if kind == "conv":
    return np.ascontiguousarray(np.transpose(a, (3, 2, 0, 1)))  # HWIO -> OIHW
  return np.ascontiguousarray(a)


def _rule_name(rule: Rule) -> str:
  return "+".join(rule.sources) + (f"[{rule.rows[0]}:{rule.rows[1]}]" if rule.rows else "")


def apply_rules(state: dict, rules: Rules, ignorable: Callable[[str], bool], path: str,
                expected: dict[Path, tuple[int, ...]], cover: bool = True) -> dict[Path, np.ndarray]:
  """Converts a flat PyTorch state dict with `rules`, strictly.

  Args:
    state: PyTorch name -> array (as `pth.load_pth` returns it).
    rules: the key table.
    ignorable: keys the file may carry that the network does not use (buffers, metadata,
      heads of other tasks); every other unused key is an error.
    path: the file's name, for messages.
    expected: Flax path (collection first) -> shape of the target model (`expected_shapes`).
    cover: the rules must produce every path in `expected` (False when a model is assembled
      from several files, each converted on its own; check the union with `check_covered`).

  Returns:
    Flax path -> float32 array.

  Raises:
    CheckpointError: unexpected/missing keys, a non-tensor or non-finite value, a shape mismatch.
  """
  used = {s for rule in rules for s in rule.sources}
  check_keys(path, state, used, ignorable)
  flat = {}
  for rule in rules:
    parts = []
    for s in rule.sources:
      value = state[s]
      if not isinstance(value, np.ndarray):
        raise CheckpointError(f"{path}: {s} is a {type(value).__name__}, expected a tensor")
      if value.dtype.kind != "f" and "float" not in value.dtype.name:  # (ml_dtypes' bfloat16)
        raise CheckpointError(f"{path}: {s} is a {value.dtype} tensor, expected floating-point "
                              f"weights")
      value = value.astype(np.float32)
      if not np.all(np.isfinite(value)):
        bad = int(np.size(value) - np.count_nonzero(np.isfinite(value)))
        raise CheckpointError(f"{path}: {s} holds {bad} non-finite values (NaN/Inf)")
      parts.append(value)
    t = parts[0] if len(parts) == 1 else np.concatenate(parts, 0)
    if rule.rows is not None:
      start, stop = rule.rows
      if t.shape[0] < stop:
        raise CheckpointError(f"{path}: {rule.sources[0]} has shape {tuple(t.shape)}, expected "
                              f"at least {stop} rows")
      t = t[start:stop]
    arr = to_flax(t, rule.kind)
    want = expected.get(rule.flax)
    if want is None:  # a table bug, not a file problem
      raise AssertionError(f"rule for {_rule_name(rule)} targets {'/'.join(rule.flax)}, "
                           f"not in the model")
    if tuple(arr.shape) != tuple(want):
      raise CheckpointError(f"{path}: {_rule_name(rule)} has shape {tuple(t.shape)} "
                            f"(-> {tuple(arr.shape)} in Flax layout), the model expects "
                            f"{tuple(want)} at {'/'.join(rule.flax)}")
    flat[rule.flax] = arr
  if cover:
    check_covered(flat, expected)
  return flat


def check_covered(flat: dict[Path, np.ndarray], expected: dict[Path, tuple[int, ...]]) -> None:
  """Asserts that the converted leaves are exactly the model's (a key-table bug otherwise)."""
  uncovered = sorted("/".join(k) for k in expected if k not in flat)
  if uncovered:
    raise AssertionError(f"key table does not cover model paths {uncovered[:8]}"
                         f"{' ...' if len(uncovered) > 8 else ''}")


def to_state_dict(variables: dict, rules: Rules) -> dict[str, np.ndarray]:
  """Inverse of `apply_rules`: Flax variables -> PyTorch-named float32 arrays."""
  from flax.traverse_util import flatten_dict
  flat = {k: np.asarray(v, np.float32) for k, v in flatten_dict(variables).items()}
  pieces: dict[str, list[tuple[int, np.ndarray]]] = collections.defaultdict(list)
  for rule in rules:
    t = to_torch(flat[rule.flax], rule.kind)
    if len(rule.sources) > 1:
      for s, part in zip(rule.sources, np.split(t, len(rule.sources), axis=0)):
        pieces[s].append((0, part))
    else:
      pieces[rule.sources[0]].append((rule.rows[0] if rule.rows else 0, t))
  return {s: np.concatenate([a for _, a in sorted(ps, key=lambda x: x[0])], 0)
          if len(ps) > 1 else ps[0][1] for s, ps in pieces.items()}


def expected_shapes(module, *inputs_shapes: tuple[int, ...], **kwargs) -> dict[Path, tuple[int, ...]]:
  """Flax path (collection first) -> shape of every variable of `module`, by `jax.eval_shape`.

  inputs_shapes: the shapes of the positional float32 inputs to `module.init`.
  """
  import jax
  import jax.numpy as jnp
  from flax.traverse_util import flatten_dict
  args = [jnp.zeros(s, jnp.float32) for s in inputs_shapes]
  shapes = jax.eval_shape(lambda: module.init(jax.random.PRNGKey(0), *args, **kwargs))
  return {k: tuple(v.shape) for k, v in flatten_dict(shapes).items()}
