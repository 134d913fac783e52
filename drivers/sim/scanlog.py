"""A simulated laser log: scans along a world's path, each with the true pose.

What a corrected CARMEN log is to the real logs: :func:`simulated_scans` gives
:class:`~cgamap.drivers.messages.LaserScan` messages whose ``pose_ref`` and ``pose_odom`` are
the simulation's truth (``cgamap map build`` corrupts the odometry itself), to write with
:func:`cgamap.drivers.carmen.write_carmen` and replay like a recorded log.
"""

from __future__ import annotations

import numpy as np

from ..carmen import beam_geometry
from ..messages import LaserScan
from .world import NoiseModel, World

# SICK LMS2xx-like: 1 cm, plus 0.05 % of the range, 1 % of the beams lost
LMS_NOISE = NoiseModel(sigma=0.01, sigma_rel=0.0005, dropout=0.01)


def simulated_scans(world: World, laps: float = 2.0, period: float = 1.0, beams: int = 180,
                    max_range: float = 80.0, noise: NoiseModel | None = LMS_NOISE,
                    seed: int = 0) -> list[LaserScan]:
    """Scans every ``period`` seconds while the robot drives ``laps`` times round the
    world's path, ``beams`` beams over 180° (FLASER geometry), returns beyond ``max_range``
    lost; deterministic for a seed."""
    if laps <= 0 or period <= 0:
        raise ValueError("laps and period must be positive")
    rng = np.random.default_rng(seed)
    a0, inc = beam_geometry(beams)
    angles = a0 + inc * np.arange(beams)
    out = []
    for k, t in enumerate(np.arange(0.0, laps * world.path_length / world.speed, period)):
        pose = tuple(float(v) for v in world.trajectory(t))
        r = world.scan(t, angles, max_range, noise, rng)
        out.append(LaserScan(seq=k, stamp_ns=int(round((t + 1.0) * 1e9)), angle_min=a0,
                             angle_increment=inc, ranges=np.where(np.isfinite(r), r, np.nan),
                             range_max=max_range, pose_ref=pose, pose_odom=pose))
    return out
