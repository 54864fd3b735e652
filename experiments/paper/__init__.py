"""The paper's numbers: Tables 1-5 of PITTA, typed in from its LaTeX source (`tables.tex` here,
verbatim) as `table{1..5}.json`, with `load_paper_table(n)` to read one, validated.

Every number is kept exactly as printed, typos included; what looks wrong is said in the
table's `notes`, never corrected (Table 4's AbsRel "1.999" at lambda = 0.2 stays 1.999).

Schema of `table<n>.json` (one JSON object):

- `table`: int, n.
- `latex_label`: str, the table's `\\label` in the paper (`table:main_res`, ...).
- `caption`: str, the caption as plain text (LaTeX markup removed, `\\ref` resolved).
- `dataset`: str, the target data set (`DrivingStereo`, `Waymo`); `source_dataset`: str, what
  the networks were pretrained on (`KITTI`).
- `transposed`: bool, true where the paper prints the metrics down the rows and the settings
  across (Tables 4, 5); the JSON always stores one row per setting.
- `decimals`: int, the digits printed after the point (3), to reprint the numbers as printed.
- `group_title`: str | null, the header of the grouping column (`Weather` in Table 1,
  `MDE Net` in Table 3; null where there is none); `label_title`: str, the header of the
  row-label column (`Method`, `Weather`, `λ`, `fraction`).
- `row_fields`: list of str, the descriptors that every row of this table carries besides
  `label`, `values`, `bold`, `underline`:
    - `group`: str, the group's label as printed (`Foggy`, `SGDepth`, ...);
    - `test_case`: str | null, our id of the test case (`foggy`, `rainy`, `sunny`, `all`; null
      where the paper does not say);
    - `method`: str, the adaptation method as our `--method` names it (`none`, `comoda`,
      `cotta`, `actmad`, `adadepth`, `pitta`);
    - `network`: str, the depth network as our model registry names it (`monodepth2`,
      `sgdepth`, `hrdepth`, `monovit`, `litemono`, `depth_anything_v2`);
    - `lambda`: number, or the string "inf" for the paper's infinity (Table 4);
    - `cnn_percent`, `bn_percent`: int, the setting "CNN a% + BN b%" (Table 5).
- `columns`: list of {`key`, `header`, `lower_is_better`}: `key` one of the 7 Eigen metric keys
  (`abs_rel`, `sq_rel`, `rmse`, `rmse_log`, `a1`, `a2`, `a3`; a1..a3 are delta < 1.25,
  1.25^2, 1.25^3), `header` as printed (plain text), `lower_is_better` false only for a1..a3.
- `rows`: list of objects: `label` (str, the row label as printed, typos kept), the
  `row_fields`, `values` ({column key: number}, every column), `bold` and `underline` (lists of
  column keys printed in bold / underlined).
- `notes`: list of str: typos and oddities, what is printed and what was probably meant.

`load_paper_table(n)` returns the object with `lambda` "inf" turned into `float("inf")`.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

from pitta_jax.metrics import METRIC_NAMES
from pitta_jax.report import HIGHER_IS_BETTER

TABLES = (1, 2, 3, 4, 5)
TOP_KEYS = ("table", "latex_label", "caption", "dataset", "source_dataset", "transposed",
            "decimals", "group_title", "label_title", "row_fields", "columns", "rows", "notes")
ROW_FIELDS = ("group", "test_case", "method", "network", "lambda", "cnn_percent", "bn_percent")
ROW_KEYS = ("label", "values", "bold", "underline")


class PaperTableError(ValueError):
  """A table file that does not follow the schema (one line, names the file)."""


def table_path(n: int) -> Path:
  """Where table `n`'s JSON lives (next to this module)."""
  if n not in TABLES:
    raise PaperTableError(f"paper table {n!r}: the paper has Tables {TABLES[0]}..{TABLES[-1]}")
  return Path(__file__).with_name(f"table{n}.json")


def load_paper_table(n: int) -> dict[str, Any]:
  """Table `n` of the paper as a dict (schema in the module docstring), validated."""
  path = table_path(n)
  try:
    data = json.loads(path.read_text(encoding="utf-8"))
  except (OSError, json.JSONDecodeError) as e:
    raise PaperTableError(f"{path}: cannot read ({e})") from None
  return check_table(data, n, str(path))


