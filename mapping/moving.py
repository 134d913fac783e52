"""Scan differencing: segments of a scan that lie where an earlier scan saw through.

A person walking or a cart rolling past is seen in one place by one scan and somewhere else
by the next.  Fused into the map, each sighting lays a piece of wall along its way: the
side of a cart that rolls along it extends one segment over its whole route, and a side
that moves across itself leaves a copy per scan.  The free-space test
(:mod:`.free_space`) removes such pieces only later, and not those seen edge-on.

Before a scan is merged, its segments are compared with a scan taken a moment earlier
(``MovingParams.gap_travel`` m of odometry or ``gap_scans`` scans back, whichever is
nearer), both placed by their corrected poses: a segment whose points lie, for a good
share of it, in front of what the earlier scan's beams returned (that beam went through
the place, so nothing stood there then) has moved in since, and is left out of the map.
The scan's pose correction still used it, and its beams still count for the free-space
test.  A cart that stops is mapped once it stands; beams that returned nothing say
nothing, and the earlier beam with the nearest return around the bearing counts (a point
at an object's edge is not compared with the background past it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MovingParams:
    enabled: bool = True
    # the earlier scan: the newest at least this far back in odometry travel (m), or this
    # many scans back if nearer (turning on the spot).  A person at 1 m/s moves 0.6 m
    # while a robot at 0.5 m/s drives 0.3 m
    gap_travel: float = 0.3
    gap_scans: int = 10
    # a point moved in when the earlier beam at its bearing returned from this far beyond
    # it (m, plus this share of its range): the two poses' errors, a few cm and 0.2 deg
    margin: float = 0.2
    margin_rel: float = 0.02
    neighbours: int = 2       # earlier beams each side of the bearing: the nearest return
    samples: int = 9          # points tested along each segment (its middle 80 %) ...
    share: float = 0.4        # ... a segment moved in when this share of them did
    min_range: float = 0.2    # points nearer than this to the earlier laser say nothing


def moved_in(points: np.ndarray, pose, ranges: np.ndarray, angle_min: float,
             angle_increment: float, params: MovingParams | None = None) -> np.ndarray:
    """Per point (m, 2; map frame): whether the scan ``ranges`` taken from the laser pose
    ``pose`` (x, y, theta; same frame) saw through its place, its beam at that bearing
    (the nearest return of the beams around it) returning from beyond it by the margin."""
    P = params or MovingParams()
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    r = np.asarray(ranges, dtype=float)
    if not len(pts) or not len(r) or angle_increment == 0:
        return np.zeros(len(pts), bool)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = pts - np.asarray(pose[:2], dtype=float)
    x, y = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    rho = np.hypot(x, y)
    beam = np.rint((np.arctan2(y, x) - angle_min) / angle_increment).astype(int)
    n = len(r)
    inside = (beam >= 0) & (beam < n) & (rho >= P.min_range)
    if angle_increment * n >= 2 * np.pi - 1e-6:  # a full circle wraps
        beam %= n
        inside = rho >= P.min_range
    # the nearest return among the beams around the bearing, whose own beam returned (no
    # return says nothing: glass, black, beyond range)
    valid = np.isfinite(r) & (r > 0)
    k = P.neighbours
    padded = np.concatenate([np.full(k, np.inf), np.where(valid, r, np.inf), np.full(k, np.inf)])
    nearest = np.lib.stride_tricks.sliding_window_view(padded, 2 * k + 1).min(axis=1)
    b = np.clip(beam, 0, n - 1)
    return inside & valid[b] & (nearest[b] > rho + P.margin + P.margin_rel * rho)


def moved_segments(a: np.ndarray, b: np.ndarray, pose, ranges: np.ndarray, angle_min: float,
                   angle_increment: float, params: MovingParams | None = None) -> np.ndarray:
    """Per segment a-b (k, 2; map frame): whether it moved in since the earlier scan
    (``ranges`` from ``pose``): ``share`` of the points sampled along its middle lie where
    that scan saw through (:func:`moved_in`)."""
    P = params or MovingParams()
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if not len(a):
        return np.zeros(0, bool)
    t = np.linspace(0.1, 0.9, max(P.samples, 1))
    pts = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
    hit = moved_in(pts.reshape(-1, 2), pose, ranges, angle_min, angle_increment, P)
    return hit.reshape(len(a), -1).mean(axis=1) >= P.share
