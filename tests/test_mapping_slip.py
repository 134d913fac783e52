"""Slip recovery (:mod:`cgamap.mapping.slip`): a scan whose odometry is a few degrees or
decimetres off, beyond the correction's reach, is found again from the Hough-domain rotation
peaks and shift votes; a scan of new ground, a turn beyond the search or a shift that a
repeating place leaves open keeps its prediction."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.correction import correct_pose
from cgamap.mapping.odometry import integrate_increments, pose_increments
from cgamap.mapping.posegraph import wrap
from cgamap.mapping.segments import segments_from_scan
from cgamap.mapping.slam2d import Mapper, MapperParams, scan_poses
from cgamap.mapping.slip import SlipParams, recover, shift_votes
from synth2d import ROOM, scan, scanned_map, world

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


@pytest.mark.parametrize("off", [(0.6, -0.5, 0.0), (-0.9, 0.3, -3.0), (1.2, 0.5, 0.0),
                                 (0.3, 1.3, 10.0)])
def test_a_shift_beyond_the_correction_is_found_again(off):
    # wheels that spun, or a shove: decimetres to a metre, with or without a turn
    full, here = _room()
    pred = TRUE + [off[0], off[1], np.deg2rad(off[2])]
    P = MapperParams().correction
    corr = correct_pose(here, full.a, full.b, pred, 0.0, P)
    assert corr.matched_fraction < 0.2  # the premise: the plain correction cannot
    got = recover(here, full.a, full.b, pred, corr, P, SlipParams())
    assert got is not None
    assert np.hypot(*(got.pose[:2] - TRUE[:2])) < 0.01
    assert abs(np.rad2deg(wrap(got.pose[2] - TRUE[2]))) < 0.2
    no_shift = recover(here, full.a, full.b, pred, corr, P, SlipParams(max_shift=0.0))
    assert no_shift is None or np.hypot(*(no_shift.pose[:2] - TRUE[:2])) > 0.2


def test_no_shift_while_the_prediction_still_matches_a_fifth_of_the_scan():
    # on real scans the right pose can match under half (open doors, people, new ground)
    # while a look-alike a metre off matches more: the shift search waits for a prediction
    # that matches almost nothing
    full, here = _room()
    pred = TRUE + [1.2, 0.0, 0.0]
    P = MapperParams().correction
    corr = correct_pose(here, full.a, full.b, pred, 0.0, P)
    assert 0.2 <= corr.matched_fraction < 0.7
    assert recover(here, full.a, full.b, pred, corr, P, SlipParams()) is None
    got = recover(here, full.a, full.b, pred, corr, P, SlipParams(shift_below=0.7))
    assert got is not None and np.hypot(*(got.pose[:2] - TRUE[:2])) < 0.01


def test_shift_votes_peak_at_the_true_shift():
    full, here = _room()
    shift = np.array([0.7, -0.4])
    c, s_ = np.cos(TRUE[2]), np.sin(TRUE[2])
    R = np.array([[c, s_], [-s_, c]])
    ga, gb = here.a @ R + TRUE[:2] - shift, here.b @ R + TRUE[:2] - shift
    got = shift_votes(ga, gb, here.length, full.a, full.b, SlipParams())
    assert len(got) >= 1
    assert np.hypot(*(got[0] - shift)) < 0.05
    few = shift_votes(ga, gb, here.length, full.a, full.b, SlipParams(), max_lines=8)
    assert np.hypot(*(few[0] - shift)) < 0.05  # the longest line pairs alone suffice here
    near = shift_votes(ga, gb, here.length, full.a, full.b, SlipParams(max_shift=0.5))
    assert not len(near) or np.hypot(*(near[0] - shift)) > 0.1  # beyond the search


def test_a_shift_that_a_repeating_place_leaves_open_is_refused():
    # a corridor with a pillar every 1.2 m: moved by one period the scan fits as well, so
    # the shift is not taken
    walls = [(-20, -1.5, 20, -1.5), (-20, 1.5, 20, 1.5)]
    for x in np.arange(-20.0, 20.0, 1.2):
        walls += [(x, 1.5, x, 1.2), (x, 1.2, x + 0.3, 1.2), (x + 0.3, 1.2, x + 0.3, 1.5)]
    w = world(walls)
    true = np.array([0.1, 0.0, 0.0])
    full = scanned_map(w, [(x, 0.0, 0.0) for x in np.arange(-12.0, 12.0, 0.6)])
    here = segments_from_scan(scan(w, true, n=360, fov=np.pi, sigma=0.005, seed=1,
                                   max_range=6.0))
    ok = correct_pose(here, full.a, full.b, true, 0.0, MapperParams().correction)
    alias = correct_pose(here, full.a, full.b, true + [1.2, 0.0, 0.0], 0.0,
                         MapperParams().correction)
    # the premise: one period on, the scan fits as well
    assert abs(alias.matched_fraction - ok.matched_fraction) < 0.05
    assert np.hypot(*(alias.pose[:2] - ok.pose[:2])) > 1.0
    pred = true + [0.6, 0.6, 0.0]
    P = MapperParams().correction
    corr = correct_pose(here, full.a, full.b, pred, 0.0, P)
    assert recover(here, full.a, full.b, pred, corr, P, SlipParams()) is None


def _corridor_run(error, at: int, slip: bool | SlipParams):
    """The simulated loop's corridors, a scan every 10 cm; at step ``at`` the odometry
    reports ``error`` (dx, dy, dtheta in the robot frame) less than the robot moved."""
    w = get_world("loop")
    t = np.arange(0, 0.25 * w.path_length / w.speed, 0.1 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    inc = pose_increments(truth)
    inc[at] -= error
    odo = integrate_increments(inc, truth[0])
    MP = MapperParams()
    sp = slip if isinstance(slip, SlipParams) else replace(MP.slip, enabled=slip)
    m = Mapper(replace(MP, slip=sp), initial_pose=truth[0])
    got = []
    for k, p in enumerate(truth):
        s = scan(w, p, n=180, sigma=0.01, seed=k)
        got.append(m.step(s.ranges, s.angle_min, s.angle_increment, odo[k]))
    # every scan's pose: its node's, or tracked from its node
    X = scan_poses(m.poses, np.array([g.node for g in got]), np.array([g.offset for g in got]),
                   np.array([g.pose for g in got]))
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


@pytest.mark.parametrize("error", [(0.0, 0.5, 0.0), (0.0, -0.8, 0.05)])
def test_a_sideways_shove_in_a_corridor_does_not_stay_in_the_map(error):
    at = 20
    m, e, _ = _corridor_run(np.array(error), at, slip=True)
    assert m.slips >= 1
    assert e[at + 1:].max() < 0.05, e.max()
    _, e0, _ = _corridor_run(np.array(error), at, slip=SlipParams(max_shift=0.0))
    assert e0[at + 5:].min() > 0.3  # the premise: rotations alone cannot
