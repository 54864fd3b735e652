"""Results files and command-line config parsing (hand-written expected values)."""

from __future__ import annotations

import argparse
import csv
import json
import math

import pytest

from pitta_jax.adapt import AdaptConfig
from pitta_jax.config_cli import add_config_arguments, config_from_args
from pitta_jax.methods.pitta import PittaConfig
from pitta_jax.data.errors import DataError
from pitta_jax.report import Row, markdown_table, write_results
from pitta_jax.text import first_and_count
from pitta_jax.sources import (dataclass_annotations, function_annotations, parse_segmentation,
                               split_options, typed_options)

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


def test_long_lists_are_named_in_part_and_counted():
  assert first_and_count(["a", "b", "c", "d"], 2) == "a, b, ... and 2 more"
  assert first_and_count([3, 1], 2, sep="; ") == "3; 1"
  assert first_and_count((), 5) == ""


def test_a_rate_over_no_frames_is_written_as_no_value(tmp_path):
  """A --resume of a finished run runs no frame: its rate is None, not a NaN that results.json
  counted among non_finite_values as if a metric had diverged."""
  from pitta_jax.outputs import rounded_or_none
  assert rounded_or_none(1.23456, 2) == 1.23 and rounded_or_none(float("nan"), 2) is None
  assert rounded_or_none(float("inf"), 2) is None  # not finite either: no value, not a count
  row = Row("synthetic", "pitta", {"abs_rel": 0.1}, {"steady_fps": rounded_or_none(float("nan"),
                                                                                  2)})
  write_results(tmp_path, [row], {})
  assert json.loads((tmp_path / "results.json").read_text())["non_finite_values"] == 0


def test_write_results_files(tmp_path):
  rows = [Row("fog", "PITTA", M2, {"fps": 3.5})]
  write_results(tmp_path, rows, {"adapt": AdaptConfig(), "pitta": PittaConfig()})
  data = json.loads((tmp_path / "results.json").read_text())
  assert data["pitta"]["lam"] == 0.2 and data["pitta"]["ld"]["window"] == 5 and data["rows"][0]["metrics"]["abs_rel"] == 0.1
  with open(tmp_path / "results.csv") as f:
    lines = list(csv.reader(f))
  assert lines[0] == ["shift", "method", "status", "abs_rel", "sq_rel", "rmse", "rmse_log", "a1",
                      "a2", "a3", "fps"]
  assert lines[1][:4] == ["fog", "PITTA", "ok", "0.100000"] and lines[1][-1] == "3.5"
  assert (tmp_path / "table.md").read_text().count("\n") == 3


def _parser():
  parser = argparse.ArgumentParser()
  add_config_arguments(parser, AdaptConfig, "adapt", "adapt")
  add_config_arguments(parser, PittaConfig, "pitta", "pitta")
  return parser


def test_every_config_field_is_a_flag_with_namespace_and_alias():
  parser = _parser()
  args = parser.parse_args(["--lr", "3e-4", "--lam", "inf", "--window", "7", "--skip-nonfinite",
                            "false", "--dynamic-classes", "person,car,8", "--selector",
                            "fraction(cnn=20,bn=80)", "--pitta.ld.mask-mode", "segment_id"])
  cfg = config_from_args(AdaptConfig, args, "adapt")
  pitta = config_from_args(PittaConfig, args, "pitta")
  assert cfg.lr == 3e-4 and math.isinf(pitta.lam) and pitta.ld.window == 7
  assert cfg.skip_nonfinite is False and pitta.ld.dynamic_classes == (1, 3, 8)
  assert pitta.ld.mask_mode == "segment_id"
  assert cfg.selector == "fraction(cnn=20,bn=80)" and cfg.optimizer == "adam"
  same = config_from_args(AdaptConfig, parser.parse_args(["--adapt.lr", "3e-4"]), "adapt")
  assert same.lr == 3e-4
  with pytest.raises(SystemExit):
    parser.parse_args(["--window", "five"])
  with pytest.raises(SystemExit):
    parser.parse_args(["--dynamic-classes", "person,unicorn"])  # one line from argparse
  with pytest.raises(ValueError, match="window must be odd"):
    config_from_args(PittaConfig, parser.parse_args(["--window", "4"]), "pitta")
  for bad, match in ((["--lr", "inf"], "lr must be a finite"), (["--lr", "1e30x"], None),
                     (["--momentum", "-5"], "momentum must be a finite")):
    if match is None:
      with pytest.raises(SystemExit):
        parser.parse_args(bad)
    else:
      with pytest.raises(ValueError, match=match):
        config_from_args(AdaptConfig, parser.parse_args(bad), "adapt")


