"""A map that stays clean when the robot comes back: the Intel lab driven through and then
back along the same path (the log's scans in reverse), so every wall of the second pass was
seen in the first.  Its segments must join the walls they see, not lie down beside them."""

from __future__ import annotations

import numpy as np
from cgamap.drivers.carmen import read_scans
from cgamap.mapping.linemap import copies
from cgamap.mapping.slam2d import Mapper
from conftest import require_data


def test_driving_back_through_the_intel_lab_adds_no_copies():
    scans = read_scans(require_data("laser/intel-corrected.log.gz"))
    poses = np.array([s.pose_ref for s in scans])  # as odometry: what is tested is the map
    m = Mapper(initial_pose=poses[0])

    def drive(order) -> int:
        for k in order:
            s = scans[k]
            m.step(s.ranges, s.angle_min, s.angle_increment, poses[k])
        return len(m.map)

    first = drive(range(len(scans)))
    second = drive(range(len(scans) - 1, -1, -1))
    print(f"online map: {first} segments after the first pass, {second} after the second; "
          f"{copies(m.map.a, m.map.b)} with a copy within 3 cm")
    # before fusions were judged by what they add, not by the wall's thickness: 927 -> 1163
    # segments, 447 of them with a copy within 3 cm; now 885 -> 950, 3.  What the second
    # pass still adds lies 3-10 cm off, where the online poses have drifted before a closure
    # pulls them back (the finishing pass fuses those: Intel driven four times ends with 800
    # segments, once with 782)
    assert second <= 1.15 * first
    assert copies(m.map.a, m.map.b) <= 0.02 * second
