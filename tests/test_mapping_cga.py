"""CGA segments: point pairs moved by the laser chain, lines, spheres (eq. 12), eq. 15."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.cga import (
    hough2d_from_points,
    motor_to_matrix,
    sphere_ipns,
    spheres_intersect,
)
from cgamap.mapping.cga_segments import (
    cga_segments,
    laser_motor,
    pair_endpoints,
    segments_to_global,
    sphere_centre_radius_2d,
)
from cgamap.mapping.matching import match_candidates, sphere_relation, sphere_vectors
from cgamap.mapping.segments import Segments
from hypothesis import given, settings
from hypothesis import strategies as st


def _segs(a, b) -> Segments:
    a, b = np.asarray(a, float), np.asarray(b, float)
    k = len(a)
    return Segments(a, b, np.full(k, 10), np.zeros(k), 0.5 * (a + b), np.zeros((k, 2, 2)),
                    np.zeros((k, 2, 2)))


def _homog(pose, mount):
    def H(p):
        c, s = np.cos(p[2]), np.sin(p[2])
        return np.array([[c, -s, p[0]], [s, c, p[1]], [0, 0, 1]])
    return H(pose) @ H(mount)


coord = st.floats(-5, 5)


@settings(max_examples=30, deadline=None)
@given(st.tuples(coord, coord, st.floats(-3.1, 3.1)), st.tuples(st.floats(-0.5, 0.5),
       st.floats(-0.5, 0.5), st.floats(-3.1, 3.1)))
def test_laser_chain_matches_homogeneous_matrices(pose, mount):
    seg = _segs([[1.0, 0.5], [-2.0, 3.0]], [[2.0, -1.0], [0.5, 4.0]])
    M = laser_motor(pose, mount)
    H = _homog(pose, mount)
    exp_a = seg.a @ H[:2, :2].T + H[:2, 2]
    exp_b = seg.b @ H[:2, :2].T + H[:2, 2]
    # sandwich on the point pairs
    cg = cga_segments(seg, M)
    pa, pb = pair_endpoints(cg.pairs)
    assert np.allclose(pa, exp_a, atol=1e-9) and np.allclose(pb, exp_b, atol=1e-9)
    # the fast path the mapper uses
    g = segments_to_global(seg, M)
    assert np.allclose(g.a, exp_a, atol=1e-9) and np.allclose(g.b, exp_b, atol=1e-9)
    assert np.allclose(motor_to_matrix(M)[:2, :2], H[:2, :2], atol=1e-9)


def test_sphere_eq12_is_midpoint_and_half_length():
    seg = _segs([[0.0, 0.0], [1.0, 1.0]], [[4.0, 0.0], [1.0, 3.0]])
    c, r = sphere_centre_radius_2d(cga_segments(seg).spheres)
    assert np.allclose(c, [[2, 0], [1, 2]]) and np.allclose(r, [2, 1])


def test_hough_of_line_matches_points():
    seg = _segs([[1.0, -1.0]], [[1.0, 2.0]])
    cg = cga_segments(seg)
    th, rho = hough2d_from_points(seg.a, seg.b)
    assert cg.theta == pytest.approx(th) and cg.rho == pytest.approx(rho)
    assert cg.rho[0] == pytest.approx(1.0) and cg.theta[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("c2, r2, sign", [
    ((1.5, 0.0), 1.0, -1),    # intersect
    ((2.0, 0.0), 1.0, 0),     # tangent
    ((3.0, 0.0), 1.0, 1),     # apart
    ((0.2, 0.0), 0.3, 1),     # inside: eq. 15 says "apart" too
])
def test_eq15_closed_form_matches_cga(c2, r2, sign):
    s1 = sphere_vectors(np.array([[-1.0, 0.0]]), np.array([[1.0, 0.0]]))
    a = np.array(c2) - [r2, 0.0]
    b = np.array(c2) + [r2, 0.0]
    s2 = sphere_vectors(a[None], b[None])
    q = sphere_relation(s1, s2)[0, 0]
    ref = spheres_intersect(sphere_ipns([0.0, 0, 0], 1.0), sphere_ipns([*c2, 0.0], r2))
    assert int(ref) == sign
    assert (0 if abs(q) < 1e-12 else int(np.sign(q))) == sign


def test_the_candidate_test_is_eq15_or_containment():
    # match_index decides by the centre distance (d <= r1 + r2); on random segments that
    # must be exactly eq. 15's sign (<= 0) or containment, from the sphere coefficients
    rng = np.random.default_rng(7)
    a1, b1 = rng.uniform(-3, 3, (40, 2)), rng.uniform(-3, 3, (40, 2))
    a2, b2 = rng.uniform(-3, 3, (50, 2)), rng.uniform(-3, 3, (50, 2))
    margin = 0.2
    ok, _ = match_candidates(a1, b1, a2, b2, np.pi / 2, 100.0, margin=margin)
    q = sphere_relation(sphere_vectors(a1, b1, margin), sphere_vectors(a2, b2, margin))
    r1 = 0.5 * np.linalg.norm(b1 - a1, axis=1)[:, None] + margin
    r2 = 0.5 * np.linalg.norm(b2 - a2, axis=1)[None, :] + margin
    d = np.linalg.norm(0.5 * (a1 + b1)[:, None] - 0.5 * (a2 + b2)[None], axis=-1)
    expect = (q <= 1e-9) | (d <= np.abs(r1 - r2))
    assert 0 < expect.sum() < expect.size and np.array_equal(ok, expect)


def test_containment_is_a_candidate():
    # a short observed piece of a long wall: its sphere lies inside the wall's sphere
    ok, _ = match_candidates(np.array([[1.0, 0.02]]), np.array([[2.0, 0.02]]),
                             np.array([[-5.0, 0.0]]), np.array([[5.0, 0.0]]),
                             np.deg2rad(5), 0.1, margin=0.0)
    assert ok[0, 0]
    # same piece, but off the wall or turned: no candidate
    ok, _ = match_candidates(np.array([[1.0, 0.5]]), np.array([[2.0, 0.5]]),
                             np.array([[-5.0, 0.0]]), np.array([[5.0, 0.0]]),
                             np.deg2rad(5), 0.1, margin=0.0)
    assert not ok[0, 0]
    ok, _ = match_candidates(np.array([[1.0, 0.0]]), np.array([[2.0, 0.3]]),
                             np.array([[-5.0, 0.0]]), np.array([[5.0, 0.0]]),
                             np.deg2rad(5), 0.5, margin=0.0)
    assert not ok[0, 0]
    # far along the same line (spheres apart): no candidate
    ok, _ = match_candidates(np.array([[9.0, 0.0]]), np.array([[10.0, 0.0]]),
                             np.array([[-5.0, 0.0]]), np.array([[5.0, 0.0]]),
                             np.deg2rad(5), 0.1, margin=0.3)
    assert not ok[0, 0]


@settings(max_examples=30, deadline=None)
@given(coord, coord, st.floats(-3.14, 3.14))
def test_laser_motor_is_the_cga_motor(x, y, th):
    from cgamap.cga import motor_from_pose2d, motor_to_pose2d
    from cgamap.mapping.cga_segments import laser_motor

    M = laser_motor((x, y, th))
    assert np.allclose(M.v, motor_from_pose2d(x, y, th).v, atol=1e-12)
    px, py, pth = (float(v) for v in motor_to_pose2d(M))
    assert (px, py) == pytest.approx((x, y), abs=1e-9)
    assert abs(np.angle(np.exp(1j * (pth - th)))) < 1e-9
