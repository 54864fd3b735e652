"""`pitta-jax demo`: the embedded benchmark end to end, no downloads, no arguments needed.

1. Loads the clear-domain source MonoDepth2 (`source_model`: shipped with the package for
   the default `SourceConfig`, else trained once and cached).
2. Generates target sequences of the synthetic driving benchmark under fog, rain, night, snow
   (unseen seeds), plus a clear sequence to show the source accuracy.
3. Runs up to seven rows per shift (`--demo.methods`; default the first three): "No
   adaptation" (the source model as is, running BN statistics), "BN batch stats" (no update,
   the frame's batch statistics: separates their effect from the loss's), "PITTA" (eqs. 3-11,
   paper defaults),
   and the paper's baselines CoMoDa, Ada-Depth, ActMAD and CoTTA, each with PITTA's L_d (paper
   Sec. 4.1), with ground-truth panoptic segmentation standing in for Mask2Former.
4. Prints a markdown table of the 7 metrics and writes results.json, results.csv, table.md and
   figures to `--out`: per shift, the last frame's depth maps (`viz`) and the per-frame AbsRel
   of every row (`plots`, matplotlib).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path
from typing import Any, Callable, Collection, Mapping

import numpy as np

from pitta_jax import viz
from pitta_jax.adapt import AdaptConfig
from pitta_jax.configs import check, option
from pitta_jax.methods import build as build_method
from pitta_jax.methods.pitta import PittaConfig
from pitta_jax.outputs import WatchedDirectory, check_passes
from pitta_jax.plots import PlotConfig, per_frame_figure, save_figure
from pitta_jax.data.image_io import write_image
from pitta_jax.data.resize import resize_frame
from pitta_jax.data.synthetic import SyntheticConfig, SyntheticSequence
from pitta_jax.report import Row, clear_earlier_results, write_results
from pitta_jax.run import EvalConfig, RunResult, Runners, run_sequence
from pitta_jax.source_model import SourceConfig, load_or_train_source
from pitta_jax.sources import method_resources

# --demo.methods key -> (row name, method, AdaptConfig changes after the method's own setting
# `methods.method_setting`); the baselines carry PITTA's L_d (paper Sec. 4.1)
ROWS = {
    "none": ("No adaptation", "none", {}),
    "bn": ("BN batch stats", "none", {"bn_stats": "batch"}),
    "pitta": ("PITTA", "pitta", {}),
    "comoda": ("CoMoDa + L_d", "comoda", {}),
    "adadepth": ("Ada-Depth + L_d", "adadepth", {}),
    "actmad": ("ActMAD + L_d", "actmad", {}),
    "cotta": ("CoTTA + L_d", "cotta", {}),
}

# the figures a run writes under --out (`_figures`' depth maps, `run_demo`'s per-frame AbsRel),
# removed at the start of a rerun so that shifts it no longer runs leave none behind
FIGURES = ("figures/*_frame[0-9][0-9][0-9]*.png", "figures/*_abs_rel_per_frame.png")


# a shift of up to this many frames is rendered once and its frames shared by the shift's rows
# (~2.5 MB a frame at 640x192: 640 MB); a longer one is rendered as each row reads it (~30 ms a
# frame on a 2-core CPU, against ~250 ms for PITTA's step), never held whole in memory
RENDER_ONCE_FRAMES = 256


@dataclasses.dataclass(frozen=True)
class DemoConfig:
  """What the demo runs (the source model is `SourceConfig`'s, the methods their configs')."""
  shifts: tuple[str, ...] = option(("fog", "rain", "night", "snow"), "target weather domains")
  severity: float = option(0.7, "synthetic weather strength in [0, 1]")
  num_frames: int = option(40, "frames per target sequence (keeps a cached re-run of the "
                               "default rows under a minute on a 2-core CPU)")
  target_seed: int = option(100, "target streets (training uses seeds 0..7)")
  methods: tuple[str, ...] = option(("none", "bn", "pitta"),
                                    "rows under each shift: none (No adaptation), bn (BN batch "
                                    "stats), pitta, and the paper's baselines with L_d: comoda, "
                                    "adadepth, actmad, cotta (slower: CoMoDa and Ada-Depth train "
                                    "depth and pose networks per frame)")
  out: str = option("pitta_out", "output directory")
  figures: PlotConfig = PlotConfig()  # the per-frame AbsRel plots (--demo.figures.dpi, ...)

  def __post_init__(self):
    from pitta_jax.data.synthetic import DOMAINS
    bad = [s for s in self.shifts if s not in DOMAINS[1:]]
    check(not bad and bool(self.shifts),
          f"shifts {bad or '()'} invalid: choose from {', '.join(DOMAINS[1:])}")
    check(self.num_frames >= 1, f"num_frames must be >= 1, got {self.num_frames}")
    try:  # frames beyond the street the renderer draws exactly: refused before any work
      from pitta_jax.data.synthetic import SyntheticConfig
      SyntheticConfig(num_frames=self.num_frames)
    except ValueError as e:
      check(False, str(e))
    check(self.target_seed >= 0, f"target_seed must be >= 0, got {self.target_seed}")
    check(0.0 <= self.severity <= 1.0, f"severity must be in [0, 1], got {self.severity}")
    bad_rows = [m for m in self.methods if m not in ROWS]
    check(not bad_rows and bool(self.methods),
          f"methods {bad_rows or '()'} invalid: choose from {', '.join(ROWS)}")
    for name, values in (("methods", self.methods), ("shifts", self.shifts)):
      twice = sorted({v for v in values if values.count(v) > 1})
      check(not twice, f"{name} {twice} given twice: each once")


def row_config(adapt: AdaptConfig, method, changes: Mapping[str, Any],
               given: Collection[str] = ()) -> AdaptConfig:
  """A row's AdaptConfig: `adapt`, then what the method requires, its own setting (e.g.
  CoTTA's selector all) except the fields in `given` (set on the command line: they win, as in
  `pitta-jax adapt`), then the row's `changes` (BN batch stats: bn_stats batch)."""
  required = {field: value for field, value, _ in method.requires}
  own = {k: v for k, v in method.setting if k not in given}
  return dataclasses.replace(adapt, method=method.name, **{**required, **own, **dict(changes)})