def test_help_comes_from_field_metadata():
  text = _parser().format_help()
  assert "learning rate alpha of eq. 11" in text and "--pitta.lam" in text
  assert "SPEC" not in text


def test_reader_options_are_typed_from_annotations():
  from pitta_jax.data.readers import READERS
  from pitta_jax.data.synthetic import SyntheticConfig
  raw = split_options(["sequences=0001", "depth=false"])
  got = typed_options(raw, function_annotations(READERS["waymo"]), "waymo")
  assert got == {"sequences": "0001", "depth": False}  # "0001" stays a string
  syn = typed_options(split_options(["num_frames=12", "severity=0.5", "domain=fog"]),
                      dataclass_annotations(SyntheticConfig), "synthetic")
  assert syn == {"num_frames": 12, "severity": 0.5, "domain": "fog"}
  with pytest.raises(DataError, match="expected int"):
    typed_options({"num_frames": "3.5"}, dataclass_annotations(SyntheticConfig), "synthetic")
  with pytest.raises(DataError, match="has no option colour"):
    typed_options({"colour": "red"}, function_annotations(READERS["waymo"]), "waymo")
  with pytest.raises(DataError, match="KEY=VALUE"):
    split_options(["foggy"])


def test_none_in_any_case_unsets_an_optional_reader_option():
  """`--option depth_dir=None` (or none, NONE) unsets an option whose annotation allows None
  (not a directory named "None"); for an option that cannot be None (the synthetic domain, a
  str) the text stays a value."""
  from pitta_jax.data.readers import READERS
  from pitta_jax.data.synthetic import SyntheticConfig
  folder = function_annotations(READERS["folder"])
  assert typed_options({"depth_dir": "None", "calib": "NONE", "panoptic_dir": "none"}, folder,
                       "folder") == {"depth_dir": None, "calib": None, "panoptic_dir": None}
  assert typed_options({"domain": "None"}, dataclass_annotations(SyntheticConfig),
                       "synthetic") == {"domain": "None"}


def test_segmentation_sources_parse():
  assert parse_segmentation("gt") == ("gt", "")
  assert parse_segmentation("png:pan/dir") == ("png", "pan/dir")
  assert parse_segmentation("mask2former:w") == ("mask2former", "w")
  for bad in ("png", "png:", "detectron:x"):
    with pytest.raises(DataError):
      parse_segmentation(bad)


def test_string_tuples_parse_as_strings():
  from pitta_jax.demo import DemoConfig
  parser = argparse.ArgumentParser()
  add_config_arguments(parser, DemoConfig, "demo", "demo")
  cfg = config_from_args(DemoConfig, parser.parse_args(["--shifts", "fog, night"]), "demo")
  assert cfg.shifts == ("fog", "night") and cfg.num_frames == 40


def test_flag_values_parse_as_the_module_documents(capsys, tmp_path):
  """config_cli's value types, hand values: a bool flag takes true|false (also 1/0, yes/no,
  on/off, in any case) and refuses anything else in one line naming the flag (not read as
  false); a comma list drops empty items (a trailing comma); an int list takes negative
  integers and COCO names (person 1, car 3)."""
  out = str(tmp_path / "unused")  # never made: each command is refused before
  from pitta_jax.cli import main
  from pitta_jax.config_cli import parse_bool, parser_for
  for text, value in (("true", True), ("False", False), (" yes ", True), ("0", False),
                      ("ON", True), ("off", False)):
    assert parse_bool(text) is value, text
  with pytest.raises(argparse.ArgumentTypeError, match="^expected true or false, got 'maybe'$"):
    parse_bool("maybe")
  with pytest.raises(SystemExit) as e:
    main(["adapt", "--dataset", "synthetic", "--out", out, "--adapt.skip-nonfinite", "maybe"])
  assert e.value.code == 2 and capsys.readouterr().err == (
      "error: argument --adapt.skip-nonfinite/--skip-nonfinite: expected true or false, got "
      "'maybe' (see pitta-jax adapt --help)\n")
  strings, _ = parser_for(tuple[str, ...])
  assert strings("fog,, night,") == ("fog", "night")
  ints, _ = parser_for(tuple[int, ...])
  assert ints("-1, 7,person,car,") == (-1, 7, 1, 3)


