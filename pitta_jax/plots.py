"""Plots of results with matplotlib: per-frame metric curves, the lambda ablation (paper Table 4)
and grouped bars for table-like comparisons (e.g. Table 5's adapted-parameter settings).

Each plot function returns a `matplotlib.figure.Figure` with its own Agg canvas, built without
pyplot, so no global backend or figure registry is touched (safe in libraries, threads and
tests); `save_figure` writes it atomically as PNG (and optionally PDF). The returned figure's
artists hold exactly the data given (a test reads them back), with non-finite values, e.g. the
metrics of frames skipped as non-finite, drawn as gaps.
"""

from __future__ import annotations

import dataclasses
import io
import math
import textwrap
from pathlib import Path
from typing import Mapping, Sequence

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from pitta_jax.configs import check, is_number, option
from pitta_jax.outputs import atomic_write_bytes
from pitta_jax.report import HEADERS

INF_LABEL = "∞"


MAX_FIGURE_PIXELS = 1e8  # ~400 MB of RGBA canvas, far above any paper figure


@dataclasses.dataclass(frozen=True)
class PlotConfig:
  """Size and formats of the written figures."""
  fig_width: float = option(7.2, "figure width in inches (PNG pixels = inches x dpi)")
  fig_height: float = option(3.6, "figure height in inches")
  dpi: int = option(100, "PNG resolution, dots per inch")
  pdf: bool = option(False, "also write each plot as a PDF beside its PNG (the demo's depth-map "
                            "images, figures/*_frameNNN.png, stay PNG only)")

  def __post_init__(self):
    for name in ("fig_width", "fig_height"):
      value = getattr(self, name)
      check(is_number(value) and math.isfinite(value) and value > 0,
            f"{name} must be a finite number > 0, got {value!r}")
    check(isinstance(self.dpi, int) and self.dpi >= 10, f"dpi must be an integer >= 10, got "
                                                       f"{self.dpi!r}")
    # found before the run, not as a failed allocation once it is done
    pixels = self.fig_width * self.dpi * self.fig_height * self.dpi
    check(pixels <= MAX_FIGURE_PIXELS,
          f"fig_width x fig_height at dpi: a {self.fig_width:g} x {self.fig_height:g} inch figure "
          f"at dpi {self.dpi} has {pixels:.3g} pixels; at most {MAX_FIGURE_PIXELS:.0e} (lower "
          f"dpi or the size)")


def _new_figure(cfg: PlotConfig, nrows: int, sharex: bool) -> tuple[Figure, np.ndarray]:
  """(Figure on its own Agg canvas, its axes array) with constrained layout (legends outside
  the axes get room without changing the figure's size)."""
  fig = Figure(figsize=(cfg.fig_width, cfg.fig_height), dpi=cfg.dpi, layout="constrained")
  FigureCanvasAgg(fig)
  axes = fig.subplots(nrows, 1, sharex=sharex, squeeze=False)[:, 0]
  return fig, axes


