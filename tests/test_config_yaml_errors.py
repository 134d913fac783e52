"""One YAML error line (drivers.yaml_errors) for every YAML reader: config, hand-eye file,
pairs file, stereo calibration, the stereo and planes commands."""

from __future__ import annotations

import argparse

import pytest
import yaml
from cgamap.calib.pairs import PairsFileError, load_pairs
from cgamap.daemon import config
from cgamap.daemon.cmd_stereo import _input_problem
from cgamap.drivers.stereo_calib import load_calibration
from cgamap.drivers.yaml_errors import yaml_error_text

BROKEN = "a: 1\nb: [2\n"  # the flow sequence never closes: the parser stops at line 3


def error_of(text: str) -> yaml.YAMLError:
    with pytest.raises(yaml.YAMLError) as info:
        yaml.safe_load(text)
    return info.value


def test_marked_error_gives_line_column_and_problem():
    msg = yaml_error_text(error_of(BROKEN))
    assert msg == "YAML syntax error at line 3, column 1: expected ',' or ']', but got " \
                  "'<stream end>'"
    tab = yaml_error_text(error_of("pairs:\n\t- 1\n"), "invalid YAML")
    assert tab.startswith("invalid YAML at line 2, column 1: found character")


def test_unmarked_errors_stay_one_line():
    reader = yaml_error_text(error_of("a: \x00"))
    assert reader.startswith("YAML syntax error: unacceptable character") and "\n" not in reader
    assert yaml_error_text(yaml.YAMLError()) == "YAML syntax error: YAMLError"


def test_config_names_line_and_column(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("log_level: info\n" + BROKEN)
    with pytest.raises(config.ConfigError) as info:
        config.load(p)
    assert "YAML syntax error at line 4, column 1" in str(info.value)
    assert "\n" not in str(info.value)


def test_hand_eye_file_syntax_error_names_the_line(tmp_path):
    (tmp_path / "he.yaml").write_text(BROKEN)
    with pytest.raises(config.ConfigError) as info:
        config.load_hand_eye(tmp_path / "he.yaml", "devices.head.hand_eye")
    assert "he.yaml" in str(info.value) and "at line 3, column 1" in str(info.value)
    assert "\n" not in str(info.value)


def test_pairs_file(tmp_path):
    p = tmp_path / "pairs.yaml"
    p.write_text(BROKEN)
    with pytest.raises(PairsFileError, match=r"pairs.yaml: invalid YAML at line 3, column 1: "):
        load_pairs(p)


def test_stereo_calibration_and_stereo_command(tmp_path):
    p = tmp_path / "calib.yaml"
    p.write_text(BROKEN)
    with pytest.raises(ValueError, match=r"stereo calibration .*calib.yaml: calibration YAML "
                                         r"syntax error at line 3, column 1: expected"):
        load_calibration(p)
    args = argparse.Namespace(device="rec")
    assert _input_problem(args, error_of(BROKEN)) == (
        "--device rec: calibration YAML syntax error at line 3, column 1: expected ',' or ']', "
        "but got '<stream end>'")
