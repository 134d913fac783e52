"""The mapping loop when the laser streams before the odometry does (a daemon starting, more
so on a busy machine): scans older than the first odometry sample have no odometry guess and
must not be mapped, or the motion until that sample is lost from the map's first steps and
their walls stay behind as ghosts (the e2e test's ghost-wall bound failed so under load)."""

from __future__ import annotations

import numpy as np
from cgamap.daemon import config as config_mod
from cgamap.daemon.demo import map_error, truth_error
from cgamap.daemon.loop import MappingLoop
from cgamap.drivers.messages import LaserScan, OdometryPose
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.posegraph import relative

# a Hokuyo UTM-30LX-like fan: 270 degrees, 0.5 degree steps
ANGLES = np.deg2rad(np.arange(-135.0, 135.01, 0.5))
T0 = 2.0            # s of the world's clock at the first scan (the robot is moving then)
SCAN_DT, ODOM_DT = 0.025, 0.02


def cfg(ready_timeout: float = 2.0) -> dict:
    return config_mod.validate({
        "devices": {"laser": {"role": "laser", "model": "hokuyo", "url": "serial:///dev/null"},
                    "base": {"role": "odometry", "model": "modbus-base",
                             "url": "tcp://127.0.0.1:1"}},
        "supervisor": {"ready_timeout": ready_timeout},
        "mapping": {"map3d": False}})


def scan(world, t: float, seq: int) -> LaserScan:
    r = world.raycast(*world.trajectory(t), ANGLES, 30.0)
    r[~np.isfinite(r)] = np.nan
    return LaserScan(seq=seq, stamp_ns=int(t * 1e9), angle_min=float(ANGLES[0]),
                     angle_increment=float(ANGLES[1] - ANGLES[0]), ranges=r,
                     device_stamp=int(round(t * 1000)))


def run(loop: MappingLoop, world, odom_from: float | None, until: float) -> None:
    """Scans from T0 at 40 Hz; odometry at 50 Hz from ``odom_from`` (None: never), zero at
    its first sample (wheel odometry starts counting when it is first read)."""
    msgs = [(T0 + i * SCAN_DT, "laser", i) for i in range(int((until - T0) / SCAN_DT))]
    if odom_from is not None:
        msgs += [(odom_from + i * ODOM_DT, "base", i)
                 for i in range(int((until - odom_from) / ODOM_DT))]
    origin = None if odom_from is None else np.array(world.trajectory(odom_from))
    for t, kind, i in sorted(msgs):
        if kind == "laser":
            loop.handle("laser", scan(world, t, i))
        else:
            x, y, th = relative(origin, np.array(world.trajectory(t)))
            loop.handle("base", OdometryPose(stamp_ns=int(t * 1e9), x=x, y=y, theta=th))
        loop.process(odometry_live=True)


def test_scans_before_the_first_odometry_are_not_mapped():
    world = get_world("loop")
    loop = MappingLoop(cfg())
    odom_from = T0 + 0.2          # the base's first reading: 16 cm of driving after the laser's
    run(loop, world, odom_from, T0 + 6.0)
    rows = list(loop.trajectory)
    assert rows and rows[0][0] >= odom_from * 1e9, rows[0]
    assert loop.counts["scans_before_odometry"] >= 8
    err = truth_error(rows, world)
    walls = map_error(loop.segments(), world, err["alignment"])
    print("pose error:", err["ate_trans_m"], "map vs true walls:", walls)
    assert err["ate_trans_m"] < 0.02
    assert walls["wall_dist_max_m"] < 0.05  # no ghost of the first scans' walls


def test_without_any_odometry_mapping_starts_after_the_wait():
    """A base that never answers must not stop the map: after ``ready_timeout`` of scans the
    loop maps without odometry (the motion then comes from matching alone)."""
    world = get_world("loop")
    loop = MappingLoop(cfg(ready_timeout=1.0))
    run(loop, world, None, T0 + 2.0)
    rows = list(loop.trajectory)
    assert rows and abs(rows[0][0] - (T0 + 1.0) * 1e9) <= SCAN_DT * 1e9
    assert loop.counts["scans_before_odometry"] == 40
