"""The depth networks the project knows, by name, and `Network`: a spec with its built module.

`MODELS[name]` is the network's `ModelSpec` (`models/<name>/`); a weights directory's
model.json names its architecture, so `pitta_jax.checkpoint.load_weights` finds the spec here.
Adding a network is one folder plus one line in `MODELS`.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import flax.linen as nn
from flax.traverse_util import flatten_dict

from pitta_jax.models import depth_anything_v2, hrdepth, litemono, monodepth2, monovit, sgdepth
from pitta_jax.models.spec import ModelSpec

MODELS: dict[str, ModelSpec] = {
    "monodepth2": monodepth2.SPEC,
    "sgdepth": sgdepth.SPEC,
    "hrdepth": hrdepth.SPEC,
    "litemono": litemono.SPEC,
    "monovit": monovit.SPEC,
    "depth_anything_v2": depth_anything_v2.SPEC,
    "depth_anything_v2_metric": depth_anything_v2.METRIC_SPEC,
}


REGISTER_HINT = ("a network of your own: `pitta_jax.models.registry.MODELS[spec.name] = spec` "
                 "first (README 'Adding a network or a method')")


def get_spec(name: str) -> ModelSpec:
  """The spec of network `name` (ValueError listing the known names otherwise)."""
  if name not in MODELS:
    raise ValueError(f"unknown model {name!r}; available: {', '.join(sorted(MODELS))} "
                     f"({REGISTER_HINT})")
  return MODELS[name]


def checked_images(images: Any) -> jax.Array:
  """`images` as an array, refused unless (B, H, W, 3) NHWC and floating (RGB in [0, 1]): an
  integer image made the networks' normalisation constants integers too (0.45 -> 0), and
  every depth NaN; an NCHW batch was reported as an unsupported input size."""
  images = jnp.asarray(images)
  if images.ndim != 4 or images.shape[-1] != 3:
    hint = " (NCHW? move the channels last)" if images.ndim == 4 and images.shape[1] == 3 else ""
    raise ValueError(f"images must be a (B, H, W, 3) NHWC batch, got shape "
                     f"{tuple(images.shape)}{hint}")
  if not jnp.issubdtype(images.dtype, jnp.floating):
    raise TypeError(f"images must be floating RGB in [0, 1], got {images.dtype} "
                    f"(divide 8-bit images by 255)")
  return images


def checked_outputs(outputs: Any, images: jax.Array, name: str) -> tuple:
  """A module's outputs, refused (ValueError naming the network) unless they are what
  `ModelSpec`'s contract asks: a tuple (or list) of maps whose first is (B, H, W, 1) at the
  images' batch and size. Why: `depth` reads `outputs[0][..., 0]`, so a bare (B, H, W, 1) array
  gave the first image's (H, W) map as the batch's depth, and a (B, H, W) map without its
  channel axis the first column of every image, (B, H), both without a word."""
  first = outputs[0] if isinstance(outputs, (tuple, list)) and len(outputs) else None
  want = (*images.shape[:3], 1)  # (B, H, W, 1)
  if first is None or tuple(getattr(first, "shape", ())) != want:
    if hasattr(outputs, "shape"):  # a bare array (a tracer under jit)
      got = f"one array of shape {tuple(outputs.shape)}, not a tuple"
    elif first is None:
      got = f"{type(outputs).__name__} {outputs!r:.80}"
    else:
      got = f"a first map of shape {tuple(getattr(first, 'shape', ()))}"
    raise ValueError(f"network {name}: module.apply must return a tuple of (B, H, W, 1) maps, "
                     f"the full-resolution one {want} first (ModelSpec's contract), got {got}")
  return tuple(outputs)


@dataclasses.dataclass(frozen=True)
class Network:
  """A depth network as the engine sees it: its spec and its Flax module.

  depth(variables, images, use_batch_stats) -> (B, H, W) depth from the full-resolution output;
  outputs(...) -> the module's output maps; capture(...) -> outputs and named intermediate
  activations (e.g. every encoder BatchNorm's output, which ActMAD aligns).
  """
  spec: ModelSpec
  module: nn.Module

  def _apply(self, variables: Any, images: jax.Array, use_batch_stats: bool,
             mutable: list[str], **kwargs) -> tuple[Any, Any]:
    """`module.apply(variables, images, train=use_batch_stats)` with `mutable` collections,
    -> (outputs, their new state). With batch statistics, `batch_stats` is mutable too and its
    new values are dropped: a network built on `flax.linen.BatchNorm` (which refuses to run in
    train mode with the collection immutable) normalises with the frame's statistics and its
    running ones stay as they were, as with `layers.BatchNorm` (whose running update, never
    read, XLA removes)."""
    if use_batch_stats and "batch_stats" in variables:
      mutable = [*mutable, "batch_stats"]
    images = checked_images(images)  # (B, H, W, 3)
    if not mutable:
      out = self.module.apply(variables, images, train=use_batch_stats, **kwargs)
      return checked_outputs(out, images, self.spec.name), {}
    out, state = self.module.apply(variables, images, train=use_batch_stats, mutable=mutable,
                                   **kwargs)
    return checked_outputs(out, images, self.spec.name), state

  def outputs(self, variables: Any, images: jax.Array, use_batch_stats: bool) -> tuple:
    return self._apply(variables, images, use_batch_stats, [])[0]

  def depth(self, variables: Any, images: jax.Array, use_batch_stats: bool) -> jax.Array:
    """images (B, H, W, 3) in [0, 1] -> depth (B, H, W) (relative for affine-invariant nets)."""
    return self.spec.to_depth(self.outputs(variables, images, use_batch_stats)[0][..., 0])

  def capture(self, variables: Any, images: jax.Array, use_batch_stats: bool,
              pattern: str) -> tuple[tuple, dict[str, jax.Array]]:
    """The outputs and the output of every submodule whose `/`-joined path matches `pattern`
    (a regular expression, e.g. r"encoder/.*bn\\d*$") and whose output is one array (a feature
    map; a module returning several, e.g. the whole encoder's list of features, is skipped),
    keyed by path, in call order."""
    rx = re.compile(pattern)

    def keep(module: nn.Module, method_name: str) -> bool:
      return method_name == "__call__" and bool(rx.fullmatch("/".join(module.path)))

    out, state = self._apply(variables, images, use_batch_stats, ["intermediates"],
                             capture_intermediates=keep)
    flat = flatten_dict(state.get("intermediates", {}), sep="/")
    return out, {k[: -len("/__call__")]: v[0] for k, v in flat.items()
                 if isinstance(v[0], jax.Array)}

  def forward_order(self) -> list[str]:
    """Module paths that own parameters, in forward (creation) order (fraction selector)."""
    return _forward_order(self.module, *self.spec.default_size)


def _forward_order(module: nn.Module, height: int, width: int) -> list[str]:
  """Module paths owning parameters, in the order the forward pass creates them."""
  import jax.numpy as jnp
  order: list[str] = []

  def init():
    variables = module.init(jax.random.PRNGKey(0), jnp.zeros((1, height, width, 3), jnp.float32))
    for key in flatten_dict(variables["params"]):  # a plain dict in creation order
      path = "/".join(key[:-1])
      if path not in order:
        order.append(path)
    return variables

  jax.eval_shape(init)  # traces only: no compute
  return order


def network(spec: ModelSpec | str, config: Mapping[str, Any] | None = None,
            module: nn.Module | None = None) -> Network:
  """The network `spec` built from a model.json `config` (or an explicit `module`)."""
  spec = get_spec(spec) if isinstance(spec, str) else spec
  return Network(spec, module if module is not None else spec.build(dict(config or {})))


__all__ = ["MODELS", "ModelSpec", "Network", "checked_outputs", "get_spec", "network"]
