"""Relocalisation in the Hough domain (seed 000 §V, PRL §5): a pose from one scan and a map.

1. Both segment sets go to (theta, rho) (the map's in the global frame, the scan's in the
   laser frame).
2. Rotation hypotheses: every pairing of a map line with a scan line votes for its wrap-aware
   angle difference (eq. 9), weighted by the shorter length, in a circular histogram taken
   modulo pi (a line's normal may point either way depending on which side the origin is);
   peaks give the rotor, refined by the average difference of the pairs in the peak, and each
   peak is tried with +pi too.
3. Translation: with the rotation fixed, a scan line l that lies on map line g gives
   n_g . T = c_g - s c_l (s = +-1, the normals' relative sign).  Two scan lines of different
   directions paired with two map lines of the same directions fix T; all such intersections
   vote in a coarse grid over the map, and the best cells are the translation hypotheses.
4. Verification (``point_refine``, the default): the best distinct coarse candidates are
   pulled in by a batched point-to-segment ICP (every scan point against the map segment
   nearest to it, read from a nearest-segment grid of the distance field; Cauchy weights;
   gates that shrink), re-ranked by the soft fit of the points (each counts
   1 - (d / inlier)^2), and the best dozen refined on all points.  The ranking is the soft
   fit less ``cross_weight`` times the fraction of beams that would pass through a mapped
   wall (free space the hypothesis contradicts; a wall counts only when its line separates
   the laser from the beam's end by ``cross_margin``, so grazing beams and small map error do
   not), the inlier count breaking ties.  "Not found" when the best inlier fraction is under
   ``min_score``.  With ``point_refine`` off, the older path: the segment correction of
   :mod:`.correction` and a grid polish on the soft score.
3b. Cluttered scans with one or two short lines give no line-pair intersection near the truth:
   a correlative sweep (the scan points against the map's near-wall mask, on a coarse grid,
   per rotation hypothesis) adds its best cells as further translation hypotheses; and when
   no hypothesis fits better than ``fallback_fit`` (the lines named no right rotation: the
   scan's segments are furniture at odd angles), the sweep runs over all rotations.
   The all-rotation sweep reads only the free-space band: grid positions within ``reach``
   of a mapped wall, where ``reach`` is a bound from the scan's own ranges (a pose passing
   ``min_score`` has a wall within the k-th shortest range, :func:`.sweep.reach_bound`), so
   empty space around or inside a big map is never read; the band's connected pieces are
   read as a few windows.  In both sweeps each scan point reads its window of the
   (phase-split) near-wall mask for all rotations in one fancy index, so the Python work is
   points x windows and the memory traffic rotations x points x positions.  The fallback's
   cells per rotation come from the columns with the best maxima (:func:`.sweep.top_cells`),
   not a selection over every count, and ties of the wide count (the bound over the cell) go
   to the cell whose own pose fits more points (a tight count in the same byte): its recall,
   not its speed, decides the cluttered scans (Intel, 3 maps x 910 scans: 129 -> 117
   failures, none new).
   The line path's sweep (a dozen rotations) reads the whole grid as before.

Symmetric places (corridors, identical rooms) give several hypotheses with similar scores; all
are returned, ranked.

This module runs the steps; they live in :mod:`.distance_field` (the field and its masks),
:mod:`.line_hypotheses` (steps 2-3), :mod:`.sweep` (3b) and :mod:`.pose_verify` (4).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .correction import CorrectionParams, correct_pose
from .distance_field import DistanceField
from .line_hypotheses import line_candidates, rotation_peaks
from .linemap import LineMap
from .matching import LineIndex, line_angles, line_normals
from .odometry import move_points
from .odometry import wrap_angle as _wrap
from .pose_verify import (
    best_distinct,
    crossed_fractions,
    distinct_cells,
    fit_scores,
    icp_poses,
    inlier_scores,
    polish_pose,
)
from .segments import Segments
from .sweep import correlative_sweep, fallback_sweep, reach_bound


@dataclass(frozen=True)
class RelocParams:
    angle_bin_deg: float = 1.0
    rotation_peaks: int = 6          # rotation hypotheses (each also tried + pi)
    min_pair_angle_deg: float = 30.0  # two scan lines used for translation differ by this
    max_scan_lines: int = 6           # longest scan segments used for hypotheses
    angle_tol_deg: float = 3.0        # map/scan line pairing under a rotation hypothesis
    grid: float = 0.2                 # translation vote cell (m)
    translation_peaks: int = 200      # cells verified per rotation hypothesis
    overlap_slack: float = 0.3        # a scan segment may stick out of its map segment by
    inlier_dist: float = 0.12
    coarse_dist: float = 0.2          # first ranking of the (coarse) translation cells
    refine: int = 6                   # best hypotheses refined by point-to-line matching
    min_score: float = 0.5            # "not found" under this fraction of inlier points
    field_resolution: float = 0.05
    verify_points: int = 40
    polish: bool = True               # final local search on the soft point score
    fit_weight: float = 100.0         # ranking = score + fit_weight * fit: by the soft fit,
    # which tells the tighter of two symmetric places apart (the inlier count only breaks ties)
    endpoint_lines: int = 1           # scan lines whose end points propose corridor positions
    # ... and this many in a corridor-like scan: under ``corridor_share`` of its segments'
    # length crosses its longest line by ``min_pair_angle_deg`` or more, so few line pairs
    # fix the position along it, and a wall piece's end at a door recess is what does.
    # Simulated 150 m corridor (100 trials against the map's trajectory): success 0.73 ->
    # 0.88, the right pose among the first three 0.74 -> 0.96; Intel: 15 % of its scans
    # are such, success 0.98 -> 0.975 (one trial lands 0.23 m off, 0.11 m before), median
    # 31 ms either way (44 ms with 6 lines for every scan)
    corridor_share: float = 0.2
    corridor_endpoint_lines: int = 6
    crossing_weight: float = 0.0      # score = inlier fraction - this * crossing fraction
    crossing_step: float = 0.08       # free-space samples along each beam (m)
    map_share: float = 0.5            # a map line pairs with a scan line at least this long
    sweep_cells: int = 20             # best cells of a correlative sweep per rotation (0: off)
    sweep_grid: float = 0.25          # cell of the sweep (m)
    sweep_points: int = 20            # scan points correlated by the sweep
    # a sweep window of more positions than this (a big building's map) is swept coarse to
    # fine: cells of sweep_coarse x sweep_coarse positions first, each with a bound on its
    # positions' counts, and only the cells whose bound reaches the best counts are counted
    # position by position (the same k best per rotation as counting every position)
    sweep_direct: int = 60_000
    sweep_coarse: int = 3
    # with a hint (``near``), the sweeps read only the positions and rotations it allows, so
    # their best cells are the best near it (swept over the whole map, a look-alike place
    # elsewhere takes them and the hint's neighbourhood gets none)
    sweep_near: bool = True
    # point-based verification (on unless off): the best coarse candidates are pulled in by
    # a batched point-to-segment ICP against the map's nearest segments, re-ranked, and the
    # best dozen refined on all points (instead of the segment correction + grid polish;
    # ``polish`` and ``crossing_weight`` belong to that older path)
    point_refine: bool = True
    icp_candidates: int = 120         # distinct coarse candidates pulled in on a subsample
    icp_points: int = 48              # scan points of that first pull
    icp_gates: tuple[float, ...] = (0.5, 0.3, 0.2, 0.12)   # gate (m) per iteration
    final_gates: tuple[float, ...] = (0.2, 0.12, 0.08, 0.06, 0.06)
    final_candidates: int = 12        # of those, refined on all points and ranked
    cross_weight: float = 0.15        # rank = fit - this * crossing fraction (free space)
    cross_skip: float = 0.3           # beam length (m) near the laser that never counts
    cross_beams: int = 60             # beams sampled for the crossing fraction
    cross_margin: float = 0.2         # a crossed wall's line lies this far (perpendicular)
    # from both the laser and the beam's end: grazing beams and a laser in a doorway the
    # map drew shut do not count
    cross_range: float = 20.0         # beams are checked up to this far from the laser
    # cluttered scans: when no hypothesis fits better than this (soft fit), sweep all
    # rotations (0: never); off with the sweep (sweep_cells 0)
    fallback_fit: float = 0.75
    fallback_rot_deg: float = 3.0
    fallback_cells: int = 10
    fallback_grid: float = 0.3
    fallback_points: int = 15         # at most 15: the wide and tight counts share a byte
    fallback_icp: int = 30            # distinct sweep candidates the ICP pulls in (the sweep
    # ranks them well: 15-120 found the same poses over 3 maps x 3 seeds)
    fallback_final: int = 6           # of those, refined on all points and ranked (6-12 the


    # same poses; half the final ICP and free-space cost of 12)


@dataclass
class Hypothesis:
    pose: np.ndarray   # (x, y, theta) of the laser in the map frame
    score: float       # fraction of scan points near map segments
    fit: float = 0.0   # soft version (1 - (d / inlier)^2 per point), breaks near-ties
    crossing: float = 0.0  # fraction of beams through mapped walls (point verification)


@dataclass
class RelocResult:
    found: bool
    pose: np.ndarray | None
    score: float
    hypotheses: list[Hypothesis]  # ranked; when found, the first is the answer


def _rotation_hypotheses(phi_g, len_g, phi_l, len_l, P: RelocParams) -> np.ndarray:
    """Rotation peaks (:func:`rotation_peaks`), each also + pi (a line's normal may point
    either way)."""
    peaks = rotation_peaks(phi_g, len_g, phi_l, len_l, P.angle_bin_deg, P.rotation_peaks)
    return np.column_stack([peaks, peaks + np.pi]).ravel()


def _line_params(a: np.ndarray, b: np.ndarray):
    n, c = line_normals(a, b)
    return n, c, line_angles(a, b)


def rivals(hypotheses: list[Hypothesis], best: Hypothesis, margin: float,
           min_dist: float = 0.3) -> list[Hypothesis]:
    """The hypotheses that score within ``margin`` of ``best`` at a place more than
    ``min_dist`` from it, one per place (best first): a look-alike corridor or room.  A
    pose with rivals is ambiguous; a robot should move and look again before it jumps."""
    out: list[Hypothesis] = []
    for h in hypotheses:
        if h is best or h.score <= best.score - margin:
            continue
        if all(np.hypot(*(h.pose[:2] - o.pose[:2])) > min_dist for o in [best, *out]):
            out.append(h)
    return out


def crossing_share(seg: Segments, min_angle_deg: float) -> float:
    """Share of a scan's segment length at ``min_angle_deg`` or more from its longest
    segment's direction: ~0 in a corridor (its walls, a few jambs), 0.3-0.5 in a room."""
    L = seg.length
    if not len(L) or L.sum() <= 0:
        return 0.0
    d = seg.b - seg.a
    phi = np.arctan2(d[:, 1], d[:, 0])
    off = np.abs(_wrap(2 * (phi - phi[np.argmax(L)]))) / 2  # lines: modulo pi
    return float(L[off >= np.deg2rad(min_angle_deg)].sum() / L.sum())


