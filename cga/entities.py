"""Geometric entities of CGA and their conversions to and from Euclidean parameters.

Entities are in OPNS (outer product null space) unless the name says ``ipns``:
point pair a^b, line a^b^einf, plane a^b^c^einf, circle a^b^c, sphere a^b^c^d.
Equation numbers refer to seed 000 (the conference paper); see DESIGN.md for the fixes.
"""

from __future__ import annotations

import numpy as np

from .algebra import GRADE_MASK, Multivector, N, blade_index, e0, einf

_E1, _E2, _E3, _EP, _EM = 1, 2, 3, 4, 5
_E12, _E13, _E23 = blade_index("e12"), blade_index("e13"), blade_index("e23")


def _vec3(x) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.shape[-1:] != (3,):
        raise ValueError(f"expected (..., 3) Euclidean coordinates, got shape {x.shape}")
    return x


def euclidean(x) -> Multivector:
    """A Euclidean vector x1 e1 + x2 e2 + x3 e3 (a direction, or a normal)."""
    x = _vec3(x)
    v = np.zeros(x.shape[:-1] + (N,))
    v[..., _E1:_E3 + 1] = x
    return Multivector(v)


def up(x) -> Multivector:
    """Conformal point up(x) = x + 1/2 x^2 einf + e0 (eq. 3), for (..., 3) arrays."""
    x = _vec3(x)
    v = np.zeros(x.shape[:-1] + (N,))
    v[..., _E1:_E3 + 1] = x
    half_sq = 0.5 * np.einsum("...i,...i->...", x, x)
    # einf = e- + e+, e0 = (e- - e+)/2
    v[..., _EP] = half_sq - 0.5
    v[..., _EM] = half_sq + 0.5
    return Multivector(v, GRADE_MASK[1])


def point_weight(X: Multivector) -> np.ndarray:
    """-X.einf: 1 for a normalised conformal point (or an IPNS sphere up(c) - r^2/2 einf)."""
    return X.v[..., _EM] - X.v[..., _EP]


def down(X: Multivector) -> np.ndarray:
    """Euclidean coordinates (..., 3) of conformal points (any non-zero weight)."""
    return X.v[..., _E1:_E3 + 1] / point_weight(X)[..., None]


def point_pair(a, b) -> Multivector:
    """OPNS point pair up(a) ^ up(b): a segment's end points (seed section IV-A)."""
    return up(a) ^ up(b)


def line(a, b) -> Multivector:
    """OPNS line up(a) ^ up(b) ^ einf through a and b, directed from a to b (eq. 28)."""
    return up(a) ^ up(b) ^ einf


def line_from_point_pair(PP: Multivector) -> Multivector:
    """The line carrying a point pair: PP ^ einf (eq. 28)."""
    return PP ^ einf


def plane(a, b, c) -> Multivector:
    """OPNS plane up(a) ^ up(b) ^ up(c) ^ einf; normal along (b - a) x (c - a)."""
    return up(a) ^ up(b) ^ up(c) ^ einf


def circle(a, b, c) -> Multivector:
    """OPNS circle through three points."""
    return up(a) ^ up(b) ^ up(c)


def sphere_ipns(center, radius) -> Multivector:
    """IPNS (dual) sphere s = up(c) - 1/2 r^2 einf (a vector; s^2 = r^2)."""
    S = up(center)
    half_r2 = 0.5 * np.asarray(radius, dtype=float) ** 2
    v = S.v.copy()
    v[..., _EP] -= half_r2
    v[..., _EM] -= half_r2
    return Multivector(v, GRADE_MASK[1])


def sphere(center, radius) -> Multivector:
    """OPNS sphere (the 4-vector a^b^c^d of four points on it), oriented so that its dual
    is the IPNS sphere up(c) - 1/2 r^2 einf with positive weight."""
    return sphere_ipns(center, radius).undual()


def _as_ipns_vector(S: Multivector) -> Multivector:
    """Accept an IPNS sphere (grade 1) or an OPNS sphere (grade 4); return the vector."""
    if np.any(np.abs(S.v[..., 16:31]) > 0) and not np.any(np.abs(S.v[..., 1:6]) > 0):
        return S.dual()
    return S.grade(1)


def sphere_center_radius(S: Multivector) -> tuple[np.ndarray, np.ndarray]:
    """Centre (..., 3) and radius (...) of a real sphere given in IPNS or OPNS form.

    An imaginary sphere (negative squared radius) gives a NaN radius.
    """
    s = _as_ipns_vector(S)
    w = point_weight(s)
    s = Multivector(s.v / w[..., None])
    r2 = s.sq_norm()
    return s.v[..., _E1:_E3 + 1], np.sqrt(np.where(r2 >= 0, r2, np.nan))


