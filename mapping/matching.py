"""Candidate pairs between segment sets: sphere test (eq. 15) + containment + (theta, rho).

Each segment is the IPNS sphere whose equator is its point pair (eq. 12): centre the
midpoint, radius half the length.  For two such vectors s1, s2 the seed's test (eq. 15) is the
sign of (s1 ^ s2)^2 = (s1 . s2)^2 - s1^2 s2^2, evaluated here on the five vector coefficients
with the G(4,1) metric (a closed form of the same product, exact for vectors):
< 0 the spheres intersect, = 0 tangent, > 0 apart *or one inside the other* (DESIGN.md), so
containment (centre distance <= |r1 - r2|) is accepted as a candidate too.  Spheres are
enlarged by a margin so that nearby pieces of one wall (and small pose errors) still meet.

Closeness in (theta, rho): the lines' undirected angle difference (eq. 9's wrap-aware
difference taken modulo pi, tested through |sin| of the angle between the directions, which
needs no wrapping) and the distance of the observed segment's end points from the map line
(the rho difference measured where the segment is, which unlike the raw rho difference does
not grow with the distance from the origin).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .jit import kernel

_METRIC = np.array([1.0, 1.0, 1.0, 1.0, -1.0])  # e1, e2, e3, e+, e-


def sphere_vectors(a: np.ndarray, b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(k, 5) IPNS sphere coefficients (e1, e2, e3, e+, e-) of segments a-b, eq. (12),
    radius enlarged by ``margin``: s = up(c) - 1/2 r^2 einf."""
    c = 0.5 * (a + b)
    r = 0.5 * np.linalg.norm(b - a, axis=-1) + margin
    half = 0.5 * (np.sum(c * c, axis=-1) - r * r)
    # up(c) = c + half_sq einf + e0, einf = e- + e+, e0 = (e- - e+)/2
    return np.column_stack([c, np.zeros(len(c)), half - 0.5, half + 0.5])


