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

A segment that beams went through over half its length, and none hit, counts one scan more
in its streak
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
    # test every this many graph nodes (0.1-0.2 ms a test on Intel); nodes are at least
    # ``MapperParams.node_travel`` apart, and every 2nd left a cart's side 1 m off a room's
    # path (nodes 0.8 m apart) in the map for two laps
    every: int = 1
    scans: int = 3              # seen through in this many tested scans in a row: it goes
    max_beams: int = 360        # every k-th beam of a denser scan (a UTM's 1 081)
    min_beams: int = 1          # beams through it in one scan (none hitting it) to count, ...
    # ... spread over this share of the part of it where a beam could count (away from the
    # ends; each beam covering its footprint): one beam through an opened door says nothing
    # of the 5 m of wall the door was fused into
    cover: float = 0.5
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
def _crossings(pts, ox, oy, a, b, cand, drift, beam_step, end_share, end_margin, margin,
               margin_rel, behind, behind_per_m, slack, slack_per_m, sin_min, hit_tol,
               min_range):
    """For the segments ``cand`` of a-b: beams through each, beams hitting it, and the share
    of it the beams through it cover.  Beams run from the origin (ox, oy) to the points
    ``pts``, about ``beam_step`` rad apart; each segment has its own ``drift`` slack."""
    k, m = len(cand), len(pts)
    through = np.zeros(k, np.int64)
    hits = np.zeros(k, np.int64)
    covered = np.zeros(k)
    rng = np.empty(m)
    dirs = np.zeros((m, 2))  # each beam's unit direction (none for a zero range)
    for i in range(m):
        rng[i] = math.sqrt((pts[i, 0] - ox) ** 2 + (pts[i, 1] - oy) ** 2)
        if rng[i] > 0.0:
            dirs[i, 0], dirs[i, 1] = (pts[i, 0] - ox) / rng[i], (pts[i, 1] - oy) / rng[i]
    edge = np.empty((k, 3))  # per candidate: its direction (x, y) and length
    for c in range(k):
        j = cand[c]
        edge[c, 0], edge[c, 1] = b[j, 0] - a[j, 0], b[j, 1] - a[j, 1]
        edge[c, 2] = math.sqrt(edge[c, 0] ** 2 + edge[c, 1] ** 2)
    # the segment each return lies on (-1: none): a beam through a segment counts only when
    # it lands on another one, a wall the map knows
    on = np.full(m, -1, np.int64)
    best = np.full(m, np.inf)
    for c in range(k):
        j, L = cand[c], edge[c, 2]
        if L <= 0.0:
            continue
        ux, uy = edge[c, 0] / L, edge[c, 1] / L
        for i in range(m):
            qx, qy = pts[i, 0] - a[j, 0], pts[i, 1] - a[j, 1]
            along = qx * ux + qy * uy
            if along < -margin or along > L + margin:
                continue
            off = abs(qx * uy - qy * ux)
            if off <= hit_tol + slack + slack_per_m * rng[i] and off < best[i]:
                best[i], on[i] = off, j
    for c in range(k):
        j, (ex, ey, L) = cand[c], edge[c]
        if L <= 0.0:
            continue
        end = min(end_share * L, end_margin)
        wx, wy = a[j, 0] - ox, a[j, 1] - oy
        lo, hi, u_min = np.inf, -np.inf, np.inf
        for i in range(m):
            r = rng[i]
            if r <= 0.0:
                continue
            dx, dy = dirs[i, 0], dirs[i, 1]
            den = dx * ey - dy * ex
            sin_inc = abs(den) / L
            if sin_inc < sin_min:  # parallel or grazing
                continue
            t = (wx * ey - wy * ex) / den           # along the beam
            s = (wx * dy - wy * dx) / den * L       # along the segment, in metres
            u = (slack + drift[c] + slack_per_m * t) / sin_inc  # how far either may be off
            if s < -u or s > L + u or t < min_range:
                continue
            if abs(r - t) <= hit_tol + u:
                hits[c] += 1
            elif (on[i] >= 0 and on[i] != j and r > t + margin + margin_rel * r + u
                  and end + u <= s and s <= L - end - u
                  and (r - t) * sin_inc > behind + drift[c] + behind_per_m * t):
                through[c] += 1
                half = 0.5 * beam_step * t / sin_inc  # the beam's footprint along it
                lo, hi, u_min = min(lo, s - half), max(hi, s + half), min(u_min, u)
        if hi > lo:  # as a share of the part a beam could count in
            part = L - 2.0 * (end + u_min)
            covered[c] = min((min(hi, L) - max(lo, 0.0)) / max(part, 1e-9), 1.0)
    return through, hits, covered


