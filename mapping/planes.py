"""Plane detection in point clouds: sequential RANSAC and the randomised 3D Hough transform.

Both detectors end the same way (``_finish_plane``): inliers of a candidate, a least-squares
refit (iterated), a connected-region check in the plane so that two coplanar but distant
patches do not become one plane, and a ``DetectedPlane`` with its Hesse form, its point in the
3D Hough space (theta, phi, rho) of DESIGN.md, its CGA plane, extent and corners (seed 000
§IV-C and §VI; PRL §3.2, eqs. 10-12: a plane n.x = rho, a point X on it when X.P = 0).

The Hough accumulator is a *ball* (Borrmann et al., 3D Research 2011): rings of constant
theta, each cut into a number of phi cells proportional to sin(theta) so that every cell
covers about the same area of the sphere of normals, and one such sphere per rho shell.
Votes are randomised (Xu's RHT): each vote is the plane through three nearby points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from cgamap.cga import Multivector, hesse_to_hough3d, plane_from_hesse

# ---- the plane record ----------------------------------------------------------------------


@dataclass
class DetectedPlane:
    """A plane n.x = rho (rho >= 0) with its support."""

    normal: np.ndarray
    rho: float
    inliers: int
    rms: float
    centroid: np.ndarray
    extent: np.ndarray  # (k, 3) convex hull of the inliers, in the plane, counter-clockwise
    corners: np.ndarray  # (4, 3) minimum-area rectangle around the inliers (the drawn quad)
    area: float  # area of the extent polygon, m^2
    inlier_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp),
                                     repr=False)

    @property
    def hough(self) -> tuple[float, float, float]:
        """(theta, phi, rho) with n = (sin t cos p, sin t sin p, cos t) (DESIGN.md)."""
        t, p, r = hesse_to_hough3d(self.normal, self.rho)
        return float(t), float(p), float(r)

    def cga(self) -> Multivector:
        """The OPNS CGA plane (dual of n + rho einf)."""
        return plane_from_hesse(self.normal, self.rho)

    def to_dict(self) -> dict:
        t, p, r = self.hough
        return {
            "normal": [round(float(v), 6) for v in self.normal],
            "rho": round(float(self.rho), 6),
            "inliers": int(self.inliers),
            "rms": round(float(self.rms), 6),
            "hough": {"theta": round(t, 6), "phi": round(p, 6), "rho": round(r, 6)},
            "centroid": [round(float(v), 5) for v in self.centroid],
            "area": round(float(self.area), 5),
            "corners": np.round(self.corners, 5).tolist(),
            "extent": np.round(self.extent, 5).tolist(),
            "cga": np.round(self.cga().v, 9).tolist(),  # OPNS plane, 32 blade coefficients
        }


# ---- geometry helpers ----------------------------------------------------------------------


def canonical(normal: np.ndarray, rho: float) -> tuple[np.ndarray, float]:
    """Unit normal and rho >= 0 (flip both when rho < 0)."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    return (-n, -float(rho)) if rho < 0 else (n, float(rho))


# numpy reduces a tall (n, 2|3) array along axis 0 slowly; column by column is ~20x faster


def _colmin(a: np.ndarray) -> np.ndarray:
    return np.array([a[:, j].min() for j in range(a.shape[1])])


def _colmax(a: np.ndarray) -> np.ndarray:
    return np.array([a[:, j].max() for j in range(a.shape[1])])


def _colmean(a: np.ndarray) -> np.ndarray:
    return np.ones(len(a)) @ a / len(a)


