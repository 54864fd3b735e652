"""Table 3: PITTA on the other networks of the paper (SGDepth, HR-Depth, MonoViT, Lite-Mono,
Depth Anything V2), adapted to DrivingStereo: rows No adaptation, No adaptation (Sunny), Sunny,
All.

    pitta-jax experiment table3 [--quick] [--dataset drivingstereo --root DIR
                                 --weights sgdepth=DIR --weights hrdepth=DIR ...]
    python -m experiments.table3 ...

The paper's "No adaptation" row does not say on which test case it is measured; ours is on All
(the case every adapted row is compared with), and a row the paper does not have, "No adaptation,
Sunny", measures the source network on the Sunny case, the reference of the Sunny row. PITTA adapts the encoder's BatchNorm layers, or
its LayerNorms where the encoder has no BatchNorm (Depth Anything V2). Lite-Mono's encoder has
both (BatchNorm in its stem, downsampling and dilated-convolution blocks, LayerNorm in its
attention blocks): its BatchNorms, as for the CNNs; so does MonoViT's (MPViT: BatchNorm after
its convolutions, LayerNorm in its transformer blocks).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

from experiments import common
from experiments.common import Entry, RowSpec

# network -> (paper's label, the selector of its encoder's norm layers)
NETWORKS = {
    "sgdepth": ("SGDepth", "encoder_bn"),
    "hrdepth": ("HR-Depth", "encoder_bn"),
    "monovit": ("MonoViT", "encoder_bn"),
    "litemono": ("Lite-Mono", "encoder_bn"),
    "depth_anything_v2": ("DepthAnythingV2", "encoder_ln"),
}
# (row label, method, test case, the paper's row: "" for ours)
ROWS = (("No adaptation", "none", "All", "No adaptation"),
        ("No adaptation (Sunny)", "none", "Sunny", ""),
        ("Sunny", "pitta", "Sunny", "Sunny"),
        ("All", "pitta", "All", "All"))
SUNNY_LABELS = frozenset(label for label, _, case, _ in ROWS if case == "Sunny")


def rows() -> list[tuple[str, str, RowSpec]]:
  """(network label, test case, row) in the paper's order."""
  out = []
  for model, (label, selector) in NETWORKS.items():
    for row_label, method, case, paper in ROWS:
      adapt = (("selector", selector),) if method == "pitta" else ()
      out.append((label, case, RowSpec(row_label, method, model, adapt=adapt, paper=paper)))
  return out


def selected(ctx) -> list[tuple[str, str, RowSpec]]:
  """The rows --rows selects, by network (label or name), row label (No adaptation (Sunny),
  All) or method."""
  return [(g, c, r) for g, c, r in rows() if ctx.wants(f"{g}: {r.label}", r.model, r.method)]


def _aligned_for_figures(entries: list[Entry]) -> list[Entry]:
  """Copies of `entries` whose Sunny series (the Sunny row and No adaptation on Sunny) start
  where All's sunny part does (All is cloudy, foggy, rainy, sunny in turn, its last part Sunny's
  frames): each is its own run, drawn under the frames of All it covers instead of from frame 0
  (NaN before: a gap)."""
  aligned = []
  for e in entries:
    series = e.extra.get("abs_rel_per_frame")
    whole = next((x.extra.get("abs_rel_per_frame") for x in entries
                  if x.group == e.group and x.label == "All"), None)
    if e.label in SUNNY_LABELS and series and whole and len(whole) > len(series):
      e = dataclasses.replace(e, label=f"{e.label}, its own run under All's sunny part", extra={
          **e.extra, "abs_rel_per_frame": [float("nan")] * (len(whole) - len(series))
          + list(series)})
    aligned.append(e)
  return aligned


def run(args, runners=None) -> int:
  from tqdm import tqdm
  from experiments.figures import per_frame_figures
  from experiments.tables import publish
  ctx = common.context(args, "table3", runners)
  elapsed = common.timer()
  cases = dict(ctx.cases(("Sunny", "All")))
  shared, resources, entries = common.runners(ctx), {}, []
  todo = selected(ctx)
  common.check_selection(ctx, todo, [x for g, _, r in rows() for x in (g, r.label)],
                         [(f"{g}: {r.label}", r.model, r.method) for g, _, r in rows()])
  common.check_flags_used(ctx, [r for _, _, r in rows()], [r for _, _, r in todo])
  common.check_rows(ctx, [(c, cases[c], r) for _, c, r in todo])
  for group, case, row in tqdm(todo, desc="rows", unit="row", disable=ctx.quiet):
    entry = common.run_row(ctx, row, case, cases[case], shared, resources)
    entry.group = group
    entries.append(entry)
  common.attach_paper(entries, 3, lambda e: None if not e.spec.paper else {
      "network": e.spec.model, "method": e.spec.method,
      "test_case": None if e.spec.method == "none" else e.label.lower()})
  caption = ("PITTA adapting other networks. Dataset: "
             + (common.SYNTHETIC_CAPTION["drivingstereo"] + f", {ctx.frames} frames per part; "
                + ("random networks (--quick)" if ctx.quick else
                   "each network trained on the clear synthetic streets by train-source")
                if ctx.dataset == "synthetic" else f"DrivingStereo at {ctx.root}")
             + ". No adaptation is measured on All (the paper's row) and on Sunny (ours). Unmarked, as in the paper: a network's rows "
               "are different test cases, not competing methods.")
  per_frame_figures(ctx.out, "table3", _aligned_for_figures(entries), ctx.quick,
                    check=lambda: common.check_out(ctx))
  return publish(ctx, "table3", entries, elapsed(), layout="rows", caption=caption,
                 group_title="MDE Net", row_title="Weather", marked=False)


def main(argv: Sequence[str] | None = None, runners=None) -> int:
  p = common.parser("table3", __doc__.split("\n\n")[0])
  return common.main_wrapper(run, p, argv, runners)


if __name__ == "__main__":  # as python -m experiments: signals and library logs handled
  from pitta_jax.cli import exit_with, interruptible
  exit_with(interruptible(main))
