"""A map that stays clean when the robot comes back: the Intel lab driven through and then
back along the same path (the log's scans in reverse), so every wall of the second pass was
seen in the first.  Its segments must join the walls they see, not lie down beside them."""

from __future__ import annotations

import numpy as np
from cgamap.drivers.carmen import read_scans
from cgamap.mapping.slam2d import Mapper
from conftest import require_data


def _twins(a: np.ndarray, b: np.ndarray, dist: float = 0.03) -> int:
    """Segments with another one overlapping them along their line, within 5 deg and with
    both its end points within ``dist`` of that line: copies of one wall."""
    d = b - a
    u = d / np.linalg.norm(d, axis=1)[:, None]
    n = np.column_stack([-u[:, 1], u[:, 0]])
    L = np.linalg.norm(d, axis=1)
    off_a = np.abs(np.einsum("ik,ijk->ij", n, a[None] - a[:, None]))
    off_b = np.abs(np.einsum("ik,ijk->ij", n, b[None] - a[:, None]))
    ta = np.einsum("ik,ijk->ij", u, a[None] - a[:, None])
    tb = np.einsum("ik,ijk->ij", u, b[None] - a[:, None])
    overlap = np.minimum(np.maximum(ta, tb), L[:, None]) - np.maximum(np.minimum(ta, tb), 0)
    twin = ((np.abs(u @ u.T) > np.cos(np.deg2rad(5.0))) & (off_a < dist) & (off_b < dist)
            & (overlap > 0.05))
    np.fill_diagonal(twin, False)
    return int(twin.any(axis=1).sum())


def test_driving_back_through_the_intel_lab_adds_no_copies():
    scans = read_scans(require_data("laser/intel-corrected.log.gz"))
    poses = np.array([s.pose_ref for s in scans])  # as odometry: what is tested is the map
    m = Mapper(initial_pose=poses[0])
    for k in [*range(len(scans)), *range(len(scans) - 1, -1, -1)]:
        s = scans[k]
        m.step(s.ranges, s.angle_min, s.angle_increment, poses[k])
        if k == len(scans) - 1 and len(m.graph.poses) == len(scans):
            first = len(m.map)
    second = len(m.map)
    print(f"online map: {first} segments after the first pass, {second} after the second; "
          f"{_twins(m.map.a, m.map.b)} with a copy within 3 cm")
    # before fusions were judged by what they add, not by the wall's thickness: 926 -> 1155
    # segments, 298 of them with a copy within 3 cm; now 870 -> 959, none.  What the second
    # pass still adds lies 3-10 cm off, where the online poses have drifted before a closure
    # pulls them back (the finishing pass fuses those: Intel driven four times ends with 777
    # segments, once with 758)
    assert second <= 1.15 * first
    assert _twins(m.map.a, m.map.b) <= 0.02 * second