def per_frame_figure(series: Mapping[str, Sequence[float]], metric: str, title: str,
                     cfg: PlotConfig = PlotConfig()) -> Figure:
  """One line per method of a per-frame metric over a test case.

  series: {method name: (N_method,) values in frame order}; non-finite values (NaN for a frame
  that was skipped or had no valid ground truth) become gaps. metric: a metric key
  (`abs_rel`, ... labelled as in the tables, e.g. "AbsRel ↓") or any axis label. The legend sits
  to the right of the axes, outside the data.
  """
  check(len(series) > 0, "per_frame_figure: no series to plot")
  fig, (ax,) = _new_figure(cfg, 1, False)
  # distinct colours past matplotlib's 10-colour cycle (Table 1 has 11 rows): tab20 beyond it
  colors = [f"C{i}" for i in range(10)] if len(series) <= 10 else [
      matplotlib.colormaps["tab20"](i) for i in range(20)]
  styles = ("-", "--", ":", "-.")
  for k, (name, values) in enumerate(series.items()):
    y = _finite_or_nan(values)  # (N,)
    # a value with no finite neighbour (a one-frame run, a frame scored between gaps) is a line
    # of one point, which draws nothing: such points get a marker
    alone = _isolated(y)  # (N,) bool
    marks = dict(marker="o", markersize=3, markevery=alone) if alone.any() else {}
    ax.plot(np.arange(y.size), y, label=name, linewidth=1.5, color=colors[k % len(colors)],
            linestyle=styles[(k // len(colors)) % len(styles)], **marks)
  ax.set_xlabel("frame")
  ax.set_ylabel(HEADERS.get(metric, metric))
  ax.set_title(title)
  ax.xaxis.set_major_locator(MaxNLocator(integer=True))
  ax.grid(True, alpha=0.3)
  fig.legend(loc="outside right upper")
  return fig


def lambda_figure(lams: Sequence[float], values: Mapping[str, Sequence[float]], title: str,
                  cfg: PlotConfig = PlotConfig()) -> Figure:
  """Metrics against the loss weight lambda of eq. 10 (the paper's Table 4), one panel per
  metric (e.g. {"abs_rel": ..., "a1": ...}).

  The finite lambdas form a line at their values; lambda = inf (L_e alone) cannot sit on that
  axis, so it is drawn as a separate marker right of the largest finite lambda, past a dotted
  break line, at a tick labelled "∞". Values are plotted as given (a printed typo shows up).
  """
  lam = np.asarray(lams, np.float64)  # (K,)
  check(lam.ndim == 1 and lam.size > 0, "lambda_figure: lams must be a non-empty 1-D sequence")
  check(not np.isnan(lam).any() and (lam >= 0).all(), "lambda_figure: lams must be >= 0")
  check(len(values) > 0, "lambda_figure: no metric to plot")
  for key, v in values.items():
    check(len(v) == lam.size, f"lambda_figure: {key} has {len(v)} values for {lam.size} lambdas")
  order = np.argsort(lam, kind="stable")
  lam = lam[order]
  finite = np.isfinite(lam)
  x_inf = _inf_position(lam[finite])
  fig, axes = _new_figure(cfg, len(values), True)
  for ax, (key, v) in zip(axes, values.items()):
    y = _finite_or_nan(v)[order]  # (K,)
    if finite.any():
      ax.plot(lam[finite], y[finite], "o-", color="C0", markersize=4, label="finite λ")
    if (~finite).any():
      ax.plot(np.full(int((~finite).sum()), x_inf), y[~finite], "s", color="C3",
              markersize=6, label=f"λ = {INF_LABEL}")
      if finite.any():
        ax.axvline((lam[finite].max() + x_inf) / 2, color="0.5", linestyle=":", linewidth=1,
                   label="_axis break")
    ax.set_ylabel(HEADERS.get(key, key))
    ax.grid(True, alpha=0.3)
  ticks = [float(t) for t in lam[finite]] + ([x_inf] if (~finite).any() else [])
  labels = [f"{t:g}" for t in lam[finite]] + ([INF_LABEL] if (~finite).any() else [])
  axes[-1].set_xticks(ticks, labels)
  axes[-1].set_xlabel("λ (weight of L_e, eq. 10)")
  axes[0].set_title(title)
  handles, names = axes[0].get_legend_handles_labels()
  fig.legend(handles, names, loc="outside right upper")
  return fig


def bar_figure(categories: Sequence[str], series: Mapping[str, Sequence[float]], metric: str,
               title: str, cfg: PlotConfig = PlotConfig()) -> Figure:
  """Grouped bars: one group per category (e.g. a table's settings), one bar per series (e.g.
  "paper" and "ours"), each labelled with its value to 3 decimals as in the tables; a
  non-finite value is an empty slot. Long category names are wrapped at spaces."""
  check(len(categories) > 0 and len(series) > 0, "bar_figure: no categories or no series")
  for name, v in series.items():
    check(len(v) == len(categories),
          f"bar_figure: {name} has {len(v)} values for {len(categories)} categories")
  fig, (ax,) = _new_figure(cfg, 1, False)
  x = np.arange(len(categories))
  width = 0.8 / len(series)
  for k, (name, v) in enumerate(series.items()):
    y = _finite_or_nan(v)  # (C,)
    bars = ax.bar(x + (k - (len(series) - 1) / 2) * width, y, width, label=name)  # NaN: no bar
    ax.bar_label(bars, labels=["" if np.isnan(value) else f"{value:.3f}" for value in y],
                 fontsize=7, padding=2)
  # wrap long category names to the width of their slot (about 8 points per character at 10 pt)
  chars = max(6, int(cfg.fig_width * 0.8 / len(categories) * 72 / 8))
  ax.set_xticks(x, [textwrap.fill(str(c), chars) for c in categories])
  ax.set_ylabel(HEADERS.get(metric, metric))
  ax.set_title(title)
  ax.margins(y=0.08)  # room for the value labels above the tallest bar
  ax.grid(True, axis="y", alpha=0.3)
  fig.legend(loc="outside right upper")
  return fig


def save_figure(fig: Figure, path: str | Path, cfg: PlotConfig = PlotConfig()) -> list[Path]:
  """Writes `fig` to `path` (must end in .png) and, with `cfg.pdf`, to the same name in .pdf;
  each file atomically (temp file + os.replace). Returns the paths written.

  The PNG is exactly fig_width x fig_height inches at cfg.dpi (no tight bounding box), so its
  pixel size is known in advance. Embedded dates are left out, so equal figures give equal files.
  """
  path = Path(path)
  if path.suffix.lower() != ".png":
    raise ValueError(f"{path}: figures are written as .png (and .pdf beside with pdf=true)")
  path.parent.mkdir(parents=True, exist_ok=True)
  written = []
  for fmt, target, metadata in (("png", path, {}),
                                ("pdf", path.with_suffix(".pdf"), {"CreationDate": None})):
    if fmt == "pdf" and not cfg.pdf:
      continue
    buffer = io.BytesIO()
    fig.savefig(buffer, format=fmt, dpi=cfg.dpi, metadata=metadata)
    atomic_write_bytes(target, buffer.getvalue())
    written.append(target)
  return written


def _finite_or_nan(values: Sequence[float]) -> np.ndarray:
  """(N,) float64 with every non-finite entry NaN (drawn as a gap; +-inf would stretch axes)."""
  y = np.asarray(values, np.float64).reshape(-1)
  return np.where(np.isfinite(y), y, np.nan)


def _isolated(y: np.ndarray) -> np.ndarray:
  """(N,) bool: the finite entries of `y` (N,) whose neighbours are both NaN or absent (a line
  through them has no segment)."""
  finite = ~np.isnan(y)
  padded = np.concatenate([[False], finite, [False]])  # (N + 2,)
  return finite & ~padded[:-2] & ~padded[2:]


def _inf_position(finite_lams: np.ndarray) -> float:
  """Where lambda = inf is drawn: one and a half typical steps right of the largest finite
  lambda (1.0 when there is none)."""
  if finite_lams.size == 0:
    return 1.0
  top = float(finite_lams.max())
  steps = np.diff(np.unique(finite_lams))
  step = float(np.median(steps)) if steps.size else max(abs(top), 1.0) * 0.5
  return top + 1.5 * step
