"""The paper's Tables 1-5 as typed into experiments/paper/table{1..5}.json.

Reference: the paper's own LaTeX (experiments/paper/tables.tex, the five table environments
verbatim), parsed here with regular expressions, independently of the JSON: every label, every
number and every bold/underline mark must agree. A few values are also checked against numbers
read off the paper by hand.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest

from experiments.paper import TABLES, PaperTableError, check_table, load_paper_table, table_path
from pitta_jax.metrics import METRIC_NAMES

TEX = Path(__file__).resolve().parents[1] / "experiments" / "paper" / "tables.tex"
HEADER_KEYS = {"AbsRel": "abs_rel", "SqRel": "sq_rel", "RMSE": "rmse", "RMSElog": "rmse_log",
               r"$\delta<1.25$": "a1", r"$\delta<1.25^2$": "a2", r"$\delta<1.25^3$": "a3",
               r"$\delta < 1.25$": "a1"}


def _braced(text: str, open_at: int) -> str:
  """The text inside the brace group that starts at text[open_at] == '{' (nesting counted)."""
  depth = 0
  for i in range(open_at, len(text)):
    depth += {"{": 1, "}": -1}.get(text[i], 0)
    if depth == 0:
      return text[open_at + 1: i]
  raise ValueError("unbalanced braces")


def _plain(cell: str) -> str:
  """A LaTeX cell as the reader sees it: formatting macros and the arrows gone."""
  cell = re.sub(r"\\rowcolor\{[^}]*\}", "", cell)
  cell = re.sub(r"\\multirow\{\d+\}\{\*\}\{([^}]*)\}", r"\1", cell)
  while re.search(r"\\(textbf|underline)\{", cell):
    cell = re.sub(r"\\(textbf|underline)\{([^{}]*)\}", r"\2", cell)
  cell = cell.replace(r"\%", "%").replace(r"$\infty$", "∞").replace(r"$\lambda$", "λ")
  return cell.replace("↓", "").replace("↑", "").strip()


def _number(cell: str) -> tuple[float, bool, bool]:
  """(value, bold, underlined) of a numeric cell."""
  value = float(re.fullmatch(r"\s*(?:\\(?:textbf|underline)\{)?\s*(\d+\.\d+)\s*\}?\s*", cell)[1])
  return value, r"\textbf" in cell, r"\underline" in cell


def _words(text: str) -> list[str]:
  """ASCII words of a caption, LaTeX command names and \\ref targets dropped."""
  text = re.sub(r"\\ref\{[^}]*\}", "", text)
  text = re.sub(r"\\[a-zA-Z]+", "", text)
  return re.findall(r"[A-Za-z]+", text)


def _parse_tex() -> list[dict]:
  """Each table environment of tables.tex -> caption, label, header cells, parsed rows."""
  tex = TEX.read_text(encoding="utf-8")
  tables = []
  for env in re.findall(r"\\begin\{table\*?\}.*?\\end\{table\*?\}", tex, re.S):
    caption = _braced(env, env.index("{", env.index(r"\caption")))
    label = re.search(r"\\label\{([^}]*)\}", env)[1]
    tabular = re.search(r"\\begin\{tabular\}\{[a-z]+\}(.*?)\\end\{tabular\}", env, re.S)[1]
    head, body = re.search(r"\\toprule(.*?)\\midrule(.*?)\\bottomrule", tabular, re.S).groups()
    header = [c.strip() for c in head.split(r"\\")[0].split("&")]
    lines = [c.replace(r"\midrule", "").strip() for c in body.split(r"\\")]
    lines = [line.split("&") for line in lines if line]
    tables.append(dict(caption=caption, label=label, header=header, lines=lines))
  return tables


def _expected_rows(n: int, parsed: dict) -> list[dict]:
  """The rows of table n from the LaTeX, in the JSON's layout (one row per setting)."""
  header, lines = parsed["header"], parsed["lines"]
  rows = []
  if n in (4, 5):  # transposed: settings across, metrics down
    metric_rows = {HEADER_KEYS[_plain(line[0])]: line[1:] for line in lines}
    for j, label in enumerate(header[1:]):
      cells = {k: _number(v[j]) for k, v in metric_rows.items()}
      rows.append(dict(group=None, label=_plain(label),
                       values={k: c[0] for k, c in cells.items()},
                       bold={k for k, c in cells.items() if c[1]},
                       underline={k for k, c in cells.items() if c[2]}))
    return rows
  first = 2 if n in (1, 3) else 1  # Tables 1 and 3 have a group column
  keys = [HEADER_KEYS[_plain(h)] for h in header[first:]]
  group = None
  for line in lines:
    if first == 2 and _plain(line[0]):
      group = _plain(line[0])
    cells = {k: _number(c) for k, c in zip(keys, line[first:])}
    rows.append(dict(group=group, label=_plain(line[first - 1]),
                     values={k: c[0] for k, c in cells.items()},
                     bold={k for k, c in cells.items() if c[1]},
                     underline={k for k, c in cells.items() if c[2]}))
  return rows


