"""Raw-point scan-to-scan ICP and the agreement figures built on it."""

from __future__ import annotations

import numpy as np
from cgamap.mapping.evaluation import icp_agreement
from cgamap.mapping.odometry import relative
from cgamap.mapping.scan_icp import icp, scan_points
from synth2d import ROOM, scan, world

WALLS = [*ROOM, (0.5, 0.2, 1.0, 0.2), (1.0, 0.2, 1.0, 0.7)]


def _pts(pose, seed=0, sigma=0.005):
    s = scan(world(WALLS), pose, n=360, fov=2 * np.pi, sigma=sigma, seed=seed)
    return scan_points(s.ranges, s.angle_min, s.angle_increment)


def test_recovers_a_known_motion():
    p0, p1 = np.array([0.0, 0.0, 0.1]), np.array([0.4, -0.3, 0.25])
    truth = relative(p0, p1)
    guess = truth + np.array([0.1, -0.05, np.deg2rad(2.0)])
    got = icp(_pts(p1, 1), _pts(p0, 2), guess)
    assert got is not None
    assert np.hypot(*(got - truth)[:2]) < 0.005
    assert abs(np.degrees(got[2] - truth[2])) < 0.1


def test_normals_only_on_flat_runs():
    sp = _pts([0.0, 0.0, 0.0], sigma=0.0)
    # a room: most points lie on walls, the corners have no normal
    assert 0.8 < sp.has_normal.mean() < 1.0
    n = sp.normals[sp.has_normal]
    axis = np.minimum(np.abs(n[:, 0]), np.abs(n[:, 1]))  # the walls are axis-aligned
    assert np.median(axis) < 0.01


def test_too_few_points_is_none():
    few = scan_points(np.full(10, 2.0), -0.5, 0.1)
    assert icp(few, _pts([0.0, 0.0, 0.0]), np.zeros(3)) is None


def test_agreement_tells_the_true_trajectory_from_a_jittered_one():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    truth = np.column_stack([0.5 + 2.0 * np.cos(t), 0.5 + 1.5 * np.sin(t), t])
    scans = [scan(world(WALLS), p, n=360, fov=2 * np.pi, sigma=0.005, seed=k)
             for k, p in enumerate(truth)]
    jitter = truth + np.column_stack([rng.normal(0, 0.03, (12, 2)),
                                      rng.normal(0, np.deg2rad(1.0), 12)])
    out = icp_agreement(scans, {"truth": truth, "jittered": jitter}, jitter)
    assert out["truth"]["pairs"] == 11
    assert out["truth"]["trans_median_m"] < 0.005 and out["truth"]["rot_median_deg"] < 0.1
    assert out["jittered"]["trans_median_m"] > 0.02 and out["jittered"]["rot_median_deg"] > 0.5
    assert out["icp_both_ways"]["trans_median_m"] < 0.002
    # a long run is sampled: pairs evenly spread, the same figures' kind
    few = icp_agreement(scans, {"truth": truth, "jittered": jitter}, jitter, max_pairs=5)
    assert few["truth"]["pairs"] == 5 and few["jittered"]["trans_median_m"] > 0.02


def test_revisit_pairs_and_their_agreement():
    # two laps of the same circle, 12 scans a lap: each second-lap scan revisits its twin of
    # the first lap (12 scans earlier), within 0.5 m and 45 deg; a map that closed the loop with
    # its second lap shifted 10 cm agrees with ICP at those pairs 10 cm worse than the truth
    from cgamap.mapping.evaluation import revisit_pairs

    t = np.linspace(0, 4 * np.pi, 24, endpoint=False)
    truth = np.column_stack([0.5 + 2.0 * np.cos(t), 0.5 + 1.5 * np.sin(t), t % (2 * np.pi)])
    truth[12:, :2] += 0.05            # the second lap a little off the first: no twin at 0 m
    pairs = revisit_pairs(truth, min_gap=6, radius=0.5)
    assert pairs.tolist() == [[k, k + 12] for k in range(12)]
    assert len(revisit_pairs(truth, min_gap=13, radius=0.5)) == 0
    assert len(revisit_pairs(truth, min_gap=6, radius=0.01)) == 0
    scans = [scan(world(WALLS), p, n=360, fov=2 * np.pi, sigma=0.005, seed=k)
             for k, p in enumerate(truth)]
    shifted = truth.copy()
    shifted[12:, 0] += 0.10
    out = icp_agreement(scans, {"truth": truth, "shifted": shifted}, truth, pairs=pairs)
    assert out["truth"]["pairs"] == 12 and out["truth"]["trans_median_m"] < 0.005
    assert abs(out["shifted"]["trans_median_m"] - 0.10) < 0.01


def test_the_compiled_icp_is_the_numpy_one():
    """The kernel (grid instead of k-d tree, loops instead of arrays) against the numpy
    steps: the same pose to rounding, from guesses off by centimetres and degrees, and the
    same refusals."""
    from cgamap.mapping.scan_icp import icp_numpy

    rng = np.random.default_rng(5)
    worst, both = 0.0, 0
    for k in range(30):
        p0 = np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(-np.pi, np.pi)])
        p1 = p0 + np.array([*rng.normal(0, 0.3, 2), rng.normal(0, 0.2)])
        a, b = _pts(p0, 2 * k), _pts(p1, 2 * k + 1)
        guess = relative(p0, p1) + rng.normal(0, [0.08, 0.08, 0.04])
        got, ref = icp(b, a, guess), icp_numpy(b, a, guess)
        assert (got is None) == (ref is None)
        if got is not None:
            both += 1
            worst = max(worst, float(np.abs(got - ref).max()))
    assert both >= 25 and worst < 1e-9
    few = scan_points(np.full(30, 2.0), -0.5, 0.01)   # a flat stub: pairs, but too few
    for f in (icp, icp_numpy):
        assert f(few, _pts([0.0, 0.0, 0.0]), np.zeros(3)) is None
