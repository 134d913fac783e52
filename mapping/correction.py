"""Pose correction from segment matches (seed 000 eqs. 10-11): theta = theta_odo + theta_err,
T = T_odo + T_err, with the errors from matching the scan's segments against the global map.

The errors are solved by robust (Cauchy-weighted) Gauss-Newton least squares on
point-to-line distances: each observed segment matched to a map line contributes its squared
distance integrated along the segment, exactly as two Gauss points per segment (the distance
is linear along a segment).  Matches are re-found at every iteration with gates that shrink,
so a large odometry error is pulled in step by step.  The odometry prediction enters as a
prior (its covariance grows with the step), which keeps the pose defined along a corridor
where the walls fix only one direction.  The returned covariance (inverse information) and
the matched fraction of the scan are the match-quality figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .matching import LineIndex, line_normals, match_index
from .segments import Segments

_G = 0.5 / np.sqrt(3.0)  # Gauss points at t = 1/2 -+ 1/(2 sqrt 3) integrate quadratics exactly


@dataclass(frozen=True)
class CorrectionParams:
    gates: tuple[float, ...] = (0.4, 0.25, 0.15, 0.1, 0.08)
    angle_gates_deg: tuple[float, ...] = (15.0, 9.0, 5.0, 4.0, 3.0)
    prior_trans: float = 0.02          # odometry prior std (m) at zero travel ...
    prior_trans_per_m: float = 0.08    # ... plus this per metre of odometry step
    prior_rot: float = 0.01            # rad, plus per metre:
    prior_rot_per_m: float = 0.03
    sigma_point: float = 0.06          # point-to-line noise (m), map error included
    converged_gate: float = 0.12       # stop early once the gate is this tight and still
    # beyond the ends of the segment it matched, a point is compared with that segment's line
    # extrapolated, whose direction a segment l long fixes only to about extrapolation / l
    # rad: the point's variance grows with its distance past the end (0: off).  Scan-to-scan
    # matching needs it (:class:`~cgamap.mapping.slam2d.NeighbourParams`): a wall cut to a
    # stub by the other scan's field of view otherwise tilts the pair by a degree
    extrapolation: float = 0.0


@dataclass
class Correction:
    pose: np.ndarray          # corrected (x, y, theta) of the laser in the global frame
    cov: np.ndarray           # 3x3 covariance of the corrected pose
    matched_length: float     # length of scan segments matched in the last iteration (m)
    total_length: float
    rms: float                # RMS point-to-line residual of the matches (m)
    matches: np.ndarray       # map index per scan segment, -1 unmatched
    near: np.ndarray | None = None  # map segments within the widest gate of the scan

    @property
    def matched_fraction(self) -> float:
        return self.matched_length / self.total_length if self.total_length > 0 else 0.0


def _rot_t(theta) -> np.ndarray:
    """Transposes of the rotations by theta (...,) -> (..., 2, 2): row vectors
    p @ _rot_t(t) are rotated by t."""
    c, s = np.cos(theta), np.sin(theta)
    out = np.empty(np.shape(c) + (2, 2))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, s, -s, c
    return out


def _solve3(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """x with H x = g for (P, 3, 3) H (symmetric positive definite) and (P, 3) g.  One
    problem (a scan's correction) is solved by the adjugate in plain floats: numpy's calls
    on 3-element arrays cost more than the rest of a small problem's Gauss-Newton pass."""
    if len(H) != 1:
        return np.linalg.solve(H, g[..., None])[..., 0]
    (a, b, c), (_, d, e), (_, _, f) = H[0].tolist()
    g0, g1, g2 = g[0].tolist()
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    return np.array([[(A * g0 + B * g1 + C * g2) / det, (B * g0 + D * g1 + E * g2) / det,
                      (C * g0 + E * g1 + F * g2) / det]])


def _transform(p: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return p @ _rot_t(pose[2]) + pose[:2]


@dataclass
class BatchCorrection:
    """:func:`correct_batch` results, one row per pair."""

    pose: np.ndarray              # (P, 3)
    cov: np.ndarray               # (P, 3, 3)
    matched_fraction: np.ndarray  # (P,) share of the segments' length matched
    rms: np.ndarray               # (P,) RMS point-to-line residual of the matches (m)
    matches: np.ndarray           # (P, k) map segment per scan segment, -1 unmatched
    info_data: np.ndarray         # (P, 3, 3) information from the matches alone
    # (the prior's taken out): ~0 along what the lines leave free, e.g. along a corridor


def correct_batch(seg_a: np.ndarray, seg_b: np.ndarray, index: LineIndex, predicted,
                  step=1.0, params: CorrectionParams | None = None) -> BatchCorrection:
    """Eqs. (10-11) for P independent problems at once: segments (P, k, 2) in their laser
    frames against P line sets (``index`` over (P, m) segments), from the predictions
    (P, 3) after steps of ``step`` metres (scalar or (P,)).

    Pad with zero-length scan segments (they weigh nothing) and with map segments far
    away (they never match).  The Gauss-Newton passes of :func:`correct_pose` run for
    every problem together; they stop early only when all have converged."""
    params = params or CorrectionParams()
    pred = np.asarray(predicted, dtype=float)
    x = pred.copy()
    n_pairs, k = seg_a.shape[:2]
    L = np.linalg.norm(seg_b - seg_a, axis=-1)
    step = np.full(n_pairs, step, dtype=float) if np.isscalar(step) else np.asarray(step, float)
    st = params.prior_trans + params.prior_trans_per_m * step
    sr = params.prior_rot + params.prior_rot_per_m * step
    w_prior = np.stack([st ** -2, st ** -2, sr ** -2], -1)
    H0 = np.zeros((n_pairs, 3, 3))
    H0[:, [0, 1, 2], [0, 1, 2]] = w_prior
    H = H0
    matches = np.full((n_pairs, k), -1)
    use = np.zeros((n_pairs, 2 * k), bool)
    e = np.zeros((n_pairs, 2 * k))
    # the two Gauss points of every segment, laser frame
    q = np.concatenate([seg_a + (0.5 - _G) * (seg_b - seg_a),
                        seg_a + (0.5 + _G) * (seg_b - seg_a)], axis=1)
    wq = np.concatenate([L, L], axis=1) * 0.5
    rows = np.arange(n_pairs)[:, None]
    pts = np.concatenate([seg_a, seg_b, q], axis=1)  # moved together: one product per pass
    # (each pass below is a fixed number of numpy calls over all problems at once: with
    # one problem of a few dozen segments, the calls are the cost, not the arithmetic)
    if k and index.a.shape[-2]:
        var = params.sigma_point ** 2
        wq_var = wq / var
        # the Jacobian's columns and the residual as a fourth: H and g are one product
        Je = np.empty((n_pairs, 2 * k, 4))
        for gate, ag in zip(params.gates, params.angle_gates_deg, strict=True):
            t = x[:, None, :2]
            moved = pts @ _rot_t(x[:, 2]) + t
            qg = moved[:, 2 * k:]
            ok, cost = match_index(moved[:, :k], moved[:, k:2 * k], index, np.deg2rad(ag), gate)
            best = np.argmin(cost, axis=-1)
            has = ok.any(axis=-1)
            matches = np.where(has, best, -1)
            r = x - pred
            r[:, 2] = (r[:, 2] + np.pi) % (2.0 * np.pi) - np.pi  # eq. (9)
            jm = np.concatenate([best, best], axis=1)
            use = np.concatenate([has, has], axis=1)
            n = index.n[rows, jm]
            nx, ny = n[..., 0], n[..., 1]
            e = nx * qg[..., 0] + ny * qg[..., 1] - index.c[rows, jm]
            rel = qg - t
            Je[..., :2] = n
            Je[..., 2] = ny * rel[..., 0] - nx * rel[..., 1]
            Je[..., 3] = e
            scale = max(gate / 3.0, 0.03)
            if params.extrapolation > 0:
                half = index.half[rows, jm]
                off = qg - index.centre[rows, jm]
                along = off[..., 0] * ny - off[..., 1] * nx
                past = np.maximum(np.abs(along) - half, 0.0)
                w = wq / (var + (past * params.extrapolation / np.maximum(2.0 * half, 1e-3))
                          ** 2)
            else:
                w = wq_var
            w = w * use / (1.0 + (e / scale) ** 2)
            Hg = np.swapaxes(Je[..., :3] * w[..., None], -1, -2) @ Je
            H = H0 + Hg[..., :3]
            dx = -_solve3(H, w_prior * r + Hg[..., 3])
            x = x + dx
            x[:, 2] = (x[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
            if gate <= params.converged_gate and np.abs(dx).max() < 5e-4:
                break  # converged and the gates are already tight
    total = L.sum(axis=1)
    matched = np.sum(L * (matches >= 0), axis=1)
    wu = np.where(use, wq, 0.0)
    rms = np.sqrt(np.sum(wu * e ** 2, axis=1) / np.maximum(np.sum(wu, axis=1), 1e-12))
    return BatchCorrection(x, np.linalg.inv(H), matched / np.maximum(total, 1e-12), rms,
                           matches, H - H0)


def correct_pose(seg_l: Segments, map_a: np.ndarray, map_b: np.ndarray, predicted,
                 step: float = 1.0, params: CorrectionParams | None = None,
                 map_index: LineIndex | None = None) -> Correction:
    """Corrected laser pose for segments ``seg_l`` (laser frame) against map lines a-b,
    starting from the odometry prediction ``predicted`` (x, y, theta) after a step of
    ``step`` metres."""
    params = params or CorrectionParams()
    pred = np.asarray(predicted, dtype=float)
    k = len(seg_l)
    L = seg_l.length
    st = params.prior_trans + params.prior_trans_per_m * step
    sr = params.prior_rot + params.prior_rot_per_m * step
    prior_cov = np.diag([st ** 2, st ** 2, sr ** 2])
    unmatched = Correction(pred.copy(), prior_cov, 0.0, float(L.sum()), 0.0, np.full(k, -1))
    if k == 0 or len(map_a) == 0:
        return unmatched
    # map segments anywhere near the scan under the widest gate; later passes look only there
    ga, gb = _transform(seg_l.a, pred), _transform(seg_l.b, pred)
    wide = max(params.gates) * 1.5
    # only map segments whose eq. (15) sphere can reach the scan's: centre within the sum of
    # the radii (+ the margin on both) of the scan's bounding box
    if map_index is not None:
        centre, half = map_index.centre, map_index.half
    else:
        centre, half = 0.5 * (map_a + map_b), 0.5 * np.linalg.norm(map_b - map_a, axis=-1)
    lo = np.minimum(ga, gb).min(axis=0)
    hi = np.maximum(ga, gb).max(axis=0)
    reach = 0.5 * float(L.max()) + half + 2.0 * wide
    box = np.nonzero(np.all((centre >= lo - reach[:, None]) & (centre <= hi + reach[:, None]),
                            axis=1))[0]
    if map_index is not None:
        index = map_index.subset(box)
    else:
        ab, bb = map_a[box], map_b[box]
        index = LineIndex(ab, bb, centre[box], half[box], *line_normals(ab, bb))
    ok0, _ = match_index(ga, gb, index, np.deg2rad(max(params.angle_gates_deg)), wide)
    near = box[np.nonzero(ok0.any(axis=0))[0]]
    if not len(near):
        return unmatched
    sub = index.subset(np.searchsorted(box, near))
    res = correct_batch(seg_l.a[None], seg_l.b[None],
                        LineIndex(*(v[None] for v in vars(sub).values())), pred[None], step,
                        params)
    m = res.matches[0]
    matched = float(L[m >= 0].sum())
    return Correction(res.pose[0], res.cov[0], matched, float(L.sum()), float(res.rms[0]),
                      np.where(m >= 0, near[np.maximum(m, 0)], -1), near)
