"""The finishing pass's raw-point ICP along a scan pair's weak direction
(:func:`cgamap.mapping.finishing.fill_weak`): only where the pair's walls leave the
translation open, only between near-consecutive scans, only what ICP settles both ways."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.mapping.finishing import FillParams, ScanPointCache, fill_weak
from cgamap.mapping.odometry import compose_pose2d, relative
from cgamap.mapping.posegraph import EdgeArrays
from synth2d import scan, world

# a corridor along x (walls at y = +-1) with doorway recesses and a wall across its end 4 m
# on: the edges below are made by hand as a pair whose walls fixed y and the heading alone


def _recess(x0: float, x1: float, y: float, depth: float) -> list:
    return [(x0, y, x0, y + depth), (x0, y + depth, x1, y + depth), (x1, y + depth, x1, y)]


WALLS = [(-6.0, 1.0, 1.6, 1.0), *_recess(1.6, 2.0, 1.0, 0.15), (2.0, 1.0, 3.0, 1.0),
         *_recess(3.0, 3.3, 1.0, 0.15), (3.3, 1.0, 6.0, 1.0),
         (-6.0, -1.0, 1.0, -1.0), *_recess(1.0, 1.4, -1.0, -0.15), (1.4, -1.0, 6.0, -1.0),
         (4.5, -1.0, 4.5, 1.0)]
POSES = np.array([[0.0, 0.0, 0.0], [0.6, 0.05, 0.02], [1.2, -0.05, -0.01]])


def _rays():
    out = []
    for k, p in enumerate(POSES):
        s = scan(world(WALLS), p, n=361, fov=np.pi, sigma=0.003, seed=k)
        out.append((s.ranges.astype(np.float32), s.angle_min, s.angle_increment))
    return out


def _edge(i: int, j: int, along: float, weak: bool = True):
    """A pair edge as the walls would give it: right across the corridor and in heading,
    ``along`` metres wrong along it, and (``weak``) nothing known along it."""
    z = relative(POSES[i], POSES[j])
    c, s = np.cos(POSES[i, 2]), np.sin(POSES[i, 2])
    world_x = np.array([c, -s])  # the corridor's direction, in pose i's frame
    z[:2] += along * world_x
    across = np.array([s, c])
    info = np.zeros((3, 3))
    info[:2, :2] = np.outer(across, across) / 0.01 ** 2
    if not weak:
        info[:2, :2] += np.outer(world_x, world_x) / 0.01 ** 2
    info[2, 2] = 1 / np.radians(0.2) ** 2
    return z, info, world_x


def test_a_weak_pair_takes_icps_answer_along_its_weak_direction():
    # the estimate 3 cm off along the corridor (the wheels' error), and the edge with it
    z, info, along = _edge(0, 1, 0.03)
    E = EdgeArrays.of([0], [1], z, info)
    X = POSES.copy()
    X[1] = compose_pose2d(X[0], z)
    got = fill_weak(E, X, ScanPointCache(_rays()), FillParams())
    truth = relative(POSES[0], POSES[1])
    # along the corridor: ICP's answer (the truth, to millimetres); across and in heading:
    # the walls' as they were
    assert abs((got.z[0, :2] - truth[:2]) @ along) < 0.005
    across = np.array([-along[1], along[0]])
    assert (got.z[0, :2] - z[:2]) @ across == pytest.approx(0.0, abs=1e-12)
    assert got.z[0, 2] == z[2]
    added = got.info[0] - info
    assert added[:2, :2] == pytest.approx(np.outer(along, along) / 0.03 ** 2, rel=1e-6)
    assert np.all(added[2] == 0) and np.all(added[:, 2] == 0)


def test_what_is_left_as_the_walls_gave_it():
    rays = _rays()
    z1, i1, _ = _edge(0, 1, 0.12, weak=False)     # the walls knew both directions
    z2, i2, _ = _edge(0, 2, 0.12)                  # weak, but two steps apart ...
    E = EdgeArrays.of([0, 0], [1, 2], [z1, z2], [i1, i2])
    got = fill_weak(E, POSES, ScanPointCache(rays), FillParams(previous=1))  # ... one allowed
    assert np.array_equal(got.z, E.z) and np.array_equal(got.info, E.info)
    # the estimate farther from ICP's answer than max_move: a wrong start, left alone
    z, info, _ = _edge(0, 1, 0.12)
    X = POSES.copy()
    X[1, 0] += 0.8
    E = EdgeArrays.of([0], [1], z, info)
    got = fill_weak(E, X, ScanPointCache(rays), FillParams())
    assert np.array_equal(got.z, E.z)
    # a node without its raw scan (a mapper that kept none): left alone
    got = fill_weak(E, POSES, ScanPointCache([rays[0], None, rays[2]]), FillParams())
    assert np.array_equal(got.z, E.z)


def test_the_mapper_keeps_each_nodes_raw_scan_for_the_pass():
    from dataclasses import replace

    from cgamap.mapping.slam2d import Mapper, MapperParams

    poses = np.column_stack([np.linspace(0.0, 3.0, 7), np.zeros(7), np.zeros(7)])
    for fill in (True, False):
        P = MapperParams()
        P = replace(P, neighbours=replace(P.neighbours, fill=FillParams(enabled=fill)))
        m = Mapper(P, initial_pose=poses[0])
        for p in poses:
            s = scan(world(WALLS), p, n=181, fov=np.pi, sigma=0.003)
            m.step(s.ranges, s.angle_min, s.angle_increment, p)
        assert m.count == len(m.scans) == len(m.rays) == 7
        job = m.finishing_job()
        assert len(job.rays) == 7
        if fill:
            r, amin, inc = m.rays[3]
            assert r.dtype == np.float32 and len(r) == 181 and inc == pytest.approx(np.pi / 181)
        else:
            assert all(r is None for r in m.rays)
        m.compact(3)
        assert len(m.rays) == len(m.scans) == m.count
