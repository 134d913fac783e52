"""The demo's score against the simulation's truth: only the scans of the drive count."""

from __future__ import annotations

import numpy as np
from cgamap.daemon.demo import truth_error
from cgamap.drivers.sim.world import get_world


def test_scans_after_the_drive_stopped_are_not_scored():
    """The twin's robot goes on along its path once the wheels stop: a scan mapped then
    meets odometry that stands still, and its pose is not the drive's to answer for."""
    world = get_world("loop")
    stamps = np.arange(0, 20000, 100.0)   # the twin's clock (ms)
    x, y, th = world.trajectory(stamps / 1000.0)
    rows = [[1e9 + s * 1e6, s, xi, yi, ti, -1.0] for s, xi, yi, ti in
            zip(stamps, x, y, th, strict=True)]
    rows[-1][2] += 0.1    # the last scan, after the stop: 10 cm and 4 deg off
    rows[-1][4] += 0.07
    everything = truth_error(rows, world)
    drive = truth_error(rows, world, until_ms=stamps[-2])
    assert everything["poses"] == len(rows) and everything["final_trans_m"] > 0.05
    assert drive["poses"] == len(rows) - 1 and drive["poses_after_drive"] == 1
    assert drive["ate_trans_m"] < 1e-9 and drive["final_trans_m"] < 1e-9
