"""Pose hypotheses scored and refined against the map's distance field: the inlier count of
many candidates (:func:`inlier_scores`, and :func:`best_distinct` for the best one per cell
without counting every candidate to the end), the batched point-to-segment ICP
(:func:`icp_poses`), the soft fit (:func:`fit_scores`) and the free-space test
(:func:`crossed_fractions`).  Arrays in, arrays out; compiled where the candidates are many."""

from __future__ import annotations

from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from .distance_field import DistanceField
from .jit import kernel

if TYPE_CHECKING:
    from .relocalize import RelocParams


def inlier_scores(field: DistanceField, pts: np.ndarray, T: np.ndarray, th: np.ndarray,
                  inlier: float, soft: bool = False) -> np.ndarray:
    """Fraction of points within ``inlier`` of the map for each pose hypothesis (T, th);
    with ``soft``, each point counts 1 - (d / inlier)^2 instead of 1 (ties between symmetric
    places go to the pose that fits tighter)."""
    if not len(pts):
        return np.zeros(len(T))
    out = np.empty(len(T))
    # a plain count (off the grid no inlier) reads the packed inlier bits
    bits = (field.inlier_bits(inlier) if not soft and field.far >= inlier
            else np.zeros((0, 1), np.uint8))
    _score_kernel(field.dist, bits, float(field.lo[0]), float(field.lo[1]), float(field.res),
                  float(field.far), np.ascontiguousarray(pts, dtype=float),
                  np.ascontiguousarray(T, dtype=float), np.ascontiguousarray(th, dtype=float),
                  float(inlier), bool(soft), out)
    return out


@kernel
def _cell(gx, gy, lo0, lo1, res):
    """The grid cell (column, row; floats, maybe off the grid) of map point (gx, gy): the
    nearest cell, as :meth:`DistanceField.lookup_xy` takes it."""
    return np.floor((gx - lo0) / res + 0.5), np.floor((gy - lo1) / res + 0.5)


@kernel
def _cell_of(c, s, x, y, tx, ty, lo0, lo1, res):
    """:func:`_cell` of scan point (x, y) under the pose of rotation (cos c, sin s) and
    translation (tx, ty)."""
    return _cell(c * x - s * y + tx, s * x + c * y + ty, lo0, lo1, res)


@kernel
def _score_kernel(dist, bits, lo0, lo1, res, far, pts, T, th, inlier, soft, out):
    """:func:`inlier_scores` per hypothesis, the points moved, looked up (:meth:`DistanceField.
    lookup_xy`, nearest cell, off-grid far) and counted in one pass: no (hypotheses x points)
    temporaries, which on a large map's many candidates cost more than the lookups.  With
    ``bits`` non-empty (:meth:`DistanceField.inlier_bits` of ``inlier``; a plain count, far
    beyond the inlier distance), the packed bits are read instead of the distances: the
    same cells, the same answer, a 32nd of the bytes."""
    ny, nx = dist.shape
    n = pts.shape[0]
    packed = bits.shape[0] > 0
    for h in range(T.shape[0]):
        c, s = np.cos(th[h]), np.sin(th[h])
        acc = 0.0
        for j in range(n):
            qx, qy = _cell_of(c, s, pts[j, 0], pts[j, 1], T[h, 0], T[h, 1], lo0, lo1, res)
            if not (qx >= 0 and qy >= 0 and qx < nx and qy < ny):
                d = far
            elif packed:
                ix = int(qx)
                acc += (bits[int(qy), ix >> 3] >> (ix & 7)) & 1
                continue
            else:
                d = dist[int(qy), int(qx)]
            if soft:
                acc += max(0.0, 1.0 - (d / inlier) ** 2)
            elif d < inlier:
                acc += 1.0
        out[h] = acc / n


def _cell_keys(T: np.ndarray, th: np.ndarray, cell: float, ang: float) -> np.ndarray:
    """One integer per (x, y, theta) cell of ``cell`` metres and ``ang`` radians for each
    candidate (T, th): equal keys, one cell (a 1-D unique sorts far faster than rows)."""
    kx = np.floor(T[:, 0] / cell).astype(np.int64)
    ky = np.floor(T[:, 1] / cell).astype(np.int64)
    kt = np.floor(np.mod(th, 2 * np.pi) / ang).astype(np.int64)
    kx -= kx.min()
    ky -= ky.min()
    return (kx * (int(ky.max()) + 1) + ky) * (int(kt.max()) + 1) + kt


