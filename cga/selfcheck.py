"""Identities of the algebra checked on random inputs, for ``cgamap selfcheck``.

Each check returns the largest error it saw; a check passes when that is below its
tolerance.  The test-suite checks the same identities with hypothesis; this module lets an
installed copy (on the robot) prove its own arithmetic.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from . import (
    Multivector,
    angle_diff,
    apply,
    apply_points,
    apply_points_sandwich,
    camera_chain,
    closest_point_to_origin,
    down,
    einf,
    laser_chain,
    line,
    line_point_direction,
    meet,
    motor_from_matrix,
    motor_from_pose,
    motor_from_pose2d,
    motor_to_matrix,
    plane,
    plane_from_hesse,
    plane_to_hesse,
    point_pair,
    rotor,
    sphere_center_radius,
    sphere_from_point_pair,
    sphere_ipns,
    spheres_intersect,
    translator,
    up,
)


def random_rotation(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def random_pose_matrix(rng: np.random.Generator, n: int, scale: float = 3.0) -> np.ndarray:
    H = np.zeros((n, 4, 4))
    H[:, :3, :3] = random_rotation(rng, n)
    H[:, :3, 3] = rng.uniform(-scale, scale, size=(n, 3))
    H[:, 3, 3] = 1.0
    return H


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def homogeneous(Rm: np.ndarray | None = None, t=None) -> np.ndarray:
    H = np.eye(4)
    if Rm is not None:
        H[:3, :3] = Rm
    if t is not None:
        H[:3, 3] = t
    return H


def _transform(H: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", H[..., :3, :3], x) + H[..., :3, 3]


def check_up_down(rng) -> float:
    x = rng.uniform(-10, 10, size=(200, 3))
    X = up(x)
    return max(np.abs(down(X) - x).max(), np.abs((X * X).scalar_part()).max())


def check_translator(rng) -> float:
    x, t = rng.uniform(-5, 5, size=(2, 200, 3))
    return np.abs(down(apply(translator(t), up(x))) - (x + t)).max()


def check_rotor_ccw(rng) -> float:
    a = rng.uniform(-np.pi, np.pi, size=50)
    p = down(apply(rotor(np.array([0.0, 0.0, 1.0]), a), up(np.array([1.0, 0.0, 0.0]))))
    return np.abs(p[:, :2] - np.stack([np.cos(a), np.sin(a)], -1)).max()


def check_motor_matrix_points(rng) -> float:
    H = random_pose_matrix(rng, 100)
    M = motor_from_matrix(H)
    x = rng.uniform(-5, 5, size=(100, 3))
    e1 = np.abs(apply_points_sandwich(M, x) - _transform(H, x)).max()
    e2 = np.abs(apply_points(M, x) - _transform(H, x)).max()
    e3 = np.abs(motor_to_matrix(M) - H).max()
    return max(e1, e2, e3)


def check_motor_matrix_lines_planes(rng) -> float:
    H = random_pose_matrix(rng, 100)
    M = motor_from_matrix(H)
    a, b, c = rng.uniform(-5, 5, size=(3, 100, 3))
    moved_line = apply(M, line(a, b))
    expect_line = line(_transform(H, a), _transform(H, b))
    p1, d1 = line_point_direction(moved_line)
    p2, d2 = line_point_direction(expect_line)
    moved_plane = apply(M, plane(a, b, c))
    n1, r1 = plane_to_hesse(moved_plane)
    n2, r2 = plane_to_hesse(plane(_transform(H, a), _transform(H, b), _transform(H, c)))
    return max(np.abs(p1 - p2).max(), np.abs(d1 - d2).max(), np.abs(n1 - n2).max(),
               np.abs(r1 - r2).max())


def check_meet_planes(rng) -> float:
    n1, n2 = rng.normal(size=(2, 100, 3))
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 /= np.linalg.norm(n2, axis=1, keepdims=True)
    r1, r2 = rng.uniform(0, 3, size=(2, 100))
    L = meet(plane_from_hesse(n1, r1), plane_from_hesse(n2, r2))
    p, d = line_point_direction(L)
    cross = np.cross(n1, n2)
    cross /= np.linalg.norm(cross, axis=1, keepdims=True)
    on1 = np.abs(np.einsum("ij,ij->i", p, n1) - r1).max()
    on2 = np.abs(np.einsum("ij,ij->i", p, n2) - r2).max()
    return max(np.abs(d - cross).max(), on1, on2)


def check_sphere_from_pair(rng) -> float:
    a, b = rng.uniform(-5, 5, size=(2, 100, 3))
    c, r = sphere_center_radius(sphere_from_point_pair(point_pair(a, b)))
    return max(np.abs(c - (a + b) / 2).max(),
               np.abs(r - np.linalg.norm(b - a, axis=1) / 2).max())


def check_sphere_cases(rng) -> float:
    c1 = rng.uniform(-5, 5, size=(100, 3))
    u = rng.normal(size=(100, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r1, r2 = rng.uniform(0.5, 2, size=(2, 100))
    s1 = sphere_ipns(c1, r1)
    bad = 0
    for dist, expect in (((r1 + r2) * 0.9, -1), (r1 + r2, 0), ((r1 + r2) * 1.2, 1)):
        got = spheres_intersect(s1, sphere_ipns(c1 + u * dist[:, None], r2))
        bad += int(np.sum(got != expect))
    inside = spheres_intersect(sphere_ipns(c1, r1 + r2), sphere_ipns(c1 + 0.1 * u * r2[:, None],
                                                                     r2 * 0.5))
    bad += int(np.sum(inside != 1))
    return float(bad)


def check_closest_point(rng) -> float:
    a, b = rng.uniform(-5, 5, size=(2, 100, 3))
    d = b - a
    foot = a - (np.einsum("ij,ij->i", a, d) / np.einsum("ij,ij->i", d, d))[:, None] * d
    return np.abs(closest_point_to_origin(line(a, b)) - foot).max()


def check_laser_chain(rng) -> float:
    pose = rng.uniform(-5, 5, size=(50, 3))
    mount = random_pose_matrix(rng, 50, scale=0.5)
    M = laser_chain(motor_from_pose2d(pose[:, 0], pose[:, 1], pose[:, 2]), motor_from_matrix(mount))
    H = np.stack([homogeneous(rot_z(p[2]), [p[0], p[1], 0.0]) for p in pose]) @ mount
    x = rng.uniform(-5, 5, size=(50, 3))
    return max(np.abs(apply_points_sandwich(M, x) - _transform(H, x)).max(),
               np.abs(motor_to_matrix(M) - H).max())


def check_camera_chain(rng) -> float:
    worst = 0.0
    for _ in range(20):
        x, y, th, pan, tilt = rng.uniform(-3, 3, size=5)
        t_axis, t_eye = rng.uniform(-0.5, 0.5, size=(2, 3))
        R_pos = rotor(np.array([0.0, 0.0, 1.0]), th)
        R_pan = rotor(np.array([0.0, 0.0, 1.0]), pan)
        R_tilt = rotor(np.array([0.0, 1.0, 0.0]), tilt)
        M = camera_chain(translator(np.array([x, y, 0.0])), R_pos, R_pan, R_tilt, t_axis, t_eye)
        c, s = np.cos(tilt), np.sin(tilt)
        Ry = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        H = (homogeneous(rot_z(th), [x, y, 0.0]) @ homogeneous(t=t_axis)
             @ homogeneous(rot_z(pan)) @ homogeneous(Ry) @ homogeneous(t=t_eye))
        pts = rng.uniform(-3, 3, size=(20, 3))
        worst = max(worst, np.abs(apply_points_sandwich(M, pts) - _transform(H, pts)).max())
    return worst


def check_products(rng) -> float:
    A, B, C = (Multivector(rng.normal(size=(50, 32))) for _ in range(3))
    assoc = np.abs(((A * B) * C).v - (A * (B * C)).v).max()
    a, b = (Multivector.from_vector(rng.normal(size=(50, 5))) for _ in range(2))
    inner = (a * b + b * a) * 0.5  # symmetric part of two vectors is their inner product
    expect = (a | b).v[..., 0]
    wedge = (a * b - b * a) * 0.5
    return max(assoc, np.abs(inner.v[..., 0] - expect).max(),
               np.abs(inner.v[..., 1:]).max(), np.abs(wedge.v - (a ^ b).v).max(),
               np.abs((einf * einf).v).max())


def check_angle_diff(rng) -> float:
    a, b = rng.uniform(-10, 10, size=(2, 500))
    d = angle_diff(a, b)
    return max(np.abs(np.sin(d) - np.sin(a - b)).max(), np.abs(np.cos(d) - np.cos(a - b)).max(),
               float(np.any(d <= -np.pi) or np.any(d > np.pi)))


def check_pose_roundtrip(rng) -> float:
    H = random_pose_matrix(rng, 50)
    q_motor = motor_from_pose(H[:, :3, 3], H[:, :3, :3])
    return np.abs(motor_to_matrix(q_motor) - H).max()


CHECKS: list[tuple[str, Callable, float]] = [
    ("products: associativity, a.b, a^b, einf^2 = 0", check_products, 1e-9),
    ("up/down round trip, points are null", check_up_down, 1e-9),
    ("translator moves up(x) to up(x+t) (eqs. 5-6)", check_translator, 1e-9),
    ("rotor about +z is counter-clockwise (eq. 4)", check_rotor_ccw, 1e-12),
    ("motor = 4x4 matrix on points (eq. 7, fast path)", check_motor_matrix_points, 1e-9),
    ("motor = 4x4 matrix on lines and planes", check_motor_matrix_lines_planes, 1e-8),
    ("pose <-> motor <-> matrix round trip", check_pose_roundtrip, 1e-9),
    ("meet of two planes is their line", check_meet_planes, 1e-8),
    ("sphere of a point pair (eq. 12)", check_sphere_from_pair, 1e-9),
    ("sphere test cases (eq. 15), count of wrong", check_sphere_cases, 0.5),
    ("closest point to origin (eq. 27)", check_closest_point, 1e-8),
    ("wrap-aware angle difference (eq. 9)", check_angle_diff, 1e-12),
    ("laser chain M_GB M_BL = matrix chain", check_laser_chain, 1e-9),
    ("camera chain (eqs. 17-22) = matrix chain", check_camera_chain, 1e-9),
]


def run(seed: int = 0) -> list[tuple[str, bool, float]]:
    """Run every check; returns (name, passed, worst error)."""
    rng = np.random.default_rng(seed)
    results = []
    for name, fn, tol in CHECKS:
        try:
            err = float(fn(rng))
            results.append((name, bool(err <= tol), err))
        except Exception as exc:  # a crash in a check is a failure, reported, not raised
            results.append((f"{name} ({type(exc).__name__}: {exc})", False, float("nan")))
    return results
