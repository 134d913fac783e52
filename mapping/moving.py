"""Scan differencing: segments of a scan that lie where an earlier scan saw through.

A person walking or a cart rolling past is seen in one place by one scan and somewhere else
by the next.  Fused into the map, each sighting lays a piece of wall along its way: the
side of a cart that rolls along it extends one segment over its whole route, and a side
that moves across itself leaves a copy per scan.  The free-space test
(:mod:`.free_space`) removes such pieces only later, and not those seen edge-on.

Before a scan is merged, its segments are compared with a scan taken a moment earlier
(``MovingParams.gap_travel`` m of odometry or ``gap_scans`` scans back, whichever is
nearer; in a chain's first scans, its oldest), both placed by their corrected poses: a
segment whose points lie, for a good share of it, in front of what the earlier scan's
beams returned (that beam went through the place, so nothing stood there then) has moved
in since, and is left out of the map.  The scan's pose correction still used it, and its
beams still count for the free-space test.  A cart that stops is mapped once it stands;
beams that returned nothing say nothing, and the earlier beam with the nearest return
around the bearing counts (a point at an object's edge is not compared with the
background past it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .jit import kernel


@dataclass(frozen=True)
class MovingParams:
    enabled: bool = True
    # the earlier scan: the newest at least this far back in odometry travel (m), or this
    # many scans back if nearer (turning on the spot).  A person at 1 m/s moves 1.2 m
    # while a robot at 0.5 m/s drives 0.6 m: more than its own size, so its sides seen
    # end-on are not where it stood itself in the earlier scan (a cart 0.6 m long that
    # moved 0.6 m has its trailing face where its leading face was)
    gap_travel: float = 0.6
    gap_scans: int = 20
    # a point moved in when the earlier beam at its bearing returned from this far beyond
    # it (m, plus this share of its range): the two poses' errors, a few cm and 0.2 deg
    margin: float = 0.2
    margin_rel: float = 0.02
    neighbours: int = 2       # earlier beams each side of the bearing: the nearest return
    samples: int = 9          # points tested along each segment (its middle 80 %) ...
    share: float = 0.4        # ... a segment moved in when this share of them did
    min_range: float = 0.2    # points nearer than this to the earlier laser say nothing


@kernel
def _moved(px, py, ox, oy, th, r, angle_min, angle_increment, full_circle, neighbours,
           margin, margin_rel, min_range):
    """Per point (px, py): whether the scan ``r`` from (ox, oy, th) saw through it."""
    n, m = len(r), len(px)
    out = np.zeros(m, np.bool_)
    c, s = math.cos(th), math.sin(th)
    for i in range(m):
        dx, dy = px[i] - ox, py[i] - oy
        x, y = c * dx + s * dy, -s * dx + c * dy
        rho = math.sqrt(x * x + y * y)
        if rho < min_range:
            continue
        k = int(round((math.atan2(y, x) - angle_min) / angle_increment))
        if full_circle:
            k %= n
        elif k < 0 or k >= n:
            continue
        if not (0.0 < r[k] < np.inf):  # no return (NaN, inf, 0) says nothing
            continue
        nearest = np.inf
        for q in range(k - neighbours, k + neighbours + 1):
            if full_circle:
                q %= n
            elif q < 0 or q >= n:
                continue
            if r[q] > 0.0 and r[q] < nearest:
                nearest = r[q]
        out[i] = nearest > rho + margin + margin_rel * rho
    return out


@kernel
def _sampled(a, b, samples):
    """``samples`` points along the middle 80 % of each segment a-b: (k * samples,) x, y."""
    k = len(a)
    px, py = np.empty(k * samples), np.empty(k * samples)
    for j in range(k):
        for q in range(samples):
            t = 0.5 if samples == 1 else 0.1 + 0.8 * q / (samples - 1)
            px[j * samples + q] = a[j, 0] + t * (b[j, 0] - a[j, 0])
            py[j * samples + q] = a[j, 1] + t * (b[j, 1] - a[j, 1])
    return px, py


def moved_in(points: np.ndarray, pose, ranges: np.ndarray, angle_min: float,
             angle_increment: float, params: MovingParams | None = None) -> np.ndarray:
    """Per point (m, 2; map frame): whether the scan ``ranges`` taken from the laser pose
    ``pose`` (x, y, theta; same frame) saw through its place: the beam at its bearing
    returned, and it and its ``neighbours`` each side returned from beyond the point by
    the margin (the nearest of their returns counts)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    return _run(np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]), pose,
                ranges, angle_min, angle_increment, params or MovingParams())


def _run(px, py, pose, ranges, angle_min: float, angle_increment: float,
         P: MovingParams) -> np.ndarray:
    r = np.ascontiguousarray(ranges, dtype=float)
    if not len(px) or not len(r) or angle_increment == 0:
        return np.zeros(len(px), bool)
    full = abs(angle_increment) * len(r) >= 2 * np.pi - 1e-6
    return _moved(px, py, float(pose[0]), float(pose[1]), float(pose[2]), r,
                  float(angle_min), float(angle_increment), full, int(P.neighbours),
                  P.margin, P.margin_rel, P.min_range)


def moved_segments(a: np.ndarray, b: np.ndarray, pose, ranges: np.ndarray, angle_min: float,
                   angle_increment: float, params: MovingParams | None = None) -> np.ndarray:
    """Per segment a-b (k, 2; map frame): whether it moved in since the earlier scan
    (``ranges`` from ``pose``): ``share`` of the points sampled along its middle lie where
    that scan saw through (:func:`moved_in`)."""
    P = params or MovingParams()
    a, b = np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(b, dtype=float)
    if not len(a):
        return np.zeros(0, bool)
    ns = max(P.samples, 1)
    px, py = _sampled(a, b, ns)
    hit = _run(px, py, pose, ranges, angle_min, angle_increment, P)
    return hit.reshape(len(a), ns).mean(axis=1) >= P.share
