"""Translation hypotheses from the scan's points (relocalisation's step 3b): the points
correlated with the map's near-wall mask at every position of a coarse grid, for each rotation
hypothesis (:func:`correlative_sweep`), for all rotations when the lines name none
(:func:`fallback_sweep`), coarse to fine on a big building's map (:func:`coarse_to_fine`,
:func:`branch_and_bound`), in the free-space band a scan's ranges allow (:func:`reach_bound`)."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .distance_field import DistanceField
from .jit import kernel
from .odometry import wrap_angle as _wrap
from .pose_verify import spread_order

if TYPE_CHECKING:
    from .relocalize import RelocParams


def correlative_sweep(field: DistanceField, pts: np.ndarray, rots: np.ndarray, P: RelocParams,
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
            sc, iy, ix = coarse_to_fine(field, stack, thr, tight, step, P.sweep_coarse,
                                        oy, ox, (y0, x0, h, w),
                                        None if reach is None else band, k)
            cand_s.append(sc)
            cand_y.append(iy + y0)
            cand_x.append(ix + x0)
            continue
        acc = window_counts(stack, oy, ox, step, (y0, x0, h, w))
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
            sc, iy, ix = top_cells(acc, k, y0, x0)
        cand_s.append(sc)
        cand_y.append(iy + y0)
        cand_x.append(ix + x0)
    sc, gy, gx = (np.concatenate(v, 1) for v in (cand_s, cand_y, cand_x))
    if sc.shape[1] > k:              # the best k per rotation over all windows
        top = np.argpartition(-sc, k - 1, axis=1)[:, :k]
        gy, gx = np.take_along_axis(gy, top, 1), np.take_along_axis(gx, top, 1)
    T = field.lo + np.stack([gx.ravel(), gy.ravel()], -1) * step * res
    return T, np.repeat(np.asarray(rots, float), gy.shape[1])


def fallback_sweep(field: DistanceField, pts: np.ndarray, P: RelocParams,
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
    return correlative_sweep(field, pts, rots, Q, reach, stats, tight=P.coarse_dist, near=near,
                             turn_slack=np.deg2rad(P.fallback_rot_deg))


def reach_bound(points: np.ndarray, P: RelocParams, res: float) -> float:
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


def _band_windows(field: DistanceField, step: int, reach: float | None,
                  max_windows: int = 8) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """The sweep's positions: (band, windows).  ``band`` (grid shape) marks the grid positions
    within ``reach`` of a mapped wall -- the only places a scan with enough points on walls
    can have been taken from (see :func:`reach_bound`); empty space farther out is never read.
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


# fixed pseudo-random tie-breakers for the sweep's cell selection (see top_cells)
_TIE_NOISE = np.random.default_rng(20261123).integers(0, 256, 1 << 16).astype(np.uint16)


def tie_noise(r: np.ndarray, gy: np.ndarray, gx: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random byte per (rotation, grid row, grid column)."""
    return _TIE_NOISE[(r * 40503 + gy * 2654 + gx * 97) & 0xFFFF]


def top_cells(acc: np.ndarray, k: int, y0: int = 0,
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
        key |= tie_noise(ri, 0, x0 + np.arange(w)[None, :])
        cols = np.argsort(key, axis=1, kind="stable")[:, w - k:]
        sub = acc[ri, :, cols]                                           # (R, k, h)
    else:
        cols = np.broadcast_to(np.arange(w), (R, w))
        sub = acc.transpose(0, 2, 1)
    kc = cols.shape[1]
    sub = sub.reshape(R, -1)
    gy = np.tile(np.arange(h) + y0, kc)[None, :]
    gx = np.repeat(cols + x0, h, axis=1)
    key = (sub.astype(np.uint16) << 8) | tie_noise(ri, gy, gx)
    kk = min(k, sub.shape[1])
    top = np.argsort(key, axis=1, kind="stable")[:, sub.shape[1] - kk:]
    c_i, iy = np.divmod(top, h)
    return sub[ri, top].astype(np.int32), iy, cols[ri, c_i]


def window_counts(stack: np.ndarray, oy: np.ndarray, ox: np.ndarray, step: int,
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


def coarse_to_fine(field: DistanceField, stack: np.ndarray, thr: float,
                   tight: float | None, step: int, f: int, oy: np.ndarray, ox: np.ndarray,
                   window: tuple[int, int, int, int], band: np.ndarray | None,
                   k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`correlative_sweep`'s k best positions per rotation in one window (row y0,
    column x0, h x w positions of the grid) by their count, ties by each position's fixed byte
    (:func:`tie_noise`; :func:`top_cells` finds the same counts, its ties settled per
    column), without counting every position: a coarse cell of f x f positions is
    first counted on the max-pooled mask (:meth:`DistanceField.phase_stack` with
    ``dilate``), which bounds each of its positions' counts; cells are then counted position
    by position, best bound first, until no cell left could hold a count that reaches the
    k-th best found (branch and bound, one level: :func:`branch_and_bound`).  ``oy``, ``ox``
    (R, N): the points' pixel offsets under each rotation (pad included); ``stack``: the
    fine phase stack; ``band`` (the grid's shape): positions off it count zero.  Returns
    counts, rows and columns (R, k), the positions relative to the window."""
    y0, x0, h, w = window
    R = len(oy)
    S = f * step
    _, stack_c = field.phase_stack(thr, S, tight, dilate=(f - 1) * step)
    hc, wc = -(-h // f), -(-w // f)
    # the coarse grid starts at the window's corner: each point's pixel offset from there
    bound = window_counts(stack_c, oy + y0 * step, ox + x0 * step, S, (0, 0, hc, wc))
    ok = (np.ones((h, w), bool) if band is None
          else np.ascontiguousarray(band[y0: y0 + h, x0: x0 + w]))
    if band is not None:
        bw = np.zeros((hc * f, wc * f), bool)
        bw[:h, :w] = ok
        bound *= bw.reshape(hc, f, wc, f).any(axis=(1, 3))
    out = np.zeros((3, R, k), np.int64)
    sp = spread_order(oy.shape[1])      # the order the points are read in: counts do not change
    oy, ox = oy[:, sp], ox[:, sp]
    branch_and_bound(bound.astype(np.int32), stack, (oy % step) * step + ox % step,
                     oy // step + y0, ox // step + x0, ok, f, k, _TIE_NOISE,
                     y0, x0, 1 if tight is None else 17, out)
    return out[0].astype(np.int32), out[1], out[2]


@kernel
def branch_and_bound(bound, stack, phase, qy, qx, ok, f, k, noise, y0, x0, most, out):
    """Per rotation r: the coarse cells bucketed by their bound (``bound[r]``), counted
    position by position from the highest bound down (:func:`coarse_to_fine`), while the
    bound still reaches the k-th best count so far; then the k best positions by count and
    tie byte (``noise``, as :func:`tie_noise`) into ``out`` (counts, rows, columns: (3, R,
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
