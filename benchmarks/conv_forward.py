"""MonoDepth2's forward 3x3 convolutions: XLA:CPU's forms and libraries against PyTorch's oneDNN.

    python benchmarks/conv_forward.py                       # every layer below, both libraries
    python benchmarks/conv_forward.py --layers layer1,layer4 --libraries default

Why: the forward convolutions are about half of the PITTA step on a CPU and nearly all of an
eval-mode forward (`benchmarks/profile_step.py --conv-library default`), and the step is short
of 2x PyTorch where its forward is not faster than PyTorch's (docs/performance.md). Each layer's
3x3 stride-1 convolution (zero padding 1, NHWC) is timed in several forms, each inside a
compiled `lax.fori_loop` of `--loops` iterations whose input is the previous output through a
ReLU (as in a network, and so that XLA cannot hoist it):
- `conv`: `lax.conv_general_dilated`, as `models.conv_vjp` compiles most layers;
- `patches`: one matrix product of the input's nine shifted copies, (N H W, 9 C) @ (9 C, O)
  (what `conv_vjp` uses for ResNet's last stage, `FEW_PIXELS_*`);
- `taps`: nine products of a shifted copy with one tap of the kernel, summed;
- `winograd`: Winograd's F(2x2, 3x3) (Lavin and Gray, 2016): 4x4 input tiles at stride 2, 16
  products (tiles, C) @ (C, O) of the transformed tiles and kernel (2.25x fewer multiplies than
  the convolution), the 2x2 outputs of each tile interleaved back;
each compiled with XLA's default convolution library and with Eigen's (`--libraries`), and
`torch`: `torch.nn.functional.conv2d` in NCHW and in `channels_last` (oneDNN), same threads.
Every form is checked against `conv` (relative 1e-5). Prints one JSON line per layer: the best
ms of `--reps` runs per form, its GFLOP/s, and the load average.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from jax import lax  # noqa: E402

import bench_common as bc  # noqa: E402

# name: (H, W, C) of the layer's input at 640x192; every layer maps C -> C features
LAYERS = {
    "layer1": (48, 160, 64),   # ResNet's first stage
    "layer2": (24, 80, 128),
    "layer3": (12, 40, 256),
    "layer4": (6, 20, 512),    # the last stage (conv_vjp's patches product)
    "upconv_1": (96, 320, 32),
}
LIBRARIES = bc.CONV_LIBRARY_OPTIONS


def _shifted(x: jax.Array) -> list[jax.Array]:
  """The nine zero-padded 3x3 shifts of x (N, H, W, C), tap (i, j) in row-major order."""
  h, w = x.shape[1], x.shape[2]
  xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
  return [xp[:, i:i + h, j:j + w] for i in range(3) for j in range(3)]


def conv_form(x: jax.Array, k: jax.Array) -> jax.Array:
  return lax.conv_general_dilated(x, k, (1, 1), ((1, 1), (1, 1)),
                                  dimension_numbers=("NHWC", "HWIO", "NHWC"))


def patches_form(x: jax.Array, k: jax.Array) -> jax.Array:
  n, h, w, c = x.shape
  cols = jnp.concatenate(_shifted(x), axis=-1)                       # (N, H, W, 9 C)
  return (cols.reshape(-1, 9 * c) @ k.reshape(9 * c, -1)).reshape(n, h, w, -1)


def taps_form(x: jax.Array, k: jax.Array) -> jax.Array:
  taps = k.reshape(9, *k.shape[2:])                                  # (9, C, O)
  return sum(jnp.einsum("nhwc,co->nhwo", s, taps[t]) for t, s in enumerate(_shifted(x)))


def _winograd_rows(r: list[jax.Array]) -> list[jax.Array]:
  """B^T d of Winograd's F(2, 3) along a list of four rows (or columns) d."""
  return [r[0] - r[2], r[1] + r[2], r[2] - r[1], r[1] - r[3]]


