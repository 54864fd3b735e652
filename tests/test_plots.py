"""matplotlib figures (pitta_jax.plots): the drawn data is the data given, files are valid PNGs
of the configured size, lambda = inf and NaN frames are handled.

References: the input arrays themselves (read back from the returned Figure's Line2D and
Rectangle artists), PNG sizes computed by hand from inches x dpi and read from the file's IHDR
chunk with struct (independently of matplotlib), and the paper's Table 4 from its JSON.
"""

from __future__ import annotations

import math
import struct

import cv2
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from experiments.paper import load_paper_table
from pitta_jax.plots import PlotConfig, bar_figure, lambda_figure, per_frame_figure, save_figure

SMALL = PlotConfig(fig_width=6.4, fig_height=3.2, dpi=40)  # 256 x 128 pixels
NAN, INF = float("nan"), float("inf")


def _png_size(path) -> tuple[int, int]:
  """(width, height) from the PNG signature and IHDR chunk."""
  data = path.read_bytes()
  assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
  return struct.unpack(">II", data[16:24])


def _equal_nan(got, want) -> None:
  np.testing.assert_array_equal(np.asarray(got, float), np.asarray(want, float))  # NaN == NaN


def test_eleven_methods_get_eleven_colours():
  """Table 1's per-frame figure has 11 rows: beyond matplotlib's 10-colour cycle the 11th
  method must not take the first one's colour."""
  from matplotlib.colors import to_rgba
  fig = per_frame_figure({f"method {k}": [0.1 * k, 0.2] for k in range(11)}, "abs_rel", "t",
                         SMALL)
  colours = [to_rgba(line.get_color()) for line in fig.axes[0].get_lines()]
  assert len(set(colours)) == 11


def test_per_frame_curves_hold_the_data_and_write_a_png(tmp_path):
  series = {"No adaptation": [0.2, 0.25, NAN, 0.3], "PITTA": [0.1, INF, 0.15],
            "skipped everywhere": [NAN, NAN], "empty": []}
  fig = per_frame_figure(series, "abs_rel", "Per-frame AbsRel, fog", SMALL)
  assert isinstance(fig.canvas, FigureCanvasAgg)
  (ax,) = fig.axes
  lines = ax.get_lines()
  assert [line.get_label() for line in lines] == list(series)
  want_y = [[0.2, 0.25, NAN, 0.3], [0.1, NAN, 0.15], [NAN, NAN], []]  # inf drawn as a gap
  for line, y in zip(lines, want_y):
    _equal_nan(line.get_xdata(), np.arange(len(y)))
    _equal_nan(line.get_ydata(), y)
  assert ax.get_xlabel() == "frame" and ax.get_ylabel() == "AbsRel ↓"
  assert ax.get_title() == "Per-frame AbsRel, fog"
  (legend,) = fig.legends
  assert [t.get_text() for t in legend.get_texts()] == list(series)
  fig.canvas.draw()
  assert legend.get_window_extent().x0 >= ax.get_window_extent().x1  # outside the data
  assert len(ax.get_xticks()) > 1 and len(ax.get_yticks()) > 1

  path = tmp_path / "figs" / "fog_abs_rel.png"
  assert save_figure(fig, path, SMALL) == [path]
  assert _png_size(path) == (256, 128)  # 6.4 in x 40 dpi, 3.2 in x 40 dpi
  assert cv2.imread(str(path)).shape == (128, 256, 3)  # decodes in full
  first = path.read_bytes()
  save_figure(fig, path, SMALL)
  assert path.read_bytes() == first and sorted(p.name for p in path.parent.iterdir()) == [
      "fog_abs_rel.png"]  # same bytes again, no temporary file left


def test_pdf_beside_png_and_bad_names(tmp_path):
  cfg = PlotConfig(fig_width=4.0, fig_height=2.0, dpi=30, pdf=True)
  fig = per_frame_figure({"a": [1.0, 2.0]}, "loss", "t", cfg)
  assert fig.axes[0].get_ylabel() == "loss"  # not a metric key: used as the label itself
  written = save_figure(fig, tmp_path / "c.png", cfg)
  assert written == [tmp_path / "c.png", tmp_path / "c.pdf"]
  assert _png_size(written[0]) == (120, 60) and written[1].read_bytes()[:5] == b"%PDF-"
  with pytest.raises(ValueError, match="c.jpg: figures are written as .png"):
    save_figure(fig, tmp_path / "c.jpg", cfg)
  with pytest.raises(ValueError, match="dpi must be"):
    PlotConfig(dpi=0)
  with pytest.raises(ValueError, match="fig_width must be"):
    PlotConfig(fig_width=math.nan)
  with pytest.raises(ValueError, match="has 2.59e[+]11 pixels; at most 1e[+]08"):
    PlotConfig(dpi=100000)  # 720,000 x 360,000 pixels
  with pytest.raises(ValueError, match="no series"):
    per_frame_figure({}, "abs_rel", "t", cfg)


