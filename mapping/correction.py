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
from cgamap.cga import angle_diff

from .matching import LineIndex, match_index
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


def _transform(p: np.ndarray, pose: np.ndarray) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return p @ np.array([[c, s], [-s, c]]) + pose[:2]


def correct_pose(seg_l: Segments, map_a: np.ndarray, map_b: np.ndarray, predicted,
                 step: float = 1.0, params: CorrectionParams | None = None,
                 map_index: LineIndex | None = None) -> Correction:
    """Corrected laser pose for segments ``seg_l`` (laser frame) against map lines a-b,
    starting from the odometry prediction ``predicted`` (x, y, theta) after a step of
    ``step`` metres."""
    params = params or CorrectionParams()
    pred = np.asarray(predicted, dtype=float)
    x = pred.copy()
    k = len(seg_l)
    L = seg_l.length
    st = params.prior_trans + params.prior_trans_per_m * step
    sr = params.prior_rot + params.prior_rot_per_m * step
    P = np.diag([1 / st ** 2, 1 / st ** 2, 1 / sr ** 2])
    H = P.copy()
    matches = np.full(k, -1)
    rms = 0.0
    # the two Gauss points of every segment, laser frame
    q = np.concatenate([seg_l.a + (0.5 - _G) * (seg_l.b - seg_l.a),
                        seg_l.a + (0.5 + _G) * (seg_l.b - seg_l.a)])
    wq = np.concatenate([L, L]) * 0.5
    if k == 0 or len(map_a) == 0:
        return Correction(x, np.linalg.inv(P), 0.0, float(L.sum()), 0.0, matches)
    # map segments anywhere near the scan under the widest gate; later passes look only there
    ga, gb = _transform(seg_l.a, x), _transform(seg_l.b, x)
    index = map_index if map_index is not None else LineIndex.of(map_a, map_b)
    ok0, _ = match_index(ga, gb, index, np.deg2rad(max(params.angle_gates_deg)),
                         max(params.gates) * 1.5)
    near = np.nonzero(ok0.any(axis=0))[0]
    if not len(near):
        return Correction(x, np.linalg.inv(P), 0.0, float(L.sum()), 0.0, matches)
    sub = index.subset(near)
    mn, mc = sub.n, sub.c
    for gate, ag in zip(params.gates, params.angle_gates_deg, strict=True):
        ga, gb = _transform(seg_l.a, x), _transform(seg_l.b, x)
        ok, cost = match_index(ga, gb, sub, np.deg2rad(ag), gate)
        best = np.argmin(cost, axis=1)
        has = ok[np.arange(k), best]
        matches = np.where(has, best, -1)
        H = P.copy()
        g = P @ np.array([*(x[:2] - pred[:2]), angle_diff(x[2], pred[2])])
        if has.any():
            jm = np.concatenate([best, best])
            use = np.concatenate([has, has])
            qg = _transform(q, x)[use]
            n, c = mn[jm[use]], mc[jm[use]]
            e = np.sum(n * qg, axis=-1) - c
            rel = qg - x[:2]
            J = np.column_stack([n, n[:, 0] * -rel[:, 1] + n[:, 1] * rel[:, 0]])
            scale = max(gate / 3.0, 0.03)
            w = wq[use] / params.sigma_point ** 2 / (1.0 + (e / scale) ** 2)
            H += J.T @ (w[:, None] * J)
            g += J.T @ (w * e)
            rms = float(np.sqrt(np.sum(wq[use] * e ** 2) / np.sum(wq[use])))
        dx = -np.linalg.solve(H, g)
        x = x + dx
        x[2] = float(angle_diff(x[2], 0.0))
        if gate <= params.converged_gate and np.max(np.abs(dx)) < 5e-4:
            break  # converged and the gates are already tight
    matched = float(L[matches >= 0].sum())
    matches = np.where(matches >= 0, near[np.maximum(matches, 0)], -1)
    return Correction(x, np.linalg.inv(H), matched, float(L.sum()), rms, matches, near)