def relocalize(lmap: LineMap, seg: Segments, field: DistanceField | None = None,
               params: RelocParams | None = None,
               near: tuple[np.ndarray, float, float] | None = None) -> RelocResult:
    """Pose of the laser in the map from one scan's segments (laser frame) and points.
    ``near``: (pose, metres, radians): a prior (a loop closure's current estimate): only
    candidates within that distance and turn of the pose are verified, the pose among them."""
    P = params or RelocParams()
    field = field or DistanceField(lmap, P.field_resolution)
    # one line fixes no position, but the sweep (points against the map) may still
    min_seg = 1 if (P.point_refine and P.sweep_cells) else 2
    if len(seg) < min_seg or len(lmap) < 2 or len(seg.points) < 5:
        return RelocResult(False, None, 0.0, [])
    order = np.argsort(-seg.length)[: P.max_scan_lines]
    n_end = (P.corridor_endpoint_lines if crossing_share(seg, P.min_pair_angle_deg)
             < P.corridor_share else P.endpoint_lines)
    sa, sb = seg.a[order], seg.b[order]
    len_l = np.linalg.norm(sb - sa, axis=-1)
    len_g = lmap.length
    n_g, c_g, phi_g = _line_params(lmap.a, lmap.b)
    ga, gb = (np.ascontiguousarray(v, dtype=float) for v in (lmap.a, lmap.b))
    _, c_l0, phi_l0 = _line_params(sa, sb)
    rots = _rotation_hypotheses(phi_g, len_g, phi_l0, len_l, P)
    pts = seg.points
    if len(pts) > P.verify_points:
        pts = pts[np.linspace(0, len(pts) - 1, P.verify_points).astype(int)]
    tol = np.deg2rad(P.angle_tol_deg)
    cand_T, cand_R = [], []
    lo = field.lo
    span = field.size * field.res
    gshape = np.ceil(span / P.grid).astype(int) + 1
    sig = np.array([1.0, -1.0])  # a peak's rotation and its twin + pi: the twin turns the
    # scan's points and normals by pi (same lines, same pairing, opposite normal signs), so
    # both share the pairing, residuals and signs computed once
    for th0 in rots[0::2]:
        if near is not None and min(abs(_wrap(th0 + t * np.pi - near[0][2])) for t in (0, 1)
                                    ) > near[2] + tol:
            continue  # no candidate of this rotation or its twin could be kept
        c, s = np.cos(th0), np.sin(th0)
        R = np.array([[c, -s], [s, c]])
        ra, rb = sa @ R.T, sb @ R.T
        n_l, c_l, phi_l = _line_params(ra, rb)
        for t in (0, 1):
            th = th0 + t * np.pi
            T, D, Tf, Df = line_candidates(
                ga, gb, n_g, c_g, phi_g, len_g, ra, rb, n_l, c_l, phi_l, len_l, sig[t], tol,
                P.map_share, P.overlap_slack, np.deg2rad(P.min_pair_angle_deg), n_end)
            if len(Tf):
                cand_T.append(Tf)
                cand_R.append(th + Df)
            cell = np.floor((T - lo) / P.grid).astype(int)
            inside = np.all((cell >= 0) & (cell < gshape), axis=-1)
            T, D, cell = T[inside], D[inside], cell[inside]
            if not len(T):
                continue
            # the occupied cells only (a big map's grid is mostly empty: a dense vote grid
            # cost as much to fill and partition as everything else in a trial)
            cells, which, votes = np.unique(cell[:, 0] * gshape[1] + cell[:, 1],
                                            return_inverse=True, return_counts=True)
            kk = min(P.translation_peaks, len(cells))
            top = np.argpartition(-votes, kk - 1)[:kk] if kk < len(cells) else slice(None)
            # the hypothesis of a cell: mean of the intersections that fell in it
            sums_x = np.bincount(which, T[:, 0], len(cells))[top]
            sums_y = np.bincount(which, T[:, 1], len(cells))[top]
            sums_d = np.bincount(which, D, len(cells))[top]
            cand_T.append(np.stack([sums_x, sums_y], -1) / votes[top][:, None])
            cand_R.append(th + sums_d / votes[top])
    if P.sweep_cells and len(rots):
        Ts_, Rs_ = correlative_sweep(field, pts, rots, P, near=near if P.sweep_near else None,
                                     turn_slack=tol)
        cand_T.append(Ts_)
        cand_R.append(Rs_)
    if near is not None:
        cand_T.append(np.asarray(near[0][:2], float)[None])
        cand_R.append(np.array([near[0][2]], float))
    if not cand_T:
        return RelocResult(False, None, 0.0, [])
    T = np.concatenate(cand_T)
    th = np.concatenate(cand_R)
    if near is not None:
        keep = _near(T, th, near)
        T, th = T[keep], th[keep]
    if P.point_refine:
        hyps = _verify_points(field, seg.points, T, th, pts, P)
        if P.sweep_cells and P.fallback_fit and (
                not hyps or max(h.fit for h in hyps) < P.fallback_fit):
            # the free-space band the all-rotation sweep is restricted to (a bound from
            # the scan's ranges)
            reach = reach_bound(seg.points, P, field.res)
            T2, th2 = fallback_sweep(field, pts, P, reach,
                                     near=near if P.sweep_near else None)
            if near is not None:
                keep = _near(T2, th2, near)
                T2, th2 = T2[keep], th2[keep]
            hyps += _verify_points(field, seg.points, T2, th2, pts,
                                   replace(P, icp_candidates=P.fallback_icp,
                                           final_candidates=P.fallback_final))
        return _ranked(hyps, P)
    scores = inlier_scores(field, pts, T, th, P.coarse_dist)
    best = np.argsort(-scores)[: max(P.refine * 3, P.refine)]
    hyps: list[Hypothesis] = []
    index = LineIndex.of(lmap.a, lmap.b)
    cp = CorrectionParams(prior_trans=0.3, prior_trans_per_m=0.0, prior_rot=0.1,
                          prior_rot_per_m=0.0)
    for b in best:
        pose0 = np.array([T[b, 0], T[b, 1], _wrap(th[b])])
        if any(np.hypot(*(h.pose[:2] - pose0[:2])) < 0.3 and abs(_wrap(h.pose[2] - pose0[2]))
               < 0.05 for h in hyps):
            continue
        if len(hyps) >= P.refine:
            break
        corr = correct_pose(seg, lmap.a, lmap.b, pose0, 0.0, cp, index)
        pose = corr.pose
        if P.polish:
            pose = polish_pose(field, seg.points, pose, P.inlier_dist)
        sc = float(inlier_scores(field, seg.points, pose[None, :2], pose[None, 2],
                                 P.inlier_dist)[0])
        fit = float(inlier_scores(field, seg.points, pose[None, :2], pose[None, 2],
                                  P.inlier_dist, soft=True)[0])
        if P.crossing_weight:
            # negative evidence: beams that would pass through mapped walls (off by default:
            # maps built from real logs keep clutter in free space, and it cost more than it
            # gained on the Intel log)
            sc -= P.crossing_weight * crossing_fraction(field, seg.points, pose)
        hyps.append(Hypothesis(pose, sc, fit))
    hyps.sort(key=lambda h: -(h.score + P.fit_weight * h.fit))
    if not hyps or hyps[0].score < P.min_score:
        return RelocResult(False, None, hyps[0].score if hyps else 0.0, hyps)
    return RelocResult(True, hyps[0].pose, hyps[0].score, hyps)


