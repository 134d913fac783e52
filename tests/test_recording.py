"""MCAP recordings: each device message comes back as it was written."""

from __future__ import annotations

import numpy as np
from cgamap.daemon.recording import McapRecorder, read_mcap
from cgamap.drivers.messages import LaserScan, PanTiltState, WheelTicks


def test_messages_round_trip_through_an_mcap_file(tmp_path):
    ticks = WheelTicks(seq=3, stamp_ns=1_000_000_123, left=-5, right=70_000, left_speed=0.5,
                       right_speed=None, status=4, estop=True, errors={"timeout": 2},
                       stamp_uncertainty_ns=31_000)
    scan = LaserScan(seq=1, stamp_ns=1_000_000_000, angle_min=-1.0, angle_increment=0.5,
                     ranges=np.array([1.0, np.nan, 2.5, 3.25, 4.0]), range_min=0.0,
                     range_max=30.0)
    head = PanTiltState(seq=2, stamp_ns=1_000_000_050, pan=0.25, tilt=-0.125, moving=True)
    path = tmp_path / "run.mcap"
    with open(path, "wb") as f:
        rec = McapRecorder(f)
        for m in (scan, head, ticks):
            assert rec.write(m)
        rec.finish()
    back = {type(m): m for m in read_mcap(path)}
    assert back[WheelTicks] == ticks
    assert back[PanTiltState].pan == head.pan and back[PanTiltState].tilt == head.tilt
    got = back[LaserScan]
    assert got.stamp_ns == scan.stamp_ns and got.angle_increment == scan.angle_increment
    np.testing.assert_array_equal(np.isnan(got.ranges), np.isnan(scan.ranges))
    np.testing.assert_allclose(got.ranges[~np.isnan(got.ranges)], [1.0, 2.5, 3.25, 4.0])