def sphere_from_point_pair(PP: Multivector) -> Multivector:
    """Eq. (12): the IPNS sphere whose equator is the point pair, S = PP / (PP ^ einf).

    The pair is in OPNS form (a ^ b).  The quotient is a vector of weight -1; it is returned
    normalised to up(c) - 1/2 r^2 einf, c the segment's midpoint, r its half length.
    """
    S = (PP * (PP ^ einf).inverse()).grade(1)
    return Multivector(S.v / point_weight(S)[..., None])


def spheres_intersect(s1: Multivector, s2: Multivector) -> np.ndarray:
    """Eq. (15): the sign of (s1 ^ s2)^2 for IPNS spheres (OPNS ones are dualised first).

    -1: the spheres intersect; 0: tangent; +1: apart -- or one inside the other (DESIGN.md:
    containment also gives +1, so segment matching must test it separately).
    """
    a, b = _as_ipns_vector(s1), _as_ipns_vector(s2)
    a = Multivector(a.v / point_weight(a)[..., None])
    b = Multivector(b.v / point_weight(b)[..., None])
    sq = ((a ^ b) * (a ^ b)).scalar_part()
    # Tangency is an exact zero in exact arithmetic; rounding is relative to the size of the
    # coefficients (up(x) carries x^2/2), so the zero band scales with them.
    size = np.abs(a.v[..., 1:6]).sum(axis=-1) * np.abs(b.v[..., 1:6]).sum(axis=-1)
    return np.where(np.abs(sq) <= 1e-11 * size * size, 0, np.sign(sq)).astype(int)


# ---- lines -----------------------------------------------------------------------------------

def line_direction_moment(L: Multivector) -> tuple[np.ndarray, np.ndarray]:
    """Direction d (..., 3) and moment m = p x d (..., 3) of an OPNS line.

    For L = up(a) ^ up(b) ^ einf: d = b - a (unnormalised, keeps the line's weight) and the
    moment of a ^ b; read off the e_i ^ E and e_ij ^ einf parts, E = e0 ^ einf.
    """
    # L = (a ^ b) ^ einf + (a - b) ^ e0 ^ einf and e0 ^ einf = -e+-: d_i is the e_i+- part.
    d = np.stack([L.v[..., blade_index(f"e{i}+-")] for i in (1, 2, 3)], axis=-1)
    # a ^ b ^ einf puts m_ij on both e_ij+ and e_ij- with the same coefficient.
    m12 = L.v[..., blade_index("e12+")]
    m13 = L.v[..., blade_index("e13+")]
    m23 = L.v[..., blade_index("e23+")]
    moment = np.stack([m23, -m13, m12], axis=-1)  # bivector -> dual vector (a x b)
    return d, moment


def closest_point_to_origin(L: Multivector) -> np.ndarray:
    """Foot of the perpendicular from the origin to an OPNS line, (..., 3).

    Seed eq. (27)/(31): the projection (e0 _| L) L^-1 of the origin onto the line; read as
    a point after normalising its weight.
    """
    X = ((e0 | L) * L.inverse()).grade(1)
    return down(X)


def line_point_direction(L: Multivector) -> tuple[np.ndarray, np.ndarray]:
    """A point (the closest to the origin) and the unit direction of an OPNS line."""
    d, m = line_direction_moment(L)
    dd = np.einsum("...i,...i->...", d, d)
    p = np.cross(d, m) / dd[..., None]
    return p, d / np.sqrt(dd)[..., None]


def line_from_point_direction(p, d) -> Multivector:
    """OPNS line through p with direction d."""
    p = _vec3(p)
    return line(p, p + _vec3(d))


# ---- planes ----------------------------------------------------------------------------------

def plane_from_hesse(normal, rho) -> Multivector:
    """OPNS plane {x : n.x = rho}: the dual of the IPNS plane n + rho einf."""
    n = _vec3(normal)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    rho = np.asarray(rho, dtype=float)
    v = np.zeros(n.shape[:-1] + (N,))
    v[..., _E1:_E3 + 1] = n
    v[..., _EP] = rho
    v[..., _EM] = rho
    return Multivector(v).dual()


def plane_ipns(P: Multivector) -> Multivector:
    """IPNS form n + rho einf (unnormalised) of an OPNS plane.

    Undual (X I) rather than dual here, so that plane(a, b, c) reads with the normal
    (b - a) x (c - a) and plane_from_hesse round-trips.
    """
    return P.undual().grade(1)