@pytest.mark.parametrize("command", ["demo", "adapt", "evaluate", "train-source", "predict",
                                     "segment", "convert"])
def test_every_subcommand_help_renders(command, capsys):
  from pitta_jax.cli import main
  with pytest.raises(SystemExit) as e:
    main([command, "--help"])
  assert e.value.code == 0 and "usage:" in capsys.readouterr().out


@pytest.mark.parametrize("converter", ["monodepth2", "sgdepth", "hrdepth", "litemono", "monovit",
                                       "depth-anything-v2", "mask2former"])
def test_every_converter_help_renders(converter, capsys):
  from pitta_jax.cli import main
  with pytest.raises(SystemExit) as e:
    main(["convert", converter, "--help"])
  assert e.value.code == 0 and "--out" in capsys.readouterr().out


def test_demo_methods_are_validated():
  from pitta_jax.demo import ROWS, DemoConfig
  assert DemoConfig().methods == ("none", "bn", "pitta")
  assert set(ROWS) == {"none", "bn", "pitta", "comoda", "adadepth", "actmad", "cotta"}
  with pytest.raises(ValueError, match="methods \\['tent'\\] invalid"):
    DemoConfig(methods=("pitta", "tent"))
  with pytest.raises(ValueError, match="methods \\['none'\\] given twice"):
    DemoConfig(methods=("none", "pitta", "none"))
  with pytest.raises(ValueError, match="shifts \\['fog'\\] given twice"):
    DemoConfig(shifts=("fog", "fog"))


def test_demo_config_is_checked_at_the_ends_of_its_ranges():
  """DemoConfig's checks at their bounds (hand values): severity 0 and 1 (the range's ends),
  one frame and target seed 0 are taken; one step beyond each, and no shift or no row at all,
  are refused naming the field (a demo of no shift ran only the clear street)."""
  from pitta_jax.demo import DemoConfig
  for fine in (dict(severity=0.0), dict(severity=1.0), dict(num_frames=1), dict(target_seed=0)):
    DemoConfig(**fine)
  for bad, match in ((dict(severity=-0.1), r"^severity must be in \[0, 1\], got -0.1$"),
                     (dict(severity=1.1), r"^severity must be in \[0, 1\], got 1.1$"),
                     (dict(num_frames=0), r"^num_frames must be >= 1, got 0$"),
                     (dict(target_seed=-1), r"^target_seed must be >= 0, got -1$"),
                     (dict(shifts=()), r"^shifts \(\) invalid: choose from fog, "),
                     (dict(methods=()), r"^methods \(\) invalid: choose from none, ")):
    with pytest.raises(ValueError, match=match):
      DemoConfig(**bad)


@pytest.mark.parametrize("earlier, owner, refused", [
    ({"command": "adapt"}, "evaluate", False), ({"command": "evaluate"}, "adapt", False),
    ({"command": "adapt"}, "demo", False),     # the demo writes every file adapt wrote
    ({"demo": {}}, "adapt", True),             # the demo's figures would stay
    ({"table": "table1"}, "experiment table1", False),
    ({"table": "table1"}, "experiment table3", True), ({"table": "table1"}, "adapt", True),
    ({"command": "adapt"}, "experiment table1", True),
    ({"rows": []}, "adapt", False), ("not json", "adapt", False), ([1, 2], "demo", False)])
