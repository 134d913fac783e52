"""Synthetic 2D scans for the mapping tests: a ray cast of hand-made walls (the laser twins'
world module when it exists)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from cgamap.drivers.sim.world import NoiseModel, Wall, World


def world(walls: list[tuple[float, float, float, float]]) -> World:
    return World("test", [Wall(*w) for w in walls], np.array([[0.0, 0.0], [1.0, 0.0]]))


CORRIDOR = [(-10, -1, 10, -1), (-10, 1, 10, 1)]
L_CORNER = [(-3, 1, 3, 1), (3, 1, 3, -3)]
ROOM = [(-3, -2, 4, -2), (4, -2, 4, 3), (4, 3, -3, 3), (-3, 3, -3, -2)]


def scan(w: World, pose, n: int = 180, fov: float = np.pi, sigma: float = 0.0,
         seed: int = 0, max_range: float = 30.0) -> SimpleNamespace:
    """A LaserScan-like record (ranges NaN for no return) from ``pose`` (x, y, theta)."""
    if fov >= 2 * np.pi - 1e-9:
        amin, inc = -np.pi, 2 * np.pi / n
    else:
        amin, inc = -fov / 2, fov / n
    ang = amin + inc * np.arange(n)
    r = w.raycast(pose[0], pose[1], pose[2], ang, max_range)
    r = NoiseModel(sigma=sigma).apply(r, np.random.default_rng(seed)) if sigma else \
        np.where(np.isfinite(r), r, np.nan)
    return SimpleNamespace(ranges=r, angle_min=amin, angle_increment=inc, stamp_ns=0,
                           pose_ref=tuple(float(v) for v in pose))


def scanned_map(w: World, poses, n: int = 360):
    """A line map built from full-circle scans at the given poses (their true poses)."""
    from cgamap.mapping.linemap import LineMap, integrate
    from cgamap.mapping.segments import segments_from_scan

    m = LineMap()
    for i, p in enumerate(poses):
        seg = segments_from_scan(scan(w, p, n=n, fov=2 * np.pi))
        integrate(m, seg.transformed(*p), i)
    return m


def seg_lines(seg) -> list[tuple[float, float]]:
    """(undirected angle mod pi, distance from origin) per segment, for assertions."""
    d = seg.b - seg.a
    ang = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    n = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    return list(zip(ang, np.abs(np.sum(n * seg.a, axis=1)), strict=True))
