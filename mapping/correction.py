"""Pose correction from segment matches (seed 000 eqs. 10-11): theta = theta_odo + theta_err,
T = T_odo + T_err, with the errors from matching the scan's segments against the global map.

The errors are solved by robust (Cauchy-weighted) Gauss-Newton least squares on
point-to-line distances: each observed segment matched to a map line contributes its squared
distance integrated along the segment, exactly as two Gauss points per segment (the distance
is linear along a segment); with ``min_length`` a short segment's offset counts as if it
were that long (a third point, at its middle, carries what it lacks).  Matches are re-found
at every iteration with gates that shrink, so a large odometry error is pulled in step by
step.  The odometry prediction enters as a prior (its covariance grows with the step), which
keeps the pose defined along a corridor where the walls fix only one direction.  The returned
covariance (inverse information) and the matched fraction of the scan are the match-quality
figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .jit import inverse3_into, kernel
from .matching import LineIndex, line_normals, match_index, near_box, near_segments, pair_cost
from .odometry import move_points
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
    # matching needs it (:class:`~cgamap.mapping.finishing.NeighbourParams`): a wall cut to a
    # stub by the other scan's field of view otherwise tilts the pair by a degree
    extrapolation: float = 0.0
    # a segment shorter than this (m) fixes its line's offset as well as one this long: the
    # few points of a door jamb lie on it to a centimetre, but integrated along its length it
    # would weigh next to nothing against the walls, and along a corridor it is what fixes the
    # position (its direction keeps the weight of its own length; 0: off)
    min_length: float = 0.0

    def prior_information(self, step) -> np.ndarray:
        """The odometry prior's information (x, y, theta) after a step of ``step`` metres
        (a scalar, or an array for a batch: (..., 3))."""
        if isinstance(step, float | int):
            # one step (the mapper's, per scan): floats, then the same power on three values
            st = self.prior_trans + self.prior_trans_per_m * step
            sr = self.prior_rot + self.prior_rot_per_m * step
            return np.array([st, st, sr]) ** -2
        step = np.asarray(step, dtype=float)
        st = self.prior_trans + self.prior_trans_per_m * step
        sr = self.prior_rot + self.prior_rot_per_m * step
        out = np.empty(step.shape + (3,))
        out[..., 0] = out[..., 1] = st ** -2
        out[..., 2] = sr ** -2
        return out


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
    away (they never match).  Each problem runs the Gauss-Newton passes of
    :func:`correct_pose` and stops on its own once converged."""
    params = params or CorrectionParams()
    pred = np.ascontiguousarray(predicted, dtype=float)
    n_pairs = len(pred)
    step = np.full(n_pairs, step, dtype=float) if np.isscalar(step) else np.asarray(step, float)
    w_prior = np.ascontiguousarray(params.prior_information(step))
    f = np.ascontiguousarray
    x, H, info, matches, rms, matched = _gauss_newton(
        f(seg_a, dtype=float), f(seg_b, dtype=float), f(index.centre, dtype=float),
        f(index.half, dtype=float), f(index.n, dtype=float), f(index.c, dtype=float), pred,
        w_prior, np.array(params.gates, dtype=float),
        np.sin(np.deg2rad(np.array(params.angle_gates_deg, dtype=float))),
        params.sigma_point ** 2, params.converged_gate, params.extrapolation,
        params.min_length)
    total = np.linalg.norm(seg_b - seg_a, axis=-1).sum(axis=1)
    return BatchCorrection(x, _inverse3(H), matched / np.maximum(total, 1e-12), rms, matches,
                           info)


def _inverse3(H: np.ndarray) -> np.ndarray:
    """Inverses of symmetric (P, 3, 3) matrices (a lone 3x3 costs numpy's inv more in the
    call than in the arithmetic)."""
    out = np.empty_like(H)
    inverse3_into(H, out)
    return out


