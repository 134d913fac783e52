"""``map build --odom-noise wheels``: the robot's own wheel odometry from a log's ODOM lines,
in both ways logs keep it (raw readings that run on, and GMapping's corrected logs, which
restart them at each scan's corrected pose), its gaps, its absence, and on the real Intel log."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cgamap.daemon.cli import main
from cgamap.drivers.carmen import read_scans, read_scans_and_wheels
from cgamap.mapping.evaluation import ate, odometry_model
from cgamap.mapping.odometry import (
    compose_pose2d,
    integrate_increments,
    pose_increments,
    relative,
)
from cgamap.mapping.offline import log_odometry, wheel_steps
from conftest import head_of_log, require_data

INTEL = "laser/intel-corrected.log.gz"


def _flaser(pose, t: float, n: int = 180) -> str:
    ranges = " ".join(["3.0"] * n)
    p = " ".join(f"{v:.6f}" for v in pose)
    return f"FLASER {n} {ranges} {p} {p} {t} host {t}\n"


def _odom(pose, t: float) -> str:
    return "ODOM " + " ".join(f"{v:.6f}" for v in pose) + f" 0 0 0 {t} host {t}\n"


# corrected poses of three scans, and the wheels' own (wrong) steps between them
SCANS = np.array([[1.0, 2.0, 0.3], [1.9, 2.4, 0.5], [2.5, 3.3, 1.2]])
WHEELS = np.array([[0.95, 0.02, 0.25], [0.80, 0.30, 0.62]])


def _gmapping_log(path, gap: bool = False, coarse: bool = False) -> None:
    """A log as GMapping writes it: each scan, then an ODOM line at its corrected pose, then
    the wheels' readings from there, the last stamped with the next scan's time.  ``coarse``:
    every stamp written as the same 6-digit number (as the MIT CSAIL log's are)."""
    def t(v: float) -> float:
        return 1.13486e9 if coarse else v

    lines = [_odom((0.0, 0.0, 0.0), t(0.5))]  # the raw frame before the first scan
    for k, pose in enumerate(SCANS):
        lines.append(_flaser(pose, t(10.0 + k)))
        if k == len(SCANS) - 1:
            break
        if gap and k == 0:
            continue  # no reading at all until the next scan
        lines.append(_odom(pose, 0.0))
        half = compose_pose2d(pose, WHEELS[k] / 2)
        lines += [_odom(half, t(10.4 + k)), _odom(compose_pose2d(pose, WHEELS[k]), t(11.0 + k))]
        lines.append("NEFF 12.5\n")
    path.write_text("".join(lines))


def test_a_gmapping_log_gives_the_wheels_steps(tmp_path):
    log = tmp_path / "g.log"
    _gmapping_log(log)
    scans, w = read_scans_and_wheels(log)
    assert len(scans) == 3 and w.rebased and w.readings == 7 and w.at_scan_time == 1.0
    steps, unknown = wheel_steps(w.at, w.start)
    assert unknown == 0
    np.testing.assert_allclose(steps, WHEELS, atol=2e-6)
    odo, mount = log_odometry(scans, "wheels", 0, (w.at, w.start))
    assert mount is None
    np.testing.assert_allclose(odo[0], SCANS[0])
    np.testing.assert_allclose(odo[2], compose_pose2d(compose_pose2d(SCANS[0], WHEELS[0]),
                                                      WHEELS[1]), atol=1e-5)
    # the laser lines' own odometry fields are the corrected poses: `none` replays those
    none, _ = log_odometry(scans, "none")
    np.testing.assert_allclose(none, SCANS, atol=1e-6)


def test_a_step_without_readings_is_unknown_and_counted(tmp_path):
    log = tmp_path / "g.log"
    _gmapping_log(log, gap=True)
    scans, w = read_scans_and_wheels(log)
    assert w.rebased  # the one scan followed by a reading is at its pose
    steps, unknown = wheel_steps(w.at, w.start)
    assert unknown == 1 and np.all(steps[0] == 0.0)
    np.testing.assert_allclose(steps[1], WHEELS[1], atol=2e-6)


def test_stamps_that_cannot_tell_the_scans_apart_are_said(tmp_path, capsys):
    log = tmp_path / "g.log"
    _gmapping_log(log, coarse=True)
    scans, w = read_scans_and_wheels(log)
    assert w.rebased and w.at_scan_time == 0.0
    np.testing.assert_allclose(wheel_steps(w.at, w.start)[0], WHEELS, atol=2e-6)
    assert main(["map", "build", "--log", str(log), "--out", str(tmp_path / "o"),
                 "--odom-noise", "wheels"]) == 0
    err = capsys.readouterr().err
    assert "warning: 0% of the log's scans have an ODOM reading of their own time" in err
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["wheel_odometry"]["at_scan_time"] == 0.0


def test_raw_readings_are_taken_at_the_scans_time(tmp_path):
    # odometry at 1 m/s along x, turning 0.1 rad/s, read every second; scans between readings
    # with odometry fields that say something else (they are not what `wheels` reads)
    lines = [_odom((t, 0.0, 0.1 * t), t) for t in (0.0, 1.0)]
    lines.append(_flaser((5.0, 5.0, 0.0), 1.5))
    lines += [_odom((t, 0.0, 0.1 * t), t) for t in (2.0, 3.0)]
    lines.append(_flaser((6.0, 5.0, 0.0), 3.25))
    lines.append(_odom((4.0, 0.0, 0.4), 4.0))
    log = tmp_path / "raw.log"
    log.write_text("".join(lines))
    scans, w = read_scans_and_wheels(log)
    assert not w.rebased and w.at_scan_time == 1.0
    np.testing.assert_allclose(w.at, [[1.5, 0.0, 0.15], [3.25, 0.0, 0.325]], atol=1e-9)
    steps, unknown = wheel_steps(w.at, w.start)
    assert unknown == 0
    np.testing.assert_allclose(steps[0], relative(np.array([1.5, 0.0, 0.15]),
                                                  np.array([3.25, 0.0, 0.325])), atol=1e-9)


def test_a_log_without_odom_lines(tmp_path, capsys):
    log = tmp_path / "n.log"
    log.write_text("".join(_flaser(p, 10.0 + k) for k, p in enumerate(SCANS)))
    scans, w = read_scans_and_wheels(log)
    assert len(scans) == 3 and w is None
    with pytest.raises(ValueError, match="ODOM"):
        log_odometry(scans, "wheels", 0, None)
    code = main(["map", "build", "--log", str(log), "--out", str(tmp_path / "o"),
                 "--odom-noise", "wheels", "--quiet"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2 and len(err) == 1
    assert "--odom-noise wheels" in err[0] and "ODOM" in err[0]
    assert not (tmp_path / "o" / "map.json").exists()


def test_the_intel_log_keeps_its_robots_odometry():
    """Facts of the real log the option rests on: its ODOM lines restart at every scan's
    corrected pose (a GMapping log), and the wheels' steps between scans are a real robot's,
    longer by a few per cent and turning steadily one way, far from the corrected steps."""
    scans, w = read_scans_and_wheels(require_data(INTEL))
    assert len(scans) == len(read_scans(require_data(INTEL))) == 910
    assert w.rebased and w.readings == 14541 and w.at_scan_time == 1.0
    steps, unknown = wheel_steps(w.at, w.start)
    assert unknown == 0
    ref = np.array([s.pose_ref for s in scans])
    true = pose_increments(ref)
    length, true_length = np.hypot(*steps[:, :2].T), np.hypot(*true[:, :2].T)
    run = true_length > 0.2  # steps that drive (most of the rest turn on the spot)
    assert 1.02 < length[run].sum() / true_length[run].sum() < 1.06    # measured 1.037
    turn_error = np.angle(np.exp(1j * (steps[:, 2] - true[:, 2])))
    drift = turn_error.sum() / true_length.sum()
    assert np.degrees(drift) < -2.0                              # measured -3.3 deg per metre
    odo, _ = log_odometry(scans, "wheels", 0, (w.at, w.start))
    assert ate(odo, ref)["ate_trans_m"] > 10.0                   # dead reckoning: 24 m


def test_map_build_records_the_wheels(tmp_path):
    # 120 scans: the first loop closes at scan 103
    log = head_of_log(require_data(INTEL), tmp_path / "intel-120.log", 120)
    out = tmp_path / "m"
    assert main(["map", "build", "--log", str(log), "--out", str(out), "--odom-noise",
                 "wheels", "--quiet"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["odom_noise"] == "wheels"
    assert rep["wheel_odometry"] == {"odom_lines": rep["wheel_odometry"]["odom_lines"],
                                     "rebased": True, "unknown_steps": 0, "at_scan_time": 1.0}
    # the wheels were what the mapper got (their dead reckoning is 10.8 m off the corrected
    # poses by then), and it maps with them: 0.094 m measured
    assert rep["odometry"]["ate_trans_m"] > 5.0
    assert rep["ate_trans_m"] < 0.15
    meta = json.loads((out / "map.json").read_text())["metadata"]
    assert meta["odom_noise"] == "wheels"


def test_the_odometry_model_recovers_a_known_scale_and_drift():
    rng = np.random.default_rng(3)
    true = np.column_stack([rng.uniform(0.0, 1.0, 300), rng.normal(0, 0.02, 300),
                            rng.normal(0, 0.4, 300)])
    raw = true.copy()
    raw[:, :2] *= 1.04                                   # wheels 4 % long
    d = np.hypot(raw[:, 0], raw[:, 1])
    raw[:, 2] += np.radians(-3.0) * d                    # and turning 3 deg a metre one way
    raw[:, 2] += rng.normal(0, np.radians(1.0), 300)     # and 1 deg of noise a step
    ref = integrate_increments(true, (1.0, 2.0, 0.3))
    odo = integrate_increments(raw, (1.0, 2.0, 0.3))
    m = odometry_model(odo, ref)
    assert m["steps"] == 300
    assert m["scale"] == pytest.approx(1 / 1.04, abs=1e-4)
    assert m["drift_deg_per_m"] == pytest.approx(-3.0, abs=0.3)
    assert m["turn_residual_deg_rms"] == pytest.approx(1.0, abs=0.15)
    assert m["length_residual_m_rms"] < 1e-3