def _near(T: np.ndarray, th: np.ndarray, near: tuple) -> np.ndarray:
    """Which candidates (T, th) lie within ``near``'s (pose, metres, radians)."""
    return (np.hypot(*(T - near[0][:2]).T) < near[1]) & (
        np.abs(_wrap(th - near[0][2])) < near[2])


def _verify_points(field: DistanceField, pts: np.ndarray, T: np.ndarray, th: np.ndarray,
                   coarse_pts: np.ndarray, P: RelocParams) -> list[Hypothesis]:
    """Point-based verification of the coarse candidates (all vectorised over hypotheses):
    the best distinct ones by their inlier fraction at ``coarse_dist`` (of ``coarse_pts``)
    are pulled in by point-to-line ICP on a subsample and re-ranked by their soft fit; the
    best few are refined on all points and ranked by the fit less the free-space evidence
    (beams through mapped walls)."""
    sel = best_distinct(field, coarse_pts, T, th, P.coarse_dist, 0.3, np.deg2rad(3.0),
                        P.icp_candidates)
    sub = pts
    if len(sub) > P.icp_points:
        sub = sub[np.linspace(0, len(sub) - 1, P.icp_points).astype(int)]
    poses = icp_poses(field, sub, np.column_stack([T[sel], th[sel]]), P.icp_gates)
    _, fit = fit_scores(field, sub, poses, P.inlier_dist)
    order = np.argsort(-fit, kind="stable")
    keep = distinct_cells(poses[:, :2], poses[:, 2], order, 0.3, np.deg2rad(3.0),
                          P.final_candidates)
    poses = icp_poses(field, pts, poses[keep], P.final_gates)
    score, fit = fit_scores(field, pts, poses, P.inlier_dist)
    cross = crossed_fractions(field, pts, poses, P) if P.cross_beams else np.zeros(len(poses))
    return [Hypothesis(q.copy(), float(a), float(b), float(c))
            for q, a, b, c in zip(poses, score, fit, cross, strict=True)]


