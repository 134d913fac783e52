"""``cgamap map build --params FILE``: mapper parameters from YAML (the daemon's
``mapping.params2d``), checked before any work, recorded with the map, and the map's segment
extraction used again by ``cgamap relocalize``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cgamap.daemon.cli import main
from conftest import head_of_log, require_data

INTEL = "laser/intel-corrected.log.gz"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def short_log(tmp_path_factory):
    return head_of_log(require_data(INTEL), tmp_path_factory.mktemp("log") /
                       "intel-short.log.gz", 120)


def _build(log, out, *extra) -> int:
    return main(["map", "build", "--log", str(log), "--out", str(out), "--quiet", *extra])


def test_params_change_the_build_and_are_recorded(short_log, tmp_path, capsys):
    p = tmp_path / "p.yaml"
    p.write_text("segments:\n  min_length: 0.5   # only walls\n  range_max: 30.0\n"
                 "loop: {radius: 5.0}\n")
    assert _build(short_log, tmp_path / "m", "--params", str(p)) == 0
    assert _build(short_log, tmp_path / "d") == 0
    want = {"segments": {"min_length": 0.5, "range_max": 30.0}, "loop": {"radius": 5.0}}
    rep = json.loads((tmp_path / "m" / "report.json").read_text())
    meta = json.loads((tmp_path / "m" / "map.json").read_text())["metadata"]
    assert rep["params2d"] == want and meta["params2d"] == want
    default = json.loads((tmp_path / "d" / "report.json").read_text())
    assert "params2d" not in default
    assert rep["segments"] < 0.7 * default["segments"]  # measured 107 against 207
    capsys.readouterr()
    # relocalising cuts the scans as the map was built: a map recorded with an extraction
    # that keeps no segment finds nothing, the same map without the record finds the poses
    args = ["relocalize", "--map", str(tmp_path / "m" / "map.json"), "--log", str(short_log),
            "--trials", "5", "--json"]
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["successes"] >= 3
    doc = json.loads((tmp_path / "m" / "map.json").read_text())
    doc["metadata"]["params2d"]["segments"]["min_points"] = 10_000
    (tmp_path / "m" / "map.json").write_text(json.dumps(doc))
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["successes"] == 0


def test_a_cgamapd_config_gives_its_mapping_params2d(short_log, tmp_path):
    # config/sim.yaml sets no 2D mapper parameter: the defaults
    assert _build(short_log, tmp_path / "m", "--params", str(REPO / "config" / "sim.yaml")) == 0
    assert "params2d" not in json.loads((tmp_path / "m" / "report.json").read_text())


@pytest.mark.parametrize("text, needle", [
    ("segments:\n  min_lenght: 0.5\n", "unknown 2D mapper parameter 'segments.min_lenght'"),
    ("segments: {min_length: x}\n", "segments.min_length: expected number like 0.15, got 'x'"),
    ("neighbours: {floor: [0.01]}\n", "neighbours.floor: expected"),
    ("a: [1\n", "YAML syntax error at line 2"),
    ("loop: {}\nloop: {}\n", "loop: duplicate key at line 2"),
    ("- 1\n- 2\n", "top level: expected a mapping of mapper parameters, got list"),
    ("mount: [0.2, 0, 0]\n", "mount: the laser's mount comes from the log"),
    ("mapping:\n  params2d: {map: {clear: {enabled: 1}}}\n",
     "mapping.params2d.map.clear.enabled: expected"),
])
def test_bad_params_are_one_line_before_any_work(text, needle, tmp_path, capsys):
    p = tmp_path / "p.yaml"
    p.write_text(text)
    # the log is not even read: the parameters are checked first
    assert _build(tmp_path / "no.log", tmp_path / "out", "--params", str(p)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--params: {p}: " in err and needle in err, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_missing_or_unreadable_params_file(tmp_path, capsys):
    assert _build(tmp_path / "no.log", tmp_path / "out", "--params",
                  str(tmp_path / "none.yaml")) == 2
    assert "No such file or directory" in capsys.readouterr().err
    assert _build(tmp_path / "no.log", tmp_path / "out", "--params", str(tmp_path)) == 2
    assert "is a directory, not a parameter file" in capsys.readouterr().err
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe\x00")
    assert _build(tmp_path / "no.log", tmp_path / "out", "--params",
                  str(tmp_path / "bin.yaml")) == 2
    assert "not a text (YAML) file" in capsys.readouterr().err


def test_relocalize_refuses_a_map_with_bad_recorded_params(tmp_path, capsys):
    import numpy as np
    from cgamap.mapping.linemap import LineMap
    from cgamap.mapping.mapio import save_map
    from cgamap.mapping.segments import extract_segments

    lm = LineMap()
    ang = np.linspace(-np.pi / 2, np.pi / 2, 181)
    lm.append(extract_segments(2.0 / np.maximum(np.abs(np.cos(ang)), 0.3), -np.pi / 2,
                               np.pi / 180), 0)
    m = tmp_path / "map.json"
    save_map(lm, m, {"params2d": {"segments": {"min_pionts": 3}}})
    log = tmp_path / "a.log"
    log.write_text("ODOM 0 0 0 0 0 0 1 h 1\n")
    assert main(["relocalize", "--map", str(m), "--log", str(log)]) == 2
    err = capsys.readouterr().err
    assert "--map: unknown segment parameter 'metadata.params2d.segments.min_pionts'" in err


def test_progress_to_a_log_file_is_one_line_per_tenth(short_log, tmp_path, capsys):
    # capsys's stderr is no terminal: lines, not carriage returns run together
    assert main(["map", "build", "--log", str(short_log), "--out", str(tmp_path / "m")]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    counts = [ln.split(": ")[1] for ln in err.splitlines() if ln.startswith("map build: ")
              and ln.split(": ")[1].split("/")[0].isdigit()]
    assert counts[-1] == "120/120" and len(counts) == 10
