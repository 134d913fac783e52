"""The G(4,1) core: every identity of the foundation issue on random inputs (hypothesis)."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap import cga
from cgamap.cga import (
    BLADE_NAMES,
    Multivector,
    angle_diff,
    apply,
    apply_points,
    apply_points_sandwich,
    camera_chain,
    circle,
    closest_point_to_origin,
    down,
    e0,
    e1,
    e2,
    einf,
    em,
    ep,
    hesse_to_hough3d,
    hough2d_from_points,
    hough2d_to_line,
    hough3d_to_hesse,
    join,
    laser_chain,
    line,
    line_point_direction,
    line_to_hough2d,
    meet,
    motor_from_matrix,
    motor_from_pose,
    motor_from_pose2d,
    motor_to_matrix,
    motor_to_pose2d,
    plane,
    plane_from_hesse,
    plane_from_hough3d,
    plane_to_hesse,
    plane_to_hough3d,
    point_pair,
    rotor,
    rotor_to_quaternion,
    sphere,
    sphere_center_radius,
    sphere_from_point_pair,
    sphere_ipns,
    spheres_intersect,
    translator,
    up,
)
from cgamap.cga.selfcheck import homogeneous, random_pose_matrix, rot_z
from cgamap.cga.selfcheck import run as selfcheck_run
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

coord = st.floats(-20, 20, allow_nan=False, allow_infinity=False)
vec3 = arrays(np.float64, 3, elements=coord)
points = arrays(np.float64, (8, 3), elements=coord)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
seeds = st.integers(0, 2**32 - 1)


def transform(H, x):
    return x @ H[:3, :3].T + H[:3, 3]


def test_basis_and_signature():
    assert (e1 * e1).allclose(1) and (ep * ep).allclose(1) and (em * em).allclose(-1)
    assert (e0 * e0).allclose(0) and (einf * einf).allclose(0)
    assert (e0 | einf).allclose(-1)
    assert (e1 * e2).allclose(-(e2 * e1))
    assert (cga.I * cga.I).allclose(-1)
    assert len(BLADE_NAMES) == 32 and BLADE_NAMES[0] == "1" and BLADE_NAMES[-1] == "e123+-"


def test_grade_reverse_dual_inverse():
    rng = np.random.default_rng(1)
    X = Multivector(rng.normal(size=(10, 32)))
    assert np.allclose(sum(X.grade(k).v for k in range(6)), X.v)
    assert np.allclose((X * X.inverse()).v, Multivector.scalar(np.ones(10)).v, atol=1e-8)
    assert np.allclose(X.dual().undual().v, X.v)
    A, B = Multivector(rng.normal(size=(2, 32)))
    assert (~(A * B)).allclose(~B * ~A)
    # batch against single operand agrees with the element-wise product
    single = X[3]
    assert np.allclose((X * single).v[5], (X[5] * single).v)
    assert np.allclose((single * X).v[5], (single * X[5]).v)


@given(points)
def test_up_down_round_trip_and_null(x):
    X = up(x)
    assert np.allclose(down(X), x, atol=1e-9 * (1 + np.abs(x).max()))
    assert np.allclose((X * X).v, 0, atol=1e-9 * (1 + (x**2).sum(axis=1).max()))
    assert np.allclose(down(X * 3.5), x, atol=1e-9 * (1 + np.abs(x).max()))


@given(points, vec3)
def test_translator_moves_points(x, t):
    moved = down(apply(translator(t), up(x)))
    assert np.allclose(moved, x + t, atol=1e-8 * (1 + np.abs(x).max() + np.abs(t).max()) ** 2)


def test_translator_sign_pinned():
    # DESIGN.md: T = 1 + 1/2 einf t = 1 - 1/2 t einf moves up(x) to up(x + t).
    t = np.array([1.0, 2.0, 3.0])
    T = translator(t)
    assert T.allclose(1.0 - 0.5 * (cga.euclidean(t) * einf))
    assert np.allclose(down(apply(T, up(np.zeros(3)))), t)


def test_rotor_sign_pinned():
    # R = cos(t/2) - sin(t/2) e12 turns counter-clockwise about +z.
    R = rotor(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    assert R.allclose(np.cos(np.pi / 4) - np.sin(np.pi / 4) * (e1 * e2))
    assert np.allclose(down(apply(R, up(np.array([1.0, 0.0, 0.0])))), [0, 1, 0], atol=1e-12)
    Rx = rotor(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # y -> z
    assert np.allclose(down(apply(Rx, up(np.array([0.0, 1.0, 0.0])))), [0, 0, 1], atol=1e-12)


@settings(max_examples=50)
@given(seeds)
def test_motor_equals_matrix_on_points_lines_planes(seed):
    rng = np.random.default_rng(seed)
    H = random_pose_matrix(rng, 1)[0]
    M = motor_from_matrix(H)
    assert np.allclose(motor_to_matrix(M), H, atol=1e-9)
    a, b, c = rng.uniform(-5, 5, size=(3, 3))
    x = rng.uniform(-5, 5, size=(50, 3))
    assert np.allclose(apply_points(M, x), transform(H, x), atol=1e-9)
    assert np.allclose(apply_points_sandwich(M, x), transform(H, x), atol=1e-9)
    p1, d1 = line_point_direction(apply(M, line(a, b)))
    p2, d2 = line_point_direction(line(transform(H, a), transform(H, b)))
    assert np.allclose(p1, p2, atol=1e-8) and np.allclose(d1, d2, atol=1e-9)
    n1, r1 = plane_to_hesse(apply(M, plane(a, b, c)))
    n2, r2 = plane_to_hesse(plane(transform(H, a), transform(H, b), transform(H, c)))
    assert np.allclose(n1, n2, atol=1e-8) and np.isclose(r1, r2, atol=1e-8)
    # a point pair and a sphere move with their points
    cs, rs = sphere_center_radius(apply(M, sphere(a, 1.5)))
    assert np.allclose(cs, transform(H, a), atol=1e-8) and np.isclose(rs, 1.5)
    pp = apply(M, point_pair(a, b))
    assert np.allclose(sphere_center_radius(sphere_from_point_pair(pp))[0],
                       transform(H, (a + b) / 2), atol=1e-8)


def test_motor_batch_and_pose2d():
    rng = np.random.default_rng(3)
    pose = rng.uniform(-4, 4, size=(20, 3))
    M = motor_from_pose2d(pose[:, 0], pose[:, 1], pose[:, 2])
    x, y, th = motor_to_pose2d(M)
    assert np.allclose(x, pose[:, 0]) and np.allclose(y, pose[:, 1])
    assert np.allclose(angle_diff(th, pose[:, 2]), 0, atol=1e-12)
    H = random_pose_matrix(rng, 20)
    Q = rotor_to_quaternion(motor_from_matrix(H))
    assert np.allclose(motor_to_matrix(motor_from_pose(H[:, :3, 3], Q)), H, atol=1e-9)


@given(arrays(np.float64, 3, elements=st.floats(-1, 1)), arrays(np.float64, 3,
       elements=st.floats(-1, 1)), st.floats(-3, 3), st.floats(-3, 3))
def test_meet_of_two_planes_is_their_line(n1, n2, r1, r2):
    c = np.cross(n1, n2)
    if np.linalg.norm(n1) < 0.1 or np.linalg.norm(n2) < 0.1 or np.linalg.norm(c) < 0.05 * \
            np.linalg.norm(n1) * np.linalg.norm(n2):
        return
    n1u, n2u = n1 / np.linalg.norm(n1), n2 / np.linalg.norm(n2)
    p, d = line_point_direction(meet(plane_from_hesse(n1, r1), plane_from_hesse(n2, r2)))
    assert np.isclose(p @ n1u, r1, atol=1e-7) and np.isclose(p @ n2u, r2, atol=1e-7)
    cu = np.cross(n1u, n2u)
    assert np.allclose(d, cu / np.linalg.norm(cu), atol=1e-7)  # orientation pinned: n1 x n2


def test_meet_orientation_pinned_and_join():
    z0 = plane_from_hesse(np.array([0.0, 0.0, 1.0]), 0.0)
    x0 = plane_from_hesse(np.array([1.0, 0.0, 0.0]), 0.0)
    p, d = line_point_direction(meet(z0, x0))
    assert np.allclose(d, [0, 1, 0]) and np.allclose(p, 0)
    # join of a line and a point off it is the plane through them
    L = line(np.array([0.0, 0, 0]), np.array([1.0, 0, 0]))
    P = join(L, up(np.array([0.0, 1.0, 0.0])))
    n, rho = plane_to_hesse(P)
    assert np.allclose(np.abs(n), [0, 0, 1]) and np.isclose(rho, 0)
    # meet of a line and a plane is a flat point on both
    F = meet(line(np.array([0.0, 0, -1]), np.array([0.0, 0, 1])), z0)
    assert F.grades() == {2}


def test_plane_constructors_agree():
    a, b, c = np.array([0.0, 0, 1]), np.array([1.0, 0, 1]), np.array([0.0, 1, 1])
    n, rho = plane_to_hesse(plane(a, b, c), canonical=False)
    assert np.allclose(n, [0, 0, 1]) and np.isclose(rho, 1)  # normal along (b-a)x(c-a)
    n2, rho2 = plane_to_hesse(plane_from_hesse(np.array([0.0, 0, -2]), -1.0), canonical=False)
    assert np.allclose(n2, [0, 0, -1]) and np.isclose(rho2, -1)
    n3, rho3 = plane_to_hesse(plane_from_hesse(np.array([0.0, 0, -2]), -1.0))  # canonical
    assert np.allclose(n3, [0, 0, 1]) and np.isclose(rho3, 1)


@given(st.floats(0, np.pi), st.floats(-np.pi + 1e-6, np.pi), st.floats(0, 10))
def test_hough3d_round_trip(theta, phi, rho):
    n, r = hough3d_to_hesse(theta, phi, rho)
    t2, p2, r2 = hesse_to_hough3d(n, r)
    assert np.isclose(t2, theta, atol=1e-7) and np.isclose(r2, rho)
    if 1e-6 < theta < np.pi - 1e-6:
        assert np.isclose(angle_diff(p2, phi), 0, atol=1e-7)
    t3, p3, r3 = plane_to_hough3d(plane_from_hough3d(theta, phi, rho))
    assert np.allclose(hough3d_to_hesse(t3, p3, r3)[0], n, atol=1e-7) or rho < 1e-9


def test_hough3d_conventions():
    theta, phi, rho = hesse_to_hough3d(np.array([0.0, -1.0, 0.0]), -2.0)  # flipped to rho >= 0
    assert np.isclose(theta, np.pi / 2) and np.isclose(phi, np.pi / 2) and np.isclose(rho, 2)
    theta, phi, rho = hesse_to_hough3d(np.array([-1.0, 0.0, 0.0]), 1.0)
    assert np.isclose(phi, np.pi)  # phi in (-pi, pi]


@given(vec3, vec3)
def test_sphere_from_point_pair_eq12(a, b):
    if np.linalg.norm(a - b) < 1e-3:
        return
    S = sphere_from_point_pair(point_pair(a, b))
    assert S.grades(1e-9 * (1 + np.abs(S.v).max())) <= {1}
    c, r = sphere_center_radius(S)
    scale = 1 + np.abs(a).max() + np.abs(b).max()
    assert np.allclose(c, (a + b) / 2, atol=1e-8 * scale**2)
    assert np.isclose(r, np.linalg.norm(a - b) / 2, atol=1e-7 * scale**2)


@pytest.mark.parametrize("form", ["ipns", "opns"])
def test_sphere_intersection_cases_eq15(form):
    make = sphere_ipns if form == "ipns" else sphere
    c = np.array([1.0, -2.0, 0.5])
    u = np.array([0.6, 0.8, 0.0])
    s1 = make(c, 1.0)
    assert spheres_intersect(s1, make(c + 2.5 * u, 2.0)) == -1  # intersecting
    assert spheres_intersect(s1, make(c + 3.0 * u, 2.0)) == 0  # tangent
    assert spheres_intersect(s1, make(c + 3.5 * u, 2.0)) == 1  # apart
    assert spheres_intersect(make(c, 3.0), make(c + 0.5 * u, 1.0)) == 1  # one inside the other


@given(vec3, vec3)
def test_closest_point_to_origin_eq27(a, b):
    d = b - a
    if np.linalg.norm(d) < 1e-2:
        return
    foot = a - (a @ d) / (d @ d) * d
    scale = 1 + np.abs(a).max() + np.abs(b).max()
    assert np.allclose(closest_point_to_origin(line(a, b)), foot, atol=1e-7 * scale**2)
    p, _ = line_point_direction(line(a, b))
    assert np.allclose(p, foot, atol=1e-7 * scale**2)


@given(arrays(np.float64, 2, elements=st.floats(-10, 10)),
       arrays(np.float64, 2, elements=st.floats(-10, 10)))
def test_hough2d_conventions(a, b):
    if np.linalg.norm(a - b) < 1e-3:
        return
    theta, rho = hough2d_from_points(a, b)
    assert 0 <= theta < 2 * np.pi and rho >= 0
    n = np.array([np.cos(theta), np.sin(theta)])
    assert np.isclose(n @ a, rho, atol=1e-7) and np.isclose(n @ b, rho, atol=1e-7)
    L = line(np.r_[a, 0.0], np.r_[b, 0.0])
    t2, r2 = line_to_hough2d(L)
    assert np.isclose(r2, rho, atol=1e-7)
    if rho > 1e-6:
        assert np.isclose(angle_diff(t2, theta), 0, atol=1e-7)
    t3, r3 = line_to_hough2d(hough2d_to_line(theta, rho))
    assert np.isclose(r3, rho, atol=1e-7)


def test_angle_diff_eq9():
    assert np.isclose(angle_diff(0.1, 2 * np.pi - 0.1), 0.2)
    assert np.isclose(angle_diff(2 * np.pi - 0.1, 0.1), -0.2)
    assert np.isclose(angle_diff(np.pi, -np.pi), 0)


@settings(max_examples=30)
@given(seeds)
def test_laser_chain_equals_matrix_chain(seed):
    rng = np.random.default_rng(seed)
    x, y, th = rng.uniform(-5, 5, size=3)
    mount = random_pose_matrix(rng, 1, scale=0.5)[0]
    M = laser_chain(motor_from_pose2d(x, y, th), motor_from_matrix(mount))
    H = homogeneous(rot_z(th), [x, y, 0.0]) @ mount
    pts = rng.uniform(-5, 5, size=(30, 3))
    assert np.allclose(apply_points_sandwich(M, pts), transform(H, pts), atol=1e-9)
    # a laser segment as a point pair reaches the global frame with its end points
    pp = apply(M, point_pair(pts[0], pts[1]))
    c, r = sphere_center_radius(sphere_from_point_pair(pp))
    assert np.allclose(c, transform(H, (pts[0] + pts[1]) / 2), atol=1e-8)


@settings(max_examples=30)
@given(seeds)
def test_camera_chain_equals_matrix_chain(seed):
    rng = np.random.default_rng(seed)
    x, y, th, pan, tilt = rng.uniform(-3, 3, size=5)
    t_axis, t_eye = rng.uniform(-0.5, 0.5, size=(2, 3))
    z, yax = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])
    R_eye_m = random_pose_matrix(rng, 1)[0][:3, :3]
    M = camera_chain(translator(np.array([x, y, 0.0])), rotor(z, th), rotor(z, pan),
                     rotor(yax, tilt), t_axis, t_eye, R_eye=motor_from_pose(np.zeros(3), R_eye_m))
    c, s = np.cos(tilt), np.sin(tilt)
    Ry = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    H = (homogeneous(rot_z(th), [x, y, 0.0]) @ homogeneous(t=t_axis) @ homogeneous(rot_z(pan))
         @ homogeneous(Ry) @ homogeneous(t=t_eye) @ homogeneous(R_eye_m))
    pts = rng.uniform(-3, 3, size=(30, 3))
    assert np.allclose(apply_points_sandwich(M, pts), transform(H, pts), atol=1e-9)
    assert np.allclose(motor_to_matrix(M), H, atol=1e-9)


def test_circle_and_entities_grades():
    a, b, c = np.eye(3)
    assert circle(a, b, c).grades() == {3}
    assert line(a, b).grades() == {3}
    assert plane(a, b, c).grades() == {4}
    assert point_pair(a, b).grades() == {2}
    assert sphere(a, 1.0).grades() == {4}


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError, match="32 coefficients"):
        Multivector(np.zeros(5))
    with pytest.raises(ValueError, match="3\\) Euclidean"):
        up(np.zeros((4, 2)))
    with pytest.raises(TypeError):
        _ = e1 * "x"


def test_selfcheck_all_pass():
    results = selfcheck_run(seed=7)
    assert all(ok for _, ok, _ in results), [r for r in results if not r[1]]


def test_cli_selfcheck_and_version(capsys):
    from cgamap.daemon.cli import main

    assert main(["selfcheck"]) == 0
    out = capsys.readouterr().out
    assert "14/14 identities pass" in out
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert "cgamap" in capsys.readouterr().out


@settings(max_examples=50)
@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-10, 10))
def test_planar_motor_closed_form_equals_translator_rotor(x, y, th):
    general = translator(np.array([x, y, 0.0])) * rotor(np.array([0.0, 0.0, 1.0]), th)
    assert np.allclose(motor_from_pose2d(x, y, th).v, general.v, atol=1e-12)
    x2, y2, th2 = motor_to_pose2d(general * 3.0)  # any positive scale reads the same pose
    assert np.isclose(x2, x, atol=1e-9) and np.isclose(y2, y, atol=1e-9)
    assert np.isclose(angle_diff(th2, th), 0, atol=1e-12)
