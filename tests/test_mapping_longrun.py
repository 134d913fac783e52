"""A long run with a bounded pose graph (``MapperParams.max_nodes``): the oldest nodes go,
the map stays, and tracking against it keeps working."""

from __future__ import annotations

import numpy as np
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.evaluation import ate
from cgamap.mapping.finishing import NeighbourParams
from cgamap.mapping.odometry import add_odometry_noise
from cgamap.mapping.slam2d import Mapper, MapperParams
from synth2d import scan


def _run(max_nodes: int, laps: int = 4):
    w = get_world("loop")
    t = np.arange(0, laps * w.path_length / w.speed, 0.7 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    scans = [scan(w, p, n=180, sigma=0.01, seed=k) for k, p in enumerate(truth)]
    odo = add_odometry_noise(truth, "high", seed=4)
    m = Mapper(MapperParams(max_nodes=max_nodes,
                            neighbours=NeighbourParams(enabled=False)), initial_pose=odo[0])
    est, sizes = [], []
    for s, o in zip(scans, odo, strict=True):
        est.append(m.step(s.ranges, s.angle_min, s.angle_increment, o).pose)
        sizes.append((m.count, len(m.map.c_node), len(m.map), len(m.graph.ei)))
    return m, np.array(est), truth, np.array(sizes)


def test_bounded_graph_keeps_tracking():
    m, est, truth, sizes = _run(max_nodes=40)
    n = len(truth)
    assert n > 150  # several times the bound
    assert sizes[:, 0].max() <= 40
    # contributions and edges stay bounded too, and the map does not pile up duplicates
    assert sizes[-1, 1] <= 1.2 * sizes[:, 1][sizes[:, 0] == 40].max()
    assert sizes[:, 3].max() < 40 * 6
    assert sizes[-1, 2] <= 60
    # every node index the map and the graph hold is a live node
    assert m.map.c_node.min() >= 0 and m.map.c_node.max() < m.count
    assert np.all(np.diff(m.map.c_node) >= 0)  # in node order: closures slice it by node
    assert max(max(m.graph.ei), max(m.graph.ej)) < m.count and 0 in m.anchors
    # the online poses (as the robot saw them, scan by scan) stay on the truth
    err = ate(est, truth)
    assert err["ate_trans_m"] < 0.1 and err["ate_rot_deg"] < 1.5, err


def test_unbounded_run_is_unchanged_by_the_option():
    """max_nodes above the run's length changes nothing."""
    a = _run(max_nodes=0, laps=1)
    b = _run(max_nodes=10_000, laps=1)
    assert np.array_equal(a[1], b[1])


def test_aging_is_spread_as_the_contributions_grow(monkeypatch):
    """A drop copies every contribution row: with many rows, short segments are judged
    less often (at most once per ``age_rows`` rows, in scans), never more often than
    ``age_every``."""
    import cgamap.mapping.slam2d as slam2d
    from cgamap.mapping.linemap import MapParams

    calls: list[tuple[int, int]] = []
    real = slam2d.age_out

    def counted(lmap, stamp, *args):
        calls.append((stamp, len(lmap.c_seg)))
        return real(lmap, stamp, *args)

    monkeypatch.setattr(slam2d, "age_out", counted)
    w = get_world("loop")
    t = np.arange(0, w.path_length / w.speed, 0.7 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    rows = 10
    m = Mapper(MapperParams(map=MapParams(age_every=4, age_rows=rows),
                            neighbours=NeighbourParams(enabled=False)), initial_pose=truth[0])
    for k, p in enumerate(truth[:80]):
        s = scan(w, p, n=180, sigma=0.01, seed=k)
        m.step(s.ranges, s.angle_min, s.angle_increment, p)
    stamps = np.array([c[0] for c in calls])
    size = np.array([c[1] for c in calls])
    gaps = np.diff(stamps)
    assert len(calls) >= 3 and stamps[0] == 0 and np.all(gaps >= 4)
    assert np.all(gaps[size[1:] < 5 * rows] == 4)     # few rows: every 4th scan, as before
    # many rows: the next judgement waits a scan per ``rows`` rows
    assert np.all(gaps >= size[1:] // rows) and np.any(gaps > 4)



def test_a_passer_by_seen_once_at_a_dense_rate_leaves_no_wall():
    """Scanning every 5 cm, a person's side (0.8 m) seen in one scan is not seen again by
    the next scans from nearly the same place: it goes (MapParams.age_travel); with the
    rule off, or a scan every 0.3 m (a sparse log's glimpse of a wall), it stays.  The
    free-space clearing, which would also see through it here, is off: the rule is for the
    sides seen edge-on, which no beam goes through; so is the scan differencing, which
    would not map it at all."""
    from dataclasses import replace

    from synth2d import ROOM, world

    room, passing = world(ROOM), world([*ROOM, (-1.0, 1.5, -0.2, 1.5)])
    for step, n, age_travel, kept in ((0.05, 40, 1.0, False), (0.05, 40, 0.0, True),
                                      (0.3, 21, 1.0, True)):
        truth = np.column_stack([-2.5 + step * np.arange(n), np.full(n, -1.0), np.zeros(n)])
        # every scan a node: the glimpse is mapped, for the aging to judge (a scan tracked
        # between nodes maps nothing)
        MP = MapperParams(neighbours=NeighbourParams(enabled=False), node_travel=0.0,
                          node_turn=0.0)
        MP = replace(MP, moving=replace(MP.moving, enabled=False),  # it would not map it
                     map=replace(MP.map, age_travel=age_travel,
                                 clear=replace(MP.map.clear, enabled=False)))
        m = Mapper(MP, initial_pose=truth[0])
        for k, p in enumerate(truth):
            s = scan(passing if k == 3 else room, p, n=360, sigma=0.005, seed=k)
            m.step(s.ranges, s.angle_min, s.angle_increment, p)
        mid = 0.5 * (m.map.a + m.map.b)
        there = (np.abs(mid[:, 1] - 1.5) < 0.1) & (np.abs(mid[:, 0] + 0.6) < 0.3)
        assert there.any() == kept, (step, age_travel)


def test_retired_contributions_serve_the_submaps_and_follow_compaction():
    """Contributions of glimpses aged out (``Mapper._retired``) join the closure submap of
    their nodes, and a compaction drops those of the nodes it drops and renumbers the rest."""
    m, *_ = _run(max_nodes=0, laps=1)
    n, X = m.count, m.poses
    j = n // 2
    before = len(m._submap(X, j, n - 1))
    a, b = np.array([[0.5, 1.0], [0.5, 2.0], [0.5, 3.0]]), np.array([[1.5, 1.0]] * 3)
    m._retired = (np.array([1, j, n - 1]), a, b)
    sub = m._submap(X, j, n - 1)
    assert len(sub) == before + 1  # only node j's row is within j +- window
    # in j's own frame, node j's row is where it was recorded
    assert np.any(np.all(np.isclose(sub.a, a[1]), axis=1))
    cut = m.compact(n - j)
    assert cut == j
    np.testing.assert_array_equal(m._retired[0], [0, n - 1 - j])
    np.testing.assert_array_equal(m._retired[1], a[1:])