def _rank_key(h: Hypothesis, P: RelocParams) -> float:
    """Ranking: the soft fit less the free-space evidence; with ``fit_weight`` 0, the inlier
    fraction alone (the loop closer's choice)."""
    return h.score + P.fit_weight * (h.fit - P.cross_weight * h.crossing)


def _ranked(hyps: list[Hypothesis], P: RelocParams) -> RelocResult:
    """Best first, starts that converged to one pose merged, at most ``refine`` kept;
    "not found" under ``min_score``."""
    out: list[Hypothesis] = []
    for h in sorted(hyps, key=lambda h: -_rank_key(h, P)):
        if any(np.hypot(*(g.pose[:2] - h.pose[:2])) < 0.1
               and abs(_wrap(g.pose[2] - h.pose[2])) < np.deg2rad(1.0) for g in out):
            continue
        out.append(h)
        if len(out) >= max(P.refine, 1):
            break
    if not out or out[0].score < P.min_score:
        return RelocResult(False, None, out[0].score if out else 0.0, out)
    return RelocResult(True, out[0].pose, out[0].score, out)


def inlier_fraction(points: np.ndarray, pose, a: np.ndarray, b: np.ndarray,
                    inlier: float) -> float:
    """Fraction of laser-frame ``points`` within ``inlier`` of segments a-b once moved by
    ``pose`` (direct point-to-segment distances: for small maps, no distance field)."""
    if not len(points) or not len(a):
        return 0.0
    g = move_points(points, np.asarray(pose, dtype=float))
    d = b - a
    L2 = np.maximum(np.sum(d * d, axis=-1), 1e-12)
    t = np.clip(((g[:, None, 0] - a[None, :, 0]) * d[None, :, 0]
                 + (g[:, None, 1] - a[None, :, 1]) * d[None, :, 1]) / L2[None, :], 0.0, 1.0)
    qx = a[None, :, 0] + t * d[None, :, 0] - g[:, None, 0]
    qy = a[None, :, 1] + t * d[None, :, 1] - g[:, None, 1]
    return float(np.mean(np.min(qx * qx + qy * qy, axis=1) < inlier * inlier))


