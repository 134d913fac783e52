"""Which scans become graph nodes (``MapperParams.node_travel``, ``node_turn``,
``node_below``, ``node_surprise``) and what becomes of the others: tracked against the map,
their poses moving with their node, placed again on the finished map."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.finishing import NeighbourParams
from cgamap.mapping.odometry import add_odometry_noise, compose_pose2d, relative
from cgamap.mapping.offline import build_map
from cgamap.mapping.slam2d import Mapper, MapperParams, scan_poses
from synth2d import ROOM, scan, world

PLAIN = MapperParams(neighbours=NeighbourParams(enabled=False))


def _step(m: Mapper, w, truth, odo, seed: int = 0):
    s = scan(w, truth, n=360, sigma=0.005, seed=seed)
    return m.step(s.ranges, s.angle_min, s.angle_increment, np.asarray(odo, float))


def test_scans_closer_than_the_gate_are_tracked_and_follow_their_node():
    room = world(ROOM)
    p0 = np.array([-1.0, 0.0, 0.0])
    m = Mapper(PLAIN, initial_pose=p0)
    assert _step(m, room, p0, p0).node == 0 and m.count == 1
    p1 = p0 + [0.1, 0.0, 0.0]
    got = _step(m, room, p1, p1, 1)
    assert m.count == 1 and m.stepped == 2  # tracked: no node, nothing merged
    assert got.node == 0 and np.allclose(got.offset, [0.1, 0.0, 0.0], atol=0.01)
    assert np.allclose(got.pose, p1, atol=0.01) and np.allclose(m.pose, got.pose)
    # the graph moves its node (a closure, the finishing pass): the tracked pose moves with it
    m.graph.poses[0] = m.graph.poses[0] + [0.3, -0.2, 0.1]
    assert np.allclose(m.pose, compose_pose2d(m.graph.poses[0], got.offset))
    m.graph.poses[0] = m.graph.poses[0] - [0.3, -0.2, 0.1]
    # half a metre since the node (not since the tracked scan): a node
    p2 = p0 + [0.55, 0.0, 0.0]
    got = _step(m, room, p2, p2, 2)
    assert m.count == 2 and got.node == 1 and not got.offset.any()
    assert list(m.node_scan) == [0, 2]
    # a turn on the spot past node_turn: a node too
    p3 = p2 + [0.0, 0.0, 0.25]
    _step(m, room, p3, p3, 3)
    assert m.count == 3
    # every scan a node when the gate is off
    m = Mapper(replace(PLAIN, node_travel=0.0, node_turn=0.0), initial_pose=p0)
    for k in range(3):
        _step(m, room, p0 + [0.1 * k, 0, 0], p0 + [0.1 * k, 0, 0], k)
    assert m.count == 3


def test_walls_that_disagree_with_the_wheels_or_new_ground_make_a_node(monkeypatch):
    from dataclasses import replace as dc_replace

    from cgamap.mapping import slam2d

    room = world(ROOM)
    p0 = np.array([-1.0, 0.0, 0.0])
    p1 = p0 + [0.1, 0.0, 0.0]
    real = slam2d.correct_pose
    shift = np.zeros(3)

    def moved(*args, **kwargs):  # the correction as a long skewed wall would make it
        c = real(*args, **kwargs)
        return dc_replace(c, pose=c.pose + shift)

    monkeypatch.setattr(slam2d, "correct_pose", moved)

    def run(params: MapperParams, by, other=None) -> int:
        m = Mapper(params, initial_pose=p0)
        _step(m, room, p0, p0)
        shift[:] = by
        _step(m, other or room, p1, p1, 1)
        shift[:] = 0.0
        return m.count

    # after 10 cm of travel the prior's sigma is 2.8 cm and 0.74 deg
    assert run(PLAIN, (0.0, 0.0, 0.0)) == 1                 # wheels and walls agree: tracked
    assert run(PLAIN, (0.04, 0.0, 0.0)) == 1                # 1.4 sigma
    assert run(PLAIN, (0.0, 0.07, 0.0)) == 2                # 2.5 sigma: the graph judges it
    assert run(PLAIN, (0.0, 0.0, np.radians(2.0))) == 2
    assert run(replace(PLAIN, node_surprise=1e9), (0.0, 0.07, 0.0)) == 1  # the rule off
    # most of the scan on walls the map does not have yet: mapped
    bigger = world([(-3, -2, 9, -2), (9, -2, 9, 6), (9, 6, -3, 6), (-3, 6, -3, -2)])
    assert run(PLAIN, (0.0, 0.0, 0.0), other=bigger) == 2


def test_a_dense_stream_builds_the_graph_a_sparse_one_would():
    """Half a lap of the loop world with a scan every 10 cm and high odometry noise: a node
    about every half metre, every scan's pose (nodes and tracked ones) near the truth."""
    w = get_world("loop")
    t = np.arange(0, 0.5 * w.path_length / w.speed, 0.1 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    scans = [scan(w, p, n=180, sigma=0.01, seed=k) for k, p in enumerate(truth)]
    odo = add_odometry_noise(truth, "high", seed=1)
    res = build_map(scans, odo, PLAIN)
    n, nodes = len(scans), res.report["graph_nodes"]
    assert nodes == len(res.node_scan) and list(res.node_scan) == sorted(set(res.node_scan))
    gaps = np.diff(res.node_scan)
    assert n / 8 < nodes < n / 3 and 4 <= np.median(gaps) <= 6, (n, nodes)
    assert len(res.poses) == n and res.report["ate_trans_m"] < 0.03, res.report["ate_trans_m"]
    # the tracked scans are placed as well as the nodes
    R = np.array([s.pose_ref for s in scans])
    err = np.hypot(*(res.poses[:, :2] - R[:, :2]).T)
    err -= np.median(err)  # the map's frame is the first pose: compare spreads
    tracked = np.ones(n, bool)
    tracked[res.node_scan] = False
    assert np.abs(err[tracked]).max() < 0.05
    dense = build_map(scans, odo, replace(PLAIN, node_travel=0.0, node_turn=0.0))
    assert dense.report["graph_nodes"] == n


def test_scan_poses_compose_each_scan_on_its_node():
    nodes = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, np.pi / 2]])
    node = np.array([0, 1, 1, 5])
    offset = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.1, 0.0, 0.0]])
    online = np.full((4, 3), 7.0)
    got = scan_poses(nodes, node, offset, online)
    assert np.allclose(got[:3], [[0, 0, 0], [1, 1, np.pi / 2], [1, 1.5, np.pi / 2]])
    assert np.allclose(got[3], 7.0)  # its node was compacted away: the online pose
    assert np.allclose(relative(got[1], got[2]), offset[2])
