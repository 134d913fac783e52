"""Pose hypotheses from lines in the Hough domain (seed 000 §V, eq. 9): the rotations that
turn the scan's lines onto the map's (:func:`rotation_peaks`), and for one rotation the
translations that put two scan lines on two map segments at once, or a scan line's end on a
map segment's (:func:`line_candidates`)."""

from __future__ import annotations

import numpy as np

from .jit import kernel, stable_argsort
from .odometry import wrap_angle as _wrap


def rotation_peaks(phi_g, len_g, phi_l, len_l, bin_deg: float, peaks: int) -> np.ndarray:
    """Eq. (9) in the Hough domain: the ``peaks`` highest peaks of the length-weighted
    histogram of undirected angle differences phi_g - phi_l (mod pi) between every map line
    and every scan line, strongest first, each refined by the weighted circular mean of the
    differences near it.  A rotation by a peak (or by it + pi) turns scan lines onto map
    lines."""
    d = np.mod(phi_g[:, None] - phi_l[None, :], np.pi)
    w = np.minimum(len_g[:, None], len_l[None, :])
    nb = int(round(180.0 / bin_deg))
    idx = np.minimum((d / np.pi * nb).astype(int), nb - 1)
    hist = np.bincount(idx.ravel(), w.ravel(), nb)
    kern = np.array([0.25, 0.5, 1.0, 0.5, 0.25])
    sm = sum(k * np.roll(hist, s) for k, s in zip(kern, range(-2, 3), strict=True))
    top = np.nonzero((sm >= np.roll(sm, 1)) & (sm > np.roll(sm, -1)) & (sm > 0))[0]
    top = top[np.argsort(-sm[top])][:peaks]
    out = np.empty(len(top))
    for k, pk in enumerate(top):
        centre = (pk + 0.5) * np.pi / nb
        dd = _wrap(2 * (d - centre)) / 2
        near = np.abs(dd) < np.deg2rad(2.5 * bin_deg)
        if near.any():
            centre = centre + np.sum(w[near] * dd[near]) / np.sum(w[near])
        out[k] = centre
    return out


