"""CARMEN log reader: message types, beam geometry, no-return handling, errors."""

from __future__ import annotations

import gzip
import math

import numpy as np
import pytest
from cgamap.drivers.carmen import (
    CarmenFormatError,
    CarmenStats,
    beam_geometry,
    read_carmen,
    read_scans,
    write_carmen,
)
from cgamap.drivers.messages import LaserScan, OdometryPose
from conftest import require_data


def _flaser(n: int, r: float = 2.0, t: float = 12.5) -> str:
    ranges = " ".join([f"{r}"] * (n - 1) + ["81.83"])
    return f"FLASER {n} {ranges} 1.0 2.0 0.5 1.1 2.1 0.6 {t} host {t}\n"


def test_beam_geometry():
    assert beam_geometry(180) == (-math.pi / 2, math.pi / 180)
    assert beam_geometry(361) == (-math.pi / 2, math.pi / 360)
    amin, inc = beam_geometry(181)
    assert amin + 180 * inc == pytest.approx(math.pi / 2)


def test_reads_all_types(tmp_path):
    log = tmp_path / "a.log"
    log.write_text(
        "# comment\nPARAM robot_frontlaser_offset 0.0 nohost 0\n"
        "ODOM 0.5 0.25 0.1 0.3 0.01 0 10.0 host 10.0\n" + _flaser(180) + "NEFF 15\n"
    )
    st = CarmenStats()
    msgs = list(read_carmen(log, stats=st))
    assert isinstance(msgs[0], OdometryPose) and msgs[0].stamp_ns == 10_000_000_000
    scan = msgs[1]
    assert isinstance(scan, LaserScan)
    assert scan.stamp_ns == 12_500_000_000
    assert scan.pose_ref == (1.0, 2.0, 0.5) and scan.pose_odom == (1.1, 2.1, 0.6)
    assert len(scan.ranges) == 180 and np.isnan(scan.ranges[-1])
    assert np.all(scan.ranges[:-1] == 2.0)
    assert st.scans == 1 and st.odometry == 1 and st.ignored == 3


def test_gzip_and_robotlaser(tmp_path):
    n = 5
    line = ("ROBOTLASER1 0 -1.5708 3.14159 0.785398 20.0 0.01 0 5 1 2 3 20 4 0 "
            "0.1 0.2 0.3 1 2 0.4 0 0 0 0 0 7.25 host 7.25\n")
    log = tmp_path / "b.log.gz"
    with gzip.open(log, "wt") as fh:
        fh.write(line)
    (scan,) = read_scans(log)
    assert scan.pose_ref == (0.1, 0.2, 0.3)
    assert scan.angle_increment == pytest.approx(3.14159 / (n - 1))
    assert np.isnan(scan.ranges[3]) and scan.ranges[4] == 4.0
    assert scan.stamp_ns == 7_250_000_000


def test_robotlaser_beams_follow_the_resolution_field(tmp_path):
    # 180 beams a degree apart, fov written as pi: (n - 1) * 1 deg is 179 deg, and spreading
    # the beams over the fov field would put the last one a degree off
    ranges = " ".join(["2.0"] * 180)
    log = tmp_path / "r.log"
    log.write_text(f"ROBOTLASER1 0 -1.570796 3.141593 0.017453 81.9 0.01 0 180 {ranges} 0 "
                   "1 2 0.5 0.9 2 0.5 0 0 0 0 0 3.0 host 3.0\n")
    (scan,) = read_scans(log)
    assert scan.angle_increment == pytest.approx(0.017453)
    assert scan.pose_ref == (1.0, 2.0, 0.5) and scan.pose_odom == (0.9, 2.0, 0.5)


