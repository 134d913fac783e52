"""Slip recovery: a scan that the odometry put beyond the correction's reach.

The correction (:mod:`.correction`) starts from the odometry's prediction and pulls the pose
in from there, with its first gates (0.4 m, 15 deg) as its reach and the odometry prior
holding it near the prediction.  Wheels that slip, a robot that is pushed or lifted, or a
base whose odometry stands while the robot still rolls, all put the prediction a few degrees
off: along a wall ten metres long, 4 deg moves the far end 0.7 m, past the gates.  The scan
then matches little or nothing, its walls enter the map rotated, and the next scans match
those, so the error stays for good.

When a scan against a mapped neighbourhood matches less than ``below`` of its length, the
rotation is searched in the Hough domain instead (seed 000 §V, eq. 9, as relocalisation does
globally): the length-weighted histogram of angle differences between the scan's lines (at
the prediction) and the map's lines nearby peaks at the rotation that lays the scan onto the
walls.  Each peak within ``max_turn`` becomes a prediction, all are corrected at once
(:func:`.correction.correct_batch`) with the odometry prior widened to a ``step``-metre step,
and the best is taken only when it matches clearly more than the prediction did (``margin``)
and at least ``accept`` of the scan: a scan of new ground keeps its odometry pose.

A shove or wheels that spin in place move the robot (or not) without a turn: when no rotation
hypothesis is taken and the prediction matched almost nothing (``shift_below``), the
translation is searched too, again in the Hough domain.  At each rotation (none and the
peaks), a scan line and a map line of the same direction say how far the scan must move
along the map line's normal (the difference of their rho); two such constraints on lines
that cross give a shift, and the length-weighted votes of all crossing pairs within
``max_shift`` peak at the shift that lays the scan onto the walls.  The peaks are corrected,
and the best is taken only when it matches most of the scan (``shift_accept``), lies beyond
the correction's reach (``min_shift``), and no clearly different pose matches nearly as well
(a corridor whose doors repeat).  The bar is high on purpose.  On the Intel log, a scan whose
odometry was right can match under half its length (open doors, people, new ground), while a
pose a metre along the corridor matches 60-98 % of it.  With a lower bar (any scan the
rotations could not place, 60 % to accept) the search jumped such scans by 1-1.5 m and
nearly doubled the trajectory error; with this one it moves no Intel scan in 16 noise seeds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .correction import Correction, CorrectionParams, correct_batch
from .line_hypotheses import rotation_peaks
from .matching import LineIndex, line_angles, line_normals, near_box
from .odometry import wrap_angle
from .segments import Segments


@dataclass(frozen=True)
class SlipParams:
    enabled: bool = True
    below: float = 0.5           # try when the correction matched less than this share ...
    min_map: float = 2.0         # ... and this much map (m of walls) lies near the scan
    max_turn: float = np.deg2rad(20.0)  # rotation hypotheses within this of the prediction
    peaks: int = 4               # histogram peaks tried (1 deg bins)
    step: float = 1.0            # the odometry prior as wide as after this step (m)
    accept: float = 0.6          # take a hypothesis matching at least this share ...
    margin: float = 0.25         # ... and this much more than the prediction did
    # then shifts, only when the prediction matched less than ``shift_below`` of the scan
    # and a shift matches at least ``shift_accept``: within ``max_shift`` of the prediction
    # (m; 0: rotations only), voted on cells ``shift_cell`` large (m), ``shifts`` peaks per
    # rotation, refused when a pose ``rival_apart`` (m) from the best matches within
    # ``rival`` of it
    shift_below: float = 0.2
    shift_accept: float = 0.8
    min_shift: float = 0.3       # nearer the prediction is the correction's to find
    max_shift: float = 1.5
    shift_cell: float = 0.1
    shifts: int = 3
    rival_apart: float = 0.3
    rival: float = 0.1


def recover(seg: Segments, map_a: np.ndarray, map_b: np.ndarray, predicted,
            corr: Correction, params: CorrectionParams, P: SlipParams
            ) -> Correction | None:
    """A better correction than ``corr`` (the prediction's) from the rotation hypotheses,
    then from the shifts, or None."""
    pred = np.asarray(predicted, dtype=float)
    if len(seg) == 0 or len(map_a) == 0:
        return None
    ga, gb = _place(seg, pred)
    half = 0.5 * np.linalg.norm(map_b - map_a, axis=-1)
    centre = 0.5 * (map_a + map_b)
    # map segments that could meet the scan's: centre within reach of its bounding box
    reach = float(np.max(np.hypot(*np.vstack([seg.a, seg.b]).T))) * np.sin(P.max_turn) + 0.5
    near = near_box(centre, half, ga, gb, reach)
    if 2.0 * half[near].sum() < P.min_map:
        return None
    ma, mb = map_a[near], map_b[near]
    rot = rotation_peaks(line_angles(ma, mb), 2.0 * half[near], line_angles(ga, gb),
                         seg.length, 1.0, P.peaks)
    rot = wrap_angle(2.0 * rot) / 2.0  # undirected: the turn within (-90, 90] deg
    rot = rot[np.abs(rot) <= P.max_turn]
    hyp = np.tile(pred, (len(rot), 1))
    hyp[:, 2] = wrap_angle(pred[2] + rot)
    got = _best(seg, ma, mb, near, hyp, corr, params, P, P.accept, rivals=False)
    if got is not None or P.max_shift <= 0 or corr.matched_fraction >= P.shift_below:
        return got
    near = near_box(centre, half, ga, gb, reach + P.max_shift)
    ma, mb = map_a[near], map_b[near]
    # each rotation unshifted too: a rival any shift must clearly beat
    hyps = []
    for r in (0.0, *rot):
        pose = np.array([pred[0], pred[1], wrap_angle(pred[2] + r)])
        hyps.append(pose)
        for t in shift_votes(*_place(seg, pose), seg.length, ma, mb, P):
            hyps.append([pose[0] + t[0], pose[1] + t[1], pose[2]])
    got = _best(seg, ma, mb, near, np.array(hyps).reshape(-1, 3), corr, params, P,
                P.shift_accept, rivals=True)
    if got is None or np.hypot(*(got.pose[:2] - pred[:2])) < P.min_shift:
        return None
    return got


def _place(seg: Segments, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scan's segment end points (a, b) in the map at ``pose``."""
    g = seg.transformed(*(float(v) for v in pose))
    return g.a, g.b


def _best(seg: Segments, ma: np.ndarray, mb: np.ndarray, near: np.ndarray, hyp: np.ndarray,
          corr: Correction, params: CorrectionParams, P: SlipParams, accept: float,
          rivals: bool) -> Correction | None:
    """The hypotheses corrected together; the best if it matches ``accept`` of the scan and
    ``margin`` more than the prediction did (and, with ``rivals``, no clearly different pose
    matches nearly as well)."""
    if not len(hyp):
        return None
    idx = LineIndex.of(ma, mb)
    batch = LineIndex(*(np.broadcast_to(v, (len(hyp),) + v.shape) for v in vars(idx).values()))
    k = len(seg)
    res = correct_batch(np.broadcast_to(seg.a, (len(hyp), k, 2)),
                        np.broadcast_to(seg.b, (len(hyp), k, 2)), batch, hyp, P.step, params)
    best = int(np.lexsort((res.rms, -res.matched_fraction))[0])
    got = float(res.matched_fraction[best])
    if got < max(accept, corr.matched_fraction + P.margin):
        return None
    if rivals:
        apart = np.hypot(*(res.pose[:, :2] - res.pose[best, :2]).T) > P.rival_apart
        if np.any(apart & (res.matched_fraction >= got - P.rival)):
            return None
    m = res.matches[best]
    L = seg.length
    return Correction(res.pose[best], res.cov[best], float(L[m >= 0].sum()), float(L.sum()),
                      float(res.rms[best]), np.where(m >= 0, near[np.maximum(m, 0)], -1),
                      None)


def shift_votes(ga: np.ndarray, gb: np.ndarray, length: np.ndarray, ma: np.ndarray,
                mb: np.ndarray, P: SlipParams, angle_tol: float = np.deg2rad(2.0),
                min_cross: float = np.deg2rad(30.0), max_lines: int = 400) -> np.ndarray:
    """Shifts (<= ``P.shifts``, strongest first) that move scan segments ga-gb onto map
    segments ma-mb, from the Hough domain: a scan line and a map line of the same direction
    fix the shift along the map line's normal (their rho difference); two of them on lines
    crossing at ``min_cross`` or more fix it, and each such pair votes, weighted by the
    shorter of its lines, on ``P.shift_cell`` cells within ``P.max_shift`` (of the line
    pairs, the ``max_lines`` longest)."""
    n, c = line_normals(ma, mb)
    same = np.abs(wrap_angle(2.0 * (line_angles(ma, mb)[:, None]
                                    - line_angles(ga, gb)[None, :]))) / 2.0 < angle_tol
    mid = 0.5 * (ga + gb)
    delta = c[:, None] - n @ mid.T                       # (map, scan): shift along n
    ml = np.linalg.norm(mb - ma, axis=-1)
    j, i = np.nonzero(same & (np.abs(delta) <= P.max_shift))
    if len(j) < 2:
        return np.zeros((0, 2))
    w = np.minimum(ml[j], length[i])
    if len(j) > max_lines:
        # the pairs of pairs are quadratic: a cluttered map near the scan keeps the longest
        keep = np.argsort(-w)[:max_lines]
        j, i, w = j[keep], i[keep], w[keep]
    A, d = n[j], delta[j, i]
    det = A[:, None, 0] * A[None, :, 1] - A[:, None, 1] * A[None, :, 0]
    ok = (np.abs(det) > np.sin(min_cross)) & (i[:, None] < i[None, :])
    p, q = np.nonzero(ok)
    if not len(p):
        return np.zeros((0, 2))
    dt = det[p, q]
    t = np.column_stack([(d[p] * A[q, 1] - A[p, 1] * d[q]) / dt,
                         (A[p, 0] * d[q] - d[p] * A[q, 0]) / dt])
    # each moved scan segment must lie along its map segment, not only on its line
    on = _along(mid[i[p]] + t, ma[j[p]], mb[j[p]]) & _along(mid[i[q]] + t, ma[j[q]], mb[j[q]])
    keep = on & (np.hypot(t[:, 0], t[:, 1]) <= P.max_shift)
    t, wt = t[keep], np.minimum(w[p], w[q])[keep]
    if not len(t):
        return np.zeros((0, 2))
    cell = np.floor(t / P.shift_cell).astype(int)
    cells, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.ravel()
    votes = np.bincount(inv, wt, len(cells))
    # the strongest cells, each at least ``rival_apart`` from the ones taken before: a
    # peak's neighbour cells are the same shift, and a look-alike must get its own try
    top: list[int] = []
    for k in np.argsort(-votes):
        if all(np.abs(cells[k] - cells[u]).max() * P.shift_cell > P.rival_apart for u in top):
            top.append(int(k))
            if len(top) == P.shifts:
                break
    return np.column_stack([np.bincount(inv, wt * t[:, 0], len(cells))[top],
                            np.bincount(inv, wt * t[:, 1], len(cells))[top]]) / votes[top, None]


def _along(p: np.ndarray, a: np.ndarray, b: np.ndarray, slack: float = 0.3) -> np.ndarray:
    """Whether points p project within segments a-b (+- ``slack`` m)."""
    d = b - a
    L = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
    s = np.einsum("ij,ij->i", p - a, d) / L
    return (s >= -slack) & (s <= L + slack)
