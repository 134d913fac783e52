"""The mapper's finishing pass: scan-to-scan edges between neighbouring scans."""

from __future__ import annotations

import numpy as np
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.correction import CorrectionParams, correct_batch, correct_pose
from cgamap.mapping.evaluation import ate
from cgamap.mapping.finishing import NeighbourParams, pad_segments
from cgamap.mapping.matching import LineIndex
from cgamap.mapping.odometry import add_odometry_noise, compose_pose2d, relative
from cgamap.mapping.segments import extract_segments
from cgamap.mapping.slam2d import Mapper, MapperParams
from synth2d import scan, world

ROOM = world([(0, 0, 8, 0), (8, 0, 8, 5), (8, 5, 0, 5), (0, 5, 0, 0), (3, 2, 4.5, 2)])


def _segs(w, pose, seed=0):
    s = scan(w, pose, n=361, sigma=0.005, seed=seed)
    return extract_segments(s.ranges, s.angle_min, s.angle_increment)


def test_correct_batch_recovers_known_motions_and_matches_correct_pose():
    rng = np.random.default_rng(3)
    poses = [np.array([2.0 + rng.uniform(0, 3), 1.0 + rng.uniform(0, 1), rng.uniform(-3, 3)])
             for _ in range(6)]
    ref = np.array([1.5, 3.0, -0.4])
    dst = _segs(ROOM, ref, seed=99)
    src = [_segs(ROOM, p, seed=k) for k, p in enumerate(poses)]
    truth = relative(ref[None], np.array(poses))
    guess = truth + rng.normal(0, [0.08, 0.08, 0.03], (6, 3))
    A, B = pad_segments([(s.a, s.b) for s in src], 0.0)
    Da, Db = pad_segments([(dst.a, dst.b)] * 6, 1e6)
    params = CorrectionParams(gates=(0.3, 0.2, 0.12, 0.08, 0.06),
                              angle_gates_deg=(10.0, 7.0, 5.0, 3.0, 2.5))
    # a weak prior (as after a 20 m step): the data decide
    res = correct_batch(A, B, LineIndex.of(Da, Db), guess, 20.0, params)
    err = res.pose - truth
    assert np.abs(err[:, :2]).max() < 0.01 and np.abs(err[:, 2]).max() < np.deg2rad(0.3)
    assert (res.matched_fraction > 0.4).all()  # the rest: walls the reference scan cannot see
    # the one-pair function is the same solver
    for k in range(6):
        one = correct_pose(src[k], dst.a, dst.b, guess[k], 20.0, params)
        assert np.allclose(one.pose, res.pose[k], atol=1e-6)


def test_neighbour_pairs_are_spatial_and_sequential():
    m = Mapper(MapperParams(neighbours=NeighbourParams(radius=1.0, previous=2)))
    # a path out and back: node 6 returns next to node 0
    path = [(0, 0), (2, 0), (4, 0), (6, 0), (4, 0.3), (2, 0.3), (0.2, 0.3)]
    for x, y in path:
        m.graph.add_node(np.array([x, y, 0.0]))
        m.scans.append((np.zeros((3, 2)), np.ones((3, 2))))
    pairs = {tuple(p) for p in m.neighbour_pairs().tolist()}
    assert {(0, 1), (1, 2), (0, 2), (5, 6), (4, 6)} <= pairs  # predecessors
    assert {(2, 4), (1, 5), (0, 6)} <= pairs                  # revisits within 1 m
    assert (0, 3) not in pairs and (3, 6) not in pairs