def distinct_cells(T: np.ndarray, th: np.ndarray, order: np.ndarray, cell: float, ang: float,
                   k: int) -> np.ndarray:
    """The first ``k`` of ``order`` that fall in different (x, y, theta) cells: the best
    candidate of each cell, so near-duplicates do not crowd out other places."""
    if not len(order):
        return order
    # the stable sort keeps the first -- best -- candidate of each cell
    _, first = np.unique(_cell_keys(T[order], th[order], cell, ang), return_index=True)
    return order[np.sort(first)[:k]]


def best_distinct(field: DistanceField, pts: np.ndarray, T: np.ndarray, th: np.ndarray,
                  inlier: float, cell: float, ang: float, k: int) -> np.ndarray:
    """The ``k`` best candidates by their inlier fraction (:func:`inlier_scores` at ``inlier``,
    ties by index), one per (x, y, theta) cell: :func:`distinct_cells` of the candidates ranked
    by that score, the same indices, without counting every candidate's points to the end.
    A big building's map gives 10^4-10^5 candidates, most of them nowhere near a wall, and
    their full count was a fifth of a trial.  Once k cells hold a candidate with count c
    or more, the k cells picked all reach c, and a later candidate that cannot beat c (its
    points left to read would not make up the difference; at c exactly, the k earlier
    ones come first) is never picked: its count stops there (:func:`_pruned_counts`)."""
    if not len(T) or not len(pts) or field.far < inlier:
        # nothing to prune by (or off-grid points count: the packed bits cannot say it)
        order = np.argsort(-inlier_scores(field, pts, T, th, inlier), kind="stable")
        return distinct_cells(T, th, order, cell, ang, k)
    cells, cid = np.unique(_cell_keys(T, th, cell, ang), return_inverse=True)
    cid = cid.ravel().astype(np.int64)
    counts = np.empty(len(T), np.int64)
    _pruned_counts(field.inlier_bits(inlier), float(field.lo[0]), float(field.lo[1]),
                   float(field.res), np.ascontiguousarray(pts[spread_order(len(pts))], dtype=float),
                   np.ascontiguousarray(T, dtype=float), np.ascontiguousarray(th, dtype=float),
                   cid, len(cells), int(k), counts)
    done = np.nonzero(counts >= 0)[0]
    order = done[np.argsort(-counts[done], kind="stable")]
    return _first_per_cell(order, cid, len(cells), int(k))


@lru_cache(maxsize=64)
def spread_order(n: int) -> np.ndarray:
    """0 .. n-1 in bit-reversed order (0, n/2, n/4, 3n/4, ...): scan points read in this
    order spread over the scan from the first reads, so a bad pose's misses show early
    (a count that stops once it cannot reach a bar stops sooner)."""
    rev = [int(f"{i:032b}"[::-1], 2) for i in range(n)]
    out = np.argsort(np.array(rev, np.int64), kind="stable")
    out.flags.writeable = False     # shared by every caller (cached)
    return out


@kernel
def _pruned_counts(bits, lo0, lo1, res, pts, T, th, cid, n_cells, k, out):
    """:func:`best_distinct`'s counts: each candidate's inlier count (the packed bits, as
    :func:`_score_kernel` reads them), or -1 once it cannot beat the count that k distinct
    cells already hold.  That bar only rises: the cells' best counts so far are kept in a
    histogram, and the bar is the highest count that k of them reach."""
    ny = bits.shape[0]
    nx = bits.shape[1] * 8
    n = pts.shape[0]
    best = np.full(n_cells, -1, np.int64)
    hist = np.zeros(n + 1, np.int64)      # cells by their best count
    bar = 0
    for h in range(T.shape[0]):
        c, s = np.cos(th[h]), np.sin(th[h])
        acc = 0
        pruned = False
        for j in range(n):
            if acc + n - j <= bar:
                pruned = True
                break
            qx, qy = _cell_of(c, s, pts[j, 0], pts[j, 1], T[h, 0], T[h, 1], lo0, lo1, res)
            if qx >= 0 and qy >= 0 and qx < nx and qy < ny:
                ix = int(qx)
                acc += (bits[int(qy), ix >> 3] >> (ix & 7)) & 1
        if pruned:
            out[h] = -1
            continue
        out[h] = acc
        g = cid[h]
        if acc > best[g]:
            if best[g] >= 0:
                hist[best[g]] -= 1
            hist[acc] += 1
            best[g] = acc
            total = 0
            for v in range(n, bar - 1, -1):
                total += hist[v]
                if total >= k:
                    bar = v
                    break


@kernel
def _first_per_cell(order, cid, n_cells, k):
    """The first ``k`` of ``order`` whose cells (``cid``) come up for the first time."""
    seen = np.zeros(n_cells, np.bool_)
    out = np.empty(min(k, order.size), np.int64)
    m = 0
    for i in order:
        if m == out.size:
            break
        if not seen[cid[i]]:
            seen[cid[i]] = True
            out[m] = i
            m += 1
    return out[:m]


