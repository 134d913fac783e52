"""The map's distance field for relocalisation: the distance to the nearest wall on a grid
(cv2), the nearest segment of every cell, and the packed and phase-split near-wall masks
that the scores (:mod:`.pose_verify`) and the sweeps (:mod:`.sweep`) read."""

from __future__ import annotations

import cv2
import numpy as np

from .linemap import LineMap


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

    @property
    def segments(self) -> np.ndarray:
        """Per map segment, the row the nearest-segment grid (:attr:`seg_id`) points at:
        start point (x, y), unit direction (ux, uy) and length, (n, 5); built with the grid."""
        self.seg_id  # noqa: B018  (builds the grid and this table)
        return self._tab

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
