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
   ``min_score`` has a wall within the k-th shortest range, :func:`_reach`), so empty space
   around or inside a big map is never read; the band's connected pieces are read as a few
   windows.  In both sweeps each scan point reads its window of the (phase-split) near-wall
   mask for all rotations in one fancy index, so the Python work is points x windows and
   the memory traffic rotations x points x positions.  The fallback's cells per rotation
   come from the columns with the best maxima (:func:`_top_cells`), not a selection over
   every count, and ties of the wide count (the bound over the cell) go to the cell whose
   own pose fits more points (a tight count in the same byte): its recall, not its speed,
   decides the cluttered scans (Intel, 3 maps x 910 scans: 129 -> 117 failures, none new).
   The line path's sweep (a dozen rotations) reads the whole grid as before.

Symmetric places (corridors, identical rooms) give several hypotheses with similar scores; all
are returned, ranked.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from .correction import CorrectionParams, correct_pose
from .jit import kernel
from .linemap import LineMap
from .matching import LineIndex, line_angles, line_normals
from .odometry import wrap_angle as _wrap
from .segments import Segments


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


class DistanceField:
    """Distance (m) from any point to the nearest map segment, on a grid (cv2)."""

    def __init__(self, lmap: LineMap, resolution: float = 0.05, border: float = 2.0):
        pts = np.concatenate([lmap.a, lmap.b]) if len(lmap) else np.zeros((1, 2))
        self.lo = pts.min(0) - border
        hi = pts.max(0) + border
        self.res = resolution
        self.size = np.ceil((hi - self.lo) / resolution).astype(int) + 1
        img = np.full((self.size[1], self.size[0]), 255, np.uint8)
        pa = np.round((lmap.a - self.lo) / resolution).astype(np.int32)
        pb = np.round((lmap.b - self.lo) / resolution).astype(np.int32)
        for p, q in zip(pa, pb, strict=True):  # one draw per segment
            cv2.line(img, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), 0, 1)
        self.dist = cv2.distanceTransform(img, cv2.DIST_L2, 5).astype(np.float32) * resolution
        self.far = float(border)
        self._img, self._pa, self._pb = img, pa, pb
        self.a, self.b = np.asarray(lmap.a, float), np.asarray(lmap.b, float)
        self._seg_id: np.ndarray | None = None
        self._tab: np.ndarray | None = None    # per segment: a, u, length (built with seg_id)
        self._stacks: dict = {}                # phase_stack's, per (thr, step, tight)
        self._bits: dict = {}                  # inlier_bits', per threshold
        self._grid_dist: dict = {}             # grid_dist's, per step

    @property
    def seg_id(self) -> np.ndarray:
        """Index of the nearest map segment at every cell (built on first use: only the
        point refinement needs it).  The nearest drawn pixel's label (cv2, pixel labels in
        raster order) is mapped to the segment that drew it."""
        if self._seg_id is None:
            ids = np.full(self._img.shape, -1, np.int32)
            for k, (p, q) in enumerate(zip(self._pa, self._pb, strict=True)):
                cv2.line(ids, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), k, 1)
            _, lab = cv2.distanceTransformWithLabels(self._img, cv2.DIST_L2, 5,
                                                     labelType=cv2.DIST_LABEL_PIXEL)
            ys, xs = np.nonzero(self._img == 0)
            owner = np.maximum(ids[ys, xs], 0)
            # int16 where the segments allow: on a big building's map the grid is 10^7 cells
            self._seg_id = owner[np.maximum(lab, 1) - 1].astype(
                np.int16 if len(self._pa) <= np.iinfo(np.int16).max else np.int32)
            d = self.b - self.a
            L = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
            self.u = d / L[:, None]                       # unit directions
            self.seg_len = L
            self._tab = np.column_stack([self.a, self.u, self.seg_len])
            self._img = None   # the drawn walls were kept for this grid only
        return self._seg_id

    def nearest(self, gx: np.ndarray, gy: np.ndarray, full: bool = False):
        """For points (gx, gy) of any shape: (segment index, signed distance to its line,
        distance to the segment itself, off-grid mask).  Exact point-to-line geometry on
        the segment the grid names, so the answer is not quantised to the grid.  With
        ``full``, also the segment's direction (ux, uy), the point's position t along it
        and its length (what the ICP needs, without gathering them again)."""
        sid_grid = self.seg_id
        qx = np.floor((gx - self.lo[0]) / self.res + 0.5).astype(np.int64)
        qy = np.floor((gy - self.lo[1]) / self.res + 0.5).astype(np.int64)
        ok = (qx >= 0) & (qy >= 0) & (qx < self.size[0]) & (qy < self.size[1])
        sid = sid_grid[np.clip(qy, 0, self.size[1] - 1), np.clip(qx, 0, self.size[0] - 1)]
        row = self._tab[sid]
        ux, uy, L = row[..., 2], row[..., 3], row[..., 4]
        rx, ry = gx - row[..., 0], gy - row[..., 1]
        e = ux * ry - uy * rx                                # along the normal (-uy, ux)
        t = ux * rx + uy * ry
        over = np.maximum(np.maximum(-t, t - L), 0.0)
        dseg = np.where(ok, np.hypot(e, over), self.far)
        if full:
            return sid, e, dseg, ok, ux, uy, t, L
        return sid, e, dseg, ok

    def padded_mask(self, thr: float, pad_m: float = 30.0,
                    dilate: int = 0) -> tuple[int, np.ndarray]:
        """(pad, near-wall mask ``dist < thr`` with ``pad`` false pixels on every side):
        shifted slices of it read points up to ``pad_m`` metres from the laser.  With
        ``dilate`` d, a pixel holds the mask's maximum over the square of the d + 1 pixels
        from it down and right (a max-pool: read at one position, it bounds the mask read at
        any position up to d pixels further on either axis).  Not cached: only
        :meth:`phase_stack` (cached) reads it."""
        pad = int(np.ceil(pad_m / self.res))
        m = np.zeros((self.dist.shape[0] + 2 * pad + 1, self.dist.shape[1] + 2 * pad + 1),
                     np.uint8)
        m[pad: pad + self.dist.shape[0], pad: pad + self.dist.shape[1]] = self.dist < thr
        if dilate:
            m = cv2.dilate(m, np.ones((dilate + 1, dilate + 1), np.uint8), anchor=(0, 0))
        return pad, m

    def phase_stack(self, thr: float, step: int, tight: float | None = None,
                    dilate: int = 0) -> tuple[int, np.ndarray]:
        """(pad, the padded near-wall mask split into its step x step sampling phases, stacked):
        ``stack[py * step + px, j, i]`` is ``mask[py + j * step, px + i * step]``, so a read of
        the mask at a stride of ``step`` pixels from any offset is a window of one phase, and
        one fancy index over a sliding-window view reads it for many rotations at once
        (cached per map, uint8: a sum of a few dozen 0/1 reads never overflows).  With
        ``tight``, a pixel holds 16 (within ``thr``) + 1 (within ``tight``): a sum over at
        most 15 points is then the wide count and the tight count in one byte, ordered by
        the wide count first.  ``dilate``: of the max-pooled mask (:meth:`padded_mask`), the
        bounds of a coarse-to-fine sweep."""
        key = (round(thr, 4), step, None if tight is None else round(tight, 4), dilate)
        cache = self._stacks
        if key not in cache:
            pad, m = self.padded_mask(thr, dilate=dilate)
            if tight is not None:
                m = m * np.uint8(16) + self.padded_mask(tight, dilate=dilate)[1]
            ny, nx = self.grid_shape(step)
            # one row and column more than the grid: a coarse sweep's last cell reaches there
            hs, ws = 2 * pad // step + ny + 2, 2 * pad // step + nx + 2
            st = np.zeros((step * step, hs, ws), np.uint8)
            for py in range(step):          # step^2 strided copies, once per map
                for px in range(step):
                    ph = m[py::step, px::step][:hs, :ws]
                    st[py * step + px, : ph.shape[0], : ph.shape[1]] = ph
            cache[key] = (pad, st)
        return cache[key]

    def inlier_bits(self, thr: float) -> np.ndarray:
        """``dist < thr`` packed 8 cells to a byte along rows (bit i of byte j: column 8 j +
        i), cached: a hypothesis's plain inlier count reads 1/32 of the float field's bytes,
        which on a big building's map is what keeps many thousand hypotheses in cache."""
        key = round(thr, 6)
        if key not in self._bits:
            # compared in float64, as the score compares a looked-up distance
            self._bits[key] = np.packbits(self.dist < np.float64(thr), axis=1,
                                          bitorder="little")
        return self._bits[key]

    def grid_shape(self, step: int) -> tuple[int, int]:
        """(rows, columns) of the sweep's position grid at ``step`` pixels."""
        ny, nx = (np.array(self.dist.shape) + step - 1) // step
        return int(ny), int(nx)

    def grid_dist(self, step: int) -> np.ndarray:
        """The distance field at the sweep's grid positions (every ``step``-th pixel), cached:
        what the sweep's free-space band is cut from."""
        cache = self._grid_dist
        if step not in cache:
            cache[step] = np.ascontiguousarray(self.dist[::step, ::step])
        return cache[step]

    def lookup(self, p: np.ndarray) -> np.ndarray:
        """Distances for points (..., 2); points off the grid count as far."""
        return self.lookup_xy(p[..., 0], p[..., 1])

    def lookup_xy(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """:meth:`lookup` for separate coordinate arrays (nearest cell).  The field itself
        is read (no copy with a far cell appended: on a big building's map that was another
        100 MB), off-grid points answered afterwards."""
        qx = np.floor((x - self.lo[0]) / self.res + 0.5).astype(np.int64)
        qy = np.floor((y - self.lo[1]) / self.res + 0.5).astype(np.int64)
        off = (qx < 0) | (qy < 0) | (qx >= self.size[0]) | (qy >= self.size[1])
        d = self.dist[np.clip(qy, 0, self.size[1] - 1), np.clip(qx, 0, self.size[0] - 1)]
        return np.where(off, np.float32(self.far), d)


def rotation_peaks(phi_g, len_g, phi_l, len_l, bin_deg: float, peaks: int) -> np.ndarray:
    """Eq. (9) in the Hough domain: the ``peaks`` highest peaks of the length-weighted
    histogram of undirected angle differences phi_g - phi_l (mod pi) between every map line
    and every scan line, strongest first, each refined by the weighted circular mean of the
    differences near it.  A rotation by a peak (or by it + pi) turns scan lines onto map
    lines."""
    d = np.mod(phi_g[:, None] - phi_l[None, :], np.pi)
    w = np.minimum(len_g[:, None], len_l[None, :])
    nb = int(round(180.0 / bin_deg))
    idx = np.minimum((d / np.pi * nb).astype(int), nb - 1)
    hist = np.bincount(idx.ravel(), w.ravel(), nb)
    kern = np.array([0.25, 0.5, 1.0, 0.5, 0.25])
    sm = sum(k * np.roll(hist, s) for k, s in zip(kern, range(-2, 3), strict=True))
    top = np.nonzero((sm >= np.roll(sm, 1)) & (sm > np.roll(sm, -1)) & (sm > 0))[0]
    top = top[np.argsort(-sm[top])][:peaks]
    out = np.empty(len(top))
    for k, pk in enumerate(top):
        centre = (pk + 0.5) * np.pi / nb
        dd = _wrap(2 * (d - centre)) / 2
        near = np.abs(dd) < np.deg2rad(2.5 * bin_deg)
        if near.any():
            centre = centre + np.sum(w[near] * dd[near]) / np.sum(w[near])
        out[k] = centre
    return out


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
            T, D, Tf, Df = _line_candidates(
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
        Ts_, Rs_ = _sweep(field, pts, rots, P, near=near if P.sweep_near else None,
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
            reach = _reach(seg.points, P, field.res)
            T2, th2 = _fallback_sweep(field, pts, P, reach,
                                      near=near if P.sweep_near else None)
            if near is not None:
                keep = _near(T2, th2, near)
                T2, th2 = T2[keep], th2[keep]
            hyps += _verify_points(field, seg.points, T2, th2, pts,
                                   replace(P, icp_candidates=P.fallback_icp,
                                           final_candidates=P.fallback_final))
        return _ranked(hyps, P)
    scores = _score(field, pts, T, th, P.coarse_dist)
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
            pose = _polish(field, seg.points, pose, P.inlier_dist)
        sc = float(_score(field, seg.points, pose[None, :2], pose[None, 2], P.inlier_dist)[0])
        fit = float(_score(field, seg.points, pose[None, :2], pose[None, 2], P.inlier_dist,
                           soft=True)[0])
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


def _near_box(near: tuple, cell: float) -> tuple:
    """The square around a hint (pose, m, rad) that holds every position within its
    distance, one sweep cell wider (a cell's position stands for poses about it)."""
    r = near[1] + cell
    c = np.asarray(near[0][:2], float)
    return c - r, c + r


def _within_turn(rots: np.ndarray, near: tuple, slack: float) -> np.ndarray:
    """Which rotation hypotheses lie within a hint's (pose, m, rad) turn, plus ``slack``
    (a hypothesis stands for the rotations about it)."""
    return np.abs(_wrap(np.asarray(rots, float) - near[0][2])) < near[2] + slack


def _near(T: np.ndarray, th: np.ndarray, near: tuple) -> np.ndarray:
    """Which candidates (T, th) lie within ``near``'s (pose, metres, radians)."""
    return (np.hypot(*(T - near[0][:2]).T) < near[1]) & (
        np.abs(_wrap(th - near[0][2])) < near[2])


def _cell_keys(T: np.ndarray, th: np.ndarray, cell: float, ang: float) -> np.ndarray:
    """One integer per (x, y, theta) cell of ``cell`` metres and ``ang`` radians for each
    candidate (T, th): equal keys, one cell (a 1-D unique sorts far faster than rows)."""
    kx = np.floor(T[:, 0] / cell).astype(np.int64)
    ky = np.floor(T[:, 1] / cell).astype(np.int64)
    kt = np.floor(np.mod(th, 2 * np.pi) / ang).astype(np.int64)
    kx -= kx.min()
    ky -= ky.min()
    return (kx * (int(ky.max()) + 1) + ky) * (int(kt.max()) + 1) + kt


def _distinct(T: np.ndarray, th: np.ndarray, order: np.ndarray, cell: float, ang: float,
              k: int) -> np.ndarray:
    """The first ``k`` of ``order`` that fall in different (x, y, theta) cells: the best
    candidate of each cell, so near-duplicates do not crowd out other places."""
    if not len(order):
        return order
    # the stable sort keeps the first -- best -- candidate of each cell
    _, first = np.unique(_cell_keys(T[order], th[order], cell, ang), return_index=True)
    return order[np.sort(first)[:k]]


def _best_distinct(field: DistanceField, pts: np.ndarray, T: np.ndarray, th: np.ndarray,
                   inlier: float, cell: float, ang: float, k: int) -> np.ndarray:
    """The ``k`` best candidates by their inlier fraction (:func:`_score` at ``inlier``,
    ties by index), one per (x, y, theta) cell: :func:`_distinct` of the candidates ranked
    by that score, the same indices, without counting every candidate's points to the end.
    A big building's map gives 10^4-10^5 candidates, most of them nowhere near a wall, and
    their full count was a fifth of a trial.  Once k cells hold a candidate with count c
    or more, the k cells picked all reach c, and a later candidate that cannot beat c (its
    points left to read would not make up the difference; at c exactly, the k earlier
    ones come first) is never picked: its count stops there (:func:`_pruned_counts`)."""
    if not len(T) or not len(pts) or field.far < inlier:
        # nothing to prune by (or off-grid points count: the packed bits cannot say it)
        order = np.argsort(-_score(field, pts, T, th, inlier), kind="stable")
        return _distinct(T, th, order, cell, ang, k)
    cells, cid = np.unique(_cell_keys(T, th, cell, ang), return_inverse=True)
    counts = np.empty(len(T), np.int64)
    _pruned_counts(field.inlier_bits(inlier), float(field.lo[0]), float(field.lo[1]),
                   float(field.res), np.ascontiguousarray(pts[_spread(len(pts))], dtype=float),
                   np.ascontiguousarray(T, dtype=float), np.ascontiguousarray(th, dtype=float),
                   cid.ravel().astype(np.int64), len(cells), int(k), counts)
    done = np.nonzero(counts >= 0)[0]
    order = done[np.argsort(-counts[done], kind="stable")]
    return _first_per_cell(order, cid.ravel().astype(np.int64), len(cells), int(k))


@lru_cache(maxsize=64)
def _spread(n: int) -> np.ndarray:
    """0 .. n-1 in bit-reversed order (0, n/2, n/4, 3n/4, ...): scan points read in this
    order spread over the scan from the first reads, so a bad pose's misses show early
    (a count that stops once it cannot reach a bar stops sooner)."""
    rev = [int(f"{i:032b}"[::-1], 2) for i in range(n)]
    out = np.argsort(np.array(rev, np.int64), kind="stable")
    out.flags.writeable = False     # shared by every caller (cached)
    return out


@kernel
def _pruned_counts(bits, lo0, lo1, res, pts, T, th, cid, n_cells, k, out):
    """:func:`_best_distinct`'s counts: each candidate's inlier count (the packed bits, as
    :func:`_score_kernel` reads them), or -1 once it cannot beat the count that k distinct
    cells already hold.  That bar only rises: the cells' best counts so far are kept in a
    histogram, and the bar is the highest count that k of them reach."""
    ny = bits.shape[0]
    nx = bits.shape[1] * 8
    n = pts.shape[0]
    best = np.full(n_cells, -1, np.int64)
    hist = np.zeros(n + 1, np.int64)      # cells by their best count
    bar = 0
    for h in range(T.shape[0]):
        c, s = np.cos(th[h]), np.sin(th[h])
        acc = 0
        pruned = False
        for j in range(n):
            if acc + n - j <= bar:
                pruned = True
                break
            qx, qy = _cell_of(c, s, pts[j, 0], pts[j, 1], T[h, 0], T[h, 1], lo0, lo1, res)
            if qx >= 0 and qy >= 0 and qx < nx and qy < ny:
                ix = int(qx)
                acc += (bits[int(qy), ix >> 3] >> (ix & 7)) & 1
        if pruned:
            out[h] = -1
            continue
        out[h] = acc
        g = cid[h]
        if acc > best[g]:
            if best[g] >= 0:
                hist[best[g]] -= 1
            hist[acc] += 1
            best[g] = acc
            total = 0
            for v in range(n, bar - 1, -1):
                total += hist[v]
                if total >= k:
                    bar = v
                    break


@kernel
def _first_per_cell(order, cid, n_cells, k):
    """The first ``k`` of ``order`` whose cells (``cid``) come up for the first time."""
    seen = np.zeros(n_cells, np.bool_)
    out = np.empty(min(k, order.size), np.int64)
    m = 0
    for i in order:
        if m == out.size:
            break
        if not seen[cid[i]]:
            seen[cid[i]] = True
            out[m] = i
            m += 1
    return out[:m]


def _icp(field: DistanceField, pts: np.ndarray, poses: np.ndarray,
         gates: tuple[float, ...]) -> np.ndarray:
    """Batched point-to-segment Gauss-Newton for many poses at once (H, 3): each scan point
    pairs with the map segment nearest to it (:meth:`DistanceField.nearest`) when within the
    iteration's gate; its residual is the distance to the closest point of that segment
    (to the line where the point projects inside the segment, to the end point beyond it,
    so segment ends fix the position along a corridor), with Cauchy weights.  A light
    damping keeps a direction nothing fixes where it was.  Compiled (:func:`_icp_kernel`):
    in numpy its (poses x points) temporaries were half of a trial on the Intel map."""
    x = np.array(poses, dtype=float, copy=True).reshape(-1, 3)
    field.seg_id  # noqa: B018  (builds the nearest-segment grid and its table)
    _icp_kernel(field.seg_id, field._tab, float(field.lo[0]), float(field.lo[1]),
                float(field.res), float(field.far), np.ascontiguousarray(pts, dtype=float),
                np.asarray(gates, dtype=float), x)
    return x


@kernel
def _icp_kernel(seg_id, tab, lo0, lo1, res, far, pts, gates, x):
    """:func:`_icp` pose by pose, in place on ``x`` (H, 3): per gate, every point's nearest
    segment (as :meth:`DistanceField.nearest` reads it), its residual and Jacobian into the
    3 x 3 normal equations, damped by 0.5, solved by their symmetric inverse."""
    ny, nx = seg_id.shape
    for h in range(x.shape[0]):
        for gate in gates:
            c, s = np.cos(x[h, 2]), np.sin(x[h, 2])
            scale = max(gate / 3.0, 0.02)
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            b0 = b1 = b2 = 0.0
            for j in range(pts.shape[0]):
                rx = c * pts[j, 0] - s * pts[j, 1]
                ry = s * pts[j, 0] + c * pts[j, 1]
                gx, gy = rx + x[h, 0], ry + x[h, 1]
                qx = int(np.floor((gx - lo0) / res + 0.5))
                qy = int(np.floor((gy - lo1) / res + 0.5))
                on_grid = qx >= 0 and qy >= 0 and qx < nx and qy < ny
                sid = seg_id[min(max(qy, 0), ny - 1), min(max(qx, 0), nx - 1)]
                ux, uy, L = tab[sid, 2], tab[sid, 3], tab[sid, 4]
                dx, dy = gx - tab[sid, 0], gy - tab[sid, 1]
                e = ux * dy - uy * dx                   # along the normal (-uy, ux)
                t = ux * dx + uy * dy
                over = t if t < 0.0 else (t - L if t > L else 0.0)
                dseg = np.hypot(e, over) if on_grid else far
                if not dseg < gate:
                    continue
                if over != 0.0:
                    # beyond an end the residual points from the end point to the point:
                    # along the segment by the overshoot, across it by e
                    inv = 1.0 / max(dseg, 1e-9)
                    n0, n1 = (over * ux - e * uy) * inv, (over * uy + e * ux) * inv
                    e = dseg
                else:
                    n0, n1 = -uy, ux
                w = 1.0 / (1.0 + (e / scale) ** 2)
                j2 = n1 * rx - n0 * ry
                a00 += w * n0 * n0
                a01 += w * n0 * n1
                a02 += w * n0 * j2
                a11 += w * n1 * n1
                a12 += w * n1 * j2
                a22 += w * j2 * j2
                b0 += w * n0 * e
                b1 += w * n1 * e
                b2 += w * j2 * e
            a00 += 0.5
            a11 += 0.5
            a22 += 0.5
            # the symmetric inverse (cofactors): positive definite by the damping
            i00, i01, i02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
            i11, i12, i22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
            det = a00 * i00 + a01 * i01 + a02 * i02
            x[h, 0] -= (i00 * b0 + i01 * b1 + i02 * b2) / det
            x[h, 1] -= (i01 * b0 + i11 * b1 + i12 * b2) / det
            x[h, 2] -= (i02 * b0 + i12 * b1 + i22 * b2) / det
        x[h, 2] = (x[h, 2] + np.pi) % (2.0 * np.pi) - np.pi


def _fit(field: DistanceField, pts: np.ndarray, poses: np.ndarray, inlier: float):
    """(inlier fraction, soft fit) per pose (H, 3) from exact point-to-segment distances."""
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    gx = c * pts[None, :, 0] - s * pts[None, :, 1] + poses[:, 0, None]
    gy = s * pts[None, :, 0] + c * pts[None, :, 1] + poses[:, 1, None]
    d = field.nearest(gx, gy)[2]
    return np.mean(d < inlier, -1), np.mean(np.maximum(0.0, 1.0 - (d / inlier) ** 2), -1)


def _verify_points(field: DistanceField, pts: np.ndarray, T: np.ndarray, th: np.ndarray,
                   coarse_pts: np.ndarray, P: RelocParams) -> list[Hypothesis]:
    """Point-based verification of the coarse candidates (all vectorised over hypotheses):
    the best distinct ones by their inlier fraction at ``coarse_dist`` (of ``coarse_pts``)
    are pulled in by point-to-line ICP on a subsample and re-ranked by their soft fit; the
    best few are refined on all points and ranked by the fit less the free-space evidence
    (beams through mapped walls)."""
    sel = _best_distinct(field, coarse_pts, T, th, P.coarse_dist, 0.3, np.deg2rad(3.0),
                         P.icp_candidates)
    sub = pts
    if len(sub) > P.icp_points:
        sub = sub[np.linspace(0, len(sub) - 1, P.icp_points).astype(int)]
    poses = _icp(field, sub, np.column_stack([T[sel], th[sel]]), P.icp_gates)
    _, fit = _fit(field, sub, poses, P.inlier_dist)
    order = np.argsort(-fit, kind="stable")
    keep = _distinct(poses[:, :2], poses[:, 2], order, 0.3, np.deg2rad(3.0), P.final_candidates)
    poses = _icp(field, pts, poses[keep], P.final_gates)
    score, fit = _fit(field, pts, poses, P.inlier_dist)
    cross = _crossings(field, pts, poses, P) if P.cross_beams else np.zeros(len(poses))
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


def _fallback_sweep(field: DistanceField, pts: np.ndarray, P: RelocParams,
                    reach: float | None = None, stats: dict | None = None,
                    near: tuple | None = None):
    """Candidates for a scan whose lines gave no convincing pose (cluttered: its few
    segments are furniture at odd angles, so no line pairing names the rotation): the
    correlative sweep over all rotations at ``fallback_rot_deg`` steps (with ``near``, a
    hint (pose, m, rad): those within its turn, at positions within its distance)."""
    rots = np.arange(0.0, 2 * np.pi, np.deg2rad(P.fallback_rot_deg))
    Q = replace(P, sweep_cells=P.fallback_cells, sweep_grid=P.fallback_grid,
                sweep_points=P.fallback_points)
    # ties of the wide count (the bound) go to the cell whose own pose fits more points
    return _sweep(field, pts, rots, Q, reach, stats, tight=P.coarse_dist, near=near,
                  turn_slack=np.deg2rad(P.fallback_rot_deg))


def _crossings(field: DistanceField, pts: np.ndarray, poses: np.ndarray,
               P: RelocParams) -> np.ndarray:
    """Fraction of beams per pose (H, 3) that pass through a mapped wall: free space the
    hypothesis claims where the map has a wall.  Samples along each beam find the walls it
    comes near (distance field); a wall counts only when its segment's line separates the
    laser from the beam's end by ``cross_margin`` on both sides (exact, perpendicular to
    the wall), so a beam grazing a wall it ends on, or map error of a few centimetres,
    never counts."""
    if not len(pts) or not len(poses):
        return np.zeros(len(poses))
    if len(pts) > P.cross_beams:
        pts = pts[np.linspace(0, len(pts) - 1, P.cross_beams).astype(int)]
    r = np.linalg.norm(pts, axis=-1)
    step = P.crossing_step
    f = np.arange(P.cross_skip, min(float(r.max()), P.cross_range), step)  # (S,)
    u = pts / np.maximum(r, 1e-9)[:, None]
    field.seg_id  # noqa: B018  (builds the nearest-segment grid and its table)
    out = np.empty(len(poses))
    _crossings_kernel(field.dist, field.seg_id, field._tab, float(field.lo[0]),
                      float(field.lo[1]), float(field.res), np.ascontiguousarray(u), r, f,
                      # the field's own precision, as numpy compared it
                      np.float32(0.6 * step + 0.5 * field.res), float(P.cross_margin),
                      np.ascontiguousarray(poses, dtype=float), out)
    return out


@kernel
def _crossings_kernel(dist, seg_id, tab, lo0, lo1, res, u, r, f, near, margin, poses, out):
    """:func:`_crossings` pose by pose: each beam (unit direction ``u``, range ``r``) is
    sampled at the distances ``f`` short of its end by ``margin``; at a sample within
    ``near`` of a wall (the distance field, nearest cell; off the grid: none), the wall is
    the nearest segment (as :meth:`DistanceField.nearest` reads it), and the beam crosses it
    when the segment's line separates the laser from the beam's end by ``margin`` on both
    sides and the beam meets that line on the segment.  ``out``: the crossed fraction."""
    ny, nx = dist.shape
    for h in range(poses.shape[0]):
        ox, oy = poses[h, 0], poses[h, 1]
        c, s = np.cos(poses[h, 2]), np.sin(poses[h, 2])
        hits = 0
        for b in range(u.shape[0]):
            ugx = c * u[b, 0] - s * u[b, 1]
            ugy = s * u[b, 0] + c * u[b, 1]
            ex, ey = ox + ugx * r[b], oy + ugy * r[b]                 # the beam's end
            for fk in f:
                if not fk < r[b] - margin:
                    break
                sx, sy = ox + ugx * fk, oy + ugy * fk
                qx = int(np.floor((sx - lo0) / res + 0.5))
                qy = int(np.floor((sy - lo1) / res + 0.5))
                if not (qx >= 0 and qy >= 0 and qx < nx and qy < ny) or not dist[qy, qx] < near:
                    continue
                sid = seg_id[qy, qx]
                ax, ay, wx, wy = tab[sid, 0], tab[sid, 1], tab[sid, 2], tab[sid, 3]
                so = -wy * (ox - ax) + wx * (oy - ay)
                se = -wy * (ex - ax) + wx * (ey - ay)
                # where the beam meets the wall's line must lie on the segment (a beam
                # passing just past a segment's end crosses nothing)
                lam = so / (so - se if so != se else 1.0)
                along = wx * (ox - ax + lam * (ex - ox)) + wy * (oy - ay + lam * (ey - oy))
                if (np.sign(so) != np.sign(se) and abs(so) > margin and abs(se) > margin
                        and along > 0.0 and along < tab[sid, 4]):
                    hits += 1
                    break
        out[h] = hits / u.shape[0]


def _band_windows(field: DistanceField, step: int, reach: float | None,
                  max_windows: int = 8) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """The sweep's positions: (band, windows).  ``band`` (grid shape) marks the grid positions
    within ``reach`` of a mapped wall -- the only places a scan with enough points on walls
    can have been taken from (see :func:`_reach`); empty space farther out is never read.
    ``windows`` are (row, col, rows, cols) boxes around the band's connected pieces, so a
    wall piece far from the rest adds its own small box, not the empty space in between
    (more than ``max_windows`` pieces: one box around them all)."""
    g = field.grid_dist(step)
    if reach is None or not np.isfinite(reach):
        band = np.ones(g.shape, bool)
    else:
        band = g <= reach
    if band.all():
        return band, [(0, 0, g.shape[0], g.shape[1])]
    if not band.any():
        return band, []
    n, _, stats, _ = cv2.connectedComponentsWithStats(band.view(np.uint8), connectivity=8)
    boxes = [(int(st[1]), int(st[0]), int(st[3]), int(st[2])) for st in stats[1:]]
    if len(boxes) > max_windows:
        ys, xs = np.nonzero(band)
        boxes = [(int(ys.min()), int(xs.min()), int(ys.max() - ys.min() + 1),
                  int(xs.max() - xs.min() + 1))]
    return band, boxes


def _reach(points: np.ndarray, P: RelocParams, res: float) -> float:
    """How far from the nearest mapped wall the laser can be for a pose that passes
    ``min_score``: at least that fraction of the points lies within ``inlier_dist`` of a
    wall, so the nearest of those inliers -- no farther than the k-th nearest point, k the
    number of points that may miss -- puts a wall within its range + ``inlier_dist`` of the
    laser.  Plus two field pixels of rasterisation (the sweep adds its cell's half diagonal).
    A bound, not a guess: no pose that could be accepted is cut."""
    r = np.sort(np.hypot(points[:, 0], points[:, 1]))
    if not len(r) or P.min_score <= 0:
        return float("inf")
    k = max(len(r) - int(np.ceil(P.min_score * len(r))), 0)
    return float(r[k] + P.inlier_dist + 2 * res)


# fixed pseudo-random tie-breakers for the sweep's cell selection (see _top_cells)
_TIE_NOISE = np.random.default_rng(20261123).integers(0, 256, 1 << 16).astype(np.uint16)


def _tie_noise(r: np.ndarray, gy: np.ndarray, gx: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random byte per (rotation, grid row, grid column)."""
    return _TIE_NOISE[(r * 40503 + gy * 2654 + gx * 97) & 0xFFFF]


def _top_cells(acc: np.ndarray, k: int, y0: int = 0,
               x0: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(counts, rows, cols) of the ``k`` best cells of every rotation's grid ``acc`` (R, h, w)
    (a window whose first cell is grid row ``y0``, column ``x0``).  Exact, and cheaper than
    a selection over all R x h x w counts: the best k cells lie in at most k columns, so the
    columns with the k highest maxima hold them; only those are searched.  Counts tie a
    lot (a few dozen points): ties are broken by a fixed pseudo-random byte per cell, so the
    chosen cells spread over the tied places instead of piling up at one end of the grid
    (a cluster of neighbours is one place; spread, one of them is more often the right one).
    Keys of two bytes sort by radix (numpy's stable sort), faster than a partition."""
    R, h, w = acc.shape
    ri = np.arange(R)[:, None]
    if w > k:
        key = acc.max(axis=1).astype(np.uint16) << 8                    # (R, w)
        key |= _tie_noise(ri, 0, x0 + np.arange(w)[None, :])
        cols = np.argsort(key, axis=1, kind="stable")[:, w - k:]
        sub = acc[ri, :, cols]                                           # (R, k, h)
    else:
        cols = np.broadcast_to(np.arange(w), (R, w))
        sub = acc.transpose(0, 2, 1)
    kc = cols.shape[1]
    sub = sub.reshape(R, -1)
    gy = np.tile(np.arange(h) + y0, kc)[None, :]
    gx = np.repeat(cols + x0, h, axis=1)
    key = (sub.astype(np.uint16) << 8) | _tie_noise(ri, gy, gx)
    kk = min(k, sub.shape[1])
    top = np.argsort(key, axis=1, kind="stable")[:, sub.shape[1] - kk:]
    c_i, iy = np.divmod(top, h)
    return sub[ri, top].astype(np.int32), iy, cols[ri, c_i]


def _sweep(field: DistanceField, pts: np.ndarray, rots: np.ndarray, P: RelocParams,
           reach: float | None = None, stats: dict | None = None,
           tight: float | None = None, near: tuple | None = None,
           turn_slack: float = 0.0):
    """Translation hypotheses that do not need two scan lines on two map lines: for every
    rotation hypothesis, the scan points are correlated with the map's near-wall mask at every
    position of a coarse grid in the free-space band (within ``reach`` of a wall,
    :func:`_band_windows`), and the best ``sweep_cells`` positions per rotation are returned.
    The mask is widened by half a cell's diagonal, so a cell's count bounds the score of any
    pose inside it.  Cluttered scans with one or two short lines need this.

    Cost: one fancy index per scan point and band window reads that point's window of the
    mask for all rotations at once (a point's offset under each rotation picks the phase and
    start of a strided read, :meth:`DistanceField.phase_stack`), so the Python work is
    points x windows, and the memory traffic rotations x points x band positions.  ``stats``
    (if given) receives the counts: positions, band, rotations, points.  ``near`` (a hint:
    pose, m, rad): only its positions, and the rotations within its turn + ``turn_slack``,
    are swept, so the best cells are the best near it."""
    if near is not None:
        rots = np.asarray(rots, float)[_within_turn(rots, near, turn_slack)]
    res = field.res
    step = max(1, int(round(P.sweep_grid / res)))
    thr = P.coarse_dist + 0.71 * step * res
    pad, stack = field.phase_stack(thr, step, tight)
    n_pts = P.sweep_points if tight is None else min(P.sweep_points, 15)   # one byte
    if len(pts) > n_pts:
        pts = pts[np.linspace(0, len(pts) - 1, n_pts).astype(int)]
    # points beyond the padding cannot be read: dropped (by range, so every rotation
    # correlates the same points)
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < (pad - 1) * res]
    # a grid position stands for poses up to half a cell's diagonal away
    band, windows = _band_windows(field, step,
                                  None if reach is None else reach + 0.71 * step * res)
    if near is not None:
        windows = _clip_windows(windows, field, step, _near_box(near, step * res))
    if stats is not None:
        stats.update(positions=int(sum(h * w for _, _, h, w in windows)),
                     band=int(band.sum()), rotations=int(len(rots)), points=int(len(pts)))
    if not len(pts) or not len(rots) or not windows:
        return np.zeros((0, 2)), np.zeros(0)
    c, s = np.cos(rots)[:, None], np.sin(rots)[:, None]
    ox = np.round((c * pts[:, 0] - s * pts[:, 1]) / res).astype(np.int64) + pad   # (R, N)
    oy = np.round((s * pts[:, 0] + c * pts[:, 1]) / res).astype(np.int64) + pad
    k = P.sweep_cells
    cand_s, cand_y, cand_x = [], [], []
    for y0, x0, h, w in windows:     # usually one box; a few for scattered maps
        if h * w > P.sweep_direct and P.sweep_coarse > 1:
            sc, iy, ix = _coarse_to_fine(field, stack, thr, tight, step, P.sweep_coarse,
                                         oy, ox, (y0, x0, h, w),
                                         None if reach is None else band, k)
            cand_s.append(sc)
            cand_y.append(iy + y0)
            cand_x.append(ix + x0)
            continue
        acc = _window_counts(stack, oy, ox, step, (y0, x0, h, w))
        if reach is None:
            # the line path's dozen rotations: a plain partition per rotation over the
            # whole grid (its picks among tied counts are the ones the success rates were
            # measured with; cheap at a dozen rotations)
            flat = acc.reshape(len(rots), -1).astype(np.int16)
            kk = min(k, flat.shape[1])
            top = np.argpartition(-flat, kk - 1, axis=1)[:, :kk]
            sc = np.take_along_axis(flat, top, 1).astype(np.int32)
            iy, ix = np.divmod(top, w)
        else:
            acc *= band[y0: y0 + h, x0: x0 + w]    # positions off the band never win
            sc, iy, ix = _top_cells(acc, k, y0, x0)
        cand_s.append(sc)
        cand_y.append(iy + y0)
        cand_x.append(ix + x0)
    sc, gy, gx = (np.concatenate(v, 1) for v in (cand_s, cand_y, cand_x))
    if sc.shape[1] > k:              # the best k per rotation over all windows
        top = np.argpartition(-sc, k - 1, axis=1)[:, :k]
        gy, gx = np.take_along_axis(gy, top, 1), np.take_along_axis(gx, top, 1)
    T = field.lo + np.stack([gx.ravel(), gy.ravel()], -1) * step * res
    return T, np.repeat(np.asarray(rots, float), gy.shape[1])


def _clip_windows(windows: list, field: DistanceField, step: int, box: tuple) -> list:
    """The sweep's windows cut to the grid positions inside ``box`` ((x, y) low corner,
    (x, y) high corner, m): a relocalisation near a hint sweeps only there."""
    cell = step * field.res
    (bx0, by0), (bx1, by1) = (np.asarray(c, float) for c in box)
    gx0, gx1 = int(np.ceil((bx0 - field.lo[0]) / cell)), int(np.floor((bx1 - field.lo[0]) / cell))
    gy0, gy1 = int(np.ceil((by0 - field.lo[1]) / cell)), int(np.floor((by1 - field.lo[1]) / cell))
    out = []
    for y0, x0, h, w in windows:
        ya, yb = max(y0, gy0), min(y0 + h - 1, gy1)
        xa, xb = max(x0, gx0), min(x0 + w - 1, gx1)
        if ya <= yb and xa <= xb:
            out.append((ya, xa, yb - ya + 1, xb - xa + 1))
    return out


def _window_counts(stack: np.ndarray, oy: np.ndarray, ox: np.ndarray, step: int,
                   window: tuple[int, int, int, int]) -> np.ndarray:
    """The sweep's count at every position of one window (row y0, column x0, h x w positions
    of the grid at ``step`` pixels) for every rotation: (R, h, w).  ``stack``: the phase
    stack at ``step``; ``oy``, ``ox`` (R, N): the points' pixel offsets under each rotation
    (pad included).  One fancy index per point over a sliding-window view reads the point's
    window of the mask for all rotations at once: a loop over the few sampled points, not
    over positions."""
    y0, x0, h, w = window
    R, N = oy.shape
    phase = (oy % step) * step + ox % step
    qy, qx = oy // step + y0, ox // step + x0
    view = np.lib.stride_tricks.sliding_window_view(stack, (h, w), axis=(1, 2))
    acc = np.zeros((R, h, w), np.uint8 if N < 256 else np.uint16)
    for j in range(N):
        acc += view[phase[:, j], qy[:, j], qx[:, j]]
    return acc


def _coarse_to_fine(field: DistanceField, stack: np.ndarray, thr: float,
                    tight: float | None, step: int, f: int, oy: np.ndarray, ox: np.ndarray,
                    window: tuple[int, int, int, int], band: np.ndarray | None,
                    k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_sweep`'s k best positions per rotation in one window (row y0, column x0, h x w
    positions of the grid) by their count, ties by each position's fixed byte
    (:func:`_tie_noise`; :func:`_top_cells` finds the same counts, its ties settled per
    column), without counting every position: a coarse cell of f x f positions is
    first counted on the max-pooled mask (:meth:`DistanceField.phase_stack` with
    ``dilate``), which bounds each of its positions' counts; cells are then counted position
    by position, best bound first, until no cell left could hold a count that reaches the
    k-th best found (branch and bound, one level: :func:`_branch_and_bound`).  ``oy``, ``ox``
    (R, N): the points' pixel offsets under each rotation (pad included); ``stack``: the
    fine phase stack; ``band`` (the grid's shape): positions off it count zero.  Returns
    counts, rows and columns (R, k), the positions relative to the window."""
    y0, x0, h, w = window
    R = len(oy)
    S = f * step
    _, stack_c = field.phase_stack(thr, S, tight, dilate=(f - 1) * step)
    hc, wc = -(-h // f), -(-w // f)
    # the coarse grid starts at the window's corner: each point's pixel offset from there
    bound = _window_counts(stack_c, oy + y0 * step, ox + x0 * step, S, (0, 0, hc, wc))
    ok = (np.ones((h, w), bool) if band is None
          else np.ascontiguousarray(band[y0: y0 + h, x0: x0 + w]))
    if band is not None:
        bw = np.zeros((hc * f, wc * f), bool)
        bw[:h, :w] = ok
        bound *= bw.reshape(hc, f, wc, f).any(axis=(1, 3))
    out = np.zeros((3, R, k), np.int64)
    sp = _spread(oy.shape[1])      # the order the points are read in: counts do not change
    oy, ox = oy[:, sp], ox[:, sp]
    _branch_and_bound(bound.astype(np.int32), stack, (oy % step) * step + ox % step,
                      oy // step + y0, ox // step + x0, ok, f, k, _TIE_NOISE,
                      y0, x0, 1 if tight is None else 17, out)
    return out[0].astype(np.int32), out[1], out[2]


@kernel
def _branch_and_bound(bound, stack, phase, qy, qx, ok, f, k, noise, y0, x0, most, out):
    """Per rotation r: the coarse cells bucketed by their bound (``bound[r]``), counted
    position by position from the highest bound down (:func:`_coarse_to_fine`), while the
    bound still reaches the k-th best count so far; then the k best positions by count and
    tie byte (``noise``, as :func:`_tie_noise`) into ``out`` (counts, rows, columns: (3, R,
    k)), the last one repeated where fewer than k positions were counted.  ``most``: the
    most one point adds to a count (1, or 17 with the tight count in the byte).  A cell's
    positions are counted together, and stop once none can reach the k-th best count so
    far, which only rises, so the answer is that of counting every position to the end."""
    R, hc, wc = bound.shape
    h, w = ok.shape
    n_pts = phase.shape[1]
    hist = np.zeros(n_pts * most + 2, np.int64)   # cells per bound (a bound <= n_pts * most)
    order = np.empty(hc * wc, np.int64)
    cacc = np.zeros((f, f), np.int64)        # one cell's counts
    for r in range(R):
        b = bound[r].ravel()
        hist[:] = 0
        for c in range(b.size):
            hist[b[c]] += 1
        top = hist.size - 1
        while top > 0 and hist[top] == 0:
            top -= 1
        seen = np.zeros(top + 1, np.int64)      # counted positions per count
        cap = 1024
        cnt = np.empty(cap, np.int64)
        py = np.empty(cap, np.int64)
        px = np.empty(cap, np.int64)
        m = 0
        kth = 0        # the k-th best count so far (0 until k positions are counted)
        above = 0      # counted positions at kth or more
        level = top
        while level >= max(kth, 1):
            # the cells of the next few levels down, by descending bound, ascending index
            # within one: a pass over all cells per band of levels (a few thousand cells), not
            # a sort of all of them (kth is usually reached in the first band)
            lo, n_band = level, hist[level]
            while lo > max(kth, 1) and n_band < 4096:
                lo -= 1
                n_band += hist[lo]
            fill = np.zeros(level + 2, np.int64)
            for v in range(level - 1, lo - 1, -1):
                fill[v] = fill[v + 1] + hist[v + 1]
            start = fill.copy()
            for c in range(b.size):
                v = b[c]
                if v >= lo and v <= level:
                    order[fill[v]] = c
                    fill[v] += 1
            for lev in range(level, lo - 1, -1):
                # a cell whose bound is below kth cannot change the k best (a bound equal
                # to it can: ties go by the tie byte)
                if lev < max(kth, 1):
                    break
                for t in range(start[lev], start[lev] + hist[lev]):
                    cy, cx = divmod(order[t], wc)
                    fy, fx = min(f, h - cy * f), min(f, w - cx * f)
                    # the cell's positions counted together, point by point: each point
                    # reads a few adjacent bytes of one row per cell row (cache lines),
                    # where a position at a time read one byte per point far apart
                    for dy in range(fy):
                        for dx in range(fx):
                            cacc[dy, dx] = 0
                    hopeless = False
                    for j in range(n_pts):
                        best_c = 0
                        for dy in range(fy):
                            for dx in range(fx):
                                best_c = max(best_c, cacc[dy, dx])
                        if best_c + (n_pts - j) * most < kth:
                            hopeless = True
                            break
                        ph, by, bx = phase[r, j], qy[r, j] + cy * f, qx[r, j] + cx * f
                        for dy in range(fy):
                            for dx in range(fx):
                                cacc[dy, dx] += stack[ph, by + dy, bx + dx]
                    if hopeless:
                        continue
                    for dy in range(fy):
                        gy = cy * f + dy
                        for dx in range(fx):
                            gx = cx * f + dx
                            acc = cacc[dy, dx]
                            if not ok[gy, gx] or acc < kth:
                                continue
                            if m == cap:
                                cap *= 2
                                cnt2, py2, px2 = np.empty(cap, np.int64), np.empty(
                                    cap, np.int64), np.empty(cap, np.int64)
                                cnt2[:m], py2[:m], px2[:m] = cnt[:m], py[:m], px[:m]
                                cnt, py, px = cnt2, py2, px2
                            cnt[m], py[m], px[m] = acc, gy, gx
                            m += 1
                            seen[acc] += 1
                            above += 1
                            while kth < top and above - seen[kth] >= k:
                                above -= seen[kth]
                                kth += 1
            level = lo - 1
        key = np.full(m, -1, np.int64)
        for i in range(m):
            if cnt[i] >= kth:
                key[i] = (cnt[i] << 8) | noise[(r * 40503 + (py[i] + y0) * 2654
                                               + (px[i] + x0) * 97) & 0xFFFF]
        last = -1
        for slot in range(k):
            best = -1
            for i in range(m):
                if key[i] >= 0 and (best < 0 or key[i] > key[best]):
                    best = i
            if best >= 0:
                key[best] = -1
                last = best
            if last >= 0:
                out[0, r, slot], out[1, r, slot], out[2, r, slot] = cnt[last], py[last], px[last]


def _polish(field: DistanceField, pts: np.ndarray, pose: np.ndarray, inlier: float,
            steps=((0.06, 0.01), (0.03, 0.005), (0.015, 0.0025))) -> np.ndarray:
    """Local grid search (3 x 3 x 3 around the pose, shrinking) on the soft point score:
    the segments' fit can sit on a doubled wall; the points settle it."""
    if not len(pts):
        return pose
    best = np.asarray(pose, dtype=float).copy()
    o = np.array([-1.0, 0.0, 1.0])
    grid = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
    for st, sr in steps:
        cand = best + grid * [st, st, sr]
        sc = _score(field, pts, cand[:, :2], cand[:, 2], inlier, soft=True)
        best = cand[int(np.argmax(sc))]
    return best


@kernel
def _pair_kernel(A1, A2, d1, d2, u1, lo1, hi1, u2, lo2, hi2, delta1, delta2, w1, w2, out_T,
                 out_D):
    """The translations (k, 2) putting two scan lines on every pair of map segments (g1, g2)
    they fit at once (Cramer's rule on the lines ``A . T = d``, then both overlap intervals
    (lo, hi) along the segments' directions u), in row-major (g1, g2) order, and each pair's
    rotation residual, the two lines' weighted by their lengths ``w1``, ``w2``: written into
    out_T, out_D as far as they have room; returns how many fit.

    A map segment admits the translations on a piece of its line, d n + s u for s in
    (lo, hi): a pair can fit only where the two pieces' bounding boxes meet.  The second
    pieces are sorted by their boxes' left edges, so each first piece reads the few whose
    boxes can reach its own (sweep and prune) instead of all of them; those are then solved
    in index order, so the output is the full double loop's, pair for pair."""
    room = out_T.shape[0]
    eps = 1e-6  # the boxes are padded: the exact tests below decide
    n2 = A2.shape[0]
    bx0, bx1 = np.empty(n2), np.empty(n2)
    by0, by1 = np.empty(n2), np.empty(n2)
    for b in range(n2):
        cx, cy = d2[b] * A2[b, 0], d2[b] * A2[b, 1]
        x0, x1 = cx + lo2[b] * u2[b, 0], cx + hi2[b] * u2[b, 0]
        y0, y1 = cy + lo2[b] * u2[b, 1], cy + hi2[b] * u2[b, 1]
        bx0[b], bx1[b] = min(x0, x1) - eps, max(x0, x1) + eps
        by0[b], by1[b] = min(y0, y1) - eps, max(y0, y1) + eps
    order = np.argsort(bx0)
    left = bx0[order]
    width = np.max(bx1 - bx0) if n2 else 0.0
    near = np.empty(n2, np.int64)
    n = 0
    for a in range(A1.shape[0]):
        a11, a12 = A1[a, 0], A1[a, 1]
        cx, cy = d1[a] * a11, d1[a] * a12
        x0, x1 = cx + lo1[a] * u1[a, 0], cx + hi1[a] * u1[a, 0]
        y0, y1 = cy + lo1[a] * u1[a, 1], cy + hi1[a] * u1[a, 1]
        ax0, ax1 = min(x0, x1), max(x0, x1)
        ay0, ay1 = min(y0, y1), max(y0, y1)
        m = 0
        j = np.searchsorted(left, ax0 - width)
        while j < n2 and left[j] <= ax1:
            b = order[j]
            if bx1[b] >= ax0 and by0[b] <= ay1 and by1[b] >= ay0:
                near[m] = b
                m += 1
            j += 1
        for b in np.sort(near[:m]):
            a21, a22 = A2[b, 0], A2[b, 1]
            det = a11 * a22 - a12 * a21
            if abs(det) <= 0.3:
                continue  # near-parallel lines fix no point
            tx = (d1[a] * a22 - a12 * d2[b]) / det
            ty = (a11 * d2[b] - d1[a] * a21) / det
            tu = tx * u1[a, 0] + ty * u1[a, 1]
            if not (lo1[a] < tu < hi1[a]):
                continue
            tu = tx * u2[b, 0] + ty * u2[b, 1]
            if not (lo2[b] < tu < hi2[b]):
                continue
            if n < room:
                out_T[n, 0] = tx
                out_T[n, 1] = ty
                out_D[n] = (w1 * delta1[a] + w2 * delta2[b]) / (w1 + w2)
            n += 1
    return n


@kernel
def _line_candidates(ga, gb, n_g, c_g, phi_g, len_g, ra, rb, n_l, c_l, phi_l, len_l, s, tol,
                     map_share, slack, min_ang, n_end):
    """One rotation hypothesis's translation candidates from the scan's lines (the scan's
    end points ``ra``, ``rb`` turned by it, their lines' normals, offsets, angles and
    lengths; ``s`` = -1 for its twin + pi, which turns the points and normals by pi).  Scan
    line i may lie on map segment g when their angles differ by less than ``tol`` (the
    residual ``delta``, each candidate's own rotation correction: the histogram peak is only
    good to a bin or so) and the map segment is at least ``map_share`` of its length (less
    0.3 m).  On one of them the translation satisfies ``n_g . T = c_g - s sgn c_l`` (sgn:
    the normals' relative sign) and, for the scan segment to lie on the map segment and not
    only on its line, falls in an interval along it.  Returns (T, D): every translation that puts
    two scan lines at least ``min_ang`` apart on two map segments at once
    (:func:`_pair_kernel`, pairs of scan lines in order), with its rotation residual; and
    (Tf, Df): the corridor candidates of the first ``n_end`` scan lines, each end of the
    scan line aligned with each end of every map segment it may lie on (a position along
    parallel walls, which a short cross piece would fix but is often missing)."""
    G, k = len(ga), len(ra)
    off = np.zeros(k + 1, np.int64)         # per scan line: its map segments, flat
    gi = np.empty(G * k, np.int64)
    dl = np.empty(G * k)
    e = 0
    for i in range(k):
        for g in range(G):
            dd = ((2 * (phi_g[g] - phi_l[i]) + np.pi) % (2.0 * np.pi) - np.pi) / 2
            if abs(dd) < tol and len_g[g] > map_share * len_l[i] - 0.3:
                gi[e], dl[e] = g, dd
                e += 1
        off[i + 1] = e
    E = off[k]
    A, u = np.empty((E, 2)), np.empty((E, 2))
    d, lo, hi = np.empty(E), np.empty(E), np.empty(E)
    for i in range(k):
        lax, lay, lbx, lby = s * ra[i, 0], s * ra[i, 1], s * rb[i, 0], s * rb[i, 1]
        for e in range(off[i], off[i + 1]):
            g = gi[e]
            A[e, 0], A[e, 1] = n_g[g, 0], n_g[g, 1]
            dot = n_g[g, 0] * n_l[i, 0] + n_g[g, 1] * n_l[i, 1]
            sgn = 1.0 if dot > 0 else (-1.0 if dot < 0 else 0.0)
            d[e] = c_g[g] - s * sgn * c_l[i]
            # where along the map segment the translation may fall: u . T in (lo, hi), the
            # scan segment then overlapping it with a gap of at most ``slack``
            dx, dy = gb[g, 0] - ga[g, 0], gb[g, 1] - ga[g, 1]
            L = np.sqrt(dx * dx + dy * dy)
            ux, uy = dx / max(L, 1e-9), dy / max(L, 1e-9)
            u[e, 0], u[e, 1] = ux, uy
            t1 = (lax - ga[g, 0]) * ux + (lay - ga[g, 1]) * uy
            t2 = (lbx - ga[g, 0]) * ux + (lby - ga[g, 1]) * uy
            lo[e] = -slack - max(t1, t2)
            hi[e] = L + slack - min(t1, t2)
    cap = 1024
    T, D = np.empty((cap, 2)), np.empty(cap)
    n = 0
    for i1 in range(k):
        for i2 in range(i1 + 1, k):
            ang = abs((2.0 * (phi_l[i1] - phi_l[i2]) + np.pi) % (2.0 * np.pi) - np.pi) / 2
            a0, a1, b0, b1 = off[i1], off[i1 + 1], off[i2], off[i2 + 1]
            if ang < min_ang or a0 == a1 or b0 == b1:
                continue
            while True:
                m = _pair_kernel(A[a0:a1], A[b0:b1], d[a0:a1], d[b0:b1], u[a0:a1],
                                 lo[a0:a1], hi[a0:a1], u[b0:b1], lo[b0:b1], hi[b0:b1],
                                 dl[a0:a1], dl[b0:b1], len_l[i1], len_l[i2], T[n:], D[n:])
                if n + m <= cap:
                    n += m
                    break
                cap = max(2 * cap, n + m)    # out of room: grow, solve the pair again
                T2, D2 = np.empty((cap, 2)), np.empty(cap)
                T2[:n], D2[:n] = T[:n], D[:n]
                T, D = T2, D2
    nf = 0
    for i1 in range(min(n_end, k)):
        nf += 4 * (off[i1 + 1] - off[i1])
    Tf, Df = np.empty((nf, 2)), np.empty(nf)
    f = 0
    for i1 in range(min(n_end, k)):
        for end_g in range(2):
            for end_l in range(2):
                px, py = (ra[i1, 0], ra[i1, 1]) if end_l == 0 else (rb[i1, 0], rb[i1, 1])
                for e in range(off[i1], off[i1 + 1]):
                    g = gi[e]
                    vx, vy = -n_g[g, 1], n_g[g, 0]          # along the map segment
                    q = ga[g] if end_g == 0 else gb[g]
                    eg = q[0] * vx + q[1] * vy
                    el = s * (vx * px + vy * py)
                    Tf[f, 0] = d[e] * n_g[g, 0] + (eg - el) * vx
                    Tf[f, 1] = d[e] * n_g[g, 1] + (eg - el) * vy
                    Df[f] = dl[e]
                    f += 1
    return T[:n], D[:n], Tf, Df


def _score(field: DistanceField, pts: np.ndarray, T: np.ndarray, th: np.ndarray,
           inlier: float, soft: bool = False) -> np.ndarray:
    """Fraction of points within ``inlier`` of the map for each pose hypothesis (T, th);
    with ``soft``, each point counts 1 - (d / inlier)^2 instead of 1 (ties between symmetric
    places go to the pose that fits tighter)."""
    if not len(pts):
        return np.zeros(len(T))
    out = np.empty(len(T))
    # a plain count (off the grid no inlier) reads the packed inlier bits
    bits = (field.inlier_bits(inlier) if not soft and field.far >= inlier
            else np.zeros((0, 1), np.uint8))
    _score_kernel(field.dist, bits, float(field.lo[0]), float(field.lo[1]), float(field.res),
                  float(field.far), np.ascontiguousarray(pts, dtype=float),
                  np.ascontiguousarray(T, dtype=float), np.ascontiguousarray(th, dtype=float),
                  float(inlier), bool(soft), out)
    return out


@kernel
def _cell_of(c, s, x, y, tx, ty, lo0, lo1, res):
    """The grid cell (column, row; floats, maybe off the grid) of scan point (x, y) under
    the pose of rotation (cos c, sin s) and translation (tx, ty): the nearest cell, as
    :meth:`DistanceField.lookup_xy` takes it."""
    return (np.floor((c * x - s * y + tx - lo0) / res + 0.5),
            np.floor((s * x + c * y + ty - lo1) / res + 0.5))


@kernel
def _score_kernel(dist, bits, lo0, lo1, res, far, pts, T, th, inlier, soft, out):
    """:func:`_score` per hypothesis, the points moved, looked up (:meth:`DistanceField.
    lookup_xy`, nearest cell, off-grid far) and counted in one pass: no (hypotheses x points)
    temporaries, which on a large map's many candidates cost more than the lookups.  With
    ``bits`` non-empty (:meth:`DistanceField.inlier_bits` of ``inlier``; a plain count, far
    beyond the inlier distance), the packed bits are read instead of the distances: the
    same cells, the same answer, a 32nd of the bytes."""
    ny, nx = dist.shape
    n = pts.shape[0]
    packed = bits.shape[0] > 0
    for h in range(T.shape[0]):
        c, s = np.cos(th[h]), np.sin(th[h])
        acc = 0.0
        for j in range(n):
            qx, qy = _cell_of(c, s, pts[j, 0], pts[j, 1], T[h, 0], T[h, 1], lo0, lo1, res)
            if not (qx >= 0 and qy >= 0 and qx < nx and qy < ny):
                d = far
            elif packed:
                ix = int(qx)
                acc += (bits[int(qy), ix >> 3] >> (ix & 7)) & 1
                continue
            else:
                d = dist[int(qy), int(qx)]
            if soft:
                acc += max(0.0, 1.0 - (d / inlier) ** 2)
            elif d < inlier:
                acc += 1.0
        out[h] = acc / n


def inlier_fraction(points: np.ndarray, pose, a: np.ndarray, b: np.ndarray,
                    inlier: float) -> float:
    """Fraction of laser-frame ``points`` within ``inlier`` of segments a-b once moved by
    ``pose`` (direct point-to-segment distances: for small maps, no distance field)."""
    if not len(points) or not len(a):
        return 0.0
    c, s = np.cos(pose[2]), np.sin(pose[2])
    g = points @ np.array([[c, s], [-s, c]]) + np.asarray(pose[:2])
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
