"""Relocalisation in the Hough domain: known poses are found from one scan; symmetric places
give several ranked hypotheses; an unrelated scan is "not found"."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.posegraph import wrap
from cgamap.mapping.relocalize import DistanceField, RelocParams, relocalize
from cgamap.mapping.segments import segments_from_scan
from synth2d import scan, scanned_map, world


@pytest.fixture(scope="module")
def loop_world():
    w = get_world("loop")
    t = np.linspace(0, w.path_length / w.speed, 60, endpoint=False)
    poses = np.column_stack(w.trajectory(t))
    return w, poses, scanned_map(w, poses)


def test_finds_known_poses(loop_world):
    w, poses, m = loop_world
    field = DistanceField(m)
    rng = np.random.default_rng(4)
    ok = 0
    picks = rng.choice(len(poses), 12, replace=False)
    for i in picks:
        p = poses[i] + [0.05, -0.04, 0.02]  # between the mapped poses
        seg = segments_from_scan(scan(w, p, n=180, sigma=0.01, seed=int(i)))
        r = relocalize(m, seg, field)
        assert r.found
        # the loop world is symmetric (a square of corridors): the true pose must be among
        # the best-scoring hypotheses, not necessarily first
        best = r.hypotheses[0].score
        assert any(np.hypot(*(h.pose[:2] - p[:2])) < 0.1
                   and abs(wrap(h.pose[2] - p[2])) < np.deg2rad(2)
                   and h.score >= best - 0.05 for h in r.hypotheses)
        ok += bool(np.hypot(*(r.pose[:2] - p[:2])) < 0.1)
    assert ok >= 4  # and it is often first


def test_symmetric_room_gives_ranked_hypotheses():
    w = world([(-4, -2, 4, -2), (4, -2, 4, 2), (4, 2, -4, 2), (-4, 2, -4, -2)])  # a box
    m = scanned_map(w, [(0.0, 0.0, 0.0)])
    p = np.array([1.0, 0.5, 0.3])
    r = relocalize(m, segments_from_scan(scan(w, p, n=720, fov=2 * np.pi)))
    assert r.found and len(r.hypotheses) >= 2
    # ranked by the soft fit (RelocParams.fit_weight), the inlier count breaking ties
    fw = RelocParams().fit_weight
    keys = [h.score + fw * h.fit for h in r.hypotheses]
    assert keys == sorted(keys, reverse=True)
    # the point-symmetric pose explains the scan as well as the true one
    mirrored = np.array([-1.0, -0.5, wrap(0.3 + np.pi)])
    near = [h for h in r.hypotheses if h.score > 0.95]
    assert any(np.hypot(*(h.pose[:2] - p[:2])) < 0.05 for h in near)
    assert any(np.hypot(*(h.pose[:2] - mirrored[:2])) < 0.05 for h in near)


def test_rivals_name_each_look_alike_place_once():
    """The box's point-symmetric pose is a rival of the best; near-duplicates of one place
    count once, and hypotheses well below the best are none."""
    from cgamap.mapping.relocalize import Hypothesis, rivals

    w = world([(-4, -2, 4, -2), (4, -2, 4, 2), (4, 2, -4, 2), (-4, 2, -4, -2)])
    m = scanned_map(w, [(0.0, 0.0, 0.0)])
    r = relocalize(m, segments_from_scan(scan(w, (1.0, 0.5, 0.3), n=720, fov=2 * np.pi)))
    best = r.hypotheses[0]
    got = rivals(r.hypotheses, best, 0.05)
    assert len(got) == 1
    assert np.hypot(*(got[0].pose[:2] + best.pose[:2])) < 0.1  # the mirror image
    h = [Hypothesis(np.array([0.0, 0.0, 0.0]), 0.9), Hypothesis(np.array([3.0, 0, 0]), 0.88),
         Hypothesis(np.array([3.1, 0, 0]), 0.87), Hypothesis(np.array([9.0, 0, 0]), 0.7)]
    assert rivals(h, h[0], 0.05) == [h[1]]
    assert rivals(h, h[0], 0.05, min_dist=0.05) == [h[1], h[2]]
    assert rivals(h, h[0], 0.01) == []


def test_a_prior_keeps_the_search_near_it():
    """``near``: only candidates within (metres, radians) of the prior are verified.  In
    the box, the point-symmetric pose fits as well as the true one; near the true pose it
    is no longer among the hypotheses."""
    w = world([(-4, -2, 4, -2), (4, -2, 4, 2), (4, 2, -4, 2), (-4, 2, -4, -2)])
    m = scanned_map(w, [(0.0, 0.0, 0.0)])
    p = np.array([1.0, 0.5, 0.3])
    seg = segments_from_scan(scan(w, p, n=720, fov=2 * np.pi))
    prior = p + [0.3, -0.2, 0.05]
    r = relocalize(m, seg, near=(prior, 1.0, 0.3))
    assert r.found and np.hypot(*(r.pose[:2] - p[:2])) < 0.05
    for h in r.hypotheses:  # ICP moves a candidate a little: within the band and a margin
        assert np.hypot(*(h.pose[:2] - prior[:2])) < 1.5
        assert abs(wrap(h.pose[2] - prior[2])) < 0.4
    far = relocalize(m, seg)
    assert any(np.hypot(*(h.pose[:2] + p[:2])) < 0.05 for h in far.hypotheses)


def test_unrelated_scan_is_not_found(loop_world):
    _, _, m = loop_world
    # a triangular room: its walls meet at 60 degrees, no pair of the map's walls does
    h = 3.0 * np.sqrt(3.0) / 2
    other = world([(-1.5, -h / 3, 1.5, -h / 3), (1.5, -h / 3, 0.0, 2 * h / 3),
                   (0.0, 2 * h / 3, -1.5, -h / 3)])
    r = relocalize(m, segments_from_scan(scan(other, (0.0, 0.0, 0.4), n=360,
                                              fov=2 * np.pi)))
    assert not r.found and r.pose is None


def test_sweep_proposes_the_true_cell():
    # an L-shaped room: the correlative sweep alone, at the true rotation, has a cell
    # within half a diagonal of the true position among its best
    from cgamap.mapping.relocalize import _sweep
    w = world([(-4, -2, 4, -2), (4, -2, 4, 0), (4, 0, 0, 0), (0, 0, 0, 3), (0, 3, -4, 3),
               (-4, 3, -4, -2)])
    m = scanned_map(w, [(0.0, 0.0, 0.0), (-2.0, 1.0, 0.0)])
    p = np.array([-1.2, -0.7, 0.4])
    seg = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi))
    P = RelocParams()
    T, R = _sweep(DistanceField(m, P.field_resolution), seg.points, np.array([p[2]]), P)
    assert len(T) == P.sweep_cells and np.allclose(R, p[2])
    assert np.min(np.hypot(*(T - p[:2]).T)) <= 0.71 * P.sweep_grid + 0.05


def test_crossing_share_tells_a_corridor_from_a_room():
    from cgamap.mapping.relocalize import crossing_share

    corridor = world([(-10, -1, 10, -1), (-10, 1, 10, 1), (2, 1, 2, 1.3), (3, 1, 3, 1.3)])
    room = world([(-4, -2, 4, -2), (4, -2, 4, 2), (4, 2, -4, 2), (-4, 2, -4, -2)])
    c = crossing_share(segments_from_scan(scan(corridor, (0.0, 0.0, 0.2))), 30.0)
    r = crossing_share(segments_from_scan(scan(room, (1.0, 0.5, 0.3), n=720,
                                               fov=2 * np.pi)), 30.0)
    assert c < 0.1 < 0.3 < r


def test_along_a_corridor_the_wall_pieces_ends_place_the_scan():
    # the simulated 150 m corridor, door recesses at irregular spacing: few line pairs
    # cross, and the position along it comes from where the wall pieces end (measured: 20
    # of 20 with the corridor's six end-point lines, 15 of 20 with one)
    w = get_world("long_corridor")
    t = np.linspace(0, 0.5 * w.path_length / w.speed, 120, endpoint=False)
    poses = np.column_stack(w.trajectory(t))
    m = scanned_map(w, poses)
    field = DistanceField(m)
    picks = np.random.default_rng(2).choice(len(poses) - 1, 20, replace=False)

    def successes(P: RelocParams) -> int:
        ok = 0
        for i in picks:
            p = 0.5 * (poses[i] + poses[i + 1])
            r = relocalize(m, segments_from_scan(scan(w, p, n=180, sigma=0.01, seed=int(i))),
                           field, P)
            ok += bool(r.found and np.hypot(*(r.pose[:2] - p[:2])) < 0.2
                       and abs(wrap(r.pose[2] - p[2])) < np.deg2rad(3))
        return ok

    with_ends, without = successes(RelocParams()), successes(RelocParams(corridor_share=0.0))
    print("corridor relocalisation:", with_ends, "vs", without, "of", len(picks))
    assert with_ends >= 18 and with_ends > without


def test_line_pair_translations_are_every_pair_that_fits():
    # the compiled solve against the same computation over the whole (n1, n2) grid in numpy,
    # in the same order (row-major), with more fits than its first buffer holds, and on a
    # big map of short segments (where the solve reads only the pairs whose boxes meet)
    from cgamap.mapping.relocalize import _on_segment, _pair_translations

    rng = np.random.default_rng(5)
    for n1, n2, span, length in ((40, 30, 10.0, 0.0), (150, 120, 1.0, 0.0),
                                 (400, 300, 50.0, 2.0)):
        ga, ha = rng.uniform(-span, span, (n1, 2)), rng.uniform(-span, span, (n2, 2))
        if length:
            gb = ga + rng.uniform(-length, length, (n1, 2))
            hb = ha + rng.uniform(-length, length, (n2, 2))
        else:
            gb, hb = rng.uniform(-span, span, (n1, 2)), rng.uniform(-span, span, (n2, 2))
        A1 = np.column_stack([-(gb - ga)[:, 1], (gb - ga)[:, 0]])
        A1 /= np.linalg.norm(A1, axis=1)[:, None]
        A2 = np.column_stack([-(hb - ha)[:, 1], (hb - ha)[:, 0]])
        A2 /= np.linalg.norm(A2, axis=1)[:, None]
        d1, d2 = np.sum(A1 * ga, 1), np.sum(A2 * ha, 1)
        la, lb, ma, mb = (rng.uniform(-0.5, 0.5, 2) for _ in range(4))
        u1, lo1, hi1 = _on_segment(ga, gb, la, lb, 0.3)
        u2, lo2, hi2 = _on_segment(ha, hb, ma, mb, 0.3)
        e1, e2 = rng.normal(size=n1), rng.normal(size=n2)
        T, D = _pair_translations(A1, A2, d1, d2, u1, lo1, hi1, u2, lo2, hi2, e1, e2, 2.0, 1.0)
        det = A1[:, None, 0] * A2[None, :, 1] - A1[:, None, 1] * A2[None, :, 0]
        ok = np.abs(det) > 0.3
        det = np.where(ok, det, 1.0)
        tx = (d1[:, None] * A2[None, :, 1] - A1[:, None, 1] * d2[None, :]) / det
        ty = (A1[:, None, 0] * d2[None, :] - d1[:, None] * A2[None, :, 0]) / det
        t1 = tx * u1[:, None, 0] + ty * u1[:, None, 1]
        t2 = tx * u2[None, :, 0] + ty * u2[None, :, 1]
        good = (ok & (lo1[:, None] < t1) & (t1 < hi1[:, None]) & (lo2[None] < t2)
                & (t2 < hi2[None]))
        assert good.sum() >= 10
        assert np.allclose(T, np.column_stack([tx[good], ty[good]]), rtol=0, atol=1e-12)
        want_d = (2.0 * e1[:, None] + 1.0 * e2[None, :]) / 3.0
        assert np.allclose(D, want_d[good], rtol=0, atol=1e-12)
        if n1 == 150:
            assert len(T) > 4096  # this case overflowed the first buffer