@kernel
def _first_at_least(sorted_x, v):
    """The first index of ascending ``sorted_x`` whose value is >= ``v`` (its size if none):
    ``np.searchsorted(sorted_x, v)``."""
    lo, hi = 0, sorted_x.size
    while lo < hi:
        mid = (lo + hi) // 2
        if sorted_x[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel
def _pair_kernel(A1, A2, d1, d2, u1, lo1, hi1, u2, lo2, hi2, delta1, delta2, w1, w2, out_T,
                 out_D):
    """The translations (k, 2) putting two scan lines on every pair of map segments (g1, g2)
    they fit at once (Cramer's rule on the lines ``A . T = d``, then both overlap intervals
    (lo, hi) along the segments' directions u), in row-major (g1, g2) order, and each pair's
    rotation residual, the two lines' weighted by their lengths ``w1``, ``w2``: written into
    out_T, out_D as far as they have room; returns how many fit.

    A map segment admits the translations on a piece of its line, d n + s u for s in
    (lo, hi): a pair can fit only where the two pieces' bounding boxes meet.  The second
    pieces are sorted by their boxes' left edges, so each first piece reads the few whose
    boxes can reach its own (sweep and prune) instead of all of them; those are then solved
    in index order, so the output is the full double loop's, pair for pair."""
    room = out_T.shape[0]
    eps = 1e-6  # the boxes are padded: the exact tests below decide
    n2 = A2.shape[0]
    bx0, bx1 = np.empty(n2), np.empty(n2)
    by0, by1 = np.empty(n2), np.empty(n2)
    for b in range(n2):
        cx, cy = d2[b] * A2[b, 0], d2[b] * A2[b, 1]
        x0, x1 = cx + lo2[b] * u2[b, 0], cx + hi2[b] * u2[b, 0]
        y0, y1 = cy + lo2[b] * u2[b, 1], cy + hi2[b] * u2[b, 1]
        bx0[b], bx1[b] = min(x0, x1) - eps, max(x0, x1) + eps
        by0[b], by1[b] = min(y0, y1) - eps, max(y0, y1) + eps
    order = stable_argsort(bx0)
    left = bx0[order]
    width = 0.0
    for b in range(n2):
        width = max(width, bx1[b] - bx0[b])
    near = np.empty(n2, np.int64)
    n = 0
    for a in range(A1.shape[0]):
        a11, a12 = A1[a, 0], A1[a, 1]
        cx, cy = d1[a] * a11, d1[a] * a12
        x0, x1 = cx + lo1[a] * u1[a, 0], cx + hi1[a] * u1[a, 0]
        y0, y1 = cy + lo1[a] * u1[a, 1], cy + hi1[a] * u1[a, 1]
        ax0, ax1 = min(x0, x1), max(x0, x1)
        ay0, ay1 = min(y0, y1), max(y0, y1)
        m = 0
        j = _first_at_least(left, ax0 - width)
        while j < n2 and left[j] <= ax1:
            b = order[j]
            if bx1[b] >= ax0 and by0[b] <= ay1 and by1[b] >= ay0:
                near[m] = b
                m += 1
            j += 1
        hit = near[:m]
        for b in hit[stable_argsort(hit.astype(np.float64))]:      # in index order
            a21, a22 = A2[b, 0], A2[b, 1]
            det = a11 * a22 - a12 * a21
            if abs(det) <= 0.3:
                continue  # near-parallel lines fix no point
            tx = (d1[a] * a22 - a12 * d2[b]) / det
            ty = (a11 * d2[b] - d1[a] * a21) / det
            tu = tx * u1[a, 0] + ty * u1[a, 1]
            if not (lo1[a] < tu < hi1[a]):
                continue
            tu = tx * u2[b, 0] + ty * u2[b, 1]
            if not (lo2[b] < tu < hi2[b]):
                continue
            if n < room:
                out_T[n, 0] = tx
                out_T[n, 1] = ty
                out_D[n] = (w1 * delta1[a] + w2 * delta2[b]) / (w1 + w2)
            n += 1
    return n


@kernel
def line_candidates(ga, gb, n_g, c_g, phi_g, len_g, ra, rb, n_l, c_l, phi_l, len_l, s, tol,
                    map_share, slack, min_ang, n_end):
    """One rotation hypothesis's translation candidates from the scan's lines (the scan's
    end points ``ra``, ``rb`` turned by it, their lines' normals, offsets, angles and
    lengths; ``s`` = -1 for its twin + pi, which turns the points and normals by pi).  Scan
    line i may lie on map segment g when their angles differ by less than ``tol`` (the
    residual ``delta``, each candidate's own rotation correction: the histogram peak is only
    good to a bin or so) and the map segment is at least ``map_share`` of its length (less
    0.3 m).  On one of them the translation satisfies ``n_g . T = c_g - s sgn c_l`` (sgn:
    the normals' relative sign) and, for the scan segment to lie on the map segment and not
    only on its line, falls in an interval along it.  Returns (T, D): every translation that puts
    two scan lines at least ``min_ang`` apart on two map segments at once
    (:func:`_pair_kernel`, pairs of scan lines in order), with its rotation residual; and
    (Tf, Df): the corridor candidates of the first ``n_end`` scan lines, each end of the
    scan line aligned with each end of every map segment it may lie on (a position along
    parallel walls, which a short cross piece would fix but is often missing)."""
    G, k = len(ga), len(ra)
    off = np.zeros(k + 1, np.int64)         # per scan line: its map segments, flat
    gi = np.empty(G * k, np.int64)
    dl = np.empty(G * k)
    e = 0
    for i in range(k):
        for g in range(G):
            dd = ((2 * (phi_g[g] - phi_l[i]) + np.pi) % (2.0 * np.pi) - np.pi) / 2
            if abs(dd) < tol and len_g[g] > map_share * len_l[i] - 0.3:
                gi[e], dl[e] = g, dd
                e += 1
        off[i + 1] = e
    E = off[k]
    A, u = np.empty((E, 2)), np.empty((E, 2))
    d, lo, hi = np.empty(E), np.empty(E), np.empty(E)
    for i in range(k):
        lax, lay, lbx, lby = s * ra[i, 0], s * ra[i, 1], s * rb[i, 0], s * rb[i, 1]
        for e in range(off[i], off[i + 1]):
            g = gi[e]
            A[e, 0], A[e, 1] = n_g[g, 0], n_g[g, 1]
            dot = n_g[g, 0] * n_l[i, 0] + n_g[g, 1] * n_l[i, 1]
            sgn = 1.0 if dot > 0 else (-1.0 if dot < 0 else 0.0)
            d[e] = c_g[g] - s * sgn * c_l[i]
            # where along the map segment the translation may fall: u . T in (lo, hi), the
            # scan segment then overlapping it with a gap of at most ``slack``
            dx, dy = gb[g, 0] - ga[g, 0], gb[g, 1] - ga[g, 1]
            L = np.sqrt(dx * dx + dy * dy)
            ux, uy = dx / max(L, 1e-9), dy / max(L, 1e-9)
            u[e, 0], u[e, 1] = ux, uy
            t1 = (lax - ga[g, 0]) * ux + (lay - ga[g, 1]) * uy
            t2 = (lbx - ga[g, 0]) * ux + (lby - ga[g, 1]) * uy
            lo[e] = -slack - max(t1, t2)
            hi[e] = L + slack - min(t1, t2)
    cap = 1024
    T, D = np.empty((cap, 2)), np.empty(cap)
    n = 0
    for i1 in range(k):
        for i2 in range(i1 + 1, k):
            ang = abs((2.0 * (phi_l[i1] - phi_l[i2]) + np.pi) % (2.0 * np.pi) - np.pi) / 2
            a0, a1, b0, b1 = off[i1], off[i1 + 1], off[i2], off[i2 + 1]
            if ang < min_ang or a0 == a1 or b0 == b1:
                continue
            while True:
                m = _pair_kernel(A[a0:a1], A[b0:b1], d[a0:a1], d[b0:b1], u[a0:a1],
                                 lo[a0:a1], hi[a0:a1], u[b0:b1], lo[b0:b1], hi[b0:b1],
                                 dl[a0:a1], dl[b0:b1], len_l[i1], len_l[i2], T[n:], D[n:])
                if n + m <= cap:
                    n += m
                    break
                cap = max(2 * cap, n + m)    # out of room: grow, solve the pair again
                T2, D2 = np.empty((cap, 2)), np.empty(cap)
                T2[:n], D2[:n] = T[:n], D[:n]
                T, D = T2, D2
    nf = 0
    for i1 in range(min(n_end, k)):
        nf += 4 * (off[i1 + 1] - off[i1])
    Tf, Df = np.empty((nf, 2)), np.empty(nf)
    f = 0
    for i1 in range(min(n_end, k)):
        for end_g in range(2):
            for end_l in range(2):
                px, py = (ra[i1, 0], ra[i1, 1]) if end_l == 0 else (rb[i1, 0], rb[i1, 1])
                for e in range(off[i1], off[i1 + 1]):
                    g = gi[e]
                    vx, vy = -n_g[g, 1], n_g[g, 0]          # along the map segment
                    q = ga[g] if end_g == 0 else gb[g]
                    eg = q[0] * vx + q[1] * vy
                    el = s * (vx * px + vy * py)
                    Tf[f, 0] = d[e] * n_g[g, 0] + (eg - el) * vx
                    Tf[f, 1] = d[e] * n_g[g, 1] + (eg - el) * vy
                    Df[f] = dl[e]
                    f += 1
    return T[:n], D[:n], Tf, Df
