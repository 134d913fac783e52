"""Scan differencing (mapping/moving.py): what moved in where an earlier scan saw through
is not mapped."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cgamap.mapping.finishing import NeighbourParams
from cgamap.mapping.moving import MovingParams, moved_in, moved_segments
from cgamap.mapping.slam2d import Mapper, MapperParams
from synth2d import ROOM, scan, world

AMIN, INC = -np.pi / 2, np.pi / 180  # 180 beams over the half plane ahead (+x)


def wall_at(x: float, n: int = 180) -> np.ndarray:
    """Ranges of a scan from the origin facing +x onto the wall x = ``x``."""
    a = AMIN + INC * np.arange(n)
    with np.errstate(divide="ignore"):
        r = x / np.cos(a)
    return np.where((r > 0) & (r < 30.0), r, np.nan)


def test_points_where_the_earlier_beams_went_through_moved_in():
    r = wall_at(6.0)
    pose = (0.0, 0.0, 0.0)
    pts = np.array([[3.0, 0.0],     # in front of the wall: the beam went through it
                    [6.0, 0.5],     # on the wall
                    [7.0, -0.5],    # behind the wall: the earlier scan could not see it
                    [-2.0, 0.0],    # behind the laser: outside its field of view
                    [0.1, 0.0]])    # nearer than min_range
    assert moved_in(pts, pose, r, AMIN, INC).tolist() == [True, False, False, False, False]
    # within the margin of the earlier return: the two poses' errors, not a newcomer
    assert not moved_in([[5.85, 0.0]], pose, r, AMIN, INC)[0]
    # the earlier scan's frame: moved 1 m back, the wall is 7 m ahead of it
    assert moved_in([[3.0, 0.0]], (-1.0, 0.0, 0.0), wall_at(7.0), AMIN, INC)[0]
    assert not moved_in([[6.0, 0.0]], (-1.0, 0.0, 0.0), wall_at(7.0), AMIN, INC)[0]


def test_no_return_and_edges_say_nothing():
    r = wall_at(6.0)
    k = 90  # straight ahead
    for nothing in (np.nan, np.inf, 0.0):  # a beam that returned nothing (glass, black)
        r[k] = nothing
        assert not moved_in([[3.0, 0.0]], (0, 0, 0), r, AMIN, INC)[0]
    # a point at the edge of a box: its own beam returned from the wall behind, the next
    # one from the box, 3 m: the nearest return around the bearing counts
    r = wall_at(6.0)
    r[k + 1] = 3.0
    assert not moved_in([[3.0, 0.0]], (0, 0, 0), r, AMIN, INC)[0]
    assert moved_in([[3.0, 0.0]], (0, 0, 0), r, AMIN, INC,
                    MovingParams(neighbours=0))[0]


def test_a_segment_moved_in_when_a_share_of_it_did():
    r = wall_at(6.0)
    a, b = np.array([[3.0, -1.0], [6.0, -1.0]]), np.array([[3.0, 1.0], [6.0, 1.0]])
    assert moved_segments(a, b, (0, 0, 0), r, AMIN, INC).tolist() == [True, False]
    # across the wall: four of its nine points in front of it, five on or behind it
    a, b = np.array([[4.0, -1.0]]), np.array([[8.0, 1.0]])
    assert moved_segments(a, b, (0, 0, 0), r, AMIN, INC, MovingParams(share=0.4))[0]
    assert not moved_segments(a, b, (0, 0, 0), r, AMIN, INC, MovingParams(share=0.6))[0]
    assert moved_segments(np.zeros((0, 2)), np.zeros((0, 2)), (0, 0, 0), r, AMIN,
                          INC).shape == (0,)


def _drive(step: float, n: int, scene, params: MapperParams) -> Mapper:
    truth = np.column_stack([-2.5 + step * np.arange(n), np.full(n, -1.0), np.zeros(n)])
    m = Mapper(params, initial_pose=truth[0])
    for k, p in enumerate(truth):
        s = scan(scene(k), p, n=360, sigma=0.005, seed=k)
        m.step(s.ranges, s.angle_min, s.angle_increment, p)
    return m


@pytest.mark.parametrize("enabled", [True, False])
def test_a_walking_person_is_not_mapped_and_a_standing_one_is(enabled):
    """Scanning every 5 cm in a room, a person's side walks across it (10 cm a scan, from
    scan 10 on): with the differencing on, none of its sightings is mapped; a person
    standing all along is, and the room's walls never count as moved."""
    room = world(ROOM)
    walking = [world([*ROOM, (-1.5 + 0.1 * k, 1.5, -0.9 + 0.1 * k, 1.5)]) for k in range(30)]
    standing = world([*ROOM, (2.0, 0.5, 2.6, 0.5)])
    MP = MapperParams(neighbours=NeighbourParams(enabled=False))
    MP = replace(MP, moving=replace(MP.moving, enabled=enabled),
                 map=replace(MP.map, age_travel=0.0,  # the rules apart
                             clear=replace(MP.map.clear, enabled=False)))
    m = _drive(0.05, 40, lambda k: walking[k - 10] if 10 <= k < 40 else room, MP)
    mid = 0.5 * (m.map.a + m.map.b)
    on_way = (np.abs(mid[:, 1] - 1.5) < 0.1) & (mid[:, 0] > -1.6) & (mid[:, 0] < 1.6)
    if enabled:
        # each scan that became a node while the person walked saw them (the scans between
        # nodes are tracked, not mapped)
        walked = int((m.node_scan.array() >= 10).sum())
        assert not on_way.any() and m.moved >= walked >= 3
    else:
        assert on_way.any() and m.moved == 0
    m = _drive(0.05, 40, lambda k: standing, MP)
    mid = 0.5 * (m.map.a + m.map.b)
    assert ((np.abs(mid[:, 1] - 0.5) < 0.05) & (np.abs(mid[:, 0] - 2.3) < 0.2)).any()
    assert m.moved == 0


def test_a_full_circle_scan_wraps():
    """A 360-beam scan of a room 6 m round: its last beams and its first are neighbours,
    and a point behind the laser is in its field of view."""
    n = 360
    r = np.full(n, 6.0)
    amin, inc = -np.pi, 2 * np.pi / n
    pts = [[-3.0, 0.0], [-3.0, 0.01], [-6.0, 0.0], [0.0, -3.0]]
    assert moved_in(pts, (0, 0, 0), r, amin, inc).tolist() == [True, True, False, True]
    r[358] = 3.0  # beam 358 sees a box at 3 m: two beams from beam 0, across the wrap
    assert not moved_in([[-3.0, -0.001]], (0, 0, 0), r, amin, inc)[0]
