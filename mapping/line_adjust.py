"""Line bundle adjustment: the scan poses and the map's walls solved together.

The pose graph ties scans to each other through relative poses, each of them a match of two
scans' segments; a wall seen by a hundred scans enters as a hundred separate pairwise
agreements.  Here every wall of the map is an unknown line (phi, rho), with n . x = rho and
n = (cos phi, sin phi) in the global frame, and every scan segment fused into it (a
contribution of :mod:`.linemap`, kept with its own point moments) is an observation of that
line from its scan's pose.  The squared distances of a segment's N points to a line split
exactly into two terms of the segment's moments (centroid c, scatter S):

    sum (n . p_k - rho)^2 = N (n . c - rho)^2 + n^T S n
                          = N e1^2 + (lam_max - lam_min) e2^2 + N * residual

with e1 the centroid's distance from the line and e2 = sin of the angle between the segment
and the line (lam the scatter's eigenvalues).  Those two residuals per observation, weighted by
their point-count information plus a model floor (walls are not perfectly straight, ranges not
perfectly calibrated) and Cauchy-robustified, are added to the pose graph's own normal
equations and solved by sparse Gauss-Newton over poses and lines at once.

This is the paper's global map of CGA lines (seed 000, §IV-A) used as what it is: the common
frame that every scan is registered against, estimated with the poses instead of frozen where
each wall was first seen.  Which segments are one wall is decided afresh from the finished
poses (:func:`associate`), tighter than the online map could.  Measured on the Intel log with
high odometry noise over 12 seeds (bench_mapping_seeds): the independent Kümmerle relations
0.046 m / 0.86 deg -> 0.041 m / 0.74 deg (the log's own reference poses: 0.044 m / 0.68 deg),
consecutive poses against raw-point ICP 1.6 cm / 0.28 deg -> 1.2 cm / 0.20 deg (median), ATE
against the reference 0.076 -> 0.073 m mean.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .linemap import LineMap, MapParams, dedupe, integrate
from .odometry import wrap_angle as wrap
from .posegraph import ROBUST_SCALE, PoseGraph, hold_nodes, solve_normal
from .segments import Segments, tls_from_moments


@dataclass(frozen=True)
class AdjustParams:
    enabled: bool = True
    iterations: int = 10
    sigma: float = 0.01             # range noise per point (m)
    floor: tuple[float, float] = (0.01, 0.0033)  # added to each observation's std (m, rad)
    gate: float = 0.05              # observations whose centroid is farther from their wall
    # than this (m) are left out at each step (after a wider first one): a wrong association
    robust: float = 3.0             # Cauchy scale on an observation's Mahalanobis distance
    graph_weight: float = 2.0       # the pose graph's edges count this much against the lines
    min_nodes: int = 2              # a wall enters when seen from at least this many scans
    # which segments are one wall is decided afresh from the finished poses, tighter than the
    # online map (which must tolerate the drift it has not corrected yet): with the online
    # map's own merges, walls a few cm apart fused into one line bent the Intel map globally
    # (ATE against the reference up to 0.105 m on a noise seed; 0.077 m re-associated)
    association: MapParams = field(default_factory=lambda: MapParams(
        merge_angle=np.deg2rad(3.0), merge_dist=0.04, max_residual=0.02))


@dataclass
class LineObservations:
    """What the adjustment needs of a :class:`.linemap.LineMap`, as plain arrays (a snapshot:
    the map may change after it was taken).  Observation k is of line ``line[k]`` from node
    ``node[k]`` with N = ``n[k]`` points of centroid ``cent[k]`` and scatter ``scat[k]`` in
    that node's laser frame; ``phi``/``rho`` are the lines' starting values."""

    line: np.ndarray
    node: np.ndarray
    n: np.ndarray
    cent: np.ndarray
    scat: np.ndarray
    phi: np.ndarray
    rho: np.ndarray

    def __len__(self) -> int:
        return len(self.line)


@dataclass
class Contributions:
    """A line map's live contributions (each a scan segment in its node's laser frame, with
    its point moments), as a snapshot independent of the map."""

    node: np.ndarray
    n: np.ndarray
    cent: np.ndarray
    scat: np.ndarray
    a: np.ndarray
    b: np.ndarray

    @classmethod
    def of(cls, lmap: LineMap) -> Contributions:
        live = lmap.c_node >= 0
        order = np.argsort(lmap.c_node[live], kind="stable")
        pick = np.nonzero(live)[0][order]
        return cls(lmap.c_node[pick].copy(), lmap.c_n[pick].copy(), lmap.c_cent[pick].copy(),
                   lmap.c_scat[pick].copy(), lmap.c_a[pick].copy(), lmap.c_b[pick].copy())


def associate(contrib: Contributions, poses: np.ndarray, params: AdjustParams | None = None
              ) -> LineObservations:
    """Which contributions are one wall, decided afresh at ``poses`` with the tight
    ``params.association`` (the map's own merge: eq. 15 sphere test, angle, end-point
    distance, joint TLS residual), node by node in order; returns the walls' observations."""
    P = params or AdjustParams()
    lmap = LineMap()
    nodes, starts = np.unique(contrib.node, return_index=True)
    ends = np.append(starts[1:], len(contrib.node))[:len(starts)]  # no contributions: none
    X = np.asarray(poses, dtype=float)
    for node, s0, s1 in zip(nodes.tolist(), starts, ends, strict=True):  # per scan
        k = s1 - s0
        seg = Segments(contrib.a[s0:s1], contrib.b[s0:s1], contrib.n[s0:s1].astype(int),
                       np.zeros(k), contrib.cent[s0:s1], contrib.scat[s0:s1],
                       np.zeros((k, 2, 2)))
        integrate(lmap, seg.transformed(*X[node]), node, P.association, seg_l=seg, node=node)
    dedupe(lmap, P.association)
    return observations(lmap, P.min_nodes)


