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
    from cgamap.mapping.sweep import correlative_sweep
    w = world([(-4, -2, 4, -2), (4, -2, 4, 0), (4, 0, 0, 0), (0, 0, 0, 3), (0, 3, -4, 3),
               (-4, 3, -4, -2)])
    m = scanned_map(w, [(0.0, 0.0, 0.0), (-2.0, 1.0, 0.0)])
    p = np.array([-1.2, -0.7, 0.4])
    seg = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi))
    P = RelocParams()
    T, R = correlative_sweep(DistanceField(m, P.field_resolution), seg.points, np.array([p[2]]), P)
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


def _line_candidates_numpy(ga, gb, n_g, c_g, phi_g, len_g, ra, rb, n_l, c_l, phi_l, len_l, s,
                           tol, map_share, slack, min_ang, n_end):
    """The same candidates computed over whole grids in numpy: every (map segment, map
    segment) pair of every two scan lines solved, then filtered, in row-major order."""
    from cgamap.mapping.odometry import wrap_angle

    delta = wrap_angle(2 * (phi_g[:, None] - phi_l[None, :])) / 2
    pair = (np.abs(delta) < tol) & (len_g[:, None] > map_share * len_l[None, :] - 0.3)
    sgn = np.sign(n_g @ n_l.T)

    def on_segment(g, la, lb):
        d = gb[g] - ga[g]
        L = np.linalg.norm(d, axis=-1)
        u = d / np.maximum(L, 1e-9)[:, None]
        t1, t2 = np.sum((la - ga[g]) * u, -1), np.sum((lb - ga[g]) * u, -1)
        return u, -slack - np.maximum(t1, t2), L + slack - np.minimum(t1, t2)

    k = len(ra)
    on = {}
    for i in range(k):
        g = np.nonzero(pair[:, i])[0]
        if len(g):
            on[i] = (g, c_g[g] - s * sgn[g, i] * c_l[i], *on_segment(g, s * ra[i], s * rb[i]))
    T, D = [np.zeros((0, 2))], [np.zeros(0)]
    for i1 in range(k):
        for i2 in range(i1 + 1, k):
            if (abs(wrap_angle(2 * (phi_l[i1] - phi_l[i2]))) / 2 < min_ang or i1 not in on
                    or i2 not in on):
                continue
            (g1, d1, u1, lo1, hi1), (g2, d2, u2, lo2, hi2) = on[i1], on[i2]
            A1, A2 = n_g[g1], n_g[g2]
            det = A1[:, None, 0] * A2[None, :, 1] - A1[:, None, 1] * A2[None, :, 0]
            ok = np.abs(det) > 0.3
            det = np.where(ok, det, 1.0)
            tx = (d1[:, None] * A2[None, :, 1] - A1[:, None, 1] * d2[None, :]) / det
            ty = (A1[:, None, 0] * d2[None, :] - d1[:, None] * A2[None, :, 0]) / det
            t1 = tx * u1[:, None, 0] + ty * u1[:, None, 1]
            t2 = tx * u2[None, :, 0] + ty * u2[None, :, 1]
            good = (ok & (lo1[:, None] < t1) & (t1 < hi1[:, None]) & (lo2[None] < t2)
                    & (t2 < hi2[None]))
            T.append(np.column_stack([tx[good], ty[good]]))
            w1, w2 = len_l[i1], len_l[i2]
            D.append(((w1 * delta[g1, i1][:, None] + w2 * delta[g2, i2][None]) / (w1 + w2))[good])
    F, E = [np.zeros((0, 2))], [np.zeros(0)]
    for i1 in range(min(n_end, k)):
        if i1 not in on:
            continue
        g, d = on[i1][:2]
        v = np.column_stack([-n_g[g, 1], n_g[g, 0]])
        for q in (ga[g], gb[g]):
            for p in (ra[i1], rb[i1]):
                F.append(d[:, None] * n_g[g] + (np.sum(q * v, -1) - s * (v @ p))[:, None] * v)
                E.append(delta[g, i1])
    return (np.concatenate(T), np.concatenate(D), np.concatenate(F), np.concatenate(E))


def test_line_candidates_are_every_pair_that_fits_and_every_end():
    # the compiled candidates of one rotation hypothesis against the same computation over
    # whole grids in numpy, in the same order, for both twins: on random maps (long and short
    # segments), and on a dense one whose pairs overflow the first buffer (sweep and prune,
    # the buffer's growth)
    from cgamap.mapping.line_hypotheses import line_candidates
    from cgamap.mapping.matching import line_angles, line_normals

    rng = np.random.default_rng(5)
    for case in range(4):
        if case < 3:
            n, span, length = ((300, 10.0, 0.0), (900, 50.0, 2.0), (400, 5.0, 6.0))[case]
            ga = rng.uniform(-span, span, (n, 2))
            gb = (ga + rng.uniform(-length, length, (n, 2)) if length
                  else rng.uniform(-span, span, (n, 2)))
            sa = rng.uniform(-4, 4, (6, 2))
            sb = sa + rng.uniform(-3, 3, (6, 2))
        else:   # 200 walls along x and 200 along y, a scan of one of each
            y = rng.uniform(-1, 1, 200)
            ga = np.concatenate([np.column_stack([y - 5, y]), np.column_stack([y, y - 5])])
            gb = np.concatenate([np.column_stack([y + 5, y]), np.column_stack([y, y + 5])])
            sa, sb = np.array([[-1.0, 0.2], [0.3, -1.0]]), np.array([[1.0, 0.2], [0.3, 1.0]])
        n_g, c_g = line_normals(ga, gb)
        phi_g, len_g = line_angles(ga, gb), np.linalg.norm(gb - ga, axis=-1)
        n_l, c_l = line_normals(sa, sb)
        phi_l, len_l = line_angles(sa, sb), np.linalg.norm(sb - sa, axis=-1)
        tol = np.radians(20.0 if case < 3 else 3.0)
        for s in (1.0, -1.0):
            args = (ga, gb, n_g, c_g, phi_g, len_g, sa, sb, n_l, c_l, phi_l, len_l, s, tol,
                    0.5, 0.3, np.radians(30.0), 3)
            got, want = line_candidates(*args), _line_candidates_numpy(*args)
            for a, b in zip(got, want, strict=True):
                assert a.shape == b.shape and np.allclose(a, b, rtol=0, atol=1e-9)
            assert len(got[0]) >= 10 and len(got[2]) >= 10
            if case == 3:
                assert len(got[0]) > 1024     # more than the first buffer holds


def test_the_pair_solves_sort_and_search_are_numpys():
    # the compiled merge sort and binary search that the sweep and prune uses, against numpy
    # (stable order, ties included; values below, between, on and above the sorted ones)
    from cgamap.mapping.jit import stable_argsort
    from cgamap.mapping.line_hypotheses import _first_at_least

    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 7, 100, 1001):
        x = rng.integers(0, 20, n).astype(float)
        assert np.array_equal(stable_argsort(x), np.argsort(x, kind="stable"))
        xi = rng.integers(-5, 5, n)
        assert np.array_equal(stable_argsort(xi), np.argsort(xi, kind="stable"))
        x[::5] = np.nan                                   # NaNs last, as numpy puts them
        assert np.array_equal(stable_argsort(x), np.argsort(x, kind="stable"))
        xs = np.sort(x)
        for v in (-1.0, 0.0, 5.0, 5.5, 19.0, 30.0):
            assert _first_at_least(xs, v) == np.searchsorted(xs, v)