def crossing_fraction(field: DistanceField, points: np.ndarray, pose, step: float = 0.08,
                      near: float = 0.3, skip: float = 0.0, beams: int = 0) -> float:
    """Fraction of beams (laser origin -> point) that pass through a mapped wall more than
    ``near`` before their end: free space the hypothesis claims the map says is a wall.
    The first ``skip`` metres of a beam never count (a laser standing in a doorway the map
    drew shut); ``beams`` > 0 samples that many beams evenly."""
    if not len(points):
        return 0.0
    if beams and len(points) > beams:
        points = points[np.linspace(0, len(points) - 1, beams).astype(int)]
    r = np.linalg.norm(points, axis=-1)
    n = int(np.ceil(min(r.max(), 20.0) / step))
    f = (np.arange(1, n + 1) * step)[None, :]                       # distances along beams
    valid = (f < (r[:, None] - near)) & (f >= skip)
    u = points / np.maximum(r, 1e-9)[:, None]
    c, s = np.cos(pose[2]), np.sin(pose[2])
    ug = u @ np.array([[c, s], [-s, c]])
    samp = np.asarray(pose[:2])[None, None, :] + f[..., None] * ug[:, None, :]
    d = field.lookup(samp)
    hit = np.any((d < 0.6 * step + 0.5 * field.res) & valid, axis=1)
    return float(np.mean(hit))