def ipns_inner(s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """Pairwise inner products (k1, k2) of grade-1 G(4,1) coefficient vectors."""
    return (s1 * _METRIC) @ s2.T


def sphere_relation(s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """Eq. (15) for all pairs: (s1 ^ s2)^2 = (s1.s2)^2 - s1^2 s2^2, shape (k1, k2)."""
    d12 = ipns_inner(s1, s2)
    n1 = np.sum(s1 * s1 * _METRIC, axis=-1)
    n2 = np.sum(s2 * s2 * _METRIC, axis=-1)
    return d12 ** 2 - n1[:, None] * n2[None, :]


def segment_distances(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (len(p), len(a)) of 2D points p to segments a->b."""
    d = b - a
    t = np.clip(np.einsum("pk,sk->ps", p, d) - np.einsum("sk,sk->s", a, d),
                0, None) / np.maximum(np.einsum("sk,sk->s", d, d), 1e-18)
    t = np.minimum(t, 1.0)
    q = a[None] + t[..., None] * d[None]
    return np.linalg.norm(p[:, None, :] - q, axis=-1)


def line_normals(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals n (..., k, 2) and offsets c (..., k) with n.x = c on the line a-b."""
    d = b - a
    d = d / np.maximum(np.hypot(d[..., 0], d[..., 1]), 1e-12)[..., None]
    n = np.stack([-d[..., 1], d[..., 0]], axis=-1)
    return n, n[..., 0] * a[..., 0] + n[..., 1] * a[..., 1]


def line_angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Undirected direction angles of segments a-b in [0, pi) (a line's (theta, rho) angle
    up to the normal's sign)."""
    return np.mod(np.arctan2(b[..., 1] - a[..., 1], b[..., 0] - a[..., 0]), np.pi)


def near_box(centre: np.ndarray, half: np.ndarray, a: np.ndarray, b: np.ndarray,
             reach) -> np.ndarray:
    """Indices of the segments (centres, half lengths) that may reach segments a-b: centre
    within ``reach`` (scalar or per segment) plus the half length of the bounding box of
    a-b.  A cheap first cut before the eq. (15) sphere test."""
    lo = np.minimum(a, b).min(axis=0)
    hi = np.maximum(a, b).max(axis=0)
    pad = (np.asarray(reach, dtype=float) + half)[..., None]
    return np.nonzero(np.all((centre >= lo - pad) & (centre <= hi + pad), axis=1))[0]


def near_segments(map_a: np.ndarray, map_b: np.ndarray, a: np.ndarray, b: np.ndarray,
                  reach: float) -> np.ndarray:
    """:func:`near_box` for map segments given by their end points (their centres and half
    lengths computed on the way, in the same arithmetic): one compiled pass over the map
    instead of a dozen array calls over it, on every scan."""
    f = np.ascontiguousarray
    if not len(a) or not len(map_a):
        return np.zeros(0, np.int64)
    return _near_segments(f(map_a, dtype=float), f(map_b, dtype=float), f(a, dtype=float),
                          f(b, dtype=float), float(reach))


@kernel
def _near_segments(ma, mb, a, b, reach):
    lo_x = hi_x = a[0, 0]
    lo_y = hi_y = a[0, 1]
    for p in (a, b):
        for i in range(len(p)):
            lo_x, hi_x = min(lo_x, p[i, 0]), max(hi_x, p[i, 0])
            lo_y, hi_y = min(lo_y, p[i, 1]), max(hi_y, p[i, 1])
    out = np.empty(len(ma), np.int64)
    n = 0
    for j in range(len(ma)):
        dx, dy = mb[j, 0] - ma[j, 0], mb[j, 1] - ma[j, 1]
        pad = reach + 0.5 * math.sqrt(dx * dx + dy * dy)
        cx, cy = 0.5 * (ma[j, 0] + mb[j, 0]), 0.5 * (ma[j, 1] + mb[j, 1])
        if lo_x - pad <= cx <= hi_x + pad and lo_y - pad <= cy <= hi_y + pad:
            out[n] = j
            n += 1
    return out[:n]


@dataclass
class LineIndex:
    """Per-segment quantities of a fixed segment set (the map side of a match), computed
    once and reused across the correction's iterations.  Arrays may carry leading batch
    axes (one segment set per batch element, see :func:`match_index`)."""

    a: np.ndarray
    b: np.ndarray
    centre: np.ndarray
    half: np.ndarray     # half lengths (the eq. 12 sphere radii)
    n: np.ndarray        # unit normals
    c: np.ndarray        # offsets: n . x = c

    @classmethod
    def of(cls, a: np.ndarray, b: np.ndarray) -> LineIndex:
        n, c = line_normals(a, b)
        d = b - a
        return cls(a, b, 0.5 * (a + b), 0.5 * np.hypot(d[..., 0], d[..., 1]), n, c)

    def subset(self, idx) -> LineIndex:
        return LineIndex(self.a[idx], self.b[idx], self.centre[idx], self.half[idx],
                         self.n[idx], self.c[idx])


def match_candidates(a1: np.ndarray, b1: np.ndarray, a2: np.ndarray, b2: np.ndarray,
                     max_angle: float, max_dist: float,
                     margin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Candidate matrix (k1, k2) and its cost (mean |end point distance| + angle term).

    A pair is a candidate when the spheres meet (eq. 15 or containment, enlarged by
    ``margin``, default ``max_dist``), the lines' angle differs by less than ``max_angle``, and
    both end points of segment 1 lie within ``max_dist`` of line 2.
    """
    return match_index(a1, b1, LineIndex.of(a2, b2), max_angle, max_dist, margin)


def match_index(a1: np.ndarray, b1: np.ndarray, idx: LineIndex, max_angle: float,
                max_dist: float, margin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`match_candidates` against a prepared :class:`LineIndex`.

    Batched: with a1, b1 (..., k1, 2) and an index over (..., k2) segments the result is
    (..., k1, k2), each batch element matched only against its own segment set."""
    margin = max_dist if margin is None else margin
    k1, k2 = a1.shape[-2], idx.a.shape[-2]
    batch = (() if a1.ndim == 2 and idx.a.ndim == 2  # one problem (most calls)
             else np.broadcast_shapes(a1.shape[:-2], idx.a.shape[:-2]))
    if k1 == 0 or k2 == 0:
        return np.zeros(batch + (k1, k2), bool), np.zeros(batch + (k1, k2))

    def flat(v, tail):  # (..., *tail) -> (B, *tail), contiguous float64
        if (isinstance(v, np.ndarray) and v.dtype == np.float64 and v.shape == batch + tail
                and v.flags.c_contiguous):
            return v.reshape((-1,) + tail)  # already so (most calls): no copies to make
        v = np.broadcast_to(np.asarray(v, dtype=float), batch + tail)
        return np.ascontiguousarray(v.reshape((-1,) + tail))

    cost = _match_costs(flat(a1, (k1, 2)), flat(b1, (k1, 2)), flat(idx.centre, (k2, 2)),
                        flat(idx.half, (k2,)), flat(idx.n, (k2, 2)), flat(idx.c, (k2,)),
                        math.sin(max_angle), float(max_dist), float(margin))
    cost = cost.reshape(batch + (k1, k2))
    return np.isfinite(cost), cost


@kernel
def pair_cost(ax: float, ay: float, bx: float, by: float, length: float, cx: float,
              cy: float, half: float, nx: float, ny: float, c: float, sin_max: float,
              max_dist: float, margin: float) -> float:
    """The match test of observed segment a-b (``length`` long) against map segment
    (centre c, half length ``half``, line n . x = c): its cost (mean |end point distance|
    plus the |sin| of the angle between the lines, halved), inf when it is no candidate.

    Eq. (15) through the inner products of the normalised IPNS sphere vectors
    s_i = up(c_i) - r_i^2/2 einf: s_i . s_i = r_i^2 and s1 . s2 = (r1^2 + r2^2 - d^2) / 2
    (d the centre distance), so (s1 ^ s2)^2 = (s1 . s2)^2 - r1^2 r2^2 <= 0 exactly when
    (r1 - r2)^2 <= d^2 <= (r1 + r2)^2; with containment (d <= |r1 - r2|) accepted too, the
    candidates are d <= r1 + r2, both radii enlarged by ``margin`` (:func:`sphere_relation`
    is the coefficient form, pinned against ``cga.spheres_intersect`` and this by tests).
    The end points' signed distances from the line differ by length * |sin| of the
    undirected angle between the lines (n is the map direction turned by 90 deg)."""
    dx = 0.5 * (ax + bx) - cx
    dy = 0.5 * (ay + by) - cy
    rr = 0.5 * length + half + 2.0 * margin
    if not dx * dx + dy * dy <= rr * rr * (1.0 + 1e-12):  # (written so that nan fails)
        return np.inf
    ea = abs(ax * nx + ay * ny - c)
    eb_signed = bx * nx + by * ny - c
    eb = abs(eb_signed)
    sin_ang = abs(eb_signed - (ax * nx + ay * ny - c)) / max(length, 1e-12)
    if not (sin_ang < sin_max and max(ea, eb) < max_dist):
        return np.inf
    return 0.5 * (ea + eb + sin_ang)


@kernel
def _match_costs(a1, b1, centre, half, n, c, sin_max, max_dist, margin):
    """(B, k1, k2) :func:`pair_cost` of every observed segment against every map segment
    of its batch element."""
    nb, k1, k2 = a1.shape[0], a1.shape[1], centre.shape[1]
    out = np.empty((nb, k1, k2))
    for q in range(nb):
        for i in range(k1):
            ax, ay, bx, by = a1[q, i, 0], a1[q, i, 1], b1[q, i, 0], b1[q, i, 1]
            length = math.sqrt((bx - ax) ** 2 + (by - ay) ** 2)
            for j in range(k2):
                out[q, i, j] = pair_cost(ax, ay, bx, by, length, centre[q, j, 0],
                                         centre[q, j, 1], half[q, j], n[q, j, 0], n[q, j, 1],
                                         c[q, j], sin_max, max_dist, margin)
    return out