def plane_to_hesse(P: Multivector, canonical: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal (..., 3) and distance rho (...) of an OPNS plane: n.x = rho.

    The orientation is the plane's own (plane(a, b, c) has n along (b-a)x(c-a)); with
    ``canonical`` the pair is flipped where needed so that rho >= 0 (DESIGN.md).
    """
    Y = plane_ipns(P)
    n = Y.v[..., _E1:_E3 + 1]
    rho = 0.5 * (Y.v[..., _EP] + Y.v[..., _EM])
    s = np.linalg.norm(n, axis=-1)
    n = n / s[..., None]
    rho = rho / s
    if canonical:
        flip = np.where(rho < 0, -1.0, 1.0)
        n = n * flip[..., None]
        rho = rho * flip
    return n, rho


def hesse_to_hough3d(normal, rho) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta, phi, rho) with n = (sin t cos p, sin t sin p, cos t), rho >= 0, theta in [0, pi],
    phi in (-pi, pi] (DESIGN.md conventions)."""
    n = _vec3(normal)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    rho = np.asarray(rho, dtype=float)
    flip = np.where(rho < 0, -1.0, 1.0)
    n = n * flip[..., None]
    rho = rho * flip
    theta = np.arccos(np.clip(n[..., 2], -1.0, 1.0))
    phi = np.arctan2(n[..., 1], n[..., 0])
    phi = np.where(phi <= -np.pi, phi + 2 * np.pi, phi)
    return theta, phi, rho


def hough3d_to_hesse(theta, phi, rho) -> tuple[np.ndarray, np.ndarray]:
    theta, phi = np.asarray(theta, dtype=float), np.asarray(phi, dtype=float)
    n = np.stack(
        [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1
    )
    return n, np.asarray(rho, dtype=float)


def plane_to_hough3d(P: Multivector):
    return hesse_to_hough3d(*plane_to_hesse(P, canonical=True))


def plane_from_hough3d(theta, phi, rho) -> Multivector:
    return plane_from_hesse(*hough3d_to_hesse(theta, phi, rho))


# ---- 2D lines (the laser plane z = 0) --------------------------------------------------------

def hough2d_from_points(a, b) -> tuple[np.ndarray, np.ndarray]:
    """(theta, rho) of the 2D line through a and b ((..., 2) or (..., 3) with z ignored):
    x cos t + y sin t = rho, rho >= 0, theta in [0, 2 pi)."""
    a = np.asarray(a, dtype=float)[..., :2]
    b = np.asarray(b, dtype=float)[..., :2]
    d = b - a
    normal_angle = np.arctan2(d[..., 0], -d[..., 1])  # normal = direction turned by -90 deg
    n = np.stack([np.cos(normal_angle), np.sin(normal_angle)], axis=-1)
    rho = np.einsum("...i,...i->...", n, a)
    theta = np.mod(np.where(rho < 0, normal_angle + np.pi, normal_angle), 2 * np.pi)
    theta = np.where(theta >= 2 * np.pi, 0.0, theta)  # mod of a tiny negative rounds to 2 pi
    return theta, np.abs(rho)


def line_to_hough2d(L: Multivector) -> tuple[np.ndarray, np.ndarray]:
    """(theta, rho) of an OPNS line lying in the plane z = 0."""
    p, d = line_point_direction(L)
    return hough2d_from_points(p, p + d)


def hough2d_to_line(theta, rho) -> Multivector:
    """OPNS line in the plane z = 0 with x cos t + y sin t = rho."""
    theta = np.asarray(theta, dtype=float)
    rho = np.asarray(rho, dtype=float)
    z = np.zeros_like(theta + rho)
    p = np.stack([rho * np.cos(theta), rho * np.sin(theta), z], axis=-1)
    d = np.stack([-np.sin(theta) + z, np.cos(theta) + z, z], axis=-1)
    return line_from_point_direction(p, d)


def angle_diff(a, b) -> np.ndarray:
    """Seed eq. (9): the wrap-aware difference a - b of angles, in (-pi, pi]."""
    d = np.mod(np.asarray(a, dtype=float) - np.asarray(b, dtype=float) + np.pi, 2 * np.pi) - np.pi
    return np.where(d == -np.pi, np.pi, d)


# ---- incidence -------------------------------------------------------------------------------

def meet(A: Multivector, B: Multivector) -> Multivector:
    """Intersection of two OPNS blades: (A* ^ B*)*, with X* = X I^-1.

    Orientation pinned by a test: the meet of the planes n1.x = 0 and n2.x = 0 is the line
    through the origin with direction n1 x n2.
    """
    return (A.dual() ^ B.dual()).dual()


def join(A: Multivector, B: Multivector) -> Multivector:
    """Span of two OPNS blades in general position (disjoint): their outer product.

    E.g. a line and a point off it give the plane through both; a degenerate pair (a point on
    the line) gives zero, which callers test with ``is_zero``.
    """
    return A ^ B


def is_zero(X: Multivector, tol: float = 1e-9) -> np.ndarray:
    return np.all(np.abs(X.v) <= tol, axis=-1)