def check_table(data: Any, n: int, where: str) -> dict[str, Any]:
  """Validates one table object against the schema; returns it with "inf" lambdas as floats.

  Raises PaperTableError (one line starting with `where`) on the first violation.
  """
  def fail(message: str) -> None:
    raise PaperTableError(f"{where}: {message}")

  data = copy.deepcopy(data)  # the caller's object stays as it was
  if not isinstance(data, dict):
    fail("expected a JSON object")
  missing = [k for k in TOP_KEYS if k not in data]
  extra = [k for k in data if k not in TOP_KEYS]
  if missing or extra:
    fail(f"keys missing {missing}, unknown {extra}")
  if data["table"] != n:
    fail(f"'table' is {data['table']!r}, expected {n}")
  for key in ("latex_label", "caption", "dataset", "source_dataset", "label_title"):
    if not isinstance(data[key], str) or not data[key]:
      fail(f"'{key}' must be a non-empty string")
  if data["group_title"] is not None and not isinstance(data["group_title"], str):
    fail("'group_title' must be a string or null")
  if not isinstance(data["transposed"], bool):
    fail("'transposed' must be true or false")
  if not _is_int(data["decimals"]) or data["decimals"] < 0:
    fail("'decimals' must be a non-negative integer")
  if not isinstance(data["notes"], list) or not all(isinstance(s, str) and s
                                                    for s in data["notes"]):
    fail("'notes' must be a list of non-empty strings")

  columns = data["columns"]
  if not isinstance(columns, list) or not columns:
    fail("'columns' must be a non-empty list")
  keys = []
  for c in columns:
    if not isinstance(c, dict) or set(c) != {"key", "header", "lower_is_better"}:
      fail(f"column {c!r} must have exactly key, header, lower_is_better")
    if c["key"] not in METRIC_NAMES:
      fail(f"column key {c['key']!r} is not one of {', '.join(METRIC_NAMES)}")
    if c["lower_is_better"] is not (c["key"] not in HIGHER_IS_BETTER):
      fail(f"column {c['key']}: lower_is_better must be {c['key'] not in HIGHER_IS_BETTER}")
    keys.append(c["key"])
  if len(set(keys)) != len(keys):
    fail(f"duplicate column keys {keys}")

  fields = data["row_fields"]
  if not isinstance(fields, list) or any(f not in ROW_FIELDS for f in fields):
    fail(f"'row_fields' must list some of {', '.join(ROW_FIELDS)}")
  rows = data["rows"]
  if not isinstance(rows, list) or not rows:
    fail("'rows' must be a non-empty list")
  for i, row in enumerate(rows):
    if not isinstance(row, dict) or set(row) != set(ROW_KEYS) | set(fields):
      have = sorted(row) if isinstance(row, dict) else row
      fail(f"row {i} has {have}, expected {sorted(set(ROW_KEYS) | set(fields))}")
    name = f"row {i} ({row['label']!r})"
    if not isinstance(row["label"], str) or not row["label"]:
      fail(f"row {i}: 'label' must be a non-empty string")
    values = row["values"]
    if not isinstance(values, dict) or set(values) != set(keys):
      fail(f"{name}: values must have exactly the columns {keys}")
    for k, v in values.items():
      if not _is_number(v) or not math.isfinite(v):
        fail(f"{name}: {k} = {v!r} is not a finite number")
    for mark in ("bold", "underline"):
      if not isinstance(row[mark], list) or any(k not in keys for k in row[mark]):
        fail(f"{name}: '{mark}' must list column keys")
    if "lambda" in fields:
      lam = math.inf if row["lambda"] == "inf" else row["lambda"]
      if not _is_number(lam) or math.isnan(lam) or lam < 0:
        fail(f"{name}: lambda must be a number >= 0 or \"inf\", got {lam!r}")
      row["lambda"] = lam
    for key in ("cnn_percent", "bn_percent"):
      if key in fields and not (_is_int(row[key]) and 0 <= row[key] <= 100):
        fail(f"{name}: {key} must be an integer in [0, 100], got {row[key]!r}")
    for key in ("group", "method", "network"):
      if key in fields and (not isinstance(row[key], str) or not row[key]):
        fail(f"{name}: '{key}' must be a non-empty string")
    if "test_case" in fields and row["test_case"] is not None and not isinstance(
        row["test_case"], str):
      fail(f"{name}: 'test_case' must be a string or null")
  return data


def _is_number(x: Any) -> bool:
  return isinstance(x, (int, float)) and not isinstance(x, bool)


def _is_int(x: Any) -> bool:
  return isinstance(x, int) and not isinstance(x, bool)


__all__ = ["TABLES", "PaperTableError", "check_table", "load_paper_table", "table_path"]