def test_lambda_curve_puts_inf_as_a_separate_marker():
  lams = [0.3, 0.0, INF, 0.1, 0.2]  # unsorted on purpose
  abs_rel = [0.20, 0.24, 0.22, NAN, 0.19]
  a1 = [0.66, 0.61, 0.62, 0.64, 0.67]
  fig = lambda_figure(lams, {"abs_rel": abs_rel, "a1": a1}, "lambda ablation", SMALL)
  top, bottom = fig.axes
  for ax, values in ((top, abs_rel), (bottom, a1)):
    line, marker, gap = ax.get_lines()
    np.testing.assert_allclose(gap.get_xdata(), [0.375, 0.375], rtol=1e-12)  # dotted break
    _equal_nan(line.get_xdata(), [0.0, 0.1, 0.2, 0.3])
    _equal_nan(line.get_ydata(), [values[1], values[3], values[4], values[0]])
    x_inf = 0.3 + 1.5 * 0.1  # one and a half steps right of the largest finite lambda
    np.testing.assert_allclose(marker.get_xdata(), [x_inf], rtol=1e-12)
    _equal_nan(marker.get_ydata(), [values[2]])
    assert marker.get_label() == "λ = ∞"
  assert top.get_ylabel() == "AbsRel ↓" and bottom.get_ylabel() == "δ<1.25 ↑"
  labels = [t.get_text() for t in bottom.get_xticklabels()]
  assert labels == ["0", "0.1", "0.2", "0.3", "∞"]
  np.testing.assert_allclose(bottom.get_xticks(), [0.0, 0.1, 0.2, 0.3, 0.45], rtol=1e-12)
  assert [t.get_text() for t in fig.legends[0].get_texts()] == ["finite λ", "λ = ∞"]


def test_lambda_curve_of_the_paper_table_4(tmp_path):
  table = load_paper_table(4)
  lams = [r["lambda"] for r in table["rows"]]
  values = {k: [r["values"][k] for r in table["rows"]] for k in ("abs_rel", "a1")}
  fig = lambda_figure(lams, values, "Table 4", SMALL)
  line, marker, _ = fig.axes[0].get_lines()
  assert list(line.get_ydata()) == values["abs_rel"][:11]  # 1.999 at 0.2 plotted as printed
  assert list(marker.get_ydata()) == [0.218]
  np.testing.assert_allclose(marker.get_xdata(), [1.15], rtol=1e-12)
  save_figure(fig, tmp_path / "t4.png", SMALL)
  assert _png_size(tmp_path / "t4.png") == (256, 128)


def test_lambda_curve_edge_cases():
  only_inf = lambda_figure([INF], {"abs_rel": [0.2]}, "t", SMALL)
  (marker,) = only_inf.axes[0].get_lines()
  assert list(marker.get_xdata()) == [1.0] and list(marker.get_ydata()) == [0.2]
  no_inf = lambda_figure([0.0, 0.5], {"a1": [0.6, NAN]}, "t", SMALL)
  (line,) = no_inf.axes[0].get_lines()
  _equal_nan(line.get_ydata(), [0.6, NAN])
  assert "∞" not in [t.get_text() for t in no_inf.axes[0].get_xticklabels()]
  # one finite lambda has no step between lambdas: the step is half its size (at least 0.5),
  # so lambda = 4 puts inf at 4 + 1.5 * 2 = 7 (not 5.5, crowding the point at large lambdas)
  # and the break line half-way, at 5.5
  one = lambda_figure([4.0, INF], {"abs_rel": [0.2, 0.3]}, "t", SMALL)
  point, marker, gap = one.axes[0].get_lines()
  assert list(point.get_xdata()) == [4.0] and list(marker.get_xdata()) == [7.0]
  assert list(gap.get_xdata()) == [5.5, 5.5]
  assert [t.get_text() for t in one.axes[0].get_xticklabels()] == ["4", "∞"]
  with pytest.raises(ValueError, match="abs_rel has 1 values for 2 lambdas"):
    lambda_figure([0.0, 0.1], {"abs_rel": [0.2]}, "t", SMALL)
  with pytest.raises(ValueError, match="lams must be >= 0"):
    lambda_figure([-1.0], {"abs_rel": [0.2]}, "t", SMALL)