def icp_poses(field: DistanceField, pts: np.ndarray, poses: np.ndarray,
              gates: tuple[float, ...]) -> np.ndarray:
    """Batched point-to-segment Gauss-Newton for many poses at once (H, 3): each scan point
    pairs with the map segment nearest to it (:meth:`DistanceField.nearest`) when within the
    iteration's gate; its residual is the distance to the closest point of that segment
    (to the line where the point projects inside the segment, to the end point beyond it,
    so segment ends fix the position along a corridor), with Cauchy weights.  A light
    damping keeps a direction nothing fixes where it was.  Compiled (:func:`_icp_kernel`):
    in numpy its (poses x points) temporaries were half of a trial on the Intel map."""
    x = np.array(poses, dtype=float, copy=True).reshape(-1, 3)
    _icp_kernel(field.seg_id, field.segments, float(field.lo[0]), float(field.lo[1]),
                float(field.res), float(field.far), np.ascontiguousarray(pts, dtype=float),
                np.asarray(gates, dtype=float), x)
    return x


@kernel
def _icp_kernel(seg_id, tab, lo0, lo1, res, far, pts, gates, x):
    """:func:`icp_poses` pose by pose, in place on ``x`` (H, 3): per gate, every point's nearest
    segment (as :meth:`DistanceField.nearest` reads it), its residual and Jacobian into the
    3 x 3 normal equations, damped by 0.5, solved by their symmetric inverse."""
    ny, nx = seg_id.shape
    for h in range(x.shape[0]):
        for gate in gates:
            c, s = np.cos(x[h, 2]), np.sin(x[h, 2])
            scale = max(gate / 3.0, 0.02)
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            b0 = b1 = b2 = 0.0
            for j in range(pts.shape[0]):
                rx = c * pts[j, 0] - s * pts[j, 1]
                ry = s * pts[j, 0] + c * pts[j, 1]
                gx, gy = rx + x[h, 0], ry + x[h, 1]
                fx, fy = _cell(gx, gy, lo0, lo1, res)
                qx, qy = int(fx), int(fy)
                on_grid = qx >= 0 and qy >= 0 and qx < nx and qy < ny
                sid = seg_id[min(max(qy, 0), ny - 1), min(max(qx, 0), nx - 1)]
                ux, uy, L = tab[sid, 2], tab[sid, 3], tab[sid, 4]
                dx, dy = gx - tab[sid, 0], gy - tab[sid, 1]
                e = ux * dy - uy * dx                   # along the normal (-uy, ux)
                t = ux * dx + uy * dy
                over = t if t < 0.0 else (t - L if t > L else 0.0)
                dseg = np.hypot(e, over) if on_grid else far
                if not dseg < gate:
                    continue
                if over != 0.0:
                    # beyond an end the residual points from the end point to the point:
                    # along the segment by the overshoot, across it by e
                    inv = 1.0 / max(dseg, 1e-9)
                    n0, n1 = (over * ux - e * uy) * inv, (over * uy + e * ux) * inv
                    e = dseg
                else:
                    n0, n1 = -uy, ux
                w = 1.0 / (1.0 + (e / scale) ** 2)
                j2 = n1 * rx - n0 * ry
                a00 += w * n0 * n0
                a01 += w * n0 * n1
                a02 += w * n0 * j2
                a11 += w * n1 * n1
                a12 += w * n1 * j2
                a22 += w * j2 * j2
                b0 += w * n0 * e
                b1 += w * n1 * e
                b2 += w * j2 * e
            a00 += 0.5
            a11 += 0.5
            a22 += 0.5
            # the symmetric inverse (cofactors): positive definite by the damping
            i00, i01, i02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
            i11, i12, i22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
            det = a00 * i00 + a01 * i01 + a02 * i02
            x[h, 0] -= (i00 * b0 + i01 * b1 + i02 * b2) / det
            x[h, 1] -= (i01 * b0 + i11 * b1 + i12 * b2) / det
            x[h, 2] -= (i02 * b0 + i12 * b1 + i22 * b2) / det
        x[h, 2] = (x[h, 2] + np.pi) % (2.0 * np.pi) - np.pi


def fit_scores(field: DistanceField, pts: np.ndarray, poses: np.ndarray, inlier: float):
    """(inlier fraction, soft fit) per pose (H, 3) from exact point-to-segment distances."""
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    gx = c * pts[None, :, 0] - s * pts[None, :, 1] + poses[:, 0, None]
    gy = s * pts[None, :, 0] + c * pts[None, :, 1] + poses[:, 1, None]
    d = field.nearest(gx, gy)[2]
    return np.mean(d < inlier, -1), np.mean(np.maximum(0.0, 1.0 - (d / inlier) ** 2), -1)


