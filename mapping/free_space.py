"""Free-space evidence: map segments that the laser now sees through are gone.

A cart parked for minutes, a crowd standing at a booth, a door left open: what stood long
enough to be seen by many scans is fused into the map like a wall, and observation counts
alone would keep it for good.  Its absence shows in later scans, whose beams cross the place
it was and return from far beyond it.  Per scan (after its pose is corrected) each map
segment within the scan's reach is tested against the scan's points, each point the end of
a beam from the laser:

- a beam crosses the segment's interior (away from its ends) at distance t, not grazing it,
  and returns from well beyond it (range > t + margin), from another wall of the map that
  is not alongside this one: the beam went *through*;
- a beam's return lies on the segment (|range - t| <= hit tolerance): it is still there.

A segment that some beams went through and none hit counts one scan more in its streak
(``LineMap.through``); a hit, or the segment fused with an observation, resets the streak.
:func:`cgamap.mapping.linemap.age_out` drops the segments whose streak reached
``ClearParams.scans``.  Beams that returned nothing say nothing (glass, black surfaces,
beyond range), and the margins keep pose errors of centimetres and beams past a wall's end
from clearing real walls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .jit import kernel


@dataclass(frozen=True)
class ClearParams:
    enabled: bool = True
    scans: int = 3              # seen through in this many scans in a row: the segment goes
    min_beams: int = 1          # beams through it in one scan (none hitting it) to count
    # how far the laser's pose and the map's walls may be off across a beam: ``slack`` m
    # plus ``slack_per_m`` per metre of range (3 sigma of 2 cm and 0.2 degrees).  Along the
    # beam and along the segment that grows as 1 / sin(incidence): 30 m off at 16 degrees, a
    # beam past a booth's corner crosses its mapped side 0.8 m inside the end
    slack: float = 0.06
    slack_per_m: float = 0.01
    # ... plus the drift that may have built up since the segment and the laser were last
    # tied (the segment seen, or a loop closed): this share of the odometry travel.  Before
    # a loop closes, an old room's pillars seen from a pose a metre off look moved by a
    # metre; clearing them would remove what the closure needs
    drift_per_m: float = 0.03
    margin: float = 0.2         # a return this far beyond the segment (m, plus the slack) ...
    margin_rel: float = 0.01    # ... and this share of the range went through it, ...
    # ... when it lies this far from the segment's line (m, plus this per metre of range):
    # a return just behind, from a surface alongside, is more likely the same wall where a
    # heading error of degrees put it (a 60 m hall, 2.7 degrees off before a loop closed:
    # 0.5-1 m at 20 m) than a wall that went
    behind: float = 1.0
    behind_per_m: float = 0.05
    # crossings this close to an end do not count (plus the slack): this share of the
    # length, at most ``end_margin`` m (a person's 0.5 m side keeps its middle 0.3 m)
    end_share: float = 0.2
    end_margin: float = 0.15
    min_incidence_deg: float = 15.0  # beams more grazing than this do not count
    hit_tol: float = 0.05       # a return this close to the segment (m, plus the slack) hits it
    min_range: float = 0.2      # crossings nearer the laser than this do not count


@kernel
def _crossings(px, py, ox, oy, ax, ay, bx, by, drift, end_share, end_margin, margin,
               margin_rel, behind, behind_per_m, slack, slack_per_m, sin_min, hit_tol,
               min_range):
    """Per segment: beams through it and beams hitting it.  Beams run from the origin
    (ox, oy) to the points (px, py); segments are a-b, each with its own ``drift`` slack."""
    k, m = len(ax), len(px)
    through = np.zeros(k, np.int64)
    hits = np.zeros(k, np.int64)
    # the segment each return lies on (-1: none): a beam through a segment counts only when
    # it lands on another one, a wall the map knows
    on = np.full(m, -1, np.int64)
    best = np.full(m, np.inf)
    for j in range(k):
        ex, ey = bx[j] - ax[j], by[j] - ay[j]
        L = math.sqrt(ex * ex + ey * ey)
        if L <= 0.0:
            continue
        ux, uy = ex / L, ey / L
        for i in range(m):
            qx, qy = px[i] - ax[j], py[i] - ay[j]
            along = qx * ux + qy * uy
            if along < -margin or along > L + margin:
                continue
            off = abs(qx * uy - qy * ux)
            r = math.sqrt((px[i] - ox) ** 2 + (py[i] - oy) ** 2)
            if off <= hit_tol + slack + slack_per_m * r and off < best[i]:
                best[i], on[i] = off, j
    for j in range(k):
        ex, ey = bx[j] - ax[j], by[j] - ay[j]
        L = math.sqrt(ex * ex + ey * ey)
        if L <= 0.0:
            continue
        end = min(end_share * L, end_margin)
        wx, wy = ax[j] - ox, ay[j] - oy
        for i in range(m):
            dx, dy = px[i] - ox, py[i] - oy
            r = math.sqrt(dx * dx + dy * dy)
            if r <= 0.0:
                continue
            dx, dy = dx / r, dy / r
            den = dx * ey - dy * ex
            sin_inc = abs(den) / L
            if sin_inc < sin_min:  # parallel or grazing
                continue
            t = (wx * ey - wy * ex) / den           # along the beam
            s = (wx * dy - wy * dx) / den * L       # along the segment, in metres
            u = (slack + drift[j] + slack_per_m * t) / sin_inc  # how far either may be off
            if s < -u or s > L + u or t < min_range:
                continue
            if abs(r - t) <= hit_tol + u:
                hits[j] += 1
            elif (on[i] >= 0 and on[i] != j and r > t + margin + margin_rel * r + u
                  and end + u <= s and s <= L - end - u
                  and (r - t) * sin_inc > behind + drift[j] + behind_per_m * t):
                through[j] += 1
    return through, hits


def seen_through(a: np.ndarray, b: np.ndarray, origin, points: np.ndarray,
                 params: ClearParams | None = None, drift: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(through, hits) per segment a-b (k, 2): how many of the beams from ``origin`` (x, y)
    to ``points`` (m, 2), all in one frame, went through its interior and returned from
    beyond it onto another of the segments, and how many returned from on it.  ``drift``
    (k,): how far (m) each segment may have drifted from the laser, on top of the slack."""
    P = params or ClearParams()
    a, b, pts = (np.ascontiguousarray(v, dtype=float) for v in (a, b, points))
    if not len(a) or not len(pts):
        return np.zeros(len(a), int), np.zeros(len(a), int)
    drift = np.zeros(len(a)) if drift is None else np.ascontiguousarray(drift, dtype=float)
    return _crossings(pts[:, 0].copy(), pts[:, 1].copy(), float(origin[0]), float(origin[1]),
                      a[:, 0].copy(), a[:, 1].copy(), b[:, 0].copy(), b[:, 1].copy(), drift,
                      P.end_share, P.end_margin, P.margin, P.margin_rel, P.behind,
                      P.behind_per_m, P.slack, P.slack_per_m,
                      math.sin(math.radians(P.min_incidence_deg)), P.hit_tol, P.min_range)