def observations(lmap: LineMap, min_nodes: int = 2) -> LineObservations:
    """The map's walls seen from at least ``min_nodes`` graph nodes, and their observations
    (frozen contributions, node < 0, left out)."""
    live = lmap.c_node >= 0
    seg, node = lmap.c_seg[live], lmap.c_node[live]
    pairs = np.unique(np.column_stack([seg, node]), axis=0) if len(seg) else np.zeros((0, 2), int)
    seen = np.bincount(pairs[:, 0], minlength=len(lmap))
    keep = seen >= min_nodes
    remap = np.where(keep, np.cumsum(keep) - 1, -1)
    ok = remap[seg] >= 0
    d, _, _ = tls_from_moments(lmap.n_pts[keep], lmap.centroid[keep], lmap.scatter[keep])
    normal = np.column_stack([-d[:, 1], d[:, 0]])
    return LineObservations(
        remap[seg[ok]], node[ok], lmap.c_n[live][ok].astype(float),
        lmap.c_cent[live][ok], lmap.c_scat[live][ok],
        np.arctan2(normal[:, 1], normal[:, 0]),
        np.einsum("ki,ki->k", normal, lmap.centroid[keep]))


def adjust(poses: np.ndarray, graph: PoseGraph, obs: LineObservations,
           fixed: int | list[int] = 0, params: AdjustParams | None = None
           ) -> tuple[np.ndarray, dict]:
    """Poses (n, 3) re-estimated jointly with the observed lines, from ``poses`` (the graph's
    current solution), holding the ``fixed`` node(s).  Returns the poses and figures (lines,
    observations, outliers at the end, iterations)."""
    P = params or AdjustParams()
    X = np.array(poses, dtype=float)
    n, L, K = len(X), len(obs.phi), len(obs)
    info = {"lines": L, "observations": K, "outliers": 0, "iterations": 0}
    if n < 2 or K == 0:
        return X, info
    phi, rho = obs.phi.copy(), obs.rho.copy()
    line, node, c = obs.line, obs.node, obs.cent
    # each observation's own line in its laser frame: normal angle a0, spread lam_max - lam_min
    d, resid, lam_max = tls_from_moments(obs.n, c, obs.scat)
    spread = np.maximum(lam_max - resid * obs.n, 1e-6)
    a0 = np.arctan2(d[:, 0], -d[:, 1])
    w1 = 1.0 / (P.sigma ** 2 / obs.n + P.floor[0] ** 2)
    w2 = 1.0 / (P.sigma ** 2 / spread + P.floor[1] ** 2)
    nv = 3 * n + 2 * L
    # the held node(s), and a whisper of damping on the lines: a wall seen edge-on from one
    # place stays defined
    hold = hold_nodes(fixed, n, nv) + sp.diags(
        np.concatenate([np.zeros(3 * n), np.full(2 * L, 1e-6)]), format="csc")
    rows = np.concatenate([np.repeat(np.arange(K), 5), np.repeat(np.arange(K, 2 * K), 2)])
    cols = np.concatenate([
        np.column_stack([3 * node, 3 * node + 1, 3 * node + 2,
                         3 * n + 2 * line, 3 * n + 2 * line + 1]).ravel(),
        np.column_stack([3 * node + 2, 3 * n + 2 * line]).ravel()])
    wr = np.ones(K)
    edges = graph.edge_arrays()
    for it in range(P.iterations):
        th, ph = X[node, 2], phi[line]
        al = ph - th                       # the line's normal angle in the laser frame
        ca, sa, cp, sp_ = np.cos(al), np.sin(al), np.cos(ph), np.sin(ph)
        e1 = ca * c[:, 0] + sa * c[:, 1] + cp * X[node, 0] + sp_ * X[node, 1] - rho[line]
        e2 = np.sin(al - a0)
        m2 = w1 * e1 ** 2 + w2 * e2 ** 2
        # graduated as the graph's solve: the first step trusts more (a pose a few cm off
        # must not lose its walls to the gate), then the gate and Cauchy weights sort out
        first = it == 0
        scale = P.robust * (10.0 if first else 1.0)
        gate = P.gate * (4.0 if first else 1.0)
        wr = np.where(np.abs(e1) <= gate, 1.0 / (1.0 + m2 / scale ** 2), 0.0)
        de = -sa * c[:, 0] + ca * c[:, 1]  # d e1 / d alpha
        c2 = np.cos(al - a0)
        vals = np.concatenate([
            np.column_stack([cp, sp_, -de, de - sp_ * X[node, 0] + cp * X[node, 1],
                             -np.ones(K)]).ravel(),
            np.column_stack([-c2, c2]).ravel()])
        J = sp.csr_matrix((vals, (rows, cols)), shape=(2 * K, nv))
        W = np.concatenate([w1 * wr, w2 * wr])
        H = (J.T @ sp.diags(W) @ J).tocsc()
        g = J.T @ (W * np.concatenate([e1, e2]))
        Hg, gg, _ = graph.normal_equations(X, ROBUST_SCALE, edges)
        # in place: at the daemon's scale Hg is 10^7 entries, and every copy costs 130 MB
        Hg.data *= P.graph_weight
        Hg.resize((nv, nv))
        H = Hg + H + hold
        del Hg
        g[:3 * n] += P.graph_weight * gg
        dx = solve_normal(H, -g, n)
        X += dx[:3 * n].reshape(n, 3)
        X[:, 2] = wrap(X[:, 2])
        phi += dx[3 * n::2]
        rho += dx[3 * n + 1::2]
        info["iterations"] = it + 1
        if np.max(np.abs(dx[:3 * n])) < 1e-5:
            break
    info["outliers"] = int(np.sum(wr < 0.1))
    return X, info
