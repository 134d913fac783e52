"""Line segments from one 2D laser scan: split-and-merge (iterative end-point fit).

Pipeline (issue 4, step 1; Zhang & Ghosh's split-and-merge): range filter -> gap splitting
-> recursive split at the farthest point from the chord -> total-least-squares refit ->
merge of collinear neighbours -> minimum points / length.  The split and the merge loop over
points and runs in one compiled kernel (:mod:`.jit`): with 180-1081 points and a few dozen
segments a scan, numpy's per-call cost was the whole cost (0.44 ms an Intel scan, level by
level over the scan; now 0.09 ms, of it 0.007 ms in the kernel).

Each segment carries its point count, RMS residual, first and second moments (for exact
refits when the map merges observations) and the covariance of its (angle, offset).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .jit import kernel, stable_argsort


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
    scatter = np.asarray(scatter, dtype=float)
    shape = scatter.shape[:-2]
    flat = scatter.reshape(-1, 4)
    ms, lam_max, d = _tls_many(np.broadcast_to(np.asarray(n, dtype=float), shape).ravel(),
                               np.ascontiguousarray(flat[:, 0]), np.ascontiguousarray(flat[:, 1]),
                               np.ascontiguousarray(flat[:, 3]))
    return d.reshape(shape + (2,)), ms.reshape(shape), lam_max.reshape(shape)


@kernel
def tls_fit(n, sxx, sxy, syy):
    """:func:`tls_from_moments` of one point set from its centred scatter: (mean squared
    orthogonal residual, largest eigenvalue, direction x, direction y)."""
    alpha = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # major axis angle
    root = np.sqrt(max(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    half_tr = 0.5 * (sxx + syy)
    return (max(half_tr - root, 0.0) / max(n, 1.0), half_tr + root, np.cos(alpha),
            np.sin(alpha))


@kernel
def _tls_many(n, sxx, sxy, syy):
    k = len(n)
    ms, lam_max, d = np.empty(k), np.empty(k), np.empty((k, 2))
    for i in range(k):
        ms[i], lam_max[i], d[i, 0], d[i, 1] = tls_fit(n[i], sxx[i], sxy[i], syy[i])
    return ms, lam_max, d


@kernel
def _prefix_moments(p):
    """Running sums of x, y, x^2, xy, y^2 (with a leading zero row): any run's moments are
    two lookups (:func:`_run_moments`)."""
    cs = np.zeros((p.shape[0] + 1, 5))
    for i in range(p.shape[0]):
        x, y = p[i, 0], p[i, 1]
        cs[i + 1, 0] = cs[i, 0] + x
        cs[i + 1, 1] = cs[i, 1] + y
        cs[i + 1, 2] = cs[i, 2] + x * x
        cs[i + 1, 3] = cs[i, 3] + x * y
        cs[i + 1, 4] = cs[i, 4] + y * y
    return cs


@kernel
def _run_moments(cs, s, e):
    """Count, centroid (x, y) and centred scatter (xx, xy, yy) of points s..e-1."""
    n = float(e - s)
    cx, cy = (cs[e, 0] - cs[s, 0]) / n, (cs[e, 1] - cs[s, 1]) / n
    return (n, cx, cy, cs[e, 2] - cs[s, 2] - n * cx * cx, cs[e, 3] - cs[s, 3] - n * cx * cy,
            cs[e, 4] - cs[s, 4] - n * cy * cy)


def scan_points(ranges: np.ndarray, angle_min: float, angle_increment: float,
                params: SegmentParams) -> tuple[np.ndarray, np.ndarray]:
    """Valid points (m, 2) in beam order and their ranges, after the range filter."""
    r = np.asarray(ranges, dtype=float)
    ang = angle_min + angle_increment * np.arange(len(r))
    ok = np.isfinite(r) & (r >= params.range_min) & (r <= params.range_max)
    r = r[ok]
    return np.stack([r * np.cos(ang[ok]), r * np.sin(ang[ok])], axis=-1), r


@kernel
def _split_merge(p, tol, starts, ends, is_break, small, min_points, merge_residual,
                 cos_merge):
    """Split-and-merge on the runs ``starts``-``ends`` (a partition of the points, the gap
    clusters): (starts, ends) of the segments and the points' prefix moments.

    Split: a run whose farthest point from its chord lies beyond that point's tolerance
    ``tol`` is cut there (at the first such farthest point, kept off the run's end points),
    until no run of at least ``small`` points has one.  Runs under ``min_points`` go.
    Merge: adjacent runs (no gap between them) whose joint total-least-squares line has an
    RMS residual under ``merge_residual`` and whose own lines meet at under the merge
    angle are joined, the best pair first plus every other pair that touches none chosen,
    again until none qualifies."""
    n = p.shape[0]
    # split (the order runs are taken in does not matter: each is decided on its points)
    first = np.zeros(n + 1, np.bool_)
    stack = np.empty((n + 2, 2), np.int64)
    top = 0
    for q in range(len(starts)):
        stack[top, 0], stack[top, 1] = starts[q], ends[q]
        top += 1
    while top > 0:
        top -= 1
        s, e = stack[top, 0], stack[top, 1]
        first[s] = True
        ax, ay = p[s, 0], p[s, 1]
        dx, dy = p[e - 1, 0] - ax, p[e - 1, 1] - ay
        norm = max(np.sqrt(dx * dx + dy * dy), 1e-12)
        dx, dy = dx / norm, dy / norm
        worst, at = -np.inf, s
        for i in range(s, e):
            excess = abs((p[i, 0] - ax) * dy - (p[i, 1] - ay) * dx) - tol[i]
            if excess > worst:
                worst, at = excess, i
        if worst > 0 and e - s >= small:
            cut = min(max(at, s + 1), e - 1)
            stack[top, 0], stack[top, 1] = s, cut
            stack[top + 1, 0], stack[top + 1, 1] = cut, e
            top += 2
    st = np.flatnonzero(first[:n])
    en = np.empty_like(st)
    en[:-1] = st[1:]
    en[-1] = n
    keep = en - st >= min_points
    st, en = st[keep], en[keep]
    # merge
    cs = _prefix_moments(p)
    while len(st) > 1:
        k = len(st)
        ux = np.empty(k)
        uy = np.empty(k)
        for i in range(k):
            m, _, _, sxx, sxy, syy = _run_moments(cs, st[i], en[i])
            _, _, ux[i], uy[i] = tls_fit(m, sxx, sxy, syy)
        score = np.full(k - 1, np.inf)
        n_ok = 0
        for i in range(k - 1):
            if en[i] != st[i + 1] or is_break[st[i + 1]]:
                continue
            m, _, _, sxx, sxy, syy = _run_moments(cs, st[i], en[i + 1])
            ms, _, _, _ = tls_fit(m, sxx, sxy, syy)
            rms = np.sqrt(ms)
            if rms < merge_residual and abs(ux[i] * ux[i + 1] + uy[i] * uy[i + 1]) > cos_merge:
                score[i] = rms
                n_ok += 1
        if n_ok == 0:
            break
        chosen = np.zeros(k - 1, np.bool_)
        for i in stable_argsort(score)[:n_ok]:
            if (i > 0 and chosen[i - 1]) or (i + 1 < k - 1 and chosen[i + 1]):
                continue
            chosen[i] = True
        keep_start = np.ones(k, np.bool_)
        keep_end = np.ones(k, np.bool_)
        keep_start[1:][chosen] = False
        keep_end[:-1][chosen] = False
        st, en = st[keep_start], en[keep_end]
    return st, en, cs


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
    p = np.ascontiguousarray(p, dtype=float)
    starts, ends, cs = _split_merge(
        p, params.split_dist + params.split_dist_per_m * r, starts, ends, is_break,
        max(params.min_points, 3), params.min_points, params.merge_residual,
        float(np.cos(params.merge_angle)))
    if not len(starts):
        out = empty_segments()
        out.points = p
        return out
    a, b, n, res, c, S, cov = _fitted(p, cs, starts, ends, float(params.min_points),
                                      float(params.min_length), float(params.sigma_range ** 2))
    return Segments(a, b, n, res, c, S, cov, p)


@kernel
def _fitted(p, cs, starts, ends, min_points, min_length, var_floor):
    """The segments of the runs ``starts``-``ends``: each run's moments and total-least-
    squares line, its end points (the first and last point projected on the line), the
    RMS residual, and the covariance of (normal angle, offset at the centroid) from the
    residual (at least ``var_floor``) and the spread along the line; only the runs of
    ``min_points`` points and ``min_length`` metres or more."""
    k = len(starts)
    a, b, c = np.empty((k, 2)), np.empty((k, 2)), np.empty((k, 2))
    S, cov = np.empty((k, 2, 2)), np.zeros((k, 2, 2))
    n_out, res = np.empty(k, np.int64), np.empty(k)
    m = 0
    for i in range(k):
        n, cx, cy, sxx, sxy, syy = _run_moments(cs, starts[i], ends[i])
        ms, spread, dx, dy = tls_fit(n, sxx, sxy, syy)
        s0, e0 = starts[i], ends[i] - 1
        ta = (p[s0, 0] - cx) * dx + (p[s0, 1] - cy) * dy
        tb = (p[e0, 0] - cx) * dx + (p[e0, 1] - cy) * dy
        if not (n >= min_points and abs(tb - ta) >= min_length):
            continue
        a[m, 0], a[m, 1] = cx + ta * dx, cy + ta * dy
        b[m, 0], b[m, 1] = cx + tb * dx, cy + tb * dy
        c[m, 0], c[m, 1] = cx, cy
        S[m, 0, 0], S[m, 0, 1], S[m, 1, 0], S[m, 1, 1] = sxx, sxy, sxy, syy
        var = max(ms * n / max(n - 2.0, 1.0), var_floor)
        cov[m, 0, 0] = var / max(spread, 1e-9)
        cov[m, 1, 1] = var / n
        n_out[m], res[m] = int(n), np.sqrt(ms)
        m += 1
    return a[:m], b[:m], n_out[:m], res[:m], c[:m], S[:m], cov[:m]


def segments_from_scan(scan, params: SegmentParams | None = None) -> Segments:
    """Convenience: segments of a ``LaserScan``-like object (ranges, angle_min, increment)."""
    return extract_segments(scan.ranges, scan.angle_min, scan.angle_increment, params)