def test_robotlaser_written_and_read_back(tmp_path):
    inc = math.radians(0.25)
    r = np.linspace(1.0, 5.0, 1081)
    r[7] = np.nan
    scans = [LaserScan(seq=0, stamp_ns=2_500_000_000, angle_min=-math.radians(135),
                       angle_increment=inc, ranges=r, pose_ref=(1.0, 2.0, 0.3))]
    log = tmp_path / "w.log"
    assert write_carmen(log, scans, kind="ROBOTLASER1", robot_poses=[(0.8, 2.0, 0.3)]) == 1
    (back,) = read_scans(log)
    assert back.angle_min == pytest.approx(-math.radians(135))
    assert back.angle_increment == pytest.approx(inc)
    assert np.isnan(back.ranges[7]) and np.allclose(np.delete(back.ranges, 7),
                                                   np.delete(r, 7), atol=5e-4)
    assert back.pose_ref == (1.0, 2.0, 0.3) and back.pose_odom == (0.8, 2.0, 0.3)
    assert back.stamp_ns == 2_500_000_000
    with pytest.raises(ValueError, match="kind"):
        write_carmen(log, scans, kind="RAWLASER1")


def test_malformed_names_file_and_line(tmp_path):
    log = tmp_path / "c.log"
    log.write_text(_flaser(180) + "FLASER 180 1 2 3\n" + "ODOM 1 x 3 0 0 0 1 h 1\n")
    with pytest.raises(CarmenFormatError, match=r"c\.log:2"):
        list(read_carmen(log))
    st = CarmenStats()
    msgs = list(read_carmen(log, lenient=True, stats=st))
    assert len(msgs) == 1 and st.skipped == 2 and "c.log:2" in st.first_error


def test_intel_log():
    path = require_data("laser/intel-corrected.log.gz")
    st = CarmenStats()
    scans = read_scans(path, stats=st)
    assert len(scans) == 910 and st.skipped == 0
    assert st.saturated_range is None  # its no-return is 81.83 m, above the reader's limit
    assert all(len(s.ranges) == 180 for s in scans)
    stamps = np.array([s.stamp_ns for s in scans])
    # the real log's ipc stamps step back a little in 4 places; kept as recorded
    assert np.mean(np.diff(stamps) > 0) > 0.99
    assert stamps[0] == 32_906_800_000
    assert scans[0].pose_ref == pytest.approx((0.600266, -0.0320327, -0.354665))


def _scan(n: int = 180, **kw) -> LaserScan:
    a0, inc = beam_geometry(n)
    r = np.linspace(0.5, 30.0, n)
    r[3] = np.nan
    base = dict(seq=0, stamp_ns=12_500_000_000, angle_min=a0, angle_increment=inc, ranges=r,
                pose_ref=(1.0, -2.0, 0.5), pose_odom=(1.1, -2.1, 0.6))
    return LaserScan(**(base | kw))


@pytest.mark.parametrize("n", [180, 181, 361])
def test_written_log_reads_back(tmp_path, n):
    from cgamap.drivers.carmen import write_carmen

    scans = [_scan(n), _scan(n, seq=1, stamp_ns=13_000_000_000, pose_odom=None)]
    assert write_carmen(tmp_path / "w.log", scans) == 2
    back = read_scans(tmp_path / "w.log")
    assert len(back) == 2
    assert back[0].angle_min == pytest.approx(scans[0].angle_min)
    assert back[0].angle_increment == pytest.approx(scans[0].angle_increment)
    np.testing.assert_allclose(back[0].ranges, scans[0].ranges, atol=5e-4)  # NaN where NaN
    assert back[0].pose_ref == pytest.approx((1.0, -2.0, 0.5))
    assert back[0].pose_odom == pytest.approx((1.1, -2.1, 0.6))
    assert back[1].pose_odom == pytest.approx((1.0, -2.0, 0.5))  # the reference stands in
    assert back[1].stamp_ns == 13_000_000_000


def test_writer_refuses_what_flaser_cannot_say():
    from cgamap.drivers.carmen import flaser_line

    with pytest.raises(ValueError, match="FLASER implies 180 beams"):
        flaser_line(_scan(angle_min=-1.0))
    with pytest.raises(ValueError, match="neither pose_ref nor pose_odom"):
        flaser_line(_scan(pose_ref=None, pose_odom=None))