def crossed_fractions(field: DistanceField, pts: np.ndarray, poses: np.ndarray,
                      P: RelocParams) -> np.ndarray:
    """Fraction of beams per pose (H, 3) that pass through a mapped wall: free space the
    hypothesis claims where the map has a wall.  Samples along each beam find the walls it
    comes near (distance field); a wall counts only when its segment's line separates the
    laser from the beam's end by ``cross_margin`` on both sides (exact, perpendicular to
    the wall), so a beam grazing a wall it ends on, or map error of a few centimetres,
    never counts."""
    if not len(pts) or not len(poses):
        return np.zeros(len(poses))
    if len(pts) > P.cross_beams:
        pts = pts[np.linspace(0, len(pts) - 1, P.cross_beams).astype(int)]
    r = np.linalg.norm(pts, axis=-1)
    step = P.crossing_step
    f = np.arange(P.cross_skip, min(float(r.max()), P.cross_range), step)  # (S,)
    u = pts / np.maximum(r, 1e-9)[:, None]
    out = np.empty(len(poses))
    _crossings_kernel(field.dist, field.seg_id, field.segments, float(field.lo[0]),
                      float(field.lo[1]), float(field.res), np.ascontiguousarray(u), r, f,
                      # the field's own precision, as numpy compared it
                      np.float32(0.6 * step + 0.5 * field.res), float(P.cross_margin),
                      np.ascontiguousarray(poses, dtype=float), out)
    return out


@kernel
def _crossings_kernel(dist, seg_id, tab, lo0, lo1, res, u, r, f, near, margin, poses, out):
    """:func:`crossed_fractions` pose by pose: each beam (unit direction ``u``, range ``r``) is
    sampled at the distances ``f`` short of its end by ``margin``; at a sample within
    ``near`` of a wall (the distance field, nearest cell; off the grid: none), the wall is
    the nearest segment (as :meth:`DistanceField.nearest` reads it), and the beam crosses it
    when the segment's line separates the laser from the beam's end by ``margin`` on both
    sides and the beam meets that line on the segment.  ``out``: the crossed fraction."""
    ny, nx = dist.shape
    for h in range(poses.shape[0]):
        ox, oy = poses[h, 0], poses[h, 1]
        c, s = np.cos(poses[h, 2]), np.sin(poses[h, 2])
        hits = 0
        for b in range(u.shape[0]):
            ugx = c * u[b, 0] - s * u[b, 1]
            ugy = s * u[b, 0] + c * u[b, 1]
            ex, ey = ox + ugx * r[b], oy + ugy * r[b]                 # the beam's end
            for fk in f:
                if not fk < r[b] - margin:
                    break
                sx, sy = ox + ugx * fk, oy + ugy * fk
                fx, fy = _cell(sx, sy, lo0, lo1, res)
                qx, qy = int(fx), int(fy)
                if not (qx >= 0 and qy >= 0 and qx < nx and qy < ny) or not dist[qy, qx] < near:
                    continue
                sid = seg_id[qy, qx]
                ax, ay, wx, wy = tab[sid, 0], tab[sid, 1], tab[sid, 2], tab[sid, 3]
                so = -wy * (ox - ax) + wx * (oy - ay)
                se = -wy * (ex - ax) + wx * (ey - ay)
                # where the beam meets the wall's line must lie on the segment (a beam
                # passing just past a segment's end crosses nothing)
                lam = so / (so - se if so != se else 1.0)
                along = wx * (ox - ax + lam * (ex - ox)) + wy * (oy - ay + lam * (ey - oy))
                if (np.sign(so) != np.sign(se) and abs(so) > margin and abs(se) > margin
                        and along > 0.0 and along < tab[sid, 4]):
                    hits += 1
                    break
        out[h] = hits / u.shape[0]


def polish_pose(field: DistanceField, pts: np.ndarray, pose: np.ndarray, inlier: float,
                steps=((0.06, 0.01), (0.03, 0.005), (0.015, 0.0025))) -> np.ndarray:
    """Local grid search (3 x 3 x 3 around the pose, shrinking) on the soft point score:
    the segments' fit can sit on a doubled wall; the points settle it."""
    if not len(pts):
        return pose
    best = np.asarray(pose, dtype=float).copy()
    o = np.array([-1.0, 0.0, 1.0])
    grid = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
    for st, sr in steps:
        cand = best + grid * [st, st, sr]
        sc = inlier_scores(field, pts, cand[:, :2], cand[:, 2], inlier, soft=True)
        best = cand[int(np.argmax(sc))]
    return best