def fit_plane_lsq(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Total least squares plane through points: (unit normal, rho, rms distance)."""
    c = _colmean(points)
    d = points - c
    w, v = np.linalg.eigh(d.T @ d)
    n = v[:, 0]
    n, rho = canonical(n, float(n @ c))
    return n, rho, float(np.sqrt(max(w[0], 0.0) / len(points)))


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane axes (u, v) with u horizontal where possible, so extents read naturally."""
    n = np.asarray(normal, dtype=float)
    u = np.cross([0.0, 0.0, 1.0], n)
    if np.linalg.norm(u) < 1e-6:
        u = np.cross(n, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def to_plane_uv(points: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(n, 2) coordinates of points in the plane's (u, v) basis (:func:`plane_basis`)."""
    u, v = plane_basis(normal)
    return np.stack([points @ u, points @ v], axis=1)


def lift_uv(uv: np.ndarray, normal: np.ndarray, rho: float) -> np.ndarray:
    """(n, 3) points of the plane (normal, rho) at in-plane coordinates uv."""
    u, v = plane_basis(normal)
    return normal * rho + uv[:, :1] * u + uv[:, 1:2] * v


def hull_2d(uv: np.ndarray) -> np.ndarray:
    return cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(float)


def min_rect_2d(uv: np.ndarray) -> np.ndarray:
    """(4, 2) corners of the minimum-area rectangle around uv."""
    return cv2.boxPoints(cv2.minAreaRect(uv.astype(np.float32))).astype(float)


def _extent(points: np.ndarray, n: np.ndarray, rho: float
            ) -> tuple[np.ndarray, np.ndarray, float]:
    """Convex hull polygon, minimum-area rectangle corners (both in 3D) and hull area."""
    hull = hull_2d(to_plane_uv(points, n))
    box = min_rect_2d(hull)
    # ensure counter-clockwise about n
    if len(hull) >= 3:
        area2 = np.sum(hull[:, 0] * np.roll(hull[:, 1], -1) - np.roll(hull[:, 0], -1) * hull[:, 1])
        if area2 < 0:
            hull = hull[::-1]
    else:
        area2 = 0.0
    return lift_uv(hull, n, rho), lift_uv(box, n, rho), abs(float(area2)) / 2


def largest_region(points: np.ndarray, n: np.ndarray, cell: float) -> np.ndarray:
    """Mask of the points in the largest 8-connected region of occupied cells in the plane.

    Two coplanar patches more than about two cells apart fall into different regions.
    """
    u, v = plane_basis(n)
    uv = np.stack([points @ u, points @ v], axis=1)
    lo = _colmin(uv)
    span = _colmax(uv) - lo
    cell = max(cell, float(np.sqrt(span[0] * span[1] / 4e6)) if span.min() > 0 else cell)
    ij = np.floor((uv - lo) / cell).astype(np.int64)
    shape = _colmax(ij) + 1
    grid = np.zeros((int(shape[0]), int(shape[1])), dtype=np.uint8)
    grid[ij[:, 0], ij[:, 1]] = 1
    count, labels = cv2.connectedComponents(grid, connectivity=8)
    if count <= 2:
        return np.ones(len(points), dtype=bool)
    lab = labels[ij[:, 0], ij[:, 1]]
    sizes = np.bincount(lab, minlength=count)
    sizes[0] = 0
    return lab == int(np.argmax(sizes))


# ---- sampling ------------------------------------------------------------------------------


class _VoxelIndex:
    """Points sorted by voxel, for drawing index triples from one neighbourhood.

    A triple is a random seed point and two partners from the seed's voxel run, so triples
    come from one neighbourhood and hit one plane far more often than global triples.
    """

    def __init__(self, points: np.ndarray, radius: float):
        self.radius = float(radius)
        key = np.floor(points / radius).astype(np.int64)
        key -= _colmin(key)
        dims = _colmax(key) + 1
        flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
        self.order = np.argsort(flat)
        sflat = flat[self.order]
        # run start and end of every point's voxel, by the point's own index
        new_run = np.empty(len(sflat), dtype=bool)
        new_run[:1] = True
        np.not_equal(sflat[1:], sflat[:-1], out=new_run[1:])
        run_start = np.flatnonzero(new_run)
        run_end = np.append(run_start[1:], len(sflat))
        run = np.cumsum(new_run) - 1
        self.start = np.empty(len(sflat), dtype=np.int64)
        self.end = np.empty(len(sflat), dtype=np.int64)
        self.start[self.order] = run_start[run]
        self.end[self.order] = run_end[run]

    @property
    def min_area2(self) -> float:
        """Smallest |cross product| of a usable triple: slivers give noisy normals (and on
        depth-quantised clouds, the normal of one quantisation step)."""
        return (0.15 * self.radius) ** 2

    def triples(self, k: int, rng: np.random.Generator, active: np.ndarray | None = None,
                pool: np.ndarray | None = None) -> np.ndarray:
        """k triples; with ``pool`` (indices of active points) and ``active`` (their mask) the
        seed comes from the pool and triples with an inactive partner are dropped."""
        seed = rng.integers(0, len(self.order), size=k) if pool is None else \
            pool[rng.integers(0, len(pool), size=k)]
        a = self.start[seed]
        span = self.end[seed] - a
        j1 = self.order[a + (rng.random(k) * span).astype(np.int64)]
        j2 = self.order[a + (rng.random(k) * span).astype(np.int64)]
        tri = np.stack([seed, j1, j2], axis=1)
        if active is not None:
            tri = tri[active[j1] & active[j2]]
        return tri


def _local_normals(points: np.ndarray, voxels: _VoxelIndex, idx: np.ndarray,
                   rng: np.random.Generator, mates: int = 12
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (len(idx), 3) by PCA of random voxel-mates of each point, and a mask of
    the points that have one (at least 5 mates; the others are not judged)."""
    a = voxels.start[idx]
    span = voxels.end[idx] - a
    j = voxels.order[a[:, None] + (rng.random((len(idx), mates)) * span[:, None]
                                   ).astype(np.int64)]
    nb = points[j]
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("kmi,kmj->kij", nb, nb)
    _, vec = np.linalg.eigh(cov)
    return vec[:, :, 0], span >= 5


def _planes_from_triples(points: np.ndarray, tri: np.ndarray, min_area2: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (m, 3) and rho (m,) >= 0 of non-degenerate triples."""
    p0, p1, p2 = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    nrm = np.cross(p1 - p0, p2 - p0)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > min_area2
    nrm = nrm[ok] / ln[ok, None]
    rho = np.einsum("ij,ij->i", nrm, p0[ok])
    sign = np.where(rho < 0, -1.0, 1.0)
    return nrm * sign[:, None], rho * sign


# ---- the common finishing step -------------------------------------------------------------


@dataclass
class PlaneParams:
    threshold: float = 0.02  # inlier distance, m
    range_noise: float = 0.0  # extra threshold per squared range (m^-1): stereo/RGB-D depth
    min_inliers: int = 500
    max_planes: int = 10
    region_cell: float = 0.1  # connected-region grid cell, m (gaps of ~2 cells split)
    refit_iterations: int = 3  # least-squares refits on a subsample of the candidate's inliers
    final_passes: int = 2  # inliers -> largest region -> refit, over every point
    neighbourhood: float = 0.0  # voxel for local triples; 0: auto from the cloud's size
    max_points: int = 100_000  # detect on a regular decimation, then refit on every point
    # RANSAC only: a sample point supports a hypothesis only if its local normal (PCA of
    # neighbours) is within this angle (radians); 0 turns the check off. It keeps planes
    # through the edges of many surfaces (a stair's nosings) from winning.
    normal_tol: float = 0.0


# A depth camera's error grows with range squared (structured light / stereo: depth from a
# disparity quantised to a fraction of a pixel). A Kinect at 5 m reports depth in ~7 cm steps:
# with a fixed 2 cm band, one wall comes out as a stack of fake planes, one per step.
RGBD_RANGE_NOISE = 0.003  # m^-1: inlier band grows by 0.003 * range^2 (7.5 cm at 5 m)


def depth_is_quantised(points: np.ndarray, max_levels: float = 0.01) -> bool:
    """Whether the clouds' z (a camera's depth axis) takes few distinct values: a depth
    camera's disparity steps (office1.pcd: 125 values among 254,456 points)."""
    z = points.reshape(-1, 3)[:, 2]
    z = z[np.isfinite(z)]
    if len(z) < 1000:
        return False
    return len(np.unique(z)) < max_levels * len(z)


def range_noise_for(cloud: np.ndarray) -> float:
    """The ``PlaneParams.range_noise`` a cloud needs: RGBD_RANGE_NOISE for an organised
    (H, W, 3) cloud or one whose depth is visibly quantised (both mean a depth camera in its
    own frame), else 0 (a laser or merged cloud: noise independent of range)."""
    cloud = np.asarray(cloud)
    if cloud.ndim == 3 or depth_is_quantised(cloud):
        return RGBD_RANGE_NOISE
    return 0.0


class _Cloud:
    """Finite points, their inlier thresholds, and which are still unclaimed."""

    def __init__(self, pts: np.ndarray, prm: PlaneParams):
        self.pts = pts
        if prm.range_noise > 0:
            self.thr = prm.threshold + prm.range_noise * np.einsum("ij,ij->i", pts, pts)
        else:
            self.thr = np.full(len(pts), prm.threshold)
        self.active = np.ones(len(pts), dtype=bool)
        self.remaining = np.arange(len(pts))
        self.cols = np.ascontiguousarray(pts.T)  # x, y, z rows for distances without BLAS

    def distances(self, n: np.ndarray, rho: float) -> np.ndarray:
        """|n.x - rho| for every point. Written out per coordinate: a threaded BLAS gemv on
        a tall (n, 3) array burns ten times the CPU (and more wall time when cores are busy)."""
        c = self.cols
        d = c[0] * n[0]
        d += c[1] * n[1]
        d += c[2] * n[2]
        d -= rho
        return np.abs(d, out=d)

    def claim(self, idx: np.ndarray) -> None:
        self.active[idx] = False
        self.remaining = np.flatnonzero(self.active)


def _finish_plane(cl: _Cloud, n: np.ndarray, rho: float, prm: PlaneParams,
                  min_inliers: int, probe_refit: bool = True, describe: bool = True
                  ) -> tuple[DetectedPlane | None, np.ndarray]:
    """Inliers of (n, rho) among the unclaimed points, refit, largest connected region,
    refit again. Returns the plane (None when too small) and the indices it claims."""
    pts = cl.pts
    if probe_refit:
        # refine on a subsample first (the fit converges long before it sees every point)
        idx = cl.remaining
        probe = idx if len(idx) <= 30000 else idx[:: len(idx) // 30000 + 1]
        probe_pts, probe_thr = pts[probe], cl.thr[probe]
        for _ in range(prm.refit_iterations):
            near = probe_pts[np.abs(probe_pts @ n - rho) < probe_thr]
            if len(near) < 3:
                return None, idx[:0]
            n, rho, _ = fit_plane_lsq(near)
    # passes over every point (contiguous, cheaper than gathering the unclaimed ones); the
    # second settles the inlier set of the refit plane
    for _ in range(prm.final_passes):
        members = np.flatnonzero((cl.distances(n, rho) < cl.thr) & cl.active)
        if len(members) < min_inliers:
            return None, members
        P = pts[members]
        keep = largest_region(P, n, prm.region_cell)
        members, P = members[keep], P[keep]
        if len(members) < min_inliers:
            return None, members
        n_old, rho_old = n, rho
        n, rho, rms = fit_plane_lsq(P)
        # converged: another pass would select the same inliers
        if abs(rho - rho_old) < 1e-3 * prm.threshold and float(n @ n_old) > 1 - 1e-9:
            break
    if describe:
        proj = P - np.outer(P @ n - rho, n)  # measure the extent in the plane
        extent, corners, area = _extent(proj, n, rho)
    else:  # a decimated pass: the full-resolution refit describes the plane
        extent, corners, area = np.zeros((0, 3)), np.zeros((0, 3)), 0.0
    plane = DetectedPlane(normal=n, rho=rho, inliers=len(members), rms=rms,
                          centroid=_colmean(P), extent=extent, corners=corners, area=area,
                          inlier_index=members)
    return plane, members


def _as_points(cloud: np.ndarray) -> np.ndarray:
    pts = np.asarray(cloud, dtype=float).reshape(-1, 3)
    s = pts[:, 0] + pts[:, 1]
    s += pts[:, 2]  # nan and inf survive the sum
    return pts[np.isfinite(s)]


def _auto_neighbourhood(pts: np.ndarray) -> float:
    """A voxel of about 1/8 of the cloud's middle extent (robust spread of a subsample)."""
    sub = pts[:: max(1, len(pts) // 5000)]
    span = np.percentile(sub, 95, axis=0) - np.percentile(sub, 5, axis=0)
    return float(max(np.sort(span)[1:].mean() / 8.0, 0.05))


def _sequential(cloud: np.ndarray, prm: PlaneParams, propose) -> list[DetectedPlane]:
    """The shared loop: ``propose(cl, voxels, min_count)`` gives a candidate (n, rho) or
    None; each is finished on the decimated cloud, then every found plane is refit on all
    points."""
    pts = _as_points(cloud)
    step = max(1, -(-len(pts) // prm.max_points))
    work = pts[::step]
    min_work = max(3, prm.min_inliers // step)
    if len(work) < min_work:
        return []
    cl = _Cloud(work, prm)
    voxels = _VoxelIndex(work, prm.neighbourhood or _auto_neighbourhood(work))
    found: list[DetectedPlane] = []
    misses = 0
    while len(found) < prm.max_planes and len(cl.remaining) >= min_work and misses < 3:
        cand = propose(cl, voxels, min_work)
        if cand is None:
            break
        plane, claimed = _finish_plane(cl, cand[0], cand[1], prm, min_work,
                                       describe=step == 1)
        if len(claimed) == 0:
            break
        cl.claim(claimed)  # a rejected small piece leaves too, so the next round looks elsewhere
        if plane is None:
            misses += 1
            continue
        misses = 0
        found.append(plane)
    if step == 1:
        return sorted(found, key=lambda p: -p.inliers)
    full = _Cloud(pts, prm)
    planes = []
    for p in sorted(found, key=lambda p: -p.inliers):
        plane, claimed = _finish_plane(full, p.normal, p.rho, prm, prm.min_inliers,
                                       probe_refit=False)
        if plane is not None:
            planes.append(plane)
            full.claim(claimed)
    return sorted(planes, key=lambda p: -p.inliers)


# ---- sequential RANSAC ---------------------------------------------------------------------


def ransac_planes(cloud: np.ndarray, params: PlaneParams | None = None, *,
                  batch: int = 256, score_sample: int = 2000, max_hypotheses: int = 4096,
                  confidence: float = 0.999, seed: int | None = 0) -> list[DetectedPlane]:
    """Sequential RANSAC: hypotheses from local triples, scored ``batch`` at a time by one
    matrix product on a random subsample, the best one refit on all unclaimed points.

    ``inlier_index`` of each plane indexes the finite points of ``cloud`` in their order.
    Returns planes largest first.
    """
    prm = params or PlaneParams()
    rng = np.random.default_rng(seed)
    fine: list[_VoxelIndex] = []

    def propose(cl: _Cloud, voxels: _VoxelIndex, min_count: int):
        rem = cl.remaining
        m = min(score_sample, len(rem))
        pick = rem[rng.choice(len(rem), size=m, replace=False)]
        sample32 = cl.pts[pick].astype(np.float32)
        thr32 = cl.thr[pick].astype(np.float32)[:, None]
        if prm.normal_tol > 0:
            if not fine:
                fine.append(_VoxelIndex(cl.pts, voxels.radius / 3))
            local_n, known = _local_normals(cl.pts, fine[0], pick, rng)
            local_n = local_n.astype(np.float32)
            unknown = ~known[:, None]
            cos_tol = np.float32(np.cos(prm.normal_tol))
        best, best_score, tried = None, -1, 0
        while tried < max_hypotheses:
            tri = voxels.triples(batch, rng, cl.active, rem)
            normals, rhos = _planes_from_triples(cl.pts, tri, voxels.min_area2)
            tried += batch
            if len(normals) == 0:
                continue
            # one (m, batch) product scores the whole batch (einsum: a threaded BLAS call
            # costs ten times the CPU for this thin product)
            dist = np.einsum("ij,kj->ik", sample32, normals.astype(np.float32))
            dist -= rhos.astype(np.float32)
            np.abs(dist, out=dist)
            support = dist < thr32
            if prm.normal_tol > 0:
                agree = np.abs(np.einsum("ij,kj->ik", local_n, normals.astype(np.float32)))
                support &= (agree >= cos_tol) | unknown
            counts = support.sum(axis=0, dtype=np.int32)
            k = int(np.argmax(counts))
            if counts[k] > best_score:
                best, best_score = (normals[k], float(rhos[k])), int(counts[k])
            # Local triples land on a plane of inlier ratio w with probability about w/2
            # (seed on it, partners from its voxel), not w^3 as global triples would.
            w = max(best_score / m, min_count / len(rem))
            need = np.log(1 - confidence) / np.log(max(1 - w / 2, 1e-12))
            if tried >= min(need, max_hypotheses):
                break
        # the best hypothesis cannot reach min_inliers on the remaining points: done
        if best is None or best_score / m * len(rem) < 0.5 * min_count:
            return None
        return best

    return _sequential(cloud, prm, propose)


# ---- the 3D Hough transform with a ball accumulator ----------------------------------------


class BallAccumulator:
    """Cells of (about) equal area on the sphere of normals, one sphere per rho shell.

    Ring i covers theta in [i dt, (i+1) dt); it has max(1, round(2 pi sin(theta_i) / dt))
    phi cells, theta_i the ring's centre. Cell ids are laid out ring after ring, then by shell.
    Counters are kept sparse (the votes' cell ids), so a far outlier that stretches the rho
    range costs no memory.
    """

    def __init__(self, theta_step: float, rho_step: float, rho_max: float):
        self.theta_step = float(theta_step)
        self.rho_step = float(rho_step)
        self.n_rings = int(np.ceil(np.pi / theta_step))
        centres = (np.arange(self.n_rings) + 0.5) * np.pi / self.n_rings
        self.ring_theta = centres
        self.ring_cells = np.maximum(1, np.round(2 * np.pi * np.sin(centres) / theta_step)
                                     ).astype(np.int64)
        self.ring_start = np.concatenate([[0], np.cumsum(self.ring_cells)[:-1]])
        self.cells_per_shell = int(self.ring_cells.sum())
        self.n_shells = int(np.ceil(rho_max / rho_step)) + 1
        self._votes: list[np.ndarray] = []

    def cell_of(self, theta: np.ndarray, phi: np.ndarray, rho: np.ndarray) -> np.ndarray:
        ring = np.minimum((theta / np.pi * self.n_rings).astype(np.int64), self.n_rings - 1)
        nphi = self.ring_cells[ring]
        j = np.floor((phi + np.pi) / (2 * np.pi) * nphi).astype(np.int64) % nphi
        shell = np.minimum((rho / self.rho_step).astype(np.int64), self.n_shells - 1)
        return shell * self.cells_per_shell + self.ring_start[ring] + j

    def cell_centre(self, cell: int) -> tuple[float, float, float]:
        shell, c = divmod(int(cell), self.cells_per_shell)
        ring = int(np.searchsorted(self.ring_start, c, side="right") - 1)
        j = c - self.ring_start[ring]
        phi = -np.pi + (j + 0.5) * 2 * np.pi / self.ring_cells[ring]
        return float(self.ring_theta[ring]), float(phi), (shell + 0.5) * self.rho_step

    def vote(self, cells: np.ndarray) -> None:
        self._votes.append(np.asarray(cells, dtype=np.int64))

    def reset(self) -> None:
        self._votes = []

    def counts(self) -> tuple[np.ndarray, np.ndarray]:
        """(cell ids, vote counts) of every cell with a vote."""
        if not self._votes:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.unique(np.concatenate(self._votes), return_counts=True)


def hough_planes(cloud: np.ndarray, params: PlaneParams | None = None, *,
                 theta_step: float = np.radians(3.0), rho_step: float | None = None,
                 votes_per_round: int = 6000, max_rounds: int = 4, min_votes: int = 20,
                 peaks: int = 1, score_sample: int = 3000,
                 seed: int | None = 0) -> list[DetectedPlane]:
    """Randomised 3D Hough transform on a ball accumulator, then peak refit.

    Each detection: planes through local point triples vote, ``votes_per_round`` at a time
    (more rounds while the fullest cell has fewer than ``min_votes``); the ``peaks`` fullest
    cells give candidates (the median of the votes in the cell, finer than the cell centre);
    with more than one, the candidate with the most points within the threshold on a sample
    wins. The winner is refit on its inliers (``_finish_plane``), its points leave the
    cloud, and the accumulator is cleared (Borrmann et al.'s RHT resets after each plane).
    On office1.pcd the fullest cell alone (peaks=1) matched the reference fit better than
    the best-scored of several: the sample score cannot tell apart close parallel bands.
    """
    prm = params or PlaneParams()
    rng = np.random.default_rng(seed)
    rho_step = rho_step or max(2.5 * prm.threshold, 0.02)
    acc: list[BallAccumulator] = []

    def propose(cl: _Cloud, voxels: _VoxelIndex, min_count: int):
        if not acc:
            rho_max = float(np.sqrt(np.einsum("ij,ij->i", cl.pts, cl.pts).max()))
            acc.append(BallAccumulator(theta_step, rho_step, rho_max))
        ball = acc[0]
        ball.reset()
        all_n, all_r, all_c = [], [], []
        ids, votes = ball.counts()
        for _ in range(max_rounds):
            tri = voxels.triples(votes_per_round, rng, cl.active, cl.remaining)
            normals, rhos = _planes_from_triples(cl.pts, tri, voxels.min_area2)
            theta, phi, rho = hesse_to_hough3d(normals, rhos)
            cells = ball.cell_of(theta, phi, rho)
            ball.vote(cells)
            all_n.append(normals)
            all_r.append(rhos)
            all_c.append(cells)
            ids, votes = ball.counts()
            if len(votes) and votes.max() >= min_votes:
                break
        if not len(votes) or votes.max() < min_votes:
            return None
        normals, rhos, cells = (np.concatenate(x) for x in (all_n, all_r, all_c))
        k = min(peaks, int(np.count_nonzero(votes >= min_votes)))
        top = ids[np.argpartition(-votes, k - 1)[:k]]
        # candidates: per peak cell, the median of its votes (sorting groups them)
        mine = np.isin(cells, top)
        order = np.argsort(cells[mine], kind="stable")
        cn, cr, cc = normals[mine][order], rhos[mine][order], cells[mine][order]
        starts = np.flatnonzero(np.r_[True, cc[1:] != cc[:-1]])
        cand_n = np.array([np.median(g, axis=0) for g in np.split(cn, starts[1:])])
        cand_r = np.array([np.median(g) for g in np.split(cr, starts[1:])])
        cand_n /= np.linalg.norm(cand_n, axis=1, keepdims=True)
        rem = cl.remaining
        pick = rem[rng.choice(len(rem), size=min(score_sample, len(rem)), replace=False)]
        d = np.abs(cl.pts[pick] @ cand_n.T - cand_r)
        best = int(np.argmax((d < cl.thr[pick, None]).sum(axis=0)))
        return cand_n[best], float(cand_r[best])

    return _sequential(cloud, prm, propose)


def detect_planes(cloud: np.ndarray, method: str = "ransac",
                  params: PlaneParams | None = None, **kw) -> list[DetectedPlane]:
    """Planes of a cloud ((n, 3) or organised (H, W, 3) with NaN), largest first."""
    if method == "ransac":
        return ransac_planes(cloud, params, **kw)
    if method == "hough":
        return hough_planes(cloud, params, **kw)
    raise ValueError(f"unknown plane method {method!r} (ransac, hough)")


def plane_error(n1, rho1: float, n2, rho2: float) -> tuple[float, float]:
    """(angle in degrees, |rho difference|) between two planes n.x = rho, as planes: the
    pair (n, rho) and (-n, -rho) is the same plane, so the better of the two readings of
    the second counts (this matters near rho = 0, where the canonical sign flips)."""
    n1 = np.asarray(n1, float) / np.linalg.norm(n1)
    n2 = np.asarray(n2, float) / np.linalg.norm(n2)
    c = float(n1 @ n2)
    s = 1.0 if c >= 0 else -1.0
    return float(np.degrees(np.arccos(min(1.0, abs(c))))), abs(float(rho1) - s * float(rho2))


def normal_angle_deg(n1: np.ndarray, n2: np.ndarray) -> float:
    """Angle between two plane normals in degrees, orientation ignored."""
    c = abs(float(np.dot(n1, n2)) / (np.linalg.norm(n1) * np.linalg.norm(n2)))
    return float(np.degrees(np.arccos(min(1.0, c))))
