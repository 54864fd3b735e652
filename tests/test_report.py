"""Results files and command-line config parsing (hand-written expected values)."""

from __future__ import annotations

import argparse
import csv
import json
import math

import pytest

from pitta_jax.adapt import AdaptConfig
from pitta_jax.config_cli import add_dataclass_arguments, dataclass_from_args
from pitta_jax.data.errors import DataError
from pitta_jax.report import Row, markdown_table, write_results
from pitta_jax.sources import parse_options

M1 = dict(abs_rel=0.2, sq_rel=2.0, rmse=9.0, rmse_log=0.3, a1=0.7, a2=0.9, a3=0.95)
M2 = dict(abs_rel=0.1, sq_rel=3.0, rmse=8.0, rmse_log=0.2, a1=0.8, a2=0.85, a3=0.97)


def test_markdown_table_bolds_the_best_per_group():
  table = markdown_table([Row("fog", "No adaptation", M1), Row("fog", "PITTA", M2)])
  lines = table.strip().splitlines()
  assert lines[0].startswith("| Shift | Method | AbsRel")
  assert lines[2] == ("| fog | No adaptation | 0.200 | **2.000** | 9.000 | 0.300 | 0.700 | "
                      "**0.900** | 0.950 |")
  assert lines[3] == ("| fog | PITTA | **0.100** | 3.000 | **8.000** | **0.200** | **0.800** | "
                      "0.850 | **0.970** |")


def test_write_results_files(tmp_path):
  rows = [Row("fog", "PITTA", M2, {"fps": 3.5})]
  write_results(tmp_path, rows, {"adapt": AdaptConfig()})
  data = json.loads((tmp_path / "results.json").read_text())
  assert data["adapt"]["lam"] == 0.2 and data["rows"][0]["metrics"]["abs_rel"] == 0.1
  with open(tmp_path / "results.csv") as f:
    lines = list(csv.reader(f))
  assert lines[0] == ["shift", "method", "abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2",
                      "a3", "fps"]
  assert lines[1][:3] == ["fog", "PITTA", "0.100000"] and lines[1][-1] == "3.5"
  assert (tmp_path / "table.md").read_text().count("\n") == 3


def test_every_adapt_config_field_is_a_flag():
  parser = argparse.ArgumentParser()
  add_dataclass_arguments(parser, AdaptConfig, "adapt")
  args = parser.parse_args(["--lr", "3e-4", "--lam", "inf", "--window", "7", "--skip-nonfinite",
                            "false", "--dynamic-classes", "person,car,8", "--selector",
                            "fraction(cnn=20,bn=80)"])
  cfg = dataclass_from_args(AdaptConfig, args)
  assert cfg.lr == 3e-4 and math.isinf(cfg.lam) and cfg.window == 7
  assert cfg.skip_nonfinite is False and cfg.dynamic_classes == (1, 3, 8)
  assert cfg.selector == "fraction(cnn=20,bn=80)" and cfg.optimizer == "adam"
  with pytest.raises(SystemExit):
    parser.parse_args(["--window", "five"])
  with pytest.raises(ValueError, match="window must be odd"):
    dataclass_from_args(AdaptConfig, parser.parse_args(["--window", "4"]))


def test_reader_options_parse():
  assert parse_options(["weather=foggy", "num_frames=12", "severity=0.5", "depth=false"]) == {
      "weather": "foggy", "num_frames": 12, "severity": 0.5, "depth": False}
  with pytest.raises(DataError, match="KEY=VALUE"):
    parse_options(["foggy"])


def test_string_tuples_parse_as_strings():
  from pitta_jax.demo import DemoConfig
  parser = argparse.ArgumentParser()
  add_dataclass_arguments(parser, DemoConfig, "demo")
  cfg = dataclass_from_args(DemoConfig, parser.parse_args(["--shifts", "fog, night"]))
  assert cfg.shifts == ("fog", "night") and cfg.num_frames == 40
