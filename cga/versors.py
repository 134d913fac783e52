"""Rotors, translators and motors: rigid motions as versors of G(4,1).

Conventions (DESIGN.md, seed eqs. 4-7): R = cos(t/2) - sin(t/2) B for the unit bivector B of
the rotation plane (B = e12 turns counter-clockwise about +z); T = 1 + 1/2 einf t moves
up(x) to up(x + t); a motor is M = T R and acts by the sandwich M X ~M (eq. 7).
"""

from __future__ import annotations

import numpy as np

from .algebra import Multivector, N, blade_index, einf
from .entities import _vec3, down, euclidean, up

_E12, _E13, _E23 = blade_index("e12"), blade_index("e13"), blade_index("e23")
_E1P, _E1M = blade_index("e1+"), blade_index("e1-")
_E2P, _E2M = blade_index("e2+"), blade_index("e2-")
_PLANAR_MOTOR_MASK = np.isin(np.arange(N), [0, _E12, _E1P, _E1M, _E2P, _E2M]).tobytes()


def bivector_from_axis(axis) -> Multivector:
    """Unit bivector of the plane perpendicular to ``axis``: a1 e23 + a2 e31 + a3 e12."""
    a = _vec3(axis)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    v = np.zeros(a.shape[:-1] + (N,))
    v[..., _E23] = a[..., 0]
    v[..., _E13] = -a[..., 1]  # e31 = -e13
    v[..., _E12] = a[..., 2]
    return Multivector(v)


def rotor(axis_or_bivector, angle) -> Multivector:
    """R = cos(t/2) - sin(t/2) B (eq. 4); right-handed about the axis (counter-clockwise
    seen from its tip).  ``axis_or_bivector`` is a (..., 3) axis or a unit bivector."""
    if isinstance(axis_or_bivector, Multivector):
        B = axis_or_bivector
    else:
        B = bivector_from_axis(axis_or_bivector)
    t = np.asarray(angle, dtype=float)
    v = -np.sin(t / 2)[..., None] * B.v
    v = np.array(v, copy=True)
    v[..., 0] += np.cos(t / 2)
    return Multivector(v)


def translator(t) -> Multivector:
    """T = 1 + 1/2 einf t = 1 - 1/2 t einf (eqs. 5-6): moves up(x) to up(x + t)."""
    T = 1.0 + 0.5 * (einf * euclidean(t))
    return T


def motor(R: Multivector, T: Multivector) -> Multivector:
    """M = T R: rotate about the origin, then translate."""
    return T * R


def rotor_from_quaternion(q) -> Multivector:
    """Rotor of a unit quaternion (w, x, y, z): R = w - x e23 - y e31 - z e12."""
    q = np.asarray(q, dtype=float)
    v = np.zeros(q.shape[:-1] + (N,))
    v[..., 0] = q[..., 0]
    v[..., _E23] = -q[..., 1]
    v[..., _E13] = q[..., 2]
    v[..., _E12] = -q[..., 3]
    return Multivector(v)


def rotor_to_quaternion(R: Multivector) -> np.ndarray:
    """(w, x, y, z) of a rotor (or of a motor's rotation part), with w >= 0."""
    q = np.stack([R.v[..., 0], -R.v[..., _E23], R.v[..., _E13], -R.v[..., _E12]], axis=-1)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quaternion_from_matrix(Rm) -> np.ndarray:
    """Unit quaternions (w, x, y, z) from (..., 3, 3) rotation matrices (Shepperd's method)."""
    Rm = np.asarray(Rm, dtype=float)
    m = Rm.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=-1)
    k = np.argmax(cand, axis=-1)
    q = np.empty((m.shape[0], 4))
    for case in range(4):  # four numerically safe branches, chosen per matrix
        sel = k == case
        if not np.any(sel):
            continue
        r = m[sel]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[sel])
            q[sel] = np.stack([0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s,
                               (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s], -1)
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2])
            q[sel] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s,
                               (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s], -1)
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2])
            q[sel] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s,
                               0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s], -1)
        else:
            s = 2.0 * np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1])
            q[sel] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s,
                               (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s], -1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q.reshape(Rm.shape[:-2] + (4,))


def motor_from_pose(translation, rotation=None) -> Multivector:
    """Motor of a pose: ``translation`` (..., 3) and ``rotation`` as (..., 3, 3) matrices,
    (..., 4) quaternions (w, x, y, z) or a rotor; identity rotation if omitted."""
    t = _vec3(translation)
    if rotation is None:
        R = Multivector.scalar(np.ones(t.shape[:-1]))
    elif isinstance(rotation, Multivector):
        R = rotation
    else:
        rot = np.asarray(rotation, dtype=float)
        q = quaternion_from_matrix(rot) if rot.shape[-2:] == (3, 3) else rot
        R = rotor_from_quaternion(q)
    return motor(R, translator(t))