@kernel
def _in_reach(a, b, lo_x, lo_y, hi_x, hi_y):
    """Indices of the segments a-b whose bounding boxes meet the box lo-hi."""
    out = np.empty(len(a), np.int64)
    n = 0
    for j in range(len(a)):
        if (min(a[j, 0], b[j, 0]) <= hi_x and max(a[j, 0], b[j, 0]) >= lo_x
                and min(a[j, 1], b[j, 1]) <= hi_y and max(a[j, 1], b[j, 1]) >= lo_y):
            out[n] = j
            n += 1
    return out[:n]


def _beam_step(pts: np.ndarray, origin) -> float:
    """The median angle between neighbouring beams (points in beam order)."""
    if len(pts) < 2:
        return 0.0
    bearing = np.unwrap(np.arctan2(pts[:, 1] - origin[1], pts[:, 0] - origin[0]))
    return float(np.median(np.abs(np.diff(bearing))))


def _run(a, b, cand, origin, pts, P: ClearParams, drift, beam_step: float):
    return _crossings(pts, float(origin[0]), float(origin[1]), a, b, cand, drift,
                      float(beam_step), P.end_share, P.end_margin, P.margin, P.margin_rel,
                      P.behind, P.behind_per_m, P.slack, P.slack_per_m,
                      math.sin(math.radians(P.min_incidence_deg)), P.hit_tol, P.min_range)


def seen_through(a: np.ndarray, b: np.ndarray, origin, points: np.ndarray,
                 params: ClearParams | None = None, drift: np.ndarray | None = None,
                 beam_step: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(through, hits, covered) per segment a-b (k, 2): how many of the beams from
    ``origin`` (x, y) to ``points`` (m, 2), all in one frame, went through its interior and
    returned from beyond it onto another of the segments, how many returned from on it, and
    the share of the part where such a beam could count (away from its ends) that the beams
    through it cover (each its footprint, ``beam_step`` rad wide: by default the median
    angle between neighbouring points).  ``drift`` (k,): how far (m) each segment may have
    drifted from the laser, on top of the slack."""
    P = params or ClearParams()
    a, b, pts = (np.ascontiguousarray(v, dtype=float) for v in (a, b, points))
    if not len(a) or not len(pts):
        return np.zeros(len(a), int), np.zeros(len(a), int), np.zeros(len(a))
    drift = np.zeros(len(a)) if drift is None else np.ascontiguousarray(drift, dtype=float)
    if beam_step is None:
        beam_step = _beam_step(pts, origin)
    return _run(a, b, np.arange(len(a)), origin, pts, P, drift, beam_step)


def update_streaks(lmap, origin, points: np.ndarray, stamp: int,
                   params: ClearParams | None = None, travel: np.ndarray | None = None,
                   tied: int | np.ndarray = -1, beam_step: float | None = None) -> int:
    """Test the map segments within the scan's reach against one scan (``points`` (m, 2) in
    the map frame, seen from ``origin``, ``beam_step`` rad apart) and update their streaks
    in place: one more for a segment seen through over ``cover`` of it, none for one hit or
    fused at ``stamp``.  ``travel`` (per scan stamp up to ``stamp``: odometry travel so far)
    and ``tied`` (the stamp of the last loop closure; or per map segment) give each
    segment its drift allowance: ``drift_per_m`` times the travel since the later of its
    last sighting and ``tied``.  Returns how many segments were seen through."""
    P = params or ClearParams()
    if not len(lmap) or not len(points):
        return 0
    pts = np.ascontiguousarray(points, dtype=float)
    stride = -(-len(pts) // max(P.max_beams, 1))
    if stride > 1:
        pts = np.ascontiguousarray(pts[::stride])
        beam_step = None if beam_step is None else beam_step * stride
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    a, b = np.ascontiguousarray(lmap.a, dtype=float), np.ascontiguousarray(lmap.b, dtype=float)
    near = _in_reach(a, b, min(lo[0], origin[0]), min(lo[1], origin[1]),
                     max(hi[0], origin[0]), max(hi[1], origin[1]))
    if not len(near):
        return 0
    seen = lmap.last_seen[near]
    if travel is not None and len(travel) > stamp:
        tie = tied[near] if np.ndim(tied) else tied
        since = np.clip(np.maximum(seen, tie), 0, stamp)
        drift = P.drift_per_m * (travel[stamp] - travel[since])
    else:
        drift = np.zeros(len(near))
    if beam_step is None:
        beam_step = _beam_step(pts, origin)
    through, hits, covered = _run(a, b, near, origin, pts, P, drift, beam_step)
    gone = (through >= P.min_beams) & (covered >= P.cover) & (hits == 0) & (seen != stamp)
    lmap.through[near[gone]] += 1
    lmap.through[near[~gone & ((hits > 0) | (seen == stamp))]] = 0
    return int(gone.sum())