def _wall_log(path, top: str, scans: int = 30) -> None:
    """A wall 3-4 m ahead on the right half; the left half's beams read ``top``."""
    lines = []
    for k in range(scans):
        r = [f"{3.0 + 0.005 * i + 0.01 * k:.3f}" for i in range(90)] + [top] * 90
        lines.append(f"FLASER 180 {' '.join(r)} {0.1 * k} 0 0 {0.1 * k} 0 0 {k} host {k}\n")
    path.write_text("".join(lines))


def test_a_no_return_written_as_a_reading_is_dropped(tmp_path):
    # an LMS in its 8 m mode says 8.18 for "nothing there"; as points it is an arc that
    # travels with the robot
    log = tmp_path / "sat.log"
    _wall_log(log, "8.18")
    st = CarmenStats()
    scans = read_scans(log, stats=st)
    assert st.saturated_range == pytest.approx(8.18) and st.saturated_beams == 30 * 90
    assert all(np.isnan(s.ranges[90:]).all() and np.isfinite(s.ranges[:90]).all()
               for s in scans)
    assert scans[0].range_max == pytest.approx(8.18)
    kept = read_scans(log, saturation=False)
    assert np.all(kept[0].ranges[90:] == 8.18)


def test_a_longest_reading_seen_once_is_a_reading(tmp_path):
    log = tmp_path / "far.log"
    _wall_log(log, "81.83")  # the 80 m mode's no-return: NaN by the reader's maximum
    text = log.read_text().replace(" 3.000 ", " 25.370 ", 1)  # one far wall, once
    log.write_text(text)
    st = CarmenStats()
    scans = read_scans(log, stats=st)
    assert st.saturated_range is None and st.saturated_beams == 0
    assert scans[0].ranges[0] == pytest.approx(25.37)
    assert sum(np.isfinite(s.ranges).sum() for s in scans) == 30 * 90


def test_a_scan_written_as_both_flaser_and_robotlaser_is_read_once(tmp_path):
    # some loggers write each scan twice (old FLASER and new ROBOTLASER1): mapped twice,
    # every scan would match itself; a FLASER scan of its own time stays
    beams = np.linspace(1.0, 4.0, 180)
    scans = [LaserScan(seq=k, stamp_ns=1_000_000_000 * (k + 1), angle_min=-math.pi / 2,
                       angle_increment=math.pi / 180, ranges=beams + k,
                       pose_ref=(k, 0.0, 0.0)) for k in range(3)]
    flaser, robot = tmp_path / "f.log", tmp_path / "r.log"
    write_carmen(flaser, scans)
    write_carmen(robot, scans, kind="ROBOTLASER1")
    f_lines, r_lines = flaser.read_text().splitlines(True), robot.read_text().splitlines(True)
    body_f = [x for x in f_lines if x.startswith("FLASER")]
    body_r = [x for x in r_lines if x.startswith("ROBOTLASER1")]
    # both kinds of the first two scans, then the third scan as FLASER only, and a
    # FLASER at the second's time with other ranges (another laser) also stays
    other = body_f[1].replace(" 2.000 ", " 7.000 ", 1)
    log = tmp_path / "both.log"
    log.write_text("".join([body_r[0], body_f[0], body_r[1], body_f[1], other, body_f[2]]))
    st = CarmenStats()
    got = read_scans(log, stats=st)
    assert st.duplicates == 2 and len(got) == 4
    assert [s.stamp_ns for s in got] == [1_000_000_000, 2_000_000_000, 2_000_000_000,
                                          3_000_000_000]
    # a log of one kind is read whole
    st = CarmenStats()
    assert len(read_scans(flaser, stats=st)) == 3 and st.duplicates == 0
    # and the daemon's replay plays each scan once too
    from cgamap.daemon.recording import read_messages

    played = [m for m in read_messages(log) if isinstance(m, LaserScan)]
    assert [s.stamp_ns for s in played] == [s.stamp_ns for s in got]
