"""Line segments from one 2D laser scan: split-and-merge (iterative end-point fit).

Pipeline (issue 4, step 1; Zhang & Ghosh's split-and-merge): range filter -> gap splitting
-> recursive split at the farthest point from the chord -> total-least-squares refit ->
merge of collinear neighbours -> minimum points / length.  All splits of one level are done at
once over the whole scan (segment ids per point, ``reduceat`` per segment), so the cost is a
few numpy calls per level, never a Python loop over points.

Each segment carries its point count, RMS residual, first and second moments (for exact
refits when the map merges observations) and the covariance of its (angle, offset).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class SegmentParams:
    """Extraction parameters; defaults suit a SICK LMS (1° or 0.5°, its 80 m mode)."""

    range_min: float = 0.05
    # the sensor's own reach, not less: in a hall or outdoors the far walls are often the
    # only long lines a scan has.  At 25 m a simulated campus loop lost its facades and
    # drifted 2.6 m (no loop closed; 0.5 m since the 15 cm segments), a 60 m hall 2 cm; at
    # 80 m both stay under 1 cm, and the Intel log (a small building) is unchanged
    # (bench_mapping_worlds)
    range_max: float = 80.0
    split_dist: float = 0.04         # split when a point is farther than this from the chord
    split_dist_per_m: float = 0.008  # ... plus this much per metre of range (beam spread)
    gap_abs: float = 0.25            # break between consecutive points farther apart than
    gap_beams: float = 5.0           # ... max(gap_abs, gap_beams * range * angle_increment)
    merge_residual: float = 0.03     # merge neighbours when the joint RMS residual is below
    merge_angle: float = np.deg2rad(6.0)
    # short on purpose: a door recess's side or a jamb (15-30 cm) is often the only thing
    # that fixes a scan's position along a corridor.  5 points / 0.3 m -> 3 / 0.15 m
    # measured: a simulated 150 m corridor there and back 1.33 -> 0.12 m ATE (high noise);
    # Intel, seeds 0-7 (with MapParams.age_every): ATE 0.073 -> 0.068 m mean, relations
    # 0.038 -> 0.037 m.  Only-touching-a-neighbour short pieces (no isolated clutter) were
    # worse on Intel (0.078 m, seeds 0-3) and on the corridor (0.24 m): furniture helps too
    min_points: int = 3
    min_length: float = 0.15
    sigma_range: float = 0.01        # floor for the point noise in the covariance

    @classmethod
    def for_lms(cls) -> SegmentParams:
        return cls()

    @classmethod
    def for_utm(cls) -> SegmentParams:
        """Hokuyo UTM-30LX: 0.25° beams, 30 m, ~3 cm noise."""
        return cls(range_max=30.0, split_dist=0.05, gap_beams=10.0, min_points=8,
                   sigma_range=0.02)


@dataclass
class Segments:
    """k segments in one frame: end points a, b (k, 2) in scan order, with fit statistics."""

    a: np.ndarray
    b: np.ndarray
    n: np.ndarray          # points per segment
    residual: np.ndarray   # RMS orthogonal residual (m)
    centroid: np.ndarray   # (k, 2) mean of the points
    scatter: np.ndarray    # (k, 2, 2) sum of centred outer products
    cov: np.ndarray        # (k, 2, 2) covariance of (normal angle, offset at the centroid)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # filtered points

    def __len__(self) -> int:
        return len(self.n)

    @property
    def length(self) -> np.ndarray:
        return np.linalg.norm(self.b - self.a, axis=-1)

    @property
    def direction(self) -> np.ndarray:
        d = self.b - self.a
        return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)

    def subset(self, keep) -> Segments:
        return Segments(self.a[keep], self.b[keep], self.n[keep], self.residual[keep],
                        self.centroid[keep], self.scatter[keep], self.cov[keep], self.points)

    def transformed(self, x: float, y: float, theta: float) -> Segments:
        """The same segments moved by the planar pose (x, y, theta) (frame change L -> G)."""
        c, s = np.cos(theta), np.sin(theta)
        R = np.array([[c, -s], [s, c]])
        t = np.array([x, y])
        pts = self.points @ R.T + t if len(self.points) else self.points
        return Segments(self.a @ R.T + t, self.b @ R.T + t, self.n, self.residual,
                        self.centroid @ R.T + t, R @ self.scatter @ R.T, self.cov.copy(), pts)


def empty_segments() -> Segments:
    z2 = np.zeros((0, 2))
    return Segments(z2, z2, np.zeros(0, int), np.zeros(0), z2, np.zeros((0, 2, 2)),
                    np.zeros((0, 2, 2)))


def tls_from_moments(n, centroid: np.ndarray, scatter: np.ndarray) -> tuple:
    """Total-least-squares line of each point set from its moments.

    Returns (direction (k, 2) unit, smallest eigenvalue of scatter / n (the mean squared
    orthogonal residual), spread along the line sum (t - t_mean)^2).
    """
    sxx, sxy, syy = scatter[..., 0, 0], scatter[..., 0, 1], scatter[..., 1, 1]
    alpha = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # major axis angle
    half_tr = 0.5 * (sxx + syy)
    root = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy ** 2, 0.0))
    lam_min = np.maximum(half_tr - root, 0.0)
    lam_max = half_tr + root
    d = np.stack([np.cos(alpha), np.sin(alpha)], axis=-1)
    return d, lam_min / np.maximum(n, 1), lam_max


def _prefix_moments(p: np.ndarray) -> np.ndarray:
    """Running sums of x, y, x^2, xy, y^2 (with a leading zero row): any run's moments are
    two lookups."""
    return np.concatenate([np.zeros((1, 5)), np.cumsum(
        np.column_stack([p, p[:, 0] ** 2, p[:, 0] * p[:, 1], p[:, 1] ** 2]), axis=0)])


def _moments(p: np.ndarray, starts: np.ndarray, ends: np.ndarray,
             cs: np.ndarray | None = None):
    """Counts, centroids and centred scatter matrices of p[starts[i]:ends[i]] (``cs``: the
    points' :func:`_prefix_moments`, when already at hand)."""
    n = (ends - starts).astype(float)
    cs = _prefix_moments(p) if cs is None else cs
    sums = cs[ends] - cs[starts]
    c = sums[:, :2] / n[:, None]
    S = np.empty((len(n), 2, 2))
    S[:, 0, 0] = sums[:, 2] - n * c[:, 0] ** 2
    S[:, 0, 1] = S[:, 1, 0] = sums[:, 3] - n * c[:, 0] * c[:, 1]
    S[:, 1, 1] = sums[:, 4] - n * c[:, 1] ** 2
    return n, c, S


def scan_points(ranges: np.ndarray, angle_min: float, angle_increment: float,
                params: SegmentParams) -> tuple[np.ndarray, np.ndarray]:
    """Valid points (m, 2) in beam order and their ranges, after the range filter."""
    r = np.asarray(ranges, dtype=float)
    ang = angle_min + angle_increment * np.arange(len(r))
    ok = np.isfinite(r) & (r >= params.range_min) & (r <= params.range_max)
    r = r[ok]
    return np.stack([r * np.cos(ang[ok]), r * np.sin(ang[ok])], axis=-1), r


def _split(p: np.ndarray, rng: np.ndarray, starts: np.ndarray, ends: np.ndarray,
           params: SegmentParams) -> tuple[np.ndarray, np.ndarray]:
    """Iterative end-point fit over all segments at once, level by level.  The segments of
    a level partition the points (``starts``, ``ends`` must, as the gap clusters do), so
    each level is one pass over all points with their segment's ids: a segment that did
    not split (or is too short to) gives the same answer again, which is cheaper than
    tracking which segments are finished."""
    n = len(p)
    tol = params.split_dist + params.split_dist_per_m * rng
    small = max(params.min_points, 3)
    bound = np.zeros(n, bool)
    bound[starts] = True
    while True:
        st = np.flatnonzero(bound)
        en = np.append(st[1:], n)
        seg_id = np.cumsum(bound) - 1
        a, d = p[st], p[en - 1] - p[st]
        dn = d / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
        rel = p - a[seg_id]
        dseg = dn[seg_id]
        excess = np.abs(rel[:, 0] * dseg[:, 1] - rel[:, 1] * dseg[:, 0]) - tol
        worst = np.maximum.reduceat(excess, st)
        split = (worst > 0) & (en - st >= small)
        if not split.any():
            return st, en
        # the first worst point of each splitting segment, kept off its end points
        hit = np.flatnonzero((excess == worst[seg_id]) & split[seg_id])
        first = hit[np.append(True, seg_id[hit[1:]] != seg_id[hit[:-1]])]
        sid = seg_id[first]
        bound[np.clip(first, st[sid] + 1, en[sid] - 1)] = True


def _merge(p, starts, ends, params: SegmentParams, is_break: np.ndarray, cs: np.ndarray):
    """Greedy merge of adjacent collinear segments (joint TLS residual under threshold);
    never across a gap break.  ``cs``: the points' :func:`_prefix_moments`."""
    while len(starts) > 1:
        s2, e2 = starts[:-1], ends[1:]
        contiguous = (ends[:-1] == starts[1:]) & ~is_break[starts[1:]]
        n, c, S = _moments(p, s2, e2, cs)
        _, ms, _ = tls_from_moments(n, c, S)
        na, ca, Sa = _moments(p, starts, ends, cs)
        da, _, _ = tls_from_moments(na, ca, Sa)
        cosang = np.abs(np.sum(da[:-1] * da[1:], axis=-1))
        ok = contiguous & (np.sqrt(ms) < params.merge_residual) & (
            cosang > np.cos(params.merge_angle))
        if not ok.any():
            break
        # merge the best pair, plus any other non-overlapping good pairs in one sweep
        score = np.where(ok, np.sqrt(ms), np.inf)
        chosen = np.zeros(len(ok), bool)
        for i in np.argsort(score)[: int(ok.sum())]:  # loop over segment pairs, not points
            if (i > 0 and chosen[i - 1]) or (i + 1 < len(chosen) and chosen[i + 1]):
                continue
            chosen[i] = True
        keep_start = np.ones(len(starts), bool)
        keep_start[1:][chosen] = False
        keep_end = np.ones(len(ends), bool)
        keep_end[:-1][chosen] = False
        starts, ends = starts[keep_start], ends[keep_end]
    return starts, ends


def extract_segments(ranges: np.ndarray, angle_min: float, angle_increment: float,
                     params: SegmentParams | None = None) -> Segments:
    """Segments of one scan in the laser frame (split-and-merge with TLS refit)."""
    params = params or SegmentParams()
    p, r = scan_points(ranges, angle_min, angle_increment, params)
    if len(p) < params.min_points:
        out = empty_segments()
        out.points = p
        return out
    # gap splitting: consecutive points too far apart start a new cluster
    step = np.linalg.norm(np.diff(p, axis=0), axis=-1)
    gap_tol = np.maximum(params.gap_abs,
                         params.gap_beams * np.minimum(r[:-1], r[1:]) * abs(angle_increment))
    if len(ranges) * abs(angle_increment) >= 2 * np.pi - 0.5 * abs(angle_increment):
        # a full circle has no natural start: begin after the largest relative gap, so a
        # wall across the first/last beam stays one segment
        wrap = np.linalg.norm(p[0] - p[-1])
        wtol = max(params.gap_abs, params.gap_beams * min(r[0], r[-1]) * abs(angle_increment))
        rel = np.concatenate([step / gap_tol, [wrap / wtol]])
        k = (int(np.argmax(rel)) + 1) % len(p)
        if k:
            p, r = np.roll(p, -k, axis=0), np.roll(r, -k)
            step = np.linalg.norm(np.diff(p, axis=0), axis=-1)
            gap_tol = np.maximum(params.gap_abs, params.gap_beams * np.minimum(r[:-1], r[1:])
                                 * abs(angle_increment))
    breaks = np.nonzero(step > gap_tol)[0] + 1
    is_break = np.zeros(len(p) + 1, bool)
    is_break[breaks] = True
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks, [len(p)]])
    starts, ends = _split(p, r, starts, ends, params)
    keep = (ends - starts) >= params.min_points
    starts, ends = starts[keep], ends[keep]
    if not len(starts):
        out = empty_segments()
        out.points = p
        return out
    cs = _prefix_moments(p)
    starts, ends = _merge(p, starts, ends, params, is_break, cs)
    n, c, S = _moments(p, starts, ends, cs)
    d, ms, spread = tls_from_moments(n, c, S)
    # end points: first and last point projected on the refitted line
    ta = np.sum((p[starts] - c) * d, axis=-1)
    tb = np.sum((p[ends - 1] - c) * d, axis=-1)
    a = c + ta[:, None] * d
    b = c + tb[:, None] * d
    length = np.abs(tb - ta)
    keep = (n >= params.min_points) & (length >= params.min_length)
    sigma2 = np.maximum(ms * n / np.maximum(n - 2, 1), params.sigma_range ** 2)
    cov = np.zeros((len(n), 2, 2))
    cov[:, 0, 0] = sigma2 / np.maximum(spread, 1e-9)
    cov[:, 1, 1] = sigma2 / n
    seg = Segments(a, b, n.astype(int), np.sqrt(ms), c, S, cov, p)
    return seg.subset(keep)


def segments_from_scan(scan, params: SegmentParams | None = None) -> Segments:
    """Convenience: segments of a ``LaserScan``-like object (ranges, angle_min, increment)."""
    return extract_segments(scan.ranges, scan.angle_min, scan.angle_increment, params)
