"""Loop closures while mapping the real Intel log, against the reference's relative poses.
Scan 366 stands in a corridor where its two earlier visits' submaps, slid by a metre, fit the
scan as well as (scans 127-135) or better than (31-39) where the mapper had it, 3 cm from the
reference, its chain tied to the map by a closure 12 scans before.  Both closures, 1.0 m off,
used to be taken, and the live map followed them for six scans until the next solve judged
them wrong.  The tie is now refused: the drift a jump may undo is counted from the last
closure, not from the visit 120 m of travel back.  The other one stays (its submap does fit
the slid pose better: 0.98 of the scan against 0.78).

With seed 1 (and 2, 4, 6, 7 of the first eight), scan 533 is relocalised 2.2 m along a
corridor from where the mapper had it (7 cm from the reference), in the submap of scans
158-166, which the slid pose fits better (0.95 of its points against 0.62) however wide the
submap.  With ``LoopParams.confirm_jump`` set (off by default), such a jump, beyond what 5 m of
travel would drift where the walls hold the chain, is held until another scan agrees; scan
536 places the robot where it was, and the look-alike goes."""

from __future__ import annotations

import numpy as np
from conftest import require_data

LOG = "laser/intel-corrected.log.gz"


def _online_closures(seed: int, params=None):
    """Map the Intel log with ``high`` odometry noise (no finishing pass): the mapper and
    how far (m) each of its loop closures lies from the reference's relative pose."""
    from cgamap.drivers.carmen import read_scans
    from cgamap.mapping.odometry import relative
    from cgamap.mapping.offline import log_odometry
    from cgamap.mapping.slam2d import Mapper

    scans = read_scans(require_data(LOG))
    ref = np.array([s.pose_ref for s in scans])
    odo = log_odometry(scans, "high", seed)[0]
    m = Mapper(params, initial_pose=odo[0])
    for s, o in zip(scans, odo, strict=True):
        m.step(s.ranges, s.angle_min, s.angle_increment, o)
    g = m.graph
    loops = np.flatnonzero(g.loop)
    i, j = np.array(g.ei)[loops], np.array(g.ej)[loops]
    z = np.array(g.z)[loops]
    scan = m.node_scan.array()  # a scan or two barely moved from the last is no node
    off = np.hypot(*(z[:, :2] - relative(ref[scan[i]], ref[scan[j]])[:, :2]).T)
    return m, [(int(a), int(b), round(float(e), 2))
               for a, b, e in zip(scan[i], scan[j], off, strict=True)]


def test_online_closures_on_intel_agree_with_the_reference():
    m, off = _online_closures(0)
    assert len(off) >= 80, len(off)           # about 100 online closures
    bad = [c for c in off if c[2] > 0.5]
    assert len(bad) <= 1, bad                 # was 2, both at scan 366


def test_a_look_alike_two_metres_along_a_corridor_is_held_and_dropped():
    from dataclasses import replace

    from cgamap.mapping.slam2d import LoopParams, MapperParams

    m, off = _online_closures(1, MapperParams(loop=replace(LoopParams(), confirm_jump=1.0)))
    assert len(off) >= 80, len(off)
    assert not [c for c in off if c[2] > 1.0], off   # was (162, 533, 2.24)
    assert m.loop_stats["held_dropped"] >= 1, m.loop_stats
