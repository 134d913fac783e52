"""Loop closures while mapping the real Intel log, against the reference's relative poses.
Scan 366 stands in a corridor where its two earlier visits' submaps, slid by a metre, fit the
scan as well as (scans 127-135) or better than (31-39) where the mapper had it, 3 cm from the
reference, its chain tied to the map by a closure 12 scans before.  Both closures, 1.0 m off,
used to be taken, and the live map followed them for six scans until the next solve judged
them wrong.  The tie is now refused: the drift a jump may undo is counted from the last
closure, not from the visit 120 m of travel back.  The other one stays (its submap does fit
the slid pose better: 0.98 of the scan against 0.78)."""

from __future__ import annotations

import numpy as np
from conftest import require_data

LOG = "laser/intel-corrected.log.gz"


def test_online_closures_on_intel_agree_with_the_reference():
    from cgamap.drivers.carmen import read_scans
    from cgamap.mapping.odometry import relative
    from cgamap.mapping.offline import log_odometry
    from cgamap.mapping.slam2d import Mapper

    scans = read_scans(require_data(LOG))
    ref = np.array([s.pose_ref for s in scans])
    odo = log_odometry(scans, "high", 0)[0]
    m = Mapper(initial_pose=odo[0])
    for s, o in zip(scans, odo, strict=True):
        m.step(s.ranges, s.angle_min, s.angle_increment, o)
    g = m.graph
    loops = np.flatnonzero(g.loop)
    i, j = np.array(g.ei)[loops], np.array(g.ej)[loops]
    z = np.array(g.z)[loops]
    scan = m.node_scan.array()  # a scan or two barely moved from the last is no node
    off = np.hypot(*(z[:, :2] - relative(ref[scan[i]], ref[scan[j]])[:, :2]).T)
    assert len(loops) >= 80, len(loops)       # about 100 online closures
    bad = [(int(a), int(b), round(float(e), 2)) for a, b, e in zip(i, j, off, strict=True)
           if e > 0.5]
    assert len(bad) <= 1, bad                 # was 2, both at scan 366
