"""The kernel gradient of MonoDepth2's convolutions: XLA:CPU's forms against PyTorch's oneDNN.

    python benchmarks/kernel_grad.py                 # batch 1 and 4, every layer below
    python benchmarks/kernel_grad.py --batch 4 --layers conv1,upconv_1_1
    python benchmarks/kernel_grad.py --batch 1 --forms model --libraries default,eigen,onednn

Why: the baselines that adapt convolution kernels (CoMoDa: the depth and pose networks at batch
4; ActMAD and Ada-Depth: batch 1) spend much of their step in kernel gradients, a contraction
over every pixel, and that is where the JAX steps lose to PyTorch (docs/performance.md).
Each layer's kernel gradient dk[a, b, c, o] = sum_{n,i,j} x_pad[n, i s + a, j s + b, c]
g[n, i, j, o] (x: (N, H, W, C) NHWC, g: (N, Ho, Wo, O)) is timed in several forms, each inside
a compiled `lax.fori_loop` of `--loops` iterations (the engine's step is the body of a scan,
and XLA:CPU compiles loop bodies differently from straight-line code), its input produced by a
ReLU in the loop as in a network:
- `model`: what `models.conv_vjp` compiles for this shape (its `_kernel_grad`);
- `conv`: a convolution of x (batch and features swapped, zero padded first) with g as the
  kernel (`conv_vjp.kernel_grad_conv`);
- `inside`: the same convolution with the padding inside it (`pad_first=False`: the model's
  form until 2026-12-08, at batch >= 2 until 04:00 UTC that day);
- `phases`: one stride-1 kernel gradient per stride phase of the padded input, taps
  interleaved (`conv_vjp.kernel_grad_phases`; the model's form for stride 2 since 2026-12-08,
  04:00 UTC; at stride 1 the same as `conv`);
- `patches`: one matrix product of x's patches, (kh kw C, N Ho Wo) @ (N Ho Wo, O)
  (`conv_vjp.kernel_grad_patches`);
- `per_image`: `conv` for each image, summed (what `conv_vjp` used for the decoder's wide,
  shallow layers at batch >= 2 until 2026-12-05);
- `rows`: kh products, one per kernel row, of the input's kw column taps side by side read at
  that row, (kw C, N Ho Wo) @ (N Ho Wo, O) (`bench_common.kernel_grad_rows`);
- `stacked`: one product of the column taps with the cotangent shifted to each kernel row,
  (kw C, N Hp Wo) @ (N Hp Wo, kh O) (`bench_common.kernel_grad_stacked`; `rows` where strided);
- `torch`: `torch.ops.aten.convolution_backward` with only the weight gradient asked (NCHW, as
  a PyTorch user runs it; oneDNN), same threads.
`--libraries` compiles every JAX form once per XLA:CPU convolution library (`form@library`):
`default` (XLA's choice, YNNPACK), `eigen` (`pitta_jax.adapt.xla_cpu`'s Eigen option) and
`onednn`: Eigen's option plus XLA's oneDNN switches (`ONEDNN_OPTIONS`), which take effect only in
a jaxlib built with oneDNN; the line says whether they changed any value
(`onednn_changes_values`: false means the oneDNN path is not in this jaxlib, as in the CPU wheels
of jaxlib 0.10.2 measured here).
Every form is checked against `conv` (relative 1e-4). Prints one JSON line per layer and batch:
the best ms of `--reps` runs per form, the GFLOP of the contraction, and the load average.
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
from pitta_jax.models import conv_vjp  # noqa: E402

# name: (H, W, C, O, kernel, stride, padding) of the input x before padding, at 640x192.
# The decoder's layers pad by reflection before an unpadded convolution: their x is padded.
LAYERS = {
    "conv1": (192, 640, 3, 64, 7, 2, 3),            # depth encoder, the image
    "pose_conv1": (192, 640, 6, 64, 7, 2, 3),       # pose encoder, two stacked images
    "layer1": (48, 160, 64, 64, 3, 1, 1),
    "layer2_s2": (48, 160, 64, 128, 3, 2, 1),       # each stage's first, strided conv
    "layer2_ds": (48, 160, 64, 128, 1, 2, 0),       # and its 1x1 strided shortcut
    "layer2": (24, 80, 128, 128, 3, 1, 1),
    "layer3_s2": (24, 80, 128, 256, 3, 2, 1),
    "layer3": (12, 40, 256, 256, 3, 1, 1),
    "layer4_s2": (12, 40, 256, 512, 3, 2, 1),
    "layer4": (6, 20, 512, 512, 3, 1, 1),
    "upconv_4_1": (14, 42, 512, 256, 3, 1, 0),
    "upconv_2_1": (50, 162, 128, 64, 3, 1, 0),
    "upconv_1_1": (98, 322, 96, 32, 3, 1, 0),
    "upconv_0_0": (98, 322, 32, 16, 3, 1, 0),
    "upconv_0_1": (194, 642, 16, 16, 3, 1, 0),
    # the decoder's layers on the largest maps, as `layers.ring_reflect_conv3x3` convolves them
    # (zero padding 1 in the convolution, the reflected ring added apart)
    "upconv_0_1_ring": (192, 640, 16, 16, 3, 1, 1),
    "dispconv_0_ring": (192, 640, 16, 1, 3, 1, 1),
    "dispconv_1_ring": (96, 320, 32, 1, 3, 1, 1),
}


def _conv_form(x, g, k, s, p):
  return conv_vjp.kernel_grad_conv(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1))


def _inside_form(x, g, k, s, p):
  return conv_vjp.kernel_grad_conv(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1),
                                   pad_first=False)


def _phases_form(x, g, k, s, p):
  return conv_vjp.kernel_grad_phases(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1))


def _patches_form(x, g, k, s, p):
  return conv_vjp.kernel_grad_patches(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1))


def _per_image_form(x, g, k, s, p):
  return bc.per_image_kernel_grad(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1))


def _model_form(x, g, k, s, p):
  return conv_vjp._kernel_grad(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1), None)


def _rows_form(x, g, k, s, p):
  return bc.kernel_grad_rows(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1))


def _stacked_form(x, g, k, s, p):
  if s != 1:  # the rows' products where the rows are strided (`bc.row_tap_kernel_grads`)
    return _rows_form(x, g, k, s, p)
  return bc.kernel_grad_stacked(x, g, (k, k), (s, s), ((p, p), (p, p)), (1, 1))


FORMS = {"model": _model_form, "conv": _conv_form, "inside": _inside_form,
         "phases": _phases_form, "patches": _patches_form,
         "per_image": _per_image_form, "rows": _rows_form, "stacked": _stacked_form}

# XLA:CPU's oneDNN switches (flags of jaxlib 0.10's XLA; they act only where XLA was built with
# oneDNN, i.e. with INTEL_MKL)
ONEDNN_OPTIONS = {"xla_cpu_use_onednn": True, "xla_cpu_experimental_onednn_custom_call": True}
LIBRARIES = {**bc.CONV_LIBRARY_OPTIONS,
             "onednn": lambda: {**bc.CONV_LIBRARY_OPTIONS["eigen"](), **ONEDNN_OPTIONS}}


def time_jax(form, x, g, k, s, p, loops: int, reps: int, compiler_options: dict | None = None
             ) -> tuple[float, np.ndarray]:
  """Best ms per kernel gradient inside a compiled loop, and the (last) value."""
  def run(x, g):
    def body(i, acc):
      return acc + form(jax.nn.relu(x + i.astype(x.dtype)), g, k, s, p)
    return lax.fori_loop(0, loops, body, jnp.zeros((k, k, x.shape[3], g.shape[3]), x.dtype))
  compiled = jax.jit(run, compiler_options=compiler_options).lower(x, g).compile()
  value = np.asarray(compiled(x, g))
  best = bc.median_time(lambda: compiled(x, g).block_until_ready(), reps)[1]
  return 1e3 * best / loops, value / loops


def time_torch(x, g, k, s, p, reps: int) -> float:
  xt = torch.from_numpy(np.array(x)).permute(0, 3, 1, 2).contiguous()
  gt = torch.from_numpy(np.array(g)).permute(0, 3, 1, 2).contiguous()
  w = torch.zeros(g.shape[3], x.shape[3], k, k)

  def one():
    torch.ops.aten.convolution_backward(gt, torch.relu(xt), w, None, [s, s], [p, p], [1, 1],
                                        False, [0, 0], 1, [False, True, False])
  one()
  return 1e3 * bc.median_time(one, reps)[1]


def main(argv=None) -> None:
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  ap.add_argument("--batch", default="1,4", help="comma-separated batch sizes (default 1,4)")
  bc.add_per_layer_args(ap, LAYERS, FORMS, LIBRARIES, default_libraries="default", loops=3,
                        reps=3, per_loop="kernel gradients")
  args, layers, forms, libraries = bc.parse_per_layer_args(ap, argv, LAYERS, FORMS, LIBRARIES)
  torch.set_num_threads(args.threads)
  rng = np.random.default_rng(0)
  for n in (int(b) for b in args.batch.split(",")):
    for name in layers:
      h, w, c, o, k, s, p = LAYERS[name]
      ho, wo = (h + 2 * p - k) // s + 1, (w + 2 * p - k) // s + 1
      x = jnp.asarray(rng.standard_normal((n, h, w, c)), jnp.float32)
      g = jnp.asarray(rng.standard_normal((n, ho, wo, o)), jnp.float32)
      ms, values, ref = {}, {}, None
      for form in ["conv"] + [f for f in forms if f != "conv"]:
        for lib in libraries:
          key = form if libraries == ["default"] else f"{form}@{lib}"
          ms[key], values[key] = time_jax(FORMS[form], x, g, k, s, p, args.loops, args.reps,
                                          LIBRARIES[lib]())
          if ref is None:
            ref = values[key]
          err = float(np.max(np.abs(values[key] - ref)) / np.max(np.abs(ref)))
          assert err < 1e-4, (name, key, err)
      ms["torch"] = time_torch(x, g, k, s, p, args.reps)
      extra = {}
      if {"eigen", "onednn"} <= set(libraries):
        extra["onednn_changes_values"] = any(
            not np.array_equal(values[f"{f}@onednn"], values[f"{f}@eigen"]) for f in forms)
      bc.emit({"layer": name, "batch": n, "x": [n, h, w, c], "out_features": o, "kernel": k,
               "stride": s, "threads": args.threads,
               "gflop": round(2 * k * k * c * o * n * ho * wo / 1e9, 3),
               "best_ms": {f: round(v, 1) for f, v in ms.items()}, **extra, "load": bc.load()})


if __name__ == "__main__":
  main()