def test_which_earlier_results_a_command_may_replace(tmp_path, earlier, owner, refused):
  from pitta_jax.data.errors import DataError
  from pitta_jax.report import check_results_owner
  text = earlier if isinstance(earlier, str) else json.dumps(earlier)
  (tmp_path / "results.json").write_text(text)
  if refused:
    with pytest.raises(DataError, match="holds the results of `pitta-jax "):
      check_results_owner(tmp_path, owner)
  else:
    check_results_owner(tmp_path, owner)
  check_results_owner(tmp_path / "missing", owner)  # nothing there: nothing to refuse


def test_markdown_table_marks_nothing_in_a_group_of_one_row():
  # a group with one row has no best to mark (it would bold all 7 cells)
  assert "**" not in markdown_table([Row("fog", "PITTA", M1)])


def test_results_csv_has_every_rows_extra_columns(tmp_path):
  write_results(tmp_path, [Row("fog", "a", M1, {"fps": 2.0}),
                           Row("fog", "b", M2, {"fps": 3.0, "n_skipped": 1})], {})
  with open(tmp_path / "results.csv", newline="") as f:
    rows = list(csv.DictReader(f))
  assert [(r["fps"], r["n_skipped"]) for r in rows] == [("2.0", ""), ("3.0", "1")]


def test_a_blank_option_key_and_a_malformed_integer_are_named():
  """`--option " =3"` has no key once its blanks go: it is not KEY=VALUE (it was met as "has no
  option  (options: ...)" with an empty name); `--pitta.ld.dynamic-classes 1,--5` names the item
  (argparse said "invalid _parse_int_tuple value", the parser's function name)."""
  from pitta_jax.config_cli import parser_for
  with pytest.raises(DataError, match=r"^--option ' =3' is not KEY=VALUE$"):
    split_options([" =3"])
  ints, _ = parser_for(tuple[int, ...])
  with pytest.raises(argparse.ArgumentTypeError,
                     match=r"^'--5' is neither an integer nor a COCO class name$"):
    ints("1,--5")


def test_results_csv_says_a_diverged_rows_status_as_the_table_does(tmp_path):
  """`pitta-jax adapt` keeps a diverged run's means over its finite frames: table.md and
  results.json say "diverged"; results.csv gave the numbers alone, as an ok row's."""
  status = "diverged: non-finite depth from frame 3 of 10 (7 frames not scored)"
  write_results(tmp_path, [Row("fog", "a", M1), Row("fog", "b", M2, status=status)], {})
  with open(tmp_path / "results.csv", newline="") as f:
    rows = list(csv.DictReader(f))
  assert [(r["method"], r["status"], r["abs_rel"]) for r in rows] == [
      ("a", "ok", "0.200000"), ("b", status, "0.100000")]
  table = (tmp_path / "table.md").read_text()
  data = json.loads((tmp_path / "results.json").read_text())
  assert f"| fog | b | {status} |" in table and data["rows"][1]["status"] == status


def test_markdown_table_bolds_every_cell_that_prints_the_best_value():
  """The best is the best number as printed: 0.1004 and 0.1001 both print 0.100, and only the
  second was bold (the unrounded minimum), beside an equal-looking plain cell; the paper and the
  experiments' tables bold both (Table 1, All: ActMAD's and PITTA's δ<1.25 0.758)."""
  tie_a = {**M1, "abs_rel": 0.1004, "a1": 0.7584}
  tie_b = {**M2, "abs_rel": 0.1001, "a1": 0.7576}
  table = markdown_table([Row("fog", "a", tie_a), Row("fog", "b", tie_b),
                          Row("fog", "c", {**M1, "abs_rel": 0.3, "a1": 0.5})])
  cells = [line.split(" | ") for line in table.strip().splitlines()[2:]]
  assert [c[2] for c in cells] == ["**0.100**", "**0.100**", "0.300"]  # AbsRel
  assert [c[6] for c in cells] == ["**0.758**", "**0.758**", "0.500"]  # δ<1.25
  # a column whose printed values all tie has no best
  same = markdown_table([Row("fog", "a", {**M1, "rmse": 9.0001}), Row("fog", "b", M1)])
  assert all("**" not in line.split(" | ")[4] for line in same.strip().splitlines()[2:])