@pytest.fixture(scope="module")
def parsed():
  tables = _parse_tex()
  assert len(tables) == 5
  return tables


@pytest.mark.parametrize("n", TABLES)
def test_table_matches_the_latex(n, parsed):
  table = load_paper_table(n)
  tex = parsed[n - 1]
  assert table["latex_label"] == tex["label"]
  assert _words(table["caption"]) == _words(tex["caption"])
  expected = _expected_rows(n, tex)
  assert len(table["rows"]) == len(expected)
  for row, want in zip(table["rows"], expected):
    assert row["label"] == want["label"]
    assert row.get("group") == want["group"]
    assert row["values"] == want["values"], row["label"]  # exact: both parse the printed decimal
    assert set(row["bold"]) == want["bold"] and set(row["underline"]) == want["underline"]
  keys = [c["key"] for c in table["columns"]]
  assert keys == list(expected[0]["values"])
  header = [_plain(h) for h in tex["header"]]
  if table["transposed"]:
    assert table["label_title"] == header[0]
  elif table["group_title"] is None:
    assert table["label_title"] == header[0]
  else:
    assert [table["group_title"], table["label_title"]] == header[:2]


@pytest.mark.parametrize("n", TABLES)
def test_every_row_has_every_column_and_finite_numbers(n):
  table = load_paper_table(n)
  keys = [c["key"] for c in table["columns"]]
  assert set(keys) <= set(METRIC_NAMES)
  for c in table["columns"]:
    assert c["lower_is_better"] == (c["key"] in ("abs_rel", "sq_rel", "rmse", "rmse_log"))
  for row in table["rows"]:
    assert list(row["values"]) == keys
    assert all(isinstance(v, float) and math.isfinite(v) for v in row["values"].values())
    assert all(f in row for f in table["row_fields"])
  assert table["notes"]


def test_values_read_off_the_paper_by_hand():
  t1, t2, t3, t4, t5 = (load_paper_table(n) for n in TABLES)
  assert [len(t["rows"]) for t in (t1, t2, t3, t4, t5)] == [21, 7, 15, 12, 5]
  foggy_pitta = next(r for r in t1["rows"] if r["group"] == "Foggy" and r["method"] == "pitta")
  assert foggy_pitta["values"]["abs_rel"] == 0.127 and foggy_pitta["values"]["rmse"] == 8.6
  assert t2["rows"][-1]["label"] == "PITTA (ours)" and t2["rows"][-1]["values"]["rmse"] == 8.206
  lite_sunny = next(r for r in t3["rows"] if r["group"] == "Lite-Mono" and r["label"] == "Sunny")
  assert lite_sunny["values"]["sq_rel"] == 1.844 and lite_sunny["network"] == "litemono"
  # Table 4: the printed typo stays, the notes say what was probably meant
  lams = [r["lambda"] for r in t4["rows"]]
  assert lams[:11] == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]
  assert lams[11] == math.inf and t4["rows"][11]["label"] == "∞"
  assert t4["rows"][2]["values"] == {"abs_rel": 1.999, "a1": 0.670}
  assert any("1.999" in note and "0.199" in note for note in t4["notes"])
  last = t5["rows"][-1]
  assert (last["label"], last["cnn_percent"], last["bn_percent"]) == ("CNN 60% + BN 40%", 60, 40)
  assert last["values"]["a1"] == 0.284
  assert any("DetphAnythingV2" in note for note in t1["notes"])


def test_rows_name_registered_networks():
  from pitta_jax.models.registry import MODELS
  for n in TABLES:
    assert {r["network"] for r in load_paper_table(n)["rows"]} <= set(MODELS)


def test_schema_violations_are_one_line_naming_the_file():
  raw = json.loads(table_path(4).read_text(encoding="utf-8"))
  assert raw["rows"][11]["lambda"] == "inf"
  loaded = check_table(raw, 4, "t4.json")
  assert loaded["rows"][11]["lambda"] == math.inf and raw["rows"][11]["lambda"] == "inf"
  assert check_table(loaded, 4, "again")["rows"][11]["lambda"] == math.inf

  def broken(change) -> str:
    data = json.loads(json.dumps(raw))
    change(data)
    with pytest.raises(PaperTableError) as e:
      check_table(data, 4, "t4.json")
    message = str(e.value)
    assert message.startswith("t4.json: ") and "\n" not in message
    return message

  assert "values must have exactly" in broken(lambda d: d["rows"][3]["values"].pop("a1"))
  assert "not a finite number" in broken(lambda d: d["rows"][0]["values"].update(a1=float("nan")))
  assert "not a finite number" in broken(lambda d: d["rows"][0]["values"].update(a1="0.6"))
  assert "lower_is_better must be False" in broken(
      lambda d: d["columns"][1].update(lower_is_better=True))
  assert "lambda must be" in broken(lambda d: d["rows"][0].update({"lambda": "infinity"}))
  assert "keys missing ['notes']" in broken(lambda d: d.pop("notes"))
  assert "expected 4" in broken(lambda d: d.update(table=5))
  with pytest.raises(PaperTableError, match="Tables 1..5"):
    load_paper_table(6)