def update_streaks(lmap, origin, points: np.ndarray, stamp: int,
                   params: ClearParams | None = None, travel: np.ndarray | None = None,
                   tied: int = -1) -> int:
    """Test the map segments within the scan's reach against one scan (``points`` (m, 2) in
    the map frame, seen from ``origin``) and update their streaks in place: one more for a
    segment seen through, none for one hit or fused at ``stamp``.  ``travel`` (per scan
    stamp up to ``stamp``: odometry travel so far) and ``tied`` (the stamp of the last loop
    closure) give each segment its drift allowance: ``drift_per_m`` times the travel since
    the later of its last sighting and ``tied``.  Returns how many segments were seen
    through."""
    P = params or ClearParams()
    if not len(lmap) or not len(points):
        return 0
    lo = np.minimum(points.min(axis=0), origin)
    hi = np.maximum(points.max(axis=0), origin)
    a, b = lmap.a, lmap.b
    near = np.nonzero((np.minimum(a[:, 0], b[:, 0]) <= hi[0])
                      & (np.maximum(a[:, 0], b[:, 0]) >= lo[0])
                      & (np.minimum(a[:, 1], b[:, 1]) <= hi[1])
                      & (np.maximum(a[:, 1], b[:, 1]) >= lo[1]))[0]
    if not len(near):
        return 0
    drift = None
    if travel is not None and len(travel) > stamp:
        since = np.clip(np.maximum(lmap.last_seen[near], tied), 0, stamp)
        drift = P.drift_per_m * (travel[stamp] - travel[since])
    through, hits = seen_through(a[near], b[near], origin, points, P, drift)
    gone = (through >= P.min_beams) & (hits == 0) & (lmap.last_seen[near] != stamp)
    lmap.through[near[gone]] += 1
    lmap.through[near[~gone & ((hits > 0) | (lmap.last_seen[near] == stamp))]] = 0
    return int(gone.sum())
