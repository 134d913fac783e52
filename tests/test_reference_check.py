"""A log whose poses are raw odometry (nothing in a CARMEN file says so) is recognised by
how square the walls come out along its poses against along the estimate, and ``map build``
says so beside its ATE; a corrected log is not flagged."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
from cgamap.daemon.cli import main
from cgamap.drivers.carmen import read_scans, write_carmen
from cgamap.mapping.evaluation import reference_check
from cgamap.mapping.offline import log_odometry
from conftest import head_of_log, require_data

INTEL = "laser/intel-corrected.log.gz"


def _sq(on_est, rms_est, on_ref, rms_ref):
    return {"estimate": {"on_axes": on_est, "rms_deg": rms_est},
            "reference": {"on_axes": on_ref, "rms_deg": rms_ref}}


@pytest.mark.parametrize("sq, flag", [
    (_sq(0.85, 1.5, 0.85, 1.55), False),   # a SLAM reference: as square as the estimate
    (_sq(0.85, 1.5, 0.20, 4.45), True),    # drifting odometry
    (_sq(0.85, 1.5, 0.70, 4.0), False),    # off by degrees, but most walls still on the axes
    (_sq(0.85, 1.5, 0.30, 2.2), False),    # off the axes, but its RMS within the margin
    (_sq(0.30, 3.0, 0.10, 5.0), False),    # not a square building: not judged
])
def test_reference_check_rule(sq, flag):
    got = reference_check(sq)
    assert got["odometry_like"] is flag
    assert got["judged"] is (sq["estimate"]["on_axes"] >= 0.5)


def test_reference_check_needs_both_figures():
    assert reference_check({"estimate": {"on_axes": 0.9, "rms_deg": 1.0}}) is None
    assert reference_check(_sq(0.9, None, 0.9, 1.0)) is None


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("logs")
    corrected = head_of_log(require_data(INTEL), d / "intel-head.log", 300)
    scans = list(read_scans(corrected))
    odo, _ = log_odometry(scans, "high", 3)
    # what a raw log holds: the drifting odometry as the laser's and the robot's pose
    raw = [replace(s, pose_ref=tuple(o), pose_odom=tuple(o))
           for s, o in zip(scans, odo, strict=True)]
    write_carmen(d / "intel-raw.log", raw)
    return corrected, d / "intel-raw.log"


def test_map_build_flags_a_raw_log_and_not_a_corrected_one(logs, tmp_path, capsys):
    corrected, raw = logs
    assert main(["map", "build", "--log", str(raw), "--out", str(tmp_path / "raw")]) == 0
    err = capsys.readouterr().err
    assert "look like raw odometry" in err
    rep = json.loads((tmp_path / "raw" / "report.json").read_text())
    assert rep["reference_check"]["odometry_like"] is True
    meta = json.loads((tmp_path / "raw" / "map.json").read_text())["metadata"]
    assert meta["reference_odometry_like"] is True
    assert main(["relocalize", "--map", str(tmp_path / "raw" / "map.json"), "--log", str(raw),
                 "--trials", "5"]) == 0
    assert "look like raw odometry" in capsys.readouterr().err

    assert main(["map", "build", "--log", str(corrected), "--out", str(tmp_path / "ok"),
                 "--odom-noise", "high"]) == 0
    assert "raw odometry" not in capsys.readouterr().err
    rep = json.loads((tmp_path / "ok" / "report.json").read_text())
    assert rep["reference_check"]["odometry_like"] is False
    assert "reference_odometry_like" not in json.loads(
        (tmp_path / "ok" / "map.json").read_text())["metadata"]
