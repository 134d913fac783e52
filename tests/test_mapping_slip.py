"""Slip recovery (:mod:`cgamap.mapping.slip`): a scan whose odometry is a few degrees off,
beyond the correction's reach, is found again from the Hough-domain rotation peaks; a scan of
new ground or a turn beyond the search keeps its prediction."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.correction import correct_pose
from cgamap.mapping.odometry import integrate_increments, pose_increments
from cgamap.mapping.posegraph import wrap
from cgamap.mapping.segments import segments_from_scan
from cgamap.mapping.slam2d import Mapper, MapperParams
from cgamap.mapping.slip import SlipParams, recover
from synth2d import ROOM, scan, world

TRUE = np.array([0.4, -0.3, 0.25])


def _room():
    w = world(ROOM)
    full = segments_from_scan(scan(w, (0.0, 0.0, 0.0), n=720, fov=2 * np.pi))
    here = segments_from_scan(scan(w, TRUE, n=360, fov=np.pi, sigma=0.005, seed=3))
    return full, here


@pytest.mark.parametrize("turn_deg", [-9.0, -5.0, 4.0, 12.0])
def test_a_turn_beyond_the_correction_is_found_again(turn_deg):
    full, here = _room()
    pred = TRUE + [0.05, -0.04, np.deg2rad(turn_deg)]
    P = MapperParams().correction
    corr = correct_pose(here, full.a, full.b, pred, 0.0, P)  # odometry: no motion
    got = recover(here, full.a, full.b, pred, corr, P, SlipParams())
    assert got is not None
    assert np.hypot(*(got.pose[:2] - TRUE[:2])) < 0.01
    assert abs(np.rad2deg(wrap(got.pose[2] - TRUE[2]))) < 0.2
    assert got.matched_fraction > corr.matched_fraction + 0.25


def test_no_recovery_beyond_the_search_or_away_from_the_map():
    full, here = _room()
    P = MapperParams().correction
    for pred, why in [(TRUE + [0.0, 0.0, np.deg2rad(40.0)], "turn beyond max_turn"),
                      (TRUE + [30.0, 0.0, np.deg2rad(5.0)], "no map near the scan")]:
        corr = correct_pose(here, full.a, full.b, pred, 0.0, P)
        assert recover(here, full.a, full.b, pred, corr, P, SlipParams()) is None, why


def _corridor_run(error, at: int, slip: bool):
    """The simulated loop's corridors, a scan every 10 cm; at step ``at`` the odometry
    reports ``error`` (dx, dy, dtheta in the robot frame) less than the robot moved."""
    w = get_world("loop")
    t = np.arange(0, 0.25 * w.path_length / w.speed, 0.1 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    inc = pose_increments(truth)
    inc[at] -= error
    odo = integrate_increments(inc, truth[0])
    MP = MapperParams()
    m = Mapper(replace(MP, slip=replace(MP.slip, enabled=slip)), initial_pose=truth[0])
    for k, p in enumerate(truth):
        s = scan(w, p, n=180, sigma=0.01, seed=k)
        m.step(s.ranges, s.angle_min, s.angle_increment, odo[k])
    X = m.poses
    turn = np.rad2deg(np.abs(wrap(X[:, 2] - truth[:, 2])))
    return m, np.hypot(*(X[:, :2] - truth[:, :2]).T), turn


@pytest.mark.parametrize("error", [(0.0, 0.0, 0.065), (0.1, 0.05, -0.065)])
def test_a_push_in_a_corridor_does_not_stay_in_the_map(error):
    # 3.7 deg of turn the wheels did not report (a push, or a robot rolling on while its
    # odometry stands): no wall matches within the correction's gates; without the
    # recovery the scan's walls enter the map turned and the error stays for good
    at = 20
    m, e, r = _corridor_run(np.array(error), at, slip=True)
    assert m.slips >= 1
    assert r[at + 1:].max() < 0.5 and e[at + 5:].max() < 0.05, (r.max(), e.max())
    _, e0, r0 = _corridor_run(np.array(error), at, slip=False)
    assert r0[at + 1:].min() > 3.0  # the test's premise: the plain correction cannot
