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

import numpy as np
from scipy.spatial import cKDTree

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
    """A scan's points in its laser frame, their unit normals and where a normal exists,
    with a k-d tree for pairing."""

    points: np.ndarray
    normals: np.ndarray
    has_normal: np.ndarray
    tree: cKDTree


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
    return ScanPoints(pts, normals, has, cKDTree(pts) if n else cKDTree(np.zeros((1, 2))))


def icp(src: ScanPoints, dst: ScanPoints, guess, params: IcpParams | None = None
        ) -> np.ndarray | None:
    """Pose (x, y, theta) of ``src``'s frame in ``dst``'s frame, started from ``guess``;
    None when too few points pair up."""
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
