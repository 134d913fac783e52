"""Point-based verification of relocalisation hypotheses: the nearest-segment field, the
batched point-to-segment ICP, the free-space crossing count, the ranking, and the
all-rotation sweep for cluttered scans -- on hand-made maps with known answers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cgamap.mapping.linemap import LineMap
from cgamap.mapping.posegraph import wrap
from cgamap.mapping.relocalize import (
    DistanceField,
    Hypothesis,
    RelocParams,
    _crossings,
    _icp,
    _ranked,
    relocalize,
)
from cgamap.mapping.segments import Segments, segments_from_scan
from synth2d import ROOM, scan, scanned_map, world


def _segment_map(walls) -> LineMap:
    """A map holding exactly the given walls (x1, y1, x2, y2)."""
    w = np.asarray(walls, float)
    return LineMap(a=w[:, :2].copy(), b=w[:, 2:].copy(), n_pts=np.full(len(w), 10.0),
                   n_obs=np.full(len(w), 3))


def _pose_err(a, b) -> tuple[float, float]:
    return float(np.hypot(*(np.asarray(a)[:2] - np.asarray(b)[:2]))), float(
        np.degrees(abs(wrap(a[2] - b[2]))))


def test_nearest_names_the_segment_and_its_exact_distances():
    m = _segment_map([(0, 0, 4, 0), (5, 1, 5, 4)])
    f = DistanceField(m, 0.05)
    x = np.array([1.0, 2.0, 4.8, 4.5, 5.3])
    y = np.array([0.3, -0.2, 2.0, -0.5, 4.5])
    sid, e, dseg, ok = f.nearest(x, y)
    assert ok.all()
    assert sid.tolist() == [0, 0, 1, 0, 1]
    # signed distance to the line: exact, not quantised to the 5 cm grid
    assert e[0] == pytest.approx(0.3, abs=1e-9) and e[1] == pytest.approx(-0.2, abs=1e-9)
    assert abs(e[2]) == pytest.approx(0.2, abs=1e-9)
    # beyond a segment's end the distance is to the end point, not to the line
    assert dseg[3] == pytest.approx(np.hypot(0.5, 0.5), abs=1e-9)
    assert e[3] == pytest.approx(-0.5, abs=1e-9)
    assert dseg[4] == pytest.approx(np.hypot(0.3, 0.5), abs=1e-9)
    # off the grid: flagged, and counted as far
    _, _, d_off, ok_off = f.nearest(np.array([100.0]), np.array([0.0]))
    assert not ok_off[0] and d_off[0] >= f.far


def test_icp_pulls_many_starts_onto_the_true_pose():
    w = world(ROOM)
    m = _segment_map(ROOM)
    f = DistanceField(m, 0.05)
    p = np.array([0.7, 0.4, 0.3])
    pts = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi, sigma=0.005, seed=3)).points
    rng = np.random.default_rng(0)
    starts = p + np.column_stack([rng.uniform(-0.25, 0.25, (8, 2)),
                                  rng.uniform(-0.08, 0.08, 8)])
    out = _icp(f, pts, starts, RelocParams().icp_gates + RelocParams().final_gates)
    assert out.shape == starts.shape
    for q in out:
        et, er = _pose_err(q, p)
        assert et < 0.01 and er < 0.2


def test_icp_fixes_the_position_along_a_corridor_by_its_end():
    # a corridor closed at one end: the side walls fix y and theta only; the end wall's
    # points and the side walls' ends fix x
    walls = [(-8, -1, 2, -1), (-8, 1, 2, 1), (2, -1, 2, 1)]
    w, m = world(walls), _segment_map(walls)
    p = np.array([-1.0, 0.1, 0.05])
    pts = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi, max_range=6.0)).points
    P = RelocParams()
    out = _icp(DistanceField(m, 0.05), pts, (p + [0.3, 0.0, 0.0])[None],
               P.icp_gates + P.final_gates)
    assert _pose_err(out[0], p)[0] < 0.02


def test_crossings_count_beams_through_walls_not_grazing_ones():
    walls = [(-5, -3, 5, -3), (5, -3, 5, 3), (5, 3, -5, 3), (-5, 3, -5, -3), (0, -1, 0, 1)]
    w, m = world(walls), _segment_map(walls)
    f = DistanceField(m, 0.05)
    P = RelocParams()
    p = np.array([-2.5, 0.0, 0.0])   # facing the free-standing wall at x = 0
    pts = segments_from_scan(scan(w, p, n=180)).points
    # at the true pose no beam passes through a wall, though beams near the room's
    # corners graze the side walls
    assert _crossings(f, pts, p[None], P)[0] == 0.0
    # moved so the beams that ended on the free-standing wall now end behind it and the
    # others cross nothing: only the shifted beams that pass x = 0 count
    moved = p + [2.0, 0.0, 0.0]
    c = _crossings(f, pts, np.stack([p, moved]), P)
    assert c[0] == 0.0 and 0.1 < c[1] < 0.9


def test_ranking_prefers_fit_less_crossings_and_merges_duplicates():
    P = RelocParams()
    a = Hypothesis(np.array([0.0, 0.0, 0.0]), 0.95, 0.90, 0.0)
    b = Hypothesis(np.array([5.0, 0.0, 0.0]), 0.95, 0.92, 0.5)   # fits, but through walls
    c = Hypothesis(np.array([0.03, 0.0, 0.005]), 0.95, 0.89, 0.0)  # a again
    r = _ranked([b, c, a], P)
    assert r.found and r.pose is a.pose and len(r.hypotheses) == 2
    # the loop closer ranks by the inlier fraction alone (fit_weight 0)
    r0 = _ranked([a, Hypothesis(np.array([5.0, 0.0, 0.0]), 0.97, 0.5, 0.9)],
                 replace(P, fit_weight=0.0))
    assert r0.pose[0] == 5.0
    assert not _ranked([Hypothesis(np.zeros(3), 0.3, 0.3, 0.0)], P).found


def test_two_identical_rooms_are_told_apart_by_free_space():
    # two equal rooms side by side; the right one has a free-standing wall the scan (taken
    # in the left one) would pass through: the points fit both rooms, free space only one
    room = [(0, 0, 6, 0), (6, 0, 6, 4), (6, 4, 0, 4), (0, 4, 0, 0)]
    right = [(x1 + 10, y1, x2 + 10, y2) for x1, y1, x2, y2 in room]
    w = world(room)
    m = _segment_map(room + right + [(13, 1.5, 13, 2.5)])
    p = np.array([1.5, 2.0, 0.0])
    r = relocalize(m, segments_from_scan(scan(w, p, n=360, fov=2 * np.pi)))
    assert r.found
    et, er = _pose_err(r.pose, p)
    assert et < 0.05 and er < 0.5
    twin = [h for h in r.hypotheses if _pose_err(h.pose, p + [10, 0, 0])[0] < 0.1]
    assert twin and twin[0].crossing > r.hypotheses[0].crossing


def test_single_line_scan_is_placed_by_its_points():
    # only one segment survives (the others are dropped); the sweep places the points
    w = world(ROOM)
    m = scanned_map(w, [(0.0, 0.0, 0.0), (2.0, 1.0, 0.0)])
    p = np.array([1.0, 0.5, 0.4])
    seg = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi))
    one = seg.subset(np.argsort(-seg.length)[:1])
    r = relocalize(m, one)
    assert r.found
    # the room has a point symmetry only if it is centred: it is not, so the best wins
    et, er = _pose_err(r.pose, p)
    assert et < 0.05 and er < 0.5
    # without the sweep a single line is "not found" (the loop closer's setting)
    assert not relocalize(m, one, None, replace(RelocParams(), sweep_cells=0)).found


def test_cluttered_scan_found_by_the_all_rotation_sweep():
    # the scan's only segment is clutter at an odd angle (a cabinet, not in the map), so
    # the line pairing proposes wrong rotations; the room's walls are only points
    w = world(ROOM)
    m = _segment_map(ROOM)
    p = np.array([-0.5, 0.8, 1.1])
    full = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi, sigma=0.005, seed=1))
    t = np.linspace(0, 1, 12)[:, None]
    a, b = np.array([0.6, 0.2]), np.array([1.0, 0.75])       # laser frame, ~0.7 m
    clutter = a + t * (b - a)
    pts = np.concatenate([full.points[::2], clutter])
    seg = Segments(a[None], b[None], np.array([12]), np.array([0.0]), (0.5 * (a + b))[None],
                   np.zeros((1, 2, 2)), np.zeros((1, 2, 2)), pts)
    P = RelocParams()
    r = relocalize(m, seg, None, P)
    assert r.found
    et, er = _pose_err(r.pose, p)
    assert et < 0.05 and er < 0.5
    # the fallback is what found it: without it the line pairing's rotations miss
    r_off = relocalize(m, seg, None, replace(P, fallback_fit=0.0))
    assert not r_off.found or _pose_err(r_off.pose, p)[1] > 2.0