def winograd_form(x: jax.Array, k: jax.Array) -> jax.Array:
  """F(2x2, 3x3): Y = A^T [(G k G^T) * (B^T d B)] A per 4x4 tile d (H and W even)."""
  n, h, w, c = x.shape
  g = jnp.array([[1, 0, 0], [.5, .5, .5], [.5, -.5, .5], [0, 0, 1]], k.dtype)
  u = jnp.einsum("ai,ijco,bj->abco", g, k, g).reshape(16, c, -1)     # (16, C, O)
  xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
  th, tw = h // 2, w // 2
  rows = _winograd_rows([xp[:, i:i + 2 * th:2] for i in range(4)])  # 4 x (N, th, W + 2, C)
  v = jnp.stack([t for r in rows
                 for t in _winograd_rows([r[:, :, j:j + 2 * tw:2] for j in range(4)])])
  m = lax.dot_general(v.reshape(16, n * th * tw, c), u, (((2,), (1,)), ((0,), (0,))))
  m = m.reshape(4, 4, n, th, tw, -1)                                 # (4, 4, N, th, tw, O)
  t = [m[0] + m[1] + m[2], m[1] - m[2] - m[3]]                       # A^T along rows
  y = [[s[0] + s[1] + s[2], s[1] - s[2] - s[3]] for s in t]          # and along columns
  y = jnp.stack([jnp.stack(y[0], -2), jnp.stack(y[1], -2)], 2)       # (N, th, 2, tw, 2, O)
  return y.reshape(n, h, w, -1)


FORMS = {"conv": conv_form, "patches": patches_form, "taps": taps_form,
         "winograd": winograd_form}


def time_jax(form, x, k, loops: int, reps: int, compiler_options: dict | None
             ) -> tuple[float, np.ndarray]:
  """Best ms per convolution inside a compiled loop, and the loop's result."""
  def run(x, k):
    return lax.fori_loop(0, loops, lambda i, y: jax.nn.relu(form(y, k)), x)
  compiled = jax.jit(run, compiler_options=compiler_options).lower(x, k).compile()
  value = np.asarray(compiled(x, k))
  best = bc.median_time(lambda: compiled(x, k).block_until_ready(), reps)[1]
  return 1e3 * best / loops, value


def time_torch(x, k, loops: int, reps: int, channels_last: bool) -> float:
  fmt = torch.channels_last if channels_last else torch.contiguous_format
  xt = torch.from_numpy(np.array(x)).permute(0, 3, 1, 2).contiguous(memory_format=fmt)
  wt = torch.from_numpy(np.array(k)).permute(3, 2, 0, 1).contiguous(memory_format=fmt)

  @torch.no_grad()
  def run():
    y = xt
    for _ in range(loops):
      y = torch.relu(torch.nn.functional.conv2d(y, wt, padding=1))
    return y
  run()
  return 1e3 * bc.median_time(run, reps)[1] / loops


def main(argv=None) -> None:
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  bc.add_per_layer_args(ap, LAYERS, FORMS, LIBRARIES, default_libraries="default,eigen",
                        loops=10, reps=5, per_loop="convolutions")
  args, layers, forms, libraries = bc.parse_per_layer_args(ap, argv, LAYERS, FORMS, LIBRARIES)
  torch.set_num_threads(args.threads)
  rng = np.random.default_rng(0)
  for name in layers:
    h, w, c = LAYERS[name]
    x = jnp.asarray(rng.random((1, h, w, c)), jnp.float32)
    k = jnp.asarray(rng.standard_normal((3, 3, c, c)) / np.sqrt(9 * c), jnp.float32)
    gflop = 2 * 9 * c * c * h * w / 1e9
    ms, ref = {}, None
    for form in ["conv"] + [f for f in forms if f != "conv"]:
      for lib in libraries:
        key = f"{form}@{lib}"
        ms[key], value = time_jax(FORMS[form], x, k, args.loops, args.reps, LIBRARIES[lib]())
        ref = value if ref is None else ref
        err = float(np.max(np.abs(value - ref)) / np.max(np.abs(ref)))
        assert err < 1e-5, (name, key, err)
    ms["torch"] = time_torch(x, k, args.loops, args.reps, channels_last=False)
    ms["torch_channels_last"] = time_torch(x, k, args.loops, args.reps, channels_last=True)
    bc.emit({"layer": name, "x": [1, h, w, c], "out_features": c, "threads": args.threads,
             "gflop": round(gflop, 3), "best_ms": {f: round(v, 2) for f, v in ms.items()},
             "gflop_per_s": {f: round(gflop / v * 1e3) for f, v in ms.items()},
             "load": bc.load()})


if __name__ == "__main__":
  main()