def run_demo(demo: DemoConfig = DemoConfig(), adapt: AdaptConfig = AdaptConfig(),
             pitta: PittaConfig = PittaConfig(), source: SourceConfig = SourceConfig(),
             quiet: bool = False, method_configs: Mapping[str, Any] | None = None,
             given: Collection[str] = (),
             check_out: Callable[[], Any] | None = None) -> dict:
  """Runs the demo; returns the results dict (also written to `demo.out`).

  adapt: the AdaptConfig every row starts from (each method's own setting is applied on top,
  except for the fields in `given`: `row_config`);
  pitta, method_configs: the methods' configs by name (default: their paper defaults).
  check_out: called before each figure and before the results are written; it raises to stop
  the demo when `demo.out` was removed or replaced meanwhile (the command passes its locked
  --out's `OutputDir.check`). None: `demo.out` as it is at the start, where it exists
  (`outputs.WatchedDirectory`)."""
  configs = {**(method_configs or {}), "pitta": pitta}
  t_start = time.perf_counter()
  out = Path(demo.out)
  weights, train_report = load_or_train_source(source, quiet=quiet)
  clear_earlier_results(out, FIGURES)
  figures_existed = (out / "figures").exists()
  watch = WatchedDirectory(out) if check_out is None and out.is_dir() else None
  if watch is not None:
    check_out = watch.check
  elif check_out is None:  # a library call whose demo.out is made by its results
    check_out = lambda: None  # noqa: E731
  try:
    h, w = weights.height, weights.width
    runners = Runners()  # one compile per row serves every shift
    resources: dict[str, dict] = {}
    rows: list[Row] = []
    per_frame: dict[str, dict[str, list[float]]] = {}
    domains = ("clear",) + tuple(demo.shifts)
    for domain in domains:
      frames = SyntheticSequence(SyntheticConfig(
          height=h, width=w, num_frames=demo.num_frames, seed=demo.target_seed, domain=domain,
          severity=demo.severity))
      if len(frames) <= RENDER_ONCE_FRAMES:  # rendered once, shared by the shift's rows
        frames = list(frames)
      results: dict[str, RunResult] = {}
      for key in (("none",) if domain == "clear" else demo.methods):
        row, name, changes = ROWS[key]
        method = build_method(name, configs.get(name))
        cfg = row_config(adapt, method, changes, given)
        if key not in resources:  # e.g. ActMAD's source statistics, from clear training streets
          resources[key] = method_resources(method, weights, "synthetic", quiet=quiet)
        res = run_sequence(weights, frames, cfg, method, EvalConfig(), name=f"{domain}: {row}",
                           quiet=quiet, keep=(len(frames) - 1,), runners=runners,
                           resources=resources[key])
        results[row] = res
        rows.append(Row(domain, row, res.mean if res.status == "ok" else {}, {
            "fps": round(res.fps, 2), "seconds": round(res.seconds, 2), "frames": len(frames),
            "compile_seconds": round(res.compile_seconds, 1),
            "n_skipped": res.n_skipped, "mean_loss": float(np.mean(res.logs["loss"])),
            # a row's own time per frame: its chunks after the step compiled where it has any
            "ms_per_frame": round(1000.0 / (res.steady_fps if res.steady_fps == res.steady_fps
                                            else res.fps), 1),
            **({"mean_instances": float(np.mean(res.logs["n_instances"]))}
               if "n_instances" in res.logs else {})}, status=res.status))
      per_frame[domain] = {r: res.per_frame_series("abs_rel") for r, res in results.items()}
      check_out()
      _figures(out / "figures", domain, frames, results, h, w)
    # every figure before the results: an interrupt removes this run's figures, and results
    # written before them would have stayed, complete-looking, without their figures
    check_out()
    for domain, series in per_frame.items():
      figure = per_frame_figure(series, "abs_rel", f"Per-frame AbsRel, {domain}", demo.figures)
      save_figure(figure, out / "figures" / f"{domain}_abs_rel_per_frame.png", demo.figures)
    seconds = time.perf_counter() - t_start
    meta = {"demo": dataclasses.asdict(demo), "adapt": dataclasses.asdict(adapt),
            "pitta": dataclasses.asdict(pitta),
            "source": train_report, "per_frame_abs_rel": per_frame, "seconds": round(seconds, 1)}
    check_out()
    table = write_results(out, rows, meta)
    if not quiet:
      print(f"\nSource model: {train_report.get('weights_dir')} "
            f"(trained in {train_report.get('train_seconds', '?')} s)")
      print(table)
    print(f"demo finished in {seconds:.0f} s; results in {out}/ (results.json, results.csv, "
          f"table.md, figures/)")
    return {**meta, "rows": rows, "table": table}
  except BaseException:  # interrupted or failed: no figures of this run without its results
    if check_passes(check_out):  # (a directory made again there is not this run's)
      for pattern in FIGURES:
        for path in out.glob(pattern):
          path.unlink(missing_ok=True)
      if not figures_existed:  # nor the directory it made for them, once empty
        with contextlib.suppress(OSError):
          (out / "figures").rmdir()
    raise
  finally:
    if watch is not None:
      watch.close()



def _figures(directory: Path, domain: str, frames, results: dict[str, RunResult], h: int,
             w: int) -> None:
  """input | ground truth | depth per row | dynamic-instance mask, for the last frame."""
  index = len(frames) - 1
  frame = resize_frame(frames[index], h, w)
  dynamic = {s.id for s in frame.segments if s.isthing}
  mask_ids = np.where(np.isin(frame.panoptic, list(dynamic)), frame.panoptic, 0)
  gt = frame.depth
  tiles = [viz.label(viz.to_uint8(frame.image), f"input ({domain})"),
           viz.label(viz.colorize_depth(gt), "ground truth")]
  tiles += [viz.label(viz.colorize_depth(res.kept_depths[index]), name)
            for name, res in results.items()]
  tiles.append(viz.label(viz.colorize_ids(mask_ids), "dynamic instances"))
  write_image(directory / f"{domain}_frame{index:03d}.png", viz.grid([tiles[:3], tiles[3:]]))
