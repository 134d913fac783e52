"""Free-space evidence (mapping/free_space.py): map segments the laser sees through go."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cgamap.drivers.sim.scanlog import simulated_scans
from cgamap.drivers.sim.world import Mover, get_world
from cgamap.mapping.free_space import seen_through, update_streaks
from cgamap.mapping.linemap import LineMap, MapParams, age_out
from cgamap.mapping.offline import build_map, log_odometry
from cgamap.mapping.slam2d import MapperParams

WALL = ([-5.0, 6.0], [5.0, 6.0])      # a wall 6 m ahead
BOX = ([-0.5, 3.0], [0.5, 3.0])       # a box's side 3 m ahead, 3 m before the wall


def fan(ranges_fn, n: int = 181) -> np.ndarray:
    """Points of a fan of beams from the origin over 30-150 degrees."""
    a = np.radians(np.linspace(30.0, 150.0, n))
    r = ranges_fn(a)
    return np.column_stack([r * np.cos(a), r * np.sin(a)])


def to_wall(a):
    return 6.0 / np.sin(a)


def test_beams_through_a_segment_onto_a_known_wall_count():
    a, b = np.array([BOX[0], WALL[0]]), np.array([BOX[1], WALL[1]])
    through, hits, covered = seen_through(a, b, (0.0, 0.0), fan(to_wall))
    assert through[0] >= 5 and hits[0] == 0      # the box is gone
    assert covered[0] > 0.5
    assert through[1] == 0 and hits[1] > 100     # the wall is there


def test_beams_that_stop_on_a_segment_hit_it():
    def to_box(a):
        x = 3.0 / np.tan(a)
        return np.where(np.abs(x) <= 0.5, 3.0 / np.sin(a), to_wall(a))

    a, b = np.array([BOX[0], WALL[0]]), np.array([BOX[1], WALL[1]])
    through, hits, _ = seen_through(a, b, (0.0, 0.0), fan(to_box))
    assert through[0] == 0 and hits[0] >= 5


def test_no_evidence_without_a_known_wall_behind_or_from_one_alongside():
    # the returns land on nothing the map knows: they say nothing
    through, _, _ = seen_through(np.array([BOX[0]]), np.array([BOX[1]]), (0.0, 0.0),
                                 fan(to_wall))
    assert through[0] == 0
    # the wall just 0.4 m behind the segment: the same wall where a pose error put it
    a = np.array([[-0.5, 5.6], WALL[0]])
    b = np.array([[0.5, 5.6], WALL[1]])
    through, _, _ = seen_through(a, b, (0.0, 0.0), fan(to_wall))
    assert through[0] == 0


def test_an_opened_door_does_not_clear_its_wall():
    # a 5 m wall 3 m ahead, fused with its closed door; now the door (0.9 m) is open and
    # the beams through it reach the wall 6 m ahead, while the rest of the wall is hidden
    # behind a cabinet 2 m ahead (returns short of it: no evidence either way)
    def seen(a):
        x = 3.0 / np.tan(a)
        door = (x > -0.45) & (x < 0.45)
        return np.where(door, to_wall(a), 2.0 / np.sin(a))

    a = np.array([[-2.5, 3.0], WALL[0], [-3.0, 2.0]])
    b = np.array([[2.5, 3.0], WALL[1], [3.0, 2.0]])
    through, hits, covered = seen_through(a, b, (0.0, 0.0), fan(seen))
    assert through[0] > 0 and hits[0] == 0
    assert covered[0] < 0.25
    m = LineMap(a=a, b=b)
    m.last_seen = np.zeros(3, int)
    assert update_streaks(m, np.zeros(2), fan(seen), 1) == 0


def test_drift_since_the_last_tie_withholds_the_evidence():
    a, b = np.array([BOX[0], WALL[0]]), np.array([BOX[1], WALL[1]])
    through, _, _ = seen_through(a, b, (0.0, 0.0), fan(to_wall), drift=np.array([0.0, 0.0]))
    assert through[0] > 0
    # 40 m of travel since the box was last seen, no loop closed: 1.2 m of possible drift
    through, _, _ = seen_through(a, b, (0.0, 0.0), fan(to_wall), drift=np.array([1.2, 1.2]))
    assert through[0] == 0


def two_segment_map() -> LineMap:
    m = LineMap(a=np.array([BOX[0], WALL[0]]), b=np.array([BOX[1], WALL[1]]))
    m.n_obs = np.array([30, 30])
    m.created = np.zeros(2, int)
    m.last_seen = np.zeros(2, int)
    m.n_pts = np.full(2, 40.0)
    m.centroid = 0.5 * (m.a + m.b)
    m.scatter = np.zeros((2, 2, 2))
    return m


def test_streak_of_scans_drops_the_segment_and_a_hit_resets_it():
    m = two_segment_map()
    P = MapParams()
    pts = fan(to_wall)
    for stamp in (1, 2):
        assert update_streaks(m, np.zeros(2), pts, stamp, P.clear) == 1
    assert list(m.through) == [2, 0]
    # the box is back in one scan: the streak starts again
    m.last_seen[0] = 3
    update_streaks(m, np.zeros(2), pts, 3, P.clear)
    assert list(m.through) == [0, 0]
    for stamp in (4, 5, 6):
        update_streaks(m, np.zeros(2), pts, stamp, P.clear)
    assert age_out(m, 6, replace(P, clear=replace(P.clear, enabled=False))) == 0
    assert age_out(m, 6, P) == 1
    assert len(m) == 1 and m.a[0, 1] == pytest.approx(6.0)


def test_streaks_survive_subsets_and_old_states():
    m = two_segment_map()
    m.through = np.array([2, 0])
    assert list(m.subset(np.array([True, False])).through) == [2]
    # a state saved before the field existed (a daemon checkpoint): zeros of the right size
    old = LineMap(a=m.a, b=m.b, through=np.zeros(0, int))
    assert list(old.through) == [0, 0]


@pytest.mark.parametrize("clear", [True, False])
def test_a_cart_that_left_is_cleared_from_the_map(clear):
    # the simulated room, three laps; a cart (0.8 x 0.6 m) stands 1 m off the path during
    # the first lap, then leaves the building (for two laps: the cycle's stand elsewhere)
    w = get_world("room")
    lap = w.path_length / w.speed
    spot, away = (2.3, 2.0), (50.0, 50.0)
    walk = np.hypot(away[0] - spot[0], away[1] - spot[1]) / 100.0
    w.movers.append(Mover((spot, away), speed=100.0, pause=2 * lap, phase=2 * walk + 3 * lap,
                          size=(0.8, 0.6)))
    assert w.movers[0].pose(1.0)[:2] == pytest.approx(spot)
    assert w.movers[0].pose(lap + 2.0)[:2] == pytest.approx(away)
    assert w.movers[0].pose(3 * lap - 2.0)[:2] == pytest.approx(away)
    scans = simulated_scans(w, laps=3.0)
    MP = MapperParams()
    MP = replace(MP, map=replace(MP.map, clear=replace(MP.map.clear, enabled=clear)))
    res = build_map(scans, log_odometry(scans, "high", 0)[0], MP)
    assert res.report["ate_trans_m"] < 0.05
    mid = 0.5 * (res.map.a + res.map.b)
    at_cart = np.hypot(mid[:, 0] - spot[0], mid[:, 1] - spot[1]) < 0.45
    if clear:
        assert not at_cart.any()
        assert res.report["segments_cleared"] >= 1
    else:
        assert at_cart.any()  # what the clearing removes is there without it
        assert res.report["segments_cleared"] == 0


def test_a_loaded_maps_cart_that_left_is_cleared_before_a_loop_closes():
    """A map from an earlier run (a checkpoint) holds a cart that has since gone.  Scans
    matched well to that map tie the laser to it (``Mapper.frozen_tie``), so its segments
    get no drift allowance for this run's travel: the first lap, before this run closes
    any loop of its own, clears the cart (it took the first closure before)."""
    from cgamap.mapping.slam2d import Mapper

    spot = (2.3, 2.0)
    first = get_world("room")
    first.movers.append(Mover((spot, spot), size=(0.8, 0.6)))
    scans = simulated_scans(first, laps=1.0)
    m1 = Mapper(initial_pose=scans[0].pose_ref)
    for s, o in zip(scans, log_odometry(scans, "high", 0)[0], strict=True):
        m1.step(s.ranges, s.angle_min, s.angle_increment, o)
    m1.finish()

    def at_cart(lm) -> int:
        mid = 0.5 * (lm.a + lm.b)
        return int(np.count_nonzero(np.hypot(mid[:, 0] - spot[0], mid[:, 1] - spot[1]) < 0.45))

    before = at_cart(m1.map)
    assert before >= 1
    scans = simulated_scans(get_world("room"), laps=1.0)  # the cart is gone
    m2 = Mapper(initial_pose=scans[0].pose_ref)
    m2.map = m1.map
    for s, o in zip(scans, log_odometry(scans, "high", 1)[0], strict=True):
        m2.step(s.ranges, s.angle_min, s.angle_increment, o)
        assert m2.frozen_tie == m2.count - 1 or m2.count == 1  # every scan matched it
    assert m2.cleared >= 1 and at_cart(m2.map) < before
