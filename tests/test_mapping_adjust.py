"""The line adjustment (poses and walls solved together): it recovers poses from the walls
the scans share, leaves a consistent solution where it is, and a wrong association does not
bend it."""

from __future__ import annotations

import dataclasses

import numpy as np
from cgamap.mapping.finishing import NeighbourParams
from cgamap.mapping.line_adjust import AdjustParams, Contributions, adjust, associate, observations
from cgamap.mapping.linemap import LineMap, MapParams
from cgamap.mapping.odometry import relative
from cgamap.mapping.posegraph import PoseGraph
from cgamap.mapping.slam2d import Mapper, MapperParams
from synth2d import ROOM, scan, world

# a room with a pillar, so every scan sees walls in two directions
WALLS = [*ROOM, (0.5, 0.2, 1.0, 0.2), (1.0, 0.2, 1.0, 0.7)]


def _truth(n: int = 16) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([0.5 + 2.0 * np.cos(t), 0.5 + 1.5 * np.sin(t), t + np.pi / 2])


def _mapped(truth: np.ndarray, sigma: float = 0.005) -> Mapper:
    """A mapper fed the true poses as odometry (its associations are right), nothing
    adjusted yet."""
    w = world(WALLS)
    P = MapperParams(neighbours=NeighbourParams(enabled=False),
                     adjust=AdjustParams(enabled=False))
    m = Mapper(P, initial_pose=truth[0])
    for k, p in enumerate(truth):
        s = scan(w, p, n=360, fov=2 * np.pi, sigma=sigma, seed=k)
        m.step(s.ranges, s.angle_min, s.angle_increment, p)
    return m


def _weak_chain(X: np.ndarray, std=(0.3, 0.1)) -> PoseGraph:
    """Sequential edges of ``X`` that barely hold: the walls must do the work."""
    g = PoseGraph([p.copy() for p in X])
    info = np.diag([std[0] ** -2, std[0] ** -2, std[1] ** -2])
    for i in range(1, len(X)):
        g.add_edge(i - 1, i, relative(X[i - 1], X[i]), info)
    return g


def _err(X: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    d = X - truth
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return float(np.abs(d[:, :2]).max()), float(np.degrees(np.abs(d[:, 2]).max()))


def test_recovers_perturbed_poses_from_shared_walls():
    truth = _truth()
    m = _mapped(truth)
    obs = observations(m.map)
    assert len(obs.phi) >= 4 and len(obs) >= 4 * len(truth)
    rng = np.random.default_rng(3)
    X0 = truth + np.column_stack([rng.normal(0, 0.04, (len(truth), 2)),
                                  rng.normal(0, np.deg2rad(1.0), len(truth))])
    X0[0] = truth[0]  # the held node
    before = _err(X0, truth)
    # the chain says the perturbed relative poses: only the walls can undo them
    X, info = adjust(X0, _weak_chain(X0), obs, 0)
    after = _err(X, truth)
    assert before[0] > 0.05 and before[1] > 1.0
    assert after[0] < 0.01 and after[1] < 0.2, (before, after, info)
    assert info["iterations"] >= 2 and info["lines"] == len(obs.phi)


def test_a_consistent_solution_stays():
    truth = _truth()
    m = _mapped(truth, sigma=0.0)
    X, _ = adjust(truth, _weak_chain(truth), observations(m.map), 0)
    assert _err(X, truth)[0] < 2e-3 and _err(X, truth)[1] < 0.05


def test_a_wrong_association_does_not_bend_the_walls():
    truth = _truth()
    m = _mapped(truth)
    obs = observations(m.map)
    rng = np.random.default_rng(4)
    X0 = truth + np.column_stack([rng.normal(0, 0.02, (len(truth), 2)),
                                  rng.normal(0, np.deg2rad(0.5), len(truth))])
    X0[0] = truth[0]
    # node 5's observations all said to be of the first line: a merge gone wrong
    bad = np.nonzero(obs.node == 5)[0]
    wrong = dataclasses.replace(obs, line=obs.line.copy())
    wrong.line[bad] = (obs.line[bad] + 1) % len(obs.phi)
    X, info = adjust(X0, _weak_chain(X0), wrong, 0)
    assert info["outliers"] >= len(bad) // 2
    others = np.arange(len(truth)) != 5
    assert _err(X[others], truth[others])[0] < 0.01


def test_nothing_to_adjust():
    truth = _truth(4)
    empty = observations(_mapped(truth).map, min_nodes=100)
    X, info = adjust(truth, _weak_chain(truth), empty, 0)
    assert np.array_equal(X, truth) and info["observations"] == 0 and info["iterations"] == 0
    none = associate(Contributions.of(LineMap()), truth)  # a map with nothing in it
    assert len(none) == 0 and len(none.phi) == 0
    assert adjust(truth, _weak_chain(truth), none, 0)[1]["iterations"] == 0


def _contrib(parts) -> Contributions:
    """Contributions from (node, x0, x1, y) horizontal runs of points 2 cm apart."""
    rows = []
    for node, x0, x1, y in parts:
        x = np.arange(x0, x1 + 1e-9, 0.02)
        p = np.column_stack([x, np.full_like(x, y)])
        c = p.mean(0)
        rows.append((node, len(p), c, (p - c).T @ (p - c), p[0], p[-1]))
    node, n, cent, scat, a, b = (np.array(v) for v in zip(*rows, strict=True))
    return Contributions(node, n.astype(float), cent, scat, a, b)


def test_association_is_tighter_than_the_online_map():
    # nodes 0 and 1 see a wall; node 2 a cabinet face 3 cm in front of it, which the online
    # map (merge distance 0.10 m, offset 3 cm) takes for the same wall
    contrib = _contrib([(0, 0.0, 2.0, 1.0), (1, 1.0, 3.0, 1.0), (2, 0.5, 2.5, 1.03)])
    X = np.zeros((3, 3))
    tight = associate(contrib, X)
    assert len(tight.phi) == 1 and sorted(tight.node.tolist()) == [0, 1]
    assert abs(abs(tight.rho[0]) - 1.0) < 1e-6
    loose = associate(contrib, X, AdjustParams(association=MapParams()))
    assert len(loose.phi) == 1 and sorted(loose.node.tolist()) == [0, 1, 2]


def test_contributions_snapshot_is_independent_of_the_map():
    m = _mapped(_truth(6))
    snap = Contributions.of(m.map)
    assert len(snap.node) == int((m.map.c_node >= 0).sum())
    assert np.all(np.diff(snap.node) >= 0)  # node by node, as associate needs
    m.map.c_cent[:] = 0.0
    assert np.abs(snap.cent).max() > 0.1
