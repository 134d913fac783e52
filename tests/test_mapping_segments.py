"""Split-and-merge segment extraction on hand-made scans with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.mapping.segments import SegmentParams, extract_segments, segments_from_scan
from synth2d import CORRIDOR, L_CORNER, ROOM, scan, seg_lines, world


def test_corridor_two_walls():
    s = scan(world(CORRIDOR), (0.0, 0.0, 0.0))
    seg = segments_from_scan(s)
    lines = sorted(seg_lines(seg), key=lambda t: t[1])
    assert len(seg) == 2
    for ang, rho in lines:
        assert min(ang, np.pi - ang) < 1e-3 and rho == pytest.approx(1.0, abs=1e-3)
    # grazing returns spread out and are cut off by the gap test; the rest is one line
    assert np.all(seg.length > 4)


def test_l_corner_meets_at_corner():
    s = scan(world(L_CORNER), (0.0, 0.0, 0.0), n=360)
    seg = segments_from_scan(s)
    assert len(seg) == 2
    ends = np.concatenate([seg.a, seg.b])
    assert np.min(np.linalg.norm(ends - [3, 1], axis=1)) < 0.05
    ang = sorted(min(a, np.pi - a) for a, _ in seg_lines(seg))
    assert ang[0] == pytest.approx(0.0, abs=1e-3) and ang[1] == pytest.approx(np.pi / 2, abs=1e-3)


def test_room_four_walls_full_circle():
    s = scan(world(ROOM), (0.5, 0.2, 0.3), n=720, fov=2 * np.pi)
    seg = segments_from_scan(s)
    assert len(seg) == 4
    rhos = sorted(r for _, r in seg_lines(seg))
    # walls at distances from the sensor (0.5, 0.2): 2.2, 2.8, 3.5, 3.5
    assert rhos == pytest.approx([2.2, 2.8, 3.5, 3.5], abs=0.01)


def test_gap_splits_a_wall():
    walls = [(-5, 2, -0.5, 2), (0.5, 2, 5, 2)]  # a door 1 m wide in a wall
    seg = segments_from_scan(scan(world(walls), (0.0, 0.0, np.pi / 2), n=360))
    assert len(seg) == 2
    assert all(r == pytest.approx(2.0, abs=1e-3) for _, r in seg_lines(seg))
    # laser frame: the wall is 2 m ahead, the door spans y in (-0.5, 0.5)
    ys = sorted(np.concatenate([seg.a[:, 1], seg.b[:, 1]]))
    assert ys[1] == pytest.approx(-0.5, abs=0.1) and ys[2] == pytest.approx(0.5, abs=0.1)


def test_noise_residual_and_covariance():
    seg = segments_from_scan(scan(world(CORRIDOR), (0.0, 0.0, 0.0), sigma=0.01, seed=3))
    assert len(seg) == 2
    assert np.all((seg.residual > 0.005) & (seg.residual < 0.02))
    assert np.all(seg.cov[:, 0, 0] > 0) and np.all(seg.cov[:, 1, 1] > 0)
    assert np.all(seg.n > 50)


def test_range_filter_and_minimums():
    w = world(CORRIDOR + [(3, -0.2, 3, 0.1)])  # a 0.3 m post ahead: too short to keep
    p = SegmentParams(range_max=5.0, min_length=0.4)
    seg = extract_segments(*_args(scan(w, (0.0, 0.0, 0.0), n=360)), p)
    assert len(seg) == 2
    assert np.all(np.linalg.norm(np.concatenate([seg.a, seg.b]), axis=1) <= 5.0 + 1e-6)
    assert np.all(np.linalg.norm(seg.points, axis=1) <= 5.0)


def test_empty_and_all_nan():
    seg = extract_segments(np.full(180, np.nan), -np.pi / 2, np.pi / 180)
    assert len(seg) == 0
    seg = extract_segments(np.array([1.0, 1.0]), 0.0, 0.01)
    assert len(seg) == 0


def test_range_limit_is_the_sensors_reach():
    # SICK LMS2xx 80 m mode (CARMEN logs saturate at 81.83 / 81.91 m), Hokuyo UTM-30LX 30 m
    assert SegmentParams.for_lms().range_max == 80.0
    assert SegmentParams.for_utm().range_max == 30.0


def test_far_wall_kept_within_the_sensors_reach():
    # a wall 40 m ahead, seen at 0.25 deg: a segment by default, none when limited to 25 m
    ang = np.deg2rad(np.arange(-10.0, 10.0, 0.25))
    r = 40.0 / np.cos(ang)
    assert len(extract_segments(r, ang[0], ang[1] - ang[0])) == 1
    assert len(extract_segments(r, ang[0], ang[1] - ang[0], SegmentParams(range_max=25.0))) == 0


def _args(s):
    return s.ranges, s.angle_min, s.angle_increment