def test_neighbour_pairs_are_capped_and_spread_over_time():
    """Many passes over one spot: each scan keeps ``max_pairs`` earlier partners, the oldest
    and the latest visit among them and the rest evenly in between; below the cap, all."""
    from cgamap.mapping.finishing import neighbour_pairs

    n, K = 200, 8
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(0, 0.5, n), rng.uniform(0, 0.5, n), np.zeros(n)])
    scans = [(np.zeros((3, 2)), np.ones((3, 2)))] * n
    pairs = neighbour_pairs(X, scans, NeighbourParams(radius=1.0, previous=1, max_pairs=K))
    for i in (5, 8, 9, 50, 199):
        partners = np.sort(pairs[pairs[:, 1] == i, 0])
        if i <= K:
            assert partners.tolist() == list(range(i))
            continue
        assert len(partners) == K and partners[0] == 0 and partners[-1] == i - 1
        gaps = np.diff(partners)
        assert gaps.max() - gaps.min() <= 1  # evenly spread
    uncapped = neighbour_pairs(X, scans, NeighbourParams(radius=1.0, previous=1, max_pairs=0))
    assert len(uncapped) == n * (n - 1) // 2


def test_neighbour_pass_improves_a_noisy_run():
    """A lap of the simulated loop twice, high odometry noise: the finishing pass must not
    make the trajectory worse, and it adds one edge per neighbour pair it can match."""
    w = get_world("loop")
    t = np.arange(0, 2 * w.path_length / w.speed, 0.7 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    scans = [scan(w, p, n=180, sigma=0.01, seed=k) for k, p in enumerate(truth)]
    odo = add_odometry_noise(truth, "high", seed=2)
    errs = {}
    for on in (False, True):
        m = Mapper(MapperParams(neighbours=NeighbourParams(enabled=on)), initial_pose=odo[0])
        for s, o in zip(scans, odo, strict=True):
            m.step(s.ranges, s.angle_min, s.angle_increment, o)
        est = m.finish()
        # rigid-align on the first pose (the map frame is the first odometry pose)
        T = compose_pose2d(truth[0], relative(est[0], np.zeros(3)))
        al = compose_pose2d(T, est)
        errs[on] = float(np.sqrt(np.mean(np.sum((al[:, :2] - truth[:, :2]) ** 2, -1))))
        if on:
            assert m.neighbour_edges > len(scans)  # more than one neighbour per scan
        # the second lap revisits the first: the tracking sweep ties them, pass or not
        assert m.sweep_edges > 10, m.sweep_edges
    assert errs[True] <= errs[False] * 1.05 + 0.005, errs
    assert errs[True] < 0.1


def test_finish_is_the_daemons_snapshot_pass():
    """``Mapper.finish`` and the daemon's way (a job on a snapshot, applied later) are one
    computation: the same poses and the same walls from the same run."""
    w = get_world("loop")
    t = np.arange(0, 1.3 * w.path_length / w.speed, 0.7 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    scans = [scan(w, p, n=180, sigma=0.01, seed=k) for k, p in enumerate(truth)]
    odo = add_odometry_noise(truth, "high", seed=5)
    ms = []
    for _ in range(2):
        m = Mapper(MapperParams(), initial_pose=odo[0])
        for s, o in zip(scans, odo, strict=True):
            m.step(s.ranges, s.angle_min, s.angle_increment, o)
        ms.append(m)
    one, other = ms
    before = other.poses.copy()
    one.finish()
    if other.loops:
        other.optimize(final=True)
    figures = other.apply_finish(other.finishing_job(sweep=True).run())
    assert figures["edges"] > 0 and figures["max_shift_m"] > 0
    assert np.abs(other.poses - before).max() > 1e-3  # the pass did move the run
    np.testing.assert_allclose(one.poses, other.poses, atol=1e-9)
    np.testing.assert_allclose(one.map.a, other.map.a, atol=1e-9)
    assert one.adjusted == other.adjusted and one.adjusted["lines"] > 0


def test_finish_without_kept_scans_still_adjusts_the_lines():
    """No neighbour pass and no sweep: no per-scan segments are kept, and the finishing
    pass is the line adjustment alone."""
    from dataclasses import replace

    w = get_world("loop")
    t = np.arange(0, 0.6 * w.path_length / w.speed, 0.7 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    P = MapperParams(neighbours=NeighbourParams(enabled=False))
    P = replace(P, loop=replace(P.loop, sweep_every=0))
    m = Mapper(P, initial_pose=truth[0])
    for k, p in enumerate(truth):
        s = scan(w, p, n=180, sigma=0.01, seed=k)
        m.step(s.ranges, s.angle_min, s.angle_increment, p)
    assert not m.scans and not m.keep_scans
    before = m.poses.copy()
    m.finish()
    assert m.adjusted["lines"] > 0 and m.adjusted["iterations"] > 0
    assert m.sweep_edges == 0 and m.neighbour_edges == 0
    assert np.abs(m.poses - before).max() > 0


def test_online_closures_count_closure_weight_once_after_the_pass():
    """The finishing pass replaces what the online closures said with its own pairs: those
    closures stay in the graph at ``closure_weight``, scaled once however often the pass
    runs (the daemon runs it on demand)."""
    w = get_world("loop")
    t = np.arange(0, 2 * w.path_length / w.speed, 0.7 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    scans = [scan(w, p, n=180, sigma=0.01, seed=k) for k, p in enumerate(truth)]
    odo = add_odometry_noise(truth, "high", seed=2)
    NP = NeighbourParams(closure_weight=0.25)
    m = Mapper(MapperParams(neighbours=NP), initial_pose=odo[0])
    for s, o in zip(scans, odo, strict=True):
        m.step(s.ranges, s.angle_min, s.angle_increment, o)
    g = m.graph
    online = np.flatnonzero(g.loop.array())
    assert len(online) >= 1, "the run closed no loop online"
    info0 = g.info.array()[online].copy()
    m.finish()
    assert m.neighbour_edges > 0
    np.testing.assert_allclose(g.info.array()[online], 0.25 * info0)
    m.apply_finish(m.finishing_job().run())  # again, as the daemon's next optimize
    np.testing.assert_allclose(g.info.array()[online], 0.25 * info0)


def test_online_optimisation_leaves_the_finished_nodes_where_the_pass_put_them():
    """After an adopted finishing pass (the daemon's periodic optimize) the online closures
    solve only the nodes mapped since: the pass's own solution of the older ones, made with
    all its scan pairs, stays; re-solving them with those edges cost 1.2 s a closure."""
    w = get_world("loop")
    t = np.arange(0, 2.3 * w.path_length / w.speed, 0.7 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    scans = [scan(w, p, n=180, sigma=0.01, seed=k) for k, p in enumerate(truth)]
    odo = add_odometry_noise(truth, "high", seed=4)
    m = Mapper(MapperParams(neighbours=NeighbourParams(enabled=False)), initial_pose=odo[0])
    m.keep_scans = True  # as the daemon's mapper
    from dataclasses import replace

    half = int(len(scans) * 1.2 / 2.3)
    for s, o in zip(scans[:half], odo[:half], strict=True):
        m.step(s.ranges, s.angle_min, s.angle_increment, o)
    m.apply_finish(m.finishing_job(replace(m.params.neighbours, enabled=True)).run())
    assert m.finished_upto == m.count == half
    placed, opt0, loops0 = m.poses.copy(), m.optimizations, m.loops
    for s, o in zip(scans[half:], odo[half:], strict=True):
        m.step(s.ranges, s.angle_min, s.angle_increment, o)
    assert m.loops > loops0 and m.optimizations > opt0, "no online closure after the pass"
    np.testing.assert_array_equal(m.poses[:half], placed)
    assert ate(m.poses, truth)["ate_trans_m"] < 0.1


def test_pair_turns_reads_the_turn_from_the_walls_directions():
    from cgamap.mapping.finishing import pair_turns

    dst = _segs(ROOM, np.array([2.0, 2.5, 0.3]), seed=1)
    for turn_deg in (-7.0, -2.0, 4.5, 8.0):
        # the same place seen from a laser turned ``turn`` more: its walls, turned by
        # ``turn``, line up with the destination's
        src = _segs(ROOM, np.array([2.0, 2.5, 0.3 + np.deg2rad(turn_deg)]), seed=2)
        A, B = pad_segments([(src.a, src.b), (src.b, src.a)], 0.0)     # b-a: lines are undirected
        Da, Db = pad_segments([(dst.a, dst.b), (dst.a[:2], dst.b[:2])], 1e6)
        got = np.degrees(pair_turns(A, B, Da, Db, np.zeros(2), np.deg2rad(10.0)))
        assert np.allclose(got, turn_deg, atol=0.3), (turn_deg, got)
    # no two directions within reach: no turn
    A, B = pad_segments([(np.zeros((1, 2)), np.array([[1.0, 0.0]]))], 0.0)
    Da, Db = pad_segments([(np.zeros((1, 2)), np.array([[0.0, 1.0]]))], 1e6)
    assert pair_turns(A, B, Da, Db, np.zeros(1), np.deg2rad(10.0))[0] == 0.0


def test_the_pass_takes_a_pair_back_from_a_turn_beyond_the_corrections_reach():
    from dataclasses import replace

    from cgamap.mapping.finishing import neighbour_matches

    hall = world([(0, 0, 30, 0), (30, 0, 30, 6), (30, 6, 0, 6), (0, 6, 0, 0),
                  (12, 0, 12, 1.2), (19, 6, 19, 4.5), (24, 0, 24, 0.8)])
    truth = np.array([[4.0, 3.0, 0.05], [6.5, 3.3, 0.15]])
    scans = []
    for k, p in enumerate(truth):
        s = _segs(hall, p, seed=k)
        scans.append((s.a, s.b))
    X = truth.copy()
    X[1, 2] += np.deg2rad(7.0)        # the mapper took the second scan 7 deg wrong
    want = relative(truth[0], truth[1])
    NP = NeighbourParams()
    for reach, ok in ((NP.turn_reach, True), (0.0, False)):
        E = neighbour_matches(X, scans, replace(NP, turn_reach=reach), np.array([[0, 1]]))
        right = len(E) == 1 and abs(np.degrees(E.z[0, 2] - want[2])) < 0.5 and \
            np.hypot(*(E.z[0, :2] - want[:2])) < 0.05
        assert right == ok, (reach, E.z if len(E) else None, want)


def test_rounds_go_on_until_one_moves_the_map_less_than_converged():
    """``rounds`` always; then up to ``max_rounds`` while the last round moved the map (RMS
    after a rigid alignment) by ``converged`` or more; each round's move is reported."""
    w = get_world("loop")
    t = np.arange(0, 1.2 * w.path_length / w.speed, 1.0 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    scans = [scan(w, p, n=180, sigma=0.01, seed=k) for k, p in enumerate(truth)]
    odo = add_odometry_noise(truth, "high", seed=4)
    m = Mapper(MapperParams(), initial_pose=odo[0])
    for s, o in zip(scans, odo, strict=True):
        m.step(s.ranges, s.angle_min, s.angle_increment, o)

    def moves(**kw):
        NP = NeighbourParams(**kw)
        return m.finishing_job(NP, sweep=True).run().round_moves

    assert len(moves()) == 2                                   # the default: two rounds
    assert len(moves(max_rounds=4, converged=0.0)) == 4        # never settled: all four
    got = moves(max_rounds=4, converged=1e3)                   # settled at once
    assert len(got) == 2 and all(v >= 0 for v in got)
    assert len(moves(rounds=1, max_rounds=3, converged=1e3)) == 1
    assert moves(rounds=0, max_rounds=4, converged=0.0) == []  # rounds 0: no pass at all
    m.finish()
    assert len(m.round_moves) == 2
