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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .correction import Correction, CorrectionParams, correct_batch
from .matching import LineIndex, line_angles, near_box
from .odometry import wrap_angle
from .relocalize import rotation_peaks
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


def recover(seg: Segments, map_a: np.ndarray, map_b: np.ndarray, predicted,
            corr: Correction, params: CorrectionParams, P: SlipParams
            ) -> Correction | None:
    """A better correction than ``corr`` (the prediction's) from the rotation hypotheses,
    or None."""
    pred = np.asarray(predicted, dtype=float)
    if len(seg) == 0 or len(map_a) == 0:
        return None
    c, s = np.cos(pred[2]), np.sin(pred[2])
    R = np.array([[c, s], [-s, c]])  # row vectors: p @ R rotates by theta
    ga, gb = seg.a @ R + pred[:2], seg.b @ R + pred[:2]
    # map segments that could meet the scan's: centre within reach of its bounding box
    reach = float(np.max(np.hypot(*np.vstack([seg.a, seg.b]).T))) * np.sin(P.max_turn) + 0.5
    half = 0.5 * np.linalg.norm(map_b - map_a, axis=-1)
    near = near_box(0.5 * (map_a + map_b), half, ga, gb, reach)
    if 2.0 * half[near].sum() < P.min_map:
        return None
    ma, mb = map_a[near], map_b[near]
    rot = rotation_peaks(line_angles(ma, mb), 2.0 * half[near], line_angles(ga, gb),
                         seg.length, 1.0, P.peaks)
    rot = wrap_angle(2.0 * rot) / 2.0  # undirected: the turn within (-90, 90] deg
    rot = rot[np.abs(rot) <= P.max_turn]
    if not len(rot):
        return None
    hyp = np.tile(pred, (len(rot), 1))
    hyp[:, 2] = wrap_angle(pred[2] + rot)
    idx = LineIndex.of(ma, mb)
    batch = LineIndex(*(np.broadcast_to(v, (len(rot),) + v.shape) for v in vars(idx).values()))
    k = len(seg)
    res = correct_batch(np.broadcast_to(seg.a, (len(rot), k, 2)),
                        np.broadcast_to(seg.b, (len(rot), k, 2)), batch, hyp,
                        P.step, params)
    best = int(np.lexsort((res.rms, -res.matched_fraction))[0])
    got = float(res.matched_fraction[best])
    if got < max(P.accept, corr.matched_fraction + P.margin):
        return None
    m = res.matches[best]
    L = seg.length
    return Correction(res.pose[best], res.cov[best], float(L[m >= 0].sum()), float(L.sum()),
                      float(res.rms[best]), np.where(m >= 0, near[np.maximum(m, 0)], -1),
                      None)