@kernel
def _gauss_newton(sa, sb, centre, half, n, c, pred, w_prior, gates, sin_gates, var,
                  converged_gate, extrapolation, min_length):
    """The robust Gauss-Newton passes of :func:`correct_batch`, problem by problem.

    Each pass moves the scan segments by the current pose, matches each to its cheapest
    map candidate under the pass's gates (:func:`.matching.pair_cost`), and adds the
    squared point-to-line distance at the segment's two Gauss points, and for a segment
    shorter than ``min_length`` at its midpoint with the weight it lacks (Cauchy-weighted
    at a third of the gate, at least 3 cm; with ``extrapolation``, a point past the map
    segment's end weighs less as the extrapolated line's direction is less sure),
    linearised in (x, y, theta), to the odometry prior (eq. 9 wraps theta)."""
    P, k, m = sa.shape[0], sa.shape[1], centre.shape[1]
    x_out = pred.copy()
    H_out = np.zeros((P, 3, 3))
    info_out = np.zeros((P, 3, 3))
    matches = np.full((P, k), -1, np.int64)
    rms = np.zeros(P)
    matched = np.zeros(P)
    two_pi = 2.0 * np.pi
    tg = (0.5 - _G, 0.5 + _G, 0.5)
    H = np.zeros((3, 3))
    g = np.zeros(3)
    Hi = np.zeros((1, 3, 3))
    for p in range(P):
        x0, x1, x2 = pred[p, 0], pred[p, 1], pred[p, 2]
        for it in range(len(gates)):
            gate = gates[it]
            scale = max(gate / 3.0, 0.03)
            co, si = np.cos(x2), np.sin(x2)
            H[:] = 0.0
            g[:] = 0.0
            num = den = mlen = 0.0
            for i in range(k):
                ax = co * sa[p, i, 0] - si * sa[p, i, 1] + x0
                ay = si * sa[p, i, 0] + co * sa[p, i, 1] + x1
                bx = co * sb[p, i, 0] - si * sb[p, i, 1] + x0
                by = si * sb[p, i, 0] + co * sb[p, i, 1] + x1
                length = np.sqrt((bx - ax) ** 2 + (by - ay) ** 2)
                best, cost = -1, np.inf
                for j in range(m):
                    cj = pair_cost(ax, ay, bx, by, length, centre[p, j, 0], centre[p, j, 1],
                                   half[p, j], n[p, j, 0], n[p, j, 1], c[p, j], sin_gates[it],
                                   gate, gate)
                    if cj < cost:
                        best, cost = j, cj
                matches[p, i] = best
                if best < 0:
                    continue
                mlen += length
                nx, ny, cl = n[p, best, 0], n[p, best, 1], c[p, best]
                for q in range(3):
                    # two Gauss points, then the midpoint with what a short one lacks
                    t = tg[q]
                    wq = 0.5 * length if q < 2 else max(min_length - length, 0.0)
                    if wq <= 0.0:
                        continue
                    qx, qy = ax + t * (bx - ax), ay + t * (by - ay)
                    e = nx * qx + ny * qy - cl
                    j2 = ny * (qx - x0) - nx * (qy - x1)
                    if extrapolation > 0.0:
                        hl = half[p, best]
                        along = (qx - centre[p, best, 0]) * ny - (qy - centre[p, best, 1]) * nx
                        past = max(abs(along) - hl, 0.0)
                        w = wq / (var + (past * extrapolation / max(2.0 * hl, 1e-3)) ** 2)
                    else:
                        w = wq / var
                    w /= 1.0 + (e / scale) ** 2
                    H[0, 0] += w * nx * nx
                    H[0, 1] += w * nx * ny
                    H[0, 2] += w * nx * j2
                    H[1, 1] += w * ny * ny
                    H[1, 2] += w * ny * j2
                    H[2, 2] += w * j2 * j2
                    g[0] += w * nx * e
                    g[1] += w * ny * e
                    g[2] += w * j2 * e
                    if q < 2:  # the residual: the segment's points, as they are
                        num += wq * e * e
                        den += wq
            H[1, 0], H[2, 0], H[2, 1] = H[0, 1], H[0, 2], H[1, 2]
            r2 = (x2 - pred[p, 2] + np.pi) % two_pi - np.pi
            g0 = g[0] + w_prior[p, 0] * (x0 - pred[p, 0])
            g1 = g[1] + w_prior[p, 1] * (x1 - pred[p, 1])
            g2 = g[2] + w_prior[p, 2] * r2
            for d in range(3):
                info_out[p, d] = H[d]
                Hi[0, d] = H[d]
                Hi[0, d, d] += w_prior[p, d]
                H_out[p, d] = Hi[0, d]
            inverse3_into(Hi, Hi)
            d0 = Hi[0, 0, 0] * g0 + Hi[0, 0, 1] * g1 + Hi[0, 0, 2] * g2
            d1 = Hi[0, 1, 0] * g0 + Hi[0, 1, 1] * g1 + Hi[0, 1, 2] * g2
            d2 = Hi[0, 2, 0] * g0 + Hi[0, 2, 1] * g1 + Hi[0, 2, 2] * g2
            x0, x1 = x0 - d0, x1 - d1
            x2 = (x2 - d2 + np.pi) % two_pi - np.pi
            rms[p] = np.sqrt(num / max(den, 1e-12))
            matched[p] = mlen
            if gate <= converged_gate and max(abs(d0), abs(d1), abs(d2)) < 5e-4:
                break  # converged and the gates are already tight
        x_out[p, 0], x_out[p, 1], x_out[p, 2] = x0, x1, x2
    return x_out, H_out, info_out, matches, rms, matched


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

    def unmatched() -> Correction:
        prior_cov = np.diag(1.0 / params.prior_information(step))
        return Correction(pred.copy(), prior_cov, 0.0, float(L.sum()), 0.0, np.full(k, -1))

    if k == 0 or len(map_a) == 0:
        return unmatched()
    # map segments anywhere near the scan under the widest gate; later passes look only there
    ga, gb = move_points(seg_l.a, pred), move_points(seg_l.b, pred)
    wide = max(params.gates) * 1.5
    # only map segments whose eq. (15) sphere can reach the scan's: centre within the sum of
    # the radii (+ the margin on both) of the scan's bounding box
    reach = 0.5 * float(L.max()) + 2.0 * wide
    if map_index is not None:
        box = near_box(map_index.centre, map_index.half, ga, gb, reach)
        index = map_index.subset(box)
    else:
        box = near_segments(map_a, map_b, ga, gb, reach)
        ab, bb = map_a[box], map_b[box]
        index = LineIndex(ab, bb, 0.5 * (ab + bb), 0.5 * np.linalg.norm(bb - ab, axis=-1),
                          *line_normals(ab, bb))
    ok0, _ = match_index(ga, gb, index, np.deg2rad(max(params.angle_gates_deg)), wide)
    near = box[np.nonzero(ok0.any(axis=0))[0]]
    if not len(near):
        return unmatched()
    sub = index.subset(np.searchsorted(box, near))
    res = correct_batch(seg_l.a[None], seg_l.b[None],
                        LineIndex(*(v[None] for v in vars(sub).values())), pred[None], step,
                        params)
    m = res.matches[0]
    matched = float(L[m >= 0].sum())
    return Correction(res.pose[0], res.cov[0], matched, float(L.sum()), float(res.rms[0]),
                      np.where(m >= 0, near[np.maximum(m, 0)], -1), near)
