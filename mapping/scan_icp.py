"""Raw-point scan-to-scan ICP (point to line): an independent yardstick for the line mapper.

The mapper sees a scan only through its segments; this matcher sees every beam.  Each point of
the source scan is paired with the nearest point of the target scan, the distance measured along
the target's local normal (fitted on its neighbours in beam order), with trimmed, Cauchy-weighted
Gauss-Newton steps.  It is not part of the mapping pipeline: evaluation uses it to ask how well
consecutive poses of a trajectory (the estimate, or a log's own reference) agree with what the
raw ranges say (:func:`.evaluation.icp_agreement`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .jit import inverse3_into, kernel, stable_argsort
from .odometry import move_points


@dataclass(frozen=True)
class IcpParams:
    max_range: float = 30.0     # beams beyond this (or at or below min_range) are no points
    min_range: float = 0.05
    half_window: int = 2        # neighbours on each side, in beam order, for a point's normal
    max_gap: float = 0.3        # ... within this distance; also the pairing distance (m)
    flatness: float = 0.1       # a normal only where the spread across is below this share
    min_neighbours: int = 4     # of the spread along (corners and clutter have none)
    trim: float = 0.8           # pairs kept per step: this share with the smallest residuals
    scale: float = 0.02         # Cauchy scale of the residuals (m)
    iterations: int = 40
    tolerance: float = 1e-6     # stop when no pose component moves more than this
    min_pairs: int = 20


@dataclass
class ScanPoints:
    """A scan's points in its laser frame, their unit normals and where a normal exists;
    the k-d tree :func:`icp_numpy` pairs them with is made on first use (the compiled
    :func:`icp` has its own grid)."""

    points: np.ndarray
    normals: np.ndarray
    has_normal: np.ndarray

    @cached_property
    def tree(self) -> cKDTree:
        return cKDTree(self.points) if len(self.points) else cKDTree(np.zeros((1, 2)))


def scan_points(ranges, angle_min: float, angle_increment: float,
                params: IcpParams | None = None) -> ScanPoints:
    """The valid beams of a scan as points with local normals (vectorised over beams)."""
    P = params or IcpParams()
    r = np.asarray(ranges, dtype=float)
    ang = angle_min + angle_increment * np.arange(len(r))
    ok = np.isfinite(r) & (r > P.min_range) & (r < P.max_range)
    pts = np.column_stack([r[ok] * np.cos(ang[ok]), r[ok] * np.sin(ang[ok])])
    n = len(pts)
    normals = np.zeros((n, 2))
    has = np.zeros(n, bool)
    if n:
        offs = np.arange(-P.half_window, P.half_window + 1)
        idx = np.clip(np.arange(n)[:, None] + offs, 0, n - 1)
        nb = pts[idx]                                               # (n, w, 2)
        near = (np.linalg.norm(nb - pts[:, None], axis=-1) < P.max_gap)
        near &= (np.arange(n)[:, None] + offs >= 0) & (np.arange(n)[:, None] + offs < n)
        cnt = near.sum(1)
        mean = (nb * near[..., None]).sum(1) / np.maximum(cnt, 1)[:, None]
        d = (nb - mean[:, None]) * near[..., None]
        cov = np.einsum("kwi,kwj->kij", d, d)
        w, v = np.linalg.eigh(cov)                                  # ascending
        normals = v[:, :, 0]
        has = (cnt >= P.min_neighbours) & (w[:, 0] <= P.flatness * np.maximum(w[:, 1], 1e-12))
    return ScanPoints(pts, normals, has)


def icp(src: ScanPoints, dst: ScanPoints, guess, params: IcpParams | None = None
        ) -> np.ndarray | None:
    """Pose (x, y, theta) of ``src``'s frame in ``dst``'s frame, started from ``guess``;
    None when too few points pair up.  Compiled (:func:`_icp_kernel`): a build's report
    runs it on a thousand scan pairs twice (:func:`.evaluation.icp_agreement`), 0.2 ms a
    pair on the Intel log's scans against 2.7 ms for :func:`icp_numpy`, the same steps in
    numpy."""
    P = params or IcpParams()
    if len(src.points) < P.min_pairs or len(dst.points) < P.min_pairs:
        return None
    x = np.asarray(guess, dtype=float).copy()
    ok = _icp_kernel(src.points, dst.points, dst.normals, dst.has_normal, x, P.max_gap,
                     P.trim, P.scale, P.iterations, P.tolerance, P.min_pairs)
    return x if ok else None


@kernel
def _icp_kernel(src, dst, normals, has, x, max_gap, trim, scale, iterations, tolerance,
                min_pairs):
    """:func:`icp_numpy` on arrays, ``x`` updated in place; False when too few points pair.
    The nearest target point within ``max_gap`` comes from a grid of ``max_gap`` cells over
    the target (the 3 x 3 cells around a point hold every point that near)."""
    n, m = src.shape[0], dst.shape[0]
    lo0, lo1 = dst[:, 0].min(), dst[:, 1].min()
    nx = int((dst[:, 0].max() - lo0) / max_gap) + 1
    ny = int((dst[:, 1].max() - lo1) / max_gap) + 1
    cell = np.empty(m, np.int64)
    for j in range(m):
        cell[j] = int((dst[j, 0] - lo0) / max_gap) * ny + int((dst[j, 1] - lo1) / max_gap)
    start = np.zeros(nx * ny + 1, np.int64)
    for j in range(m):
        start[cell[j] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(m, np.int64)
    for j in range(m):
        order[fill[cell[j]]] = j
        fill[cell[j]] += 1
    qx, qy = np.empty(n), np.empty(n)
    pj = np.empty(n, np.int64)
    e = np.empty(n)
    gap2 = max_gap * max_gap
    for _ in range(iterations):
        c, s = np.cos(x[2]), np.sin(x[2])
        k = 0
        for i in range(n):
            px = c * src[i, 0] - s * src[i, 1] + x[0]
            py = s * src[i, 0] + c * src[i, 1] + x[1]
            fx, fy = (px - lo0) / max_gap, (py - lo1) / max_gap
            if fx < -1.0 or fy < -1.0 or fx >= nx + 1.0 or fy >= ny + 1.0:
                continue
            cx, cy = int(np.floor(fx)), int(np.floor(fy))
            best, bj = gap2, -1
            for ax in range(max(cx - 1, 0), min(cx + 2, nx)):
                for ay in range(max(cy - 1, 0), min(cy + 2, ny)):
                    a = ax * ny + ay
                    for t in range(start[a], start[a + 1]):
                        j = order[t]
                        d2 = (px - dst[j, 0]) ** 2 + (py - dst[j, 1]) ** 2
                        if d2 < best or (d2 == best and bj >= 0 and j < bj):
                            best, bj = d2, j
            if bj < 0 or not has[bj]:
                continue
            qx[k], qy[k], pj[k] = px, py, bj
            e[k] = (px - dst[bj, 0]) * normals[bj, 0] + (py - dst[bj, 1]) * normals[bj, 1]
            k += 1
        if k < min_pairs:
            return False
        # numpy's quantile (linear) of |e| over the pairs: the trim's bar
        a_e = np.abs(e[:k])
        a_e = a_e[stable_argsort(a_e)]
        pos = (k - 1) * trim
        f = int(np.floor(pos))
        bar = a_e[f] if f + 1 >= k else a_e[f] + (pos - f) * (a_e[f + 1] - a_e[f])
        bar = max(bar, 1e-3)
        H = np.zeros((1, 3, 3))
        g = np.zeros(3)
        for i in range(k):
            if abs(e[i]) > bar:
                continue
            j = pj[i]
            J0, J1 = normals[j, 0], normals[j, 1]
            J2 = J1 * (qx[i] - x[0]) - J0 * (qy[i] - x[1])
            w = 1.0 / (1.0 + (e[i] / scale) ** 2)
            J = (J0, J1, J2)
            for r in range(3):
                g[r] += w * J[r] * e[i]
                for q in range(3):
                    H[0, r, q] += w * J[r] * J[q]
        for r in range(3):
            H[0, r, r] += 1e-9
        inverse3_into(H, H)
        moved = 0.0
        for r in range(3):
            d = -(H[0, r, 0] * g[0] + H[0, r, 1] * g[1] + H[0, r, 2] * g[2])
            x[r] += d
            moved = max(moved, abs(d))
        if moved < tolerance:
            break
    x[2] = (x[2] + np.pi) % (2 * np.pi) - np.pi
    return True


def icp_numpy(src: ScanPoints, dst: ScanPoints, guess, params: IcpParams | None = None
              ) -> np.ndarray | None:
    """:func:`icp` in numpy with a k-d tree: the reference its kernel is tested against."""
    P = params or IcpParams()
    x = np.asarray(guess, dtype=float).copy()
    if len(src.points) < P.min_pairs or len(dst.points) < P.min_pairs:
        return None
    for _ in range(P.iterations):
        q = move_points(src.points, x)
        dist, j = dst.tree.query(q, distance_upper_bound=P.max_gap)
        ok = np.isfinite(dist)
        ok[ok] &= dst.has_normal[j[ok]]
        if ok.sum() < P.min_pairs:
            return None
        q, j = q[ok], j[ok]
        n = dst.normals[j]
        e = np.einsum("ki,ki->k", q - dst.points[j], n)
        keep = np.abs(e) <= max(np.quantile(np.abs(e), P.trim), 1e-3)
        q, n, e = q[keep], n[keep], e[keep]
        J = np.column_stack([n, n[:, 1] * (q[:, 0] - x[0]) - n[:, 0] * (q[:, 1] - x[1])])
        w = 1.0 / (1.0 + (e / P.scale) ** 2)
        H = J.T @ (J * w[:, None])
        dx = -np.linalg.solve(H + 1e-9 * np.eye(3), J.T @ (w * e))
        x += dx
        if np.max(np.abs(dx)) < P.tolerance:
            break
    x[2] = (x[2] + np.pi) % (2 * np.pi) - np.pi
    return x
