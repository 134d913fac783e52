"""The simulated 2D world: ray casting against known geometry, trajectory, noise."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.drivers.sim.world import WORLDS, NoiseModel, Wall, World, get_world


def box_world() -> World:
    walls = [Wall(-1, -1, 3, -1), Wall(3, -1, 3, 1), Wall(3, 1, -1, 1), Wall(-1, 1, -1, -1)]
    return World("box", walls, np.array([[0.0, 0.0], [1, 0], [1, 0.5], [0, 0.5]]))


def test_raycast_known_distances():
    w = box_world()
    angles = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2, np.pi / 4])
    r = w.raycast(0.0, 0.0, 0.0, angles)
    np.testing.assert_allclose(r, [3.0, 1.0, 1.0, 1.0, np.sqrt(2.0)], atol=1e-12)
    # heading rotates the fan
    r2 = w.raycast(0.0, 0.0, np.pi / 2, np.array([0.0, -np.pi / 2]))
    np.testing.assert_allclose(r2, [1.0, 3.0], atol=1e-12)


def test_raycast_max_range_and_open_world():
    w = World("one", [Wall(2, -1, 2, 1)], np.zeros((3, 2)))
    r = w.raycast(0, 0, 0, np.array([0.0, np.pi, 0.1]), max_range=10)
    assert r[0] == pytest.approx(2.0)
    assert np.isinf(r[1])
    assert r[2] == pytest.approx(2.0 / np.cos(0.1))
    assert np.isinf(w.raycast(0, 0, 0, np.array([0.0]), max_range=1.5)[0])


def test_raycast_matches_brute_force():
    w = get_world("room")
    rng = np.random.default_rng(1)
    angles = rng.uniform(-np.pi, np.pi, 50)
    x, y = 2.0, 1.5
    r = w.raycast(x, y, 0.3, angles)
    for a, ri in zip(angles, r, strict=True):  # per-beam reference: march along the ray
        d = np.array([np.cos(a + 0.3), np.sin(a + 0.3)])
        best = np.inf
        for s in w.segments:
            m = np.array([[d[0], s[0] - s[2]], [d[1], s[1] - s[3]]])
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            t, u = np.linalg.solve(m, np.array([s[0] - x, s[1] - y]))
            if t > 0 and 0 <= u <= 1:
                best = min(best, t)
        assert ri == pytest.approx(best, abs=1e-9)


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_trajectory_is_smooth_closed_and_inside(name):
    w = get_world(name)
    period = w.path_length / w.speed
    t = np.linspace(0, period, 2000)
    x, y, th = w.trajectory(t)
    assert np.allclose(w.trajectory(0.0), w.trajectory(period), atol=1e-6)
    assert w.trajectory(12.3) == w.trajectory(12.3)  # deterministic
    step = np.hypot(np.diff(x), np.diff(y))
    assert step.max() < 2 * w.speed * period / 2000 + 1e-6
    dth = np.angle(np.exp(1j * np.diff(th)))
    assert np.abs(dth).max() < 0.2
    # heading follows the direction of motion
    mov = np.arctan2(np.diff(y), np.diff(x))
    assert np.abs(np.angle(np.exp(1j * (mov - th[:-1])))).max() < 0.1
    # the robot keeps clear of every wall: all ranges around it > 0.25 m
    fan = np.linspace(-np.pi, np.pi, 72, endpoint=False)
    for i in range(0, 2000, 50):
        assert w.raycast(x[i], y[i], th[i], fan).min() > 0.25


def test_noise_model():
    rng = np.random.default_rng(0)
    r = np.full(20000, 5.0)
    r[:100] = np.inf
    out = NoiseModel(sigma=0.02, dropout=0.1).apply(r, rng)
    assert np.isnan(out[:100]).all()
    rest = out[100:]
    frac = np.isnan(rest).mean()
    assert 0.08 < frac < 0.12
    assert abs(np.nanstd(rest) - 0.02) < 0.002
    assert NoiseModel(0.0).apply(np.array([1.0, np.inf]), rng)[0] == 1.0


def test_heights_and_unknown_world():
    w = get_world("room")
    assert w.heights.shape == (len(w.walls), 2)
    assert (w.heights[:, 1] > 0).all()
    with pytest.raises(ValueError, match="unknown world"):
        get_world("moon")


def test_simulated_log_is_deterministic_and_true():
    from cgamap.drivers.sim.scanlog import simulated_scans

    w = get_world("hall")
    a = simulated_scans(w, laps=0.1, seed=3)
    b = simulated_scans(w, laps=0.1, seed=3)
    assert len(a) == len(b) > 5
    np.testing.assert_array_equal(a[4].ranges, b[4].ranges)
    # poses are the path's truth, and ranges are the ray cast plus the noise
    t = (a[4].stamp_ns * 1e-9) - 1.0
    assert a[4].pose_ref == pytest.approx(w.trajectory(t))
    clean = w.raycast(*w.trajectory(t), a[4].angle_min + a[4].angle_increment * np.arange(180),
                      80.0)
    ok = np.isfinite(a[4].ranges) & np.isfinite(clean)
    assert ok.mean() > 0.9
    assert np.abs(a[4].ranges[ok] - clean[ok]).max() < 0.1
    with pytest.raises(ValueError, match="positive"):
        simulated_scans(w, laps=0.0)


def test_mover_walks_its_route_and_stands_at_each_stop():
    from cgamap.drivers.sim.world import Mover

    m = Mover(((0.0, 0.0), (4.0, 0.0)), speed=2.0, pause=3.0)  # 2 s a way, 3 s a stop
    assert m.pose(1.0) == pytest.approx((2.0, 0.0, 0.0))        # half way out
    assert m.pose(3.5)[:2] == pytest.approx((4.0, 0.0))          # standing at the far stop
    x, y, h = m.pose(6.0)                                         # half way back
    assert (x, y) == pytest.approx((2.0, 0.0)) and abs(h) == pytest.approx(np.pi)
    assert m.pose(9.0)[:2] == pytest.approx((0.0, 0.0))          # home, standing
    assert m.pose(11.0) == pytest.approx(m.pose(1.0))            # the cycle is 10 s
    e = Mover(((1.0, 2.0),), size=(0.4, 0.2)).edges(0.0)
    assert e.shape == (4, 4)
    assert e[:, [0, 2]].min() == pytest.approx(0.8) and e[:, [1, 3]].max() == pytest.approx(2.1)


def test_a_scan_sees_movers_where_they_are_at_its_time():
    from cgamap.drivers.sim.world import Mover

    w = box_world()
    # a person walking across the beam 2 m ahead of the origin, on it at t = 1
    w.movers.append(Mover(((2.0, -3.0), (2.0, 3.0)), speed=3.0, pause=100.0,
                          phase=102.0, size=(0.3, 0.5)))
    beam = np.array([0.0])
    assert w.raycast(0.0, 0.0, 0.0, beam)[0] == pytest.approx(3.0)            # walls only
    assert w.raycast(0.0, 0.0, 0.0, beam, t=1.0)[0] == pytest.approx(1.75)    # its near side
    assert w.raycast(0.0, 0.0, 0.0, beam, t=0.5)[0] == pytest.approx(3.0)     # not yet there
    assert get_world("expo").movers and not get_world("hall").movers