def test_grouped_bars_hold_the_data(tmp_path):
  categories = ["CNN 0% + BN 50%", "CNN 0% + BN 100%", "CNN 20% + BN 80%"]
  series = {"paper": [0.214, 0.199, 0.828], "ours": [0.25, NAN, 0.5]}
  fig = bar_figure(categories, series, "abs_rel", "Table 5", SMALL)
  (ax,) = fig.axes
  for container, (name, values) in zip(ax.containers, series.items()):
    assert container.get_label() == name
    _equal_nan([bar.get_height() for bar in container], values)
    centres = [bar.get_x() + bar.get_width() / 2 for bar in container]
    offset = -0.2 if name == "paper" else 0.2  # two bars of width 0.4 around each category
    np.testing.assert_allclose(centres, np.arange(3) + offset, atol=1e-12)
  texts = [t.get_text() for t in ax.texts]
  assert texts == ["0.214", "0.199", "0.828", "0.250", "", "0.500"]
  assert [t.get_text().replace("\n", " ") for t in ax.get_xticklabels()] == categories
  save_figure(fig, tmp_path / "bars.png", SMALL)
  assert _png_size(tmp_path / "bars.png") == (256, 128)
  with pytest.raises(ValueError, match="ours has 1 values for 3 categories"):
    bar_figure(categories, {"ours": [0.1]}, "abs_rel", "t", SMALL)


def test_saving_again_replaces_the_file_and_dates_nothing(tmp_path, monkeypatch):
  """`save_figure` replaces an existing file with a new one (temp file + os.replace), never
  rewrites it in place: a reader that opened the old figure keeps reading it whole. The PDF
  carries no creation date: matplotlib stamps one from $SOURCE_DATE_EPOCH (else the clock)
  unless the metadata removes it, so equal figures saved at different times are equal files."""
  cfg = PlotConfig(fig_width=4.0, fig_height=2.0, dpi=30, pdf=True)
  path = tmp_path / "f.png"
  save_figure(per_frame_figure({"a": [1.0, 2.0]}, "loss", "old", cfg), path, cfg)
  old = path.read_bytes()
  with open(path, "rb") as reader:
    save_figure(per_frame_figure({"a": [3.0, 1.0, 2.0]}, "loss", "new", cfg), path, cfg)
    assert reader.read() == old  # the old file, untouched
  assert path.read_bytes() != old and _png_size(path) == (120, 60)
  fig = per_frame_figure({"a": [1.0, 2.0]}, "loss", "t", cfg)
  pdfs = []
  for epoch in ("0", "1000000000"):  # 1970 and 2001
    monkeypatch.setenv("SOURCE_DATE_EPOCH", epoch)
    save_figure(fig, tmp_path / f"d{epoch}.png", cfg)
    pdfs.append((tmp_path / f"d{epoch}.pdf").read_bytes())
  assert pdfs[0] == pdfs[1] and b"CreationDate" not in pdfs[0]


def test_a_frame_without_finite_neighbours_is_drawn_as_a_marker():
  """A line through one point draws nothing: a one-frame run, or a frame scored between two
  gaps, was absent from its figure. Such points (and only they) get a marker."""
  series = {"one frame": [0.2], "between gaps": [0.1, NAN, 0.3, 0.4, INF, 0.5],
            "whole": [0.1, 0.2], "empty": []}
  fig = per_frame_figure(series, "abs_rel", "t", SMALL)
  lines = fig.axes[0].get_lines()
  want = [[True], [True, False, False, False, False, True], None, None]  # None: no marker
  for line, mask in zip(lines, want):
    if mask is None:
      assert line.get_marker() in ("None", None, "")
    else:
      assert line.get_marker() == "o"
      np.testing.assert_array_equal(line.get_markevery(), mask)
  fig.canvas.draw()  # renders with the masks
