"""Synthetic point clouds of known planes: test and benchmark scenes.

Each maker returns (points (n, 3), truth) where truth is a list of (unit normal, rho) with
rho >= 0 for the planes the scene is made of. Frames: x forward, y left, z up (robot base).
"""

from __future__ import annotations

import numpy as np

from .planes import canonical


def sample_rect(origin, u, v, size_u: float, size_v: float, count: int,
                rng: np.random.Generator) -> np.ndarray:
    """``count`` uniform points on the rectangle origin + a u + b v, a in [0, size_u],
    b in [0, size_v] (u, v unit, orthogonal)."""
    ab = rng.random((count, 2)) * [size_u, size_v]
    return (np.asarray(origin, float) + ab[:, :1] * np.asarray(u, float)
            + ab[:, 1:] * np.asarray(v, float))


def _hesse(origin, u, v) -> tuple[np.ndarray, float]:
    n = np.cross(u, v)
    n = n / np.linalg.norm(n)
    return canonical(n, float(n @ np.asarray(origin, float)))


def _finish(patches, noise: float, outliers: float, rng, box=None):
    pts = np.concatenate(patches)
    pts = pts + rng.normal(0.0, noise, pts.shape)
    if outliers > 0:
        lo, hi = (pts.min(axis=0), pts.max(axis=0)) if box is None else box
        n_out = int(round(len(pts) * outliers / (1 - outliers)))
        pts = np.concatenate([pts, rng.uniform(lo, hi, (n_out, 3))])
    return pts[rng.permutation(len(pts))]


def three_planes(n: int = 100_000, outliers: float = 0.2, noise: float = 0.01,
                 seed: int = 1) -> tuple[np.ndarray, list]:
    """A floor and two walls meeting in a corner (the benchmark scene of issue 6)."""
    rng = np.random.default_rng(seed)
    each = int(n * (1 - outliers)) // 3
    rects = [((-2.0, -1.5, 0.0), (1, 0, 0), (0, 1, 0), 4.0, 3.0),    # floor z = 0
             ((2.0, -1.5, 0.0), (0, 1, 0), (0, 0, 1), 3.0, 2.5),     # wall x = 2
             ((-2.0, 1.5, 0.0), (1, 0, 0), (0, 0, 1), 4.0, 2.5)]     # wall y = 1.5
    patches = [sample_rect(o, u, v, a, b, each, rng) for o, u, v, a, b in rects]
    truth = [_hesse(o, u, v) for o, u, v, *_ in rects]
    pts = _finish(patches, noise, 0.0, rng)
    n_out = n - len(pts)
    pts = np.concatenate([pts, rng.uniform((-2, -1.5, 0), (2, 1.5, 2.5), (n_out, 3))])
    return pts[rng.permutation(len(pts))], truth


def corridor(width: float = 2.0, length: float = 6.0, height: float = 2.5,
             density: float = 400.0, noise: float = 0.005, outliers: float = 0.05,
             seed: int = 2) -> tuple[np.ndarray, list]:
    """Floor z = 0 and walls y = +-width/2 along x in [0, length]."""
    rng = np.random.default_rng(seed)
    rects = [((0.0, -width / 2, 0.0), (1, 0, 0), (0, 1, 0), length, width),
             ((0.0, width / 2, 0.0), (1, 0, 0), (0, 0, 1), length, height),
             ((0.0, -width / 2, 0.0), (1, 0, 0), (0, 0, 1), length, height)]
    patches = [sample_rect(o, u, v, a, b, int(density * a * b), rng) for o, u, v, a, b in rects]
    return _finish(patches, noise, outliers, rng), [_hesse(o, u, v) for o, u, v, *_ in rects]


def stairway(steps: int = 5, rise: float = 0.17, run: float = 0.28, width: float = 1.2,
             x0: float = 1.0, density: float = 3000.0, noise: float = 0.003,
             seed: int = 3) -> tuple[np.ndarray, list]:
    """A floor, then ``steps`` treads at z = k rise (k = 1..steps), risers at x = x0 + k run."""
    rng = np.random.default_rng(seed)
    rects = [((x0 - 1.0, -width / 2, 0.0), (1, 0, 0), (0, 1, 0), 1.0, width)]
    for k in range(steps):
        x = x0 + k * run
        rects.append(((x, -width / 2, k * rise), (0, 1, 0), (0, 0, 1), width, rise))  # riser
        rects.append(((x, -width / 2, (k + 1) * rise), (1, 0, 0), (0, 1, 0), run, width))
    patches = [sample_rect(o, u, v, a, b, int(density * a * b), rng) for o, u, v, a, b in rects]
    return _finish(patches, noise, 0.0, rng), [_hesse(o, u, v) for o, u, v, *_ in rects]


def doorway(wall_x: float = 3.0, door: float = 0.9, wall: float = 2.0, height: float = 2.2,
            density: float = 600.0, noise: float = 0.005, seed: int = 4
            ) -> tuple[np.ndarray, list]:
    """A wall x = wall_x with a door gap of width ``door`` centred on y = 0, and a floor."""
    rng = np.random.default_rng(seed)
    rects = [((0.0, -wall - door / 2, 0.0), (1, 0, 0), (0, 1, 0), wall_x, 2 * wall + door),
             ((wall_x, -wall - door / 2, 0.0), (0, 1, 0), (0, 0, 1), wall, height),
             ((wall_x, door / 2, 0.0), (0, 1, 0), (0, 0, 1), wall, height)]
    patches = [sample_rect(o, u, v, a, b, int(density * a * b), rng) for o, u, v, a, b in rects]
    return _finish(patches, noise, 0.0, rng), [_hesse(o, u, v) for o, u, v, *_ in rects]


def workplace(table_height: float = 0.75, table=(1.2, 0.8), at=(1.5, -0.4),
              density: float = 1500.0, noise: float = 0.004, seed: int = 5
              ) -> tuple[np.ndarray, list]:
    """A floor and a table top (a horizontal rectangle at ``table_height``)."""
    rng = np.random.default_rng(seed)
    rects = [((0.0, -2.0, 0.0), (1, 0, 0), (0, 1, 0), 3.5, 4.0),
             ((at[0], at[1], table_height), (1, 0, 0), (0, 1, 0), table[0], table[1])]
    patches = [sample_rect(o, u, v, a, b, int(density * a * b / (4 if i == 0 else 1)), rng)
               for i, (o, u, v, a, b) in enumerate(rects)]
    return _finish(patches, noise, 0.0, rng), [_hesse(o, u, v) for o, u, v, *_ in rects]


def rotate_z(points: np.ndarray, angle: float, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Points expressed in a frame turned by ``angle`` about z and moved by ``translation``:
    p' = R(angle)^T (p - t), i.e. what a robot at (t, angle) sees."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (np.asarray(points, float) - np.asarray(translation, float)) @ R