def motor_from_pose2d(x, y, theta) -> Multivector:
    """Motor of a planar pose (x, y, heading theta about +z), batched, in closed form.

    M = T R with R = c - s e12 and T = 1 + 1/2 einf t (c, s = cos, sin of theta/2) expands to
    M = c - s e12 - a/2 (e1+ + e1-) - b/2 (e2+ + e2-),  (a, b) = (c x + s y, c y - s x);
    a test pins it to the product of ``translator`` and ``rotor``.  One pose costs
    microseconds, which the per-scan paths of mapping rely on.
    """
    x, y, theta = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (x, y, theta)))
    c, s = np.cos(theta / 2.0), np.sin(theta / 2.0)
    a, b = c * x + s * y, c * y - s * x
    v = np.zeros(x.shape + (N,))
    v[..., 0] = c
    v[..., _E12] = -s
    v[..., _E1P] = v[..., _E1M] = -a / 2.0
    v[..., _E2P] = v[..., _E2M] = -b / 2.0
    return Multivector(v, _PLANAR_MOTOR_MASK)


def motor_from_matrix(H) -> Multivector:
    """Motor of (..., 4, 4) homogeneous rigid transforms."""
    H = np.asarray(H, dtype=float)
    return motor_from_pose(H[..., :3, 3], H[..., :3, :3])


def apply(M: Multivector, X: Multivector) -> Multivector:
    """M X ~M (eq. 7): move any entity (point, pair, line, plane, sphere, circle, versor)."""
    return M * X * M.reverse()


def _grade1_map(M: Multivector) -> np.ndarray:
    """(..., 5, 5) matrix A with (M x ~M) = x @ A for grade-1 x (the versor's linear action)."""
    basis = np.zeros((5, N))
    basis[np.arange(5), np.arange(1, 6)] = 1.0
    Mb = M.v[..., None, :]
    out = (Multivector(Mb) * Multivector(basis) * Multivector(Mb).reverse()).v
    return out[..., 1:6]


def motor_to_matrix(M: Multivector) -> np.ndarray:
    """(..., 4, 4) homogeneous matrix of a motor, from its action on e1, e2, e3 and e0."""
    A = _grade1_map(M)  # rows: images of e1, e2, e3, e+, e-
    H = np.zeros(M.shape + (4, 4))
    H[..., :3, :3] = np.swapaxes(A[..., :3, :3], -1, -2)
    img_e0 = 0.5 * (A[..., 4, :] - A[..., 3, :])  # image of e0 = (e- - e+)/2 is up(t)
    w = img_e0[..., 4] - img_e0[..., 3]
    H[..., :3, 3] = img_e0[..., :3] / w[..., None]
    H[..., 3, 3] = 1.0
    return H


def apply_points(M: Multivector, x) -> np.ndarray:
    """Fast path: move many Euclidean points (..., 3) by one motor (or a batch that
    broadcasts).  The sandwich is evaluated once on the basis to get the motor's affine
    action, which is then applied to all points with one matrix product."""
    x = _vec3(x)
    H = motor_to_matrix(M)
    if H.ndim == 2:
        return x @ H[:3, :3].T + H[:3, 3]
    return np.einsum("...ij,...j->...i", H[..., :3, :3], x) + H[..., :3, 3]


def apply_points_sandwich(M: Multivector, x, block: int = 1024) -> np.ndarray:
    """General path: up(x), the full sandwich M X ~M of geometric products, down.

    Evaluated in blocks of points so that the 32-coefficient temporaries stay in cache.
    """
    x = _vec3(x)
    if M.v.ndim > 1:
        return down(apply(M, up(x)))
    flat = x.reshape(-1, 3)
    out = np.empty_like(flat)
    Mr = M.reverse()
    for lo in range(0, flat.shape[0], block):
        out[lo:lo + block] = down(M * up(flat[lo:lo + block]) * Mr)
    return out.reshape(x.shape)


def motor_to_pose2d(M: Multivector) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, theta) of a motor that turns about z (the planar robot pose), read off its
    coefficients: the inverse of :func:`motor_from_pose2d` (any positive scale of M)."""
    v = M.v
    c, s = v[..., 0], -v[..., _E12]
    n = np.hypot(c, s)
    c, s = c / n, s / n
    a, b = -2.0 * v[..., _E1P] / n, -2.0 * v[..., _E2P] / n
    return c * a - s * b, s * a + c * b, 2.0 * np.arctan2(s, c)


def normalize_motor(M: Multivector) -> Multivector:
    """Rescale a motor so that M ~M = 1 (drift control after long compositions)."""
    s = (M * M.reverse()).scalar_part()
    return Multivector(M.v / np.sqrt(s)[..., None])
