"""The mapping loop without threads: odometry interpolation, scan gating, loss detection and
relocalisation, the pose between scans, state round trip, 3D frames."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.daemon import config as config_mod
from cgamap.daemon.loop import MappingLoop, PoseHistory
from cgamap.drivers.messages import LaserScan, OdometryPose
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.odometry import compose_pose2d as compose
from cgamap.mapping.posegraph import relative


def cfg(**mapping) -> dict:
    return config_mod.validate({"mapping": {"map3d": False, **mapping}})


def scan_at(world, t: float, seq: int, stamp_ns: int) -> LaserScan:
    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    r = world.raycast(*world.trajectory(t), angles, 30.0)
    r[~np.isfinite(r)] = np.nan
    return LaserScan(seq=seq, stamp_ns=stamp_ns, angle_min=float(angles[0]),
                     angle_increment=float(angles[1] - angles[0]), ranges=r)


def test_pose_history_interpolates_across_the_wrap():
    h = PoseHistory()
    h.add(0, (0.0, 0.0, np.pi - 0.1))
    h.add(100, (1.0, 2.0, -np.pi + 0.1))
    p = h.at(50)
    assert p[:2] == pytest.approx([0.5, 1.0]) and abs(abs(p[2]) - np.pi) < 1e-9
    assert h.at(-5)[0] == 0.0 and h.at(500)[0] == 1.0
    h.add(50, (9, 9, 9))  # out of order: ignored
    assert len(h) == 2


def test_relative_and_compose_are_inverse():
    a, b = np.array([1.0, -2.0, 0.7]), np.array([-0.5, 3.0, -2.9])
    assert compose(a, relative(a, b)) == pytest.approx(b)


def test_scan_waits_for_odometry_then_uses_the_interpolated_guess():
    loop = MappingLoop(cfg(), mapper2d=None, devices={})
    world = get_world("corridor")
    loop.handle("base", OdometryPose(stamp_ns=0, x=0.0, y=0.0, theta=0.0))
    loop.handle("laser", scan_at(world, 0.0, 0, 50))
    assert loop.process() == 0  # odometry not yet past the scan
    loop.handle("base", OdometryPose(stamp_ns=100, x=1.0, y=0.0, theta=0.0))
    assert loop.process() == 1
    assert loop.last_scan_odom[0] == pytest.approx(0.5)
    # between scans the pose follows odometry
    loop.handle("base", OdometryPose(stamp_ns=200, x=2.0, y=0.0, theta=0.0))
    assert loop.current_pose()[0] == pytest.approx(1.5)


def test_a_given_laser_mount_replaces_the_configured_one():
    devices = {"lms": {"role": "laser", "mount": {"x": 0.2, "y": 0.0, "yaw": 0.0}}}
    assert MappingLoop(cfg(), devices=devices).status()["laser_mount"] == [0.2, 0.0, 0.0]
    loop = MappingLoop(cfg(), devices=devices, laser_mount=(0.25, -0.05, 0.03))
    assert loop.status()["laser_mount"] == [0.25, -0.05, 0.03]
    assert loop.mapper.m.params.mount == (0.25, -0.05, 0.03)
    # a log whose laser is the robot's centre: no mount, whatever the configuration says
    assert MappingLoop(cfg(), devices=devices, laser_mount=(0, 0, 0)).status()[
        "laser_mount"] is None


def test_standing_robot_does_not_grow_the_map():
    loop = MappingLoop(cfg(scan_max_rate=100.0), devices={})
    world = get_world("corridor")
    for i in range(30):
        loop.handle("base", OdometryPose(stamp_ns=i * 20_000_000, x=0.0, y=0.0, theta=0.0))
        loop.handle("laser", scan_at(world, 0.0, i, i * 20_000_000 + 1))
        loop.process(odometry_live=False)
    # one scan, then one per 20 rate periods (a standing robot still refreshes slowly)
    assert loop.counts["scans"] == 3 and loop.counts["scans_skipped"] == 27


def test_a_scan_stamped_before_the_last_mapped_one_is_skipped_and_said(caplog):
    # a log with stamps that go back (Intel has four): never mapped out of order, counted
    loop = MappingLoop(cfg(min_travel=0.0, min_turn=0.0, scan_max_rate=1000.0), devices={})
    world = get_world("corridor")
    stamps = [0, 100, 200, 150, 300, 120, 400]
    for i, t in enumerate(stamps):
        ns = t * 1_000_000
        loop.handle("base", OdometryPose(stamp_ns=ns, x=0.01 * t, y=0.0, theta=0.0))
        loop.handle("laser", scan_at(world, 0.01 * t / world.speed, i, ns + 1))
        with caplog.at_level("WARNING"):
            loop.process(odometry_live=False)
    assert loop.counts["scans"] == 5 and loop.counts["scans_out_of_order"] == 2
    said = [r.getMessage() for r in caplog.records if "before the last mapped" in r.getMessage()]
    assert said and "0.050 s" in said[0] and "(1 so far)" in said[0]


class FakeMapper:
    def __init__(self, quality):
        self.quality = quality
        self.reloc_calls = 0
        self.slips = 0
        self.cleared = 0
        self.moved = 0
        self.p = np.zeros(3)

    def step(self, scan, odom):
        self.p = np.asarray(odom, float)
        return self.p.copy(), self.quality, 3

    def segments(self):
        return np.zeros((0, 4))

    def set_pose(self, pose):
        self.p = np.asarray(pose, float)

    def relocalize(self, scan, near=None):
        self.reloc_calls += 1
        return np.array([5.0, 6.0, 0.5]), 0.9, []


def _lose_track(fake: FakeMapper, lost_radius: float = 0.0) -> MappingLoop:
    """A loop whose matches stay poor for ``lost_after`` scans: it relocalises (with
    ``lost_radius`` 0, once, over the whole map)."""
    loop = MappingLoop(cfg(lost_quality=0.2, lost_after=4, min_travel=0.0, min_turn=0.0,
                           scan_max_rate=1000.0, lost_radius=lost_radius),
                       mapper2d=fake, devices={})
    world = get_world("corridor")
    for i in range(4):
        loop.handle("laser", scan_at(world, 0.1 * i, i, (i + 1) * 10_000_000))
        loop.process(odometry_live=False)
    return loop


def test_low_quality_for_long_triggers_relocalisation():
    fake = FakeMapper(0.05)
    loop = _lose_track(fake)
    world = get_world("corridor")
    assert fake.reloc_calls == 1 and loop.counts["relocalized"] == 1
    assert loop.current_pose().tolist() == [5.0, 6.0, 0.5]
    fake.quality = 0.9
    loop.handle("laser", scan_at(world, 0.5, 9, 90_000_000))
    loop.process(odometry_live=False)
    assert not loop.lost


def test_a_lost_robot_does_not_jump_to_an_ambiguous_pose():
    """A look-alike place scoring as well: the lost robot's own attempt keeps its pose and
    says why; asked for, relocalisation takes the best pose and names the rival."""

    class LookAlike(FakeMapper):
        def relocalize(self, scan, near=None):
            self.reloc_calls += 1
            return np.array([5.0, 6.0, 0.5]), 0.9, [(np.array([15.0, 6.0, 0.5]), 0.88)]

    fake = LookAlike(0.05)
    loop = _lose_track(fake)
    assert fake.reloc_calls == 1 and loop.counts["relocalize_ambiguous"] == 1
    assert loop.counts["relocalized"] == 0
    assert loop.current_pose().tolist() != [5.0, 6.0, 0.5]
    got = loop.relocalize()
    assert got["ok"] and got["ambiguous"] and got["alternatives"] == [[15.0, 6.0, 0.5, 0.88]]
    assert loop.current_pose().tolist() == [5.0, 6.0, 0.5]


def _drive(loop: MappingLoop, world, n: int) -> None:
    """n scans along the world's path, 0.25 s apart, each with the odometry of its instant."""
    for i in range(n):
        t = 0.25 * i
        x, y, th = world.trajectory(t)
        stamp = int(t * 1e9) + 1
        loop.handle("base", OdometryPose(stamp_ns=stamp - 1, x=x, y=y, theta=th))
        loop.handle("laser", scan_at(world, t, i, stamp))
        loop.process(odometry_live=False)


def test_real_mapper_state_round_trip_and_relocalisation():
    world = get_world("room")
    loop = MappingLoop(cfg(min_travel=0.0, min_turn=0.0, scan_max_rate=1000.0), devices={})
    _drive(loop, world, 40)
    n = len(loop.segments())
    assert n >= 4
    st = loop.state()
    again = MappingLoop(cfg(), devices={})
    again.load_state(st)
    assert len(again.segments()) == n
    assert again.current_pose() == pytest.approx(loop.current_pose())
    before = loop.current_pose()  # in the map frame (it starts at the first scan's pose)
    res = loop.relocalize()
    print("relocalize:", res, "tracked:", before)
    assert res["ok"], res  # a plain room: the pose is found, where tracking had the robot
    assert np.hypot(*(np.array(res["pose"][:2]) - before[:2])) < 0.3
    # the map's distance field is built once while the map stays as it is
    field = loop.mapper._field
    assert loop.relocalize()["ok"] and loop.mapper._field is field
    x, y, th = world.trajectory(10.0)
    loop.handle("base", OdometryPose(stamp_ns=10_000_000_000, x=x, y=y, theta=th))
    loop.handle("laser", scan_at(world, 10.0, 40, 10_000_000_001))
    loop.process(odometry_live=False)
    loop.relocalize()
    assert loop.mapper._field is not field  # a new scan changed the map


def test_a_failing_step_loses_the_message_not_the_loop():
    class Broken(FakeMapper):
        def step(self, scan, odom):
            raise FloatingPointError("bad scan")

    loop = MappingLoop(cfg(), mapper2d=Broken(0.5), devices={})
    loop.handle("laser", scan_at(get_world("corridor"), 0.0, 0, 10))
    loop.process(odometry_live=False)
    assert loop.counts["errors_scan"] == 1 and loop.counts.get("scans", 0) == 0


def test_the_daemon_bounds_its_pose_graph():
    """A daemon runs for months: its mapper keeps the newest nodes (params2d.max_nodes,
    20 000 unless set) and skips the finishing pass's per-scan store."""
    loop = MappingLoop(cfg(), devices={})
    assert loop.mapper.m.params.max_nodes == 20_000
    assert not loop.mapper.m.params.neighbours.enabled
    small = MappingLoop(cfg(min_travel=0.0, min_turn=0.0, scan_max_rate=1000.0,
                            params2d={"max_nodes": 12}), devices={})
    _drive(small, get_world("room"), 40)
    assert 0 < small.mapper.m.count <= 12
    assert len(small.segments()) >= 4  # the map outlives the dropped nodes


def test_nested_mapper_parameters_reach_the_mapper():
    """params2d sets nested parameters too: a building with glass walls turns the
    free-space clearing off (map.clear.enabled), and the daemon's own settings stay."""
    assert MappingLoop(cfg(), devices={}).mapper.m.params.map.clear.enabled
    loop = MappingLoop(cfg(params2d={"map": {"clear": {"enabled": False, "scans": 5}},
                                     "seq_sigma": [0.02, 0.01]}), devices={})
    P = loop.mapper.m.params
    assert not P.map.clear.enabled and P.map.clear.scans == 5
    assert P.map.age_scans == 12 and P.seq_sigma == (0.02, 0.01)
    assert P.max_nodes == 20_000 and not P.neighbours.enabled


@pytest.mark.parametrize("push", ["turn", "sideways"])
def test_a_push_the_wheels_did_not_see_is_counted_and_mapped_through(push):
    # from the 21st scan on the odometry reports the heading 3.7 deg short (the robot was
    # pushed round), or the robot half a metre to its right (pushed sideways, or its wheels
    # spun): the mapper finds the scan again from the walls, and the daemon counts it
    loop = MappingLoop(cfg(min_travel=0.0, min_turn=0.0, scan_max_rate=1000.0), devices={})
    world = get_world("loop")
    ts = np.arange(40) * 0.1 / world.speed
    th20 = world.trajectory(ts[20])[2]
    error = ([0.0, 0.0, 0.065] if push == "turn"
             else [-0.5 * np.sin(th20), 0.5 * np.cos(th20), 0.0])
    for i, t in enumerate(ts):
        truth = np.array(world.trajectory(t), dtype=float)
        odo = truth - (np.array(error) if i >= 20 else 0.0)
        ns = int(t * 1e9)
        loop.handle("base", OdometryPose(stamp_ns=ns, x=odo[0], y=odo[1], theta=odo[2]))
        loop.handle("laser", scan_at(world, t, i, ns))
        loop.handle("base", OdometryPose(stamp_ns=ns + 1, x=odo[0], y=odo[1], theta=odo[2]))
        loop.process(odometry_live=False)
    assert loop.counts["scans"] == 40 and loop.counts["slips_recovered"] >= 1
    moved = relative(np.array(world.trajectory(ts[0])), np.array(world.trajectory(ts[-1])))
    err = relative(moved, loop.current_pose())  # the map's frame starts at the first scan
    assert np.hypot(*err[:2]) < 0.05 and abs(np.rad2deg(err[2])) < 0.5


def test_people_on_the_move_are_counted_not_mapped():
    """A cart crossing 3 m ahead of the robot, to and fro: the daemon's status counts the
    sightings the mapper left out (segments_moving), and the map has none of them off the
    world's walls."""
    from cgamap.drivers.sim.world import Mover
    from cgamap.mapping.matching import segment_distances

    loop = MappingLoop(cfg(min_travel=0.0, min_turn=0.0, scan_max_rate=1000.0), devices={})
    world = get_world("loop")
    ts = np.arange(60) * 0.1 / world.speed
    x, y, th = world.trajectory(ts[30])
    ahead = np.array([x + 3 * np.cos(th), y + 3 * np.sin(th)])
    fwd, side = np.array([np.cos(th), np.sin(th)]), np.array([-np.sin(th), np.cos(th)])
    way = (tuple(ahead - 1.5 * side), tuple(ahead + 1.5 * side))
    world.movers.append(Mover(way, speed=1.0, size=(0.6, 0.8)))
    angles = np.linspace(-np.pi / 2, np.pi / 2, 361)
    for i, t in enumerate(ts):
        pose = np.array(world.trajectory(t), dtype=float)
        r = world.raycast(*pose, angles, 30.0, t=t)
        ns = int(t * 1e9)
        loop.handle("base", OdometryPose(stamp_ns=ns, x=pose[0], y=pose[1], theta=pose[2]))
        loop.handle("laser", LaserScan(seq=i, stamp_ns=ns, angle_min=float(angles[0]),
                                       angle_increment=float(angles[1] - angles[0]),
                                       ranges=np.where(np.isfinite(r), r, np.nan)))
        loop.handle("base", OdometryPose(stamp_ns=ns + 1, x=pose[0], y=pose[1], theta=pose[2]))
        loop.process(odometry_live=False)
    assert loop.counts["scans"] == 60 and loop.counts["segments_moving"] >= 5
    seg = loop.mapper.segments()  # in the map's frame: its first scan's pose is the origin
    T = np.array(world.trajectory(ts[0]), dtype=float)
    c, s = np.cos(T[2]), np.sin(T[2])
    mid = 0.5 * (seg[:, :2] + seg[:, 2:]) @ np.array([[c, s], [-s, c]]) + T[:2]
    d = mid - ahead
    W = world.segments
    off = segment_distances(mid, W[:, :2], W[:, 2:]).min(axis=1) > 0.25
    bad = off & (np.abs(d @ side) < 1.6) & (np.abs(d @ fwd) < 0.5)
    assert len(seg) and not bad.any()


def test_3d_parameters_reach_the_plane_detector():
    """params3d is checked when the config loads and built once: its frame keys (stride,
    max_depth, method) and the plane detector's fields (max_planes) act on a frame."""
    from cgamap.drivers.sim.stereo_render import SyntheticGrabber

    frame = SyntheticGrabber("corridor", pose=(3.0, 0.0, 0.0), tilt=0.2, seed=1).grab()

    def detected(**params3d) -> int:
        loop = MappingLoop(config_mod.validate({"mapping": {"params3d": params3d}}),
                           devices={})
        loop.on_frame(frame)
        return next(e["detected"] for e in loop.events if e["class"] == "planes")

    assert detected(stride=4, max_depth=6.0) >= 3  # two walls and the floor at least
    assert detected(stride=4, max_depth=6.0, max_planes=1) == 1
    assert detected(stride=4, max_depth=6.0, method="hough", max_planes=2) == 2
    loop = MappingLoop(config_mod.validate({"mapping": {"params3d": {"stride": 3}}}),
                       devices={})
    assert loop.frames3d.stride == 3 and loop.plane_params.threshold == 0.02


def test_a_hint_picks_the_look_alike_place_it_names():
    """``Mapper2D.relocalize(scan, near=...)``: in a box both the true pose and its point
    mirror fit a full-circle scan; a hint near either one gives that one, with no rival;
    a hint near neither gives no pose."""
    from cgamap.daemon.loop import Mapper2D
    from synth2d import scan, scanned_map, world

    w = world([(-4, -2, 4, -2), (4, -2, 4, 2), (4, 2, -4, 2), (-4, 2, -4, -2)])
    m = Mapper2D(None, {})
    m.m.map = scanned_map(w, [(0.0, 0.0, 0.0)])
    p = np.array([1.0, 0.5, 0.3])
    s = scan(w, p, n=720, fov=2 * np.pi)
    pose, _, alts = m.relocalize(s)
    mirror = np.array([-1.0, -0.5, 0.3 - np.pi])
    places = [pose, *[a for a, _ in alts]]
    for want in (p, mirror):
        assert any(np.hypot(*(q[:2] - want[:2])) < 0.05 for q in places)
        got, _, alts = m.relocalize(s, near=(want + [0.4, -0.3, 0.1], 1.0, 0.3))
        assert np.hypot(*(got[:2] - want[:2])) < 0.05 and not alts
    assert m.relocalize(s, near=(np.array([3.0, -1.5, 1.9]), 0.3, 0.1)) is None


def test_a_lost_robot_looks_near_its_pose_first():
    """With ``lost_radius``, the lost robot's first try is within that radius of the pose
    it had (the hint names it); found there, it jumps and counts ``relocalized_near``.
    Found nowhere near, the whole map is tried next, as without the radius."""

    class Near(FakeMapper):
        def __init__(self, quality, near_answer):
            super().__init__(quality)
            self.nears, self.near_answer = [], near_answer

        def relocalize(self, scan, near=None):
            self.reloc_calls += 1
            self.nears.append(near)
            self.at_call = self.p.copy()  # the pose the mapper gave last
            if near is not None:
                return None if self.near_answer is None else (self.near_answer, 0.9, [])
            return np.array([5.0, 6.0, 0.5]), 0.9, []

    fake = Near(0.05, np.array([0.3, 0.1, 0.0]))
    loop = _lose_track(fake, lost_radius=2.5)
    assert fake.reloc_calls == 1 and fake.nears[0][1] == 2.5
    assert np.allclose(fake.nears[0][0], fake.at_call)  # the hint: the pose it had
    assert loop.counts["relocalized_near"] == 1 and loop.counts["relocalized"] == 1
    assert loop.current_pose().tolist() == [0.3, 0.1, 0.0]

    class Weak(Near):  # a pose near the hint that fits too little of the scan: no answer
        def relocalize(self, scan, near=None):
            got = super().relocalize(scan, near)
            return got if near is None else (got[0], 0.6, [])

    fake = Weak(0.05, np.array([0.3, 0.1, 0.0]))
    loop = _lose_track(fake, lost_radius=2.5)
    assert fake.reloc_calls == 2 and loop.counts["relocalized_near"] == 0
    assert loop.current_pose().tolist() == [5.0, 6.0, 0.5]

    fake = Near(0.05, None)  # nothing fits near: the whole map
    loop = _lose_track(fake, lost_radius=2.5)
    assert fake.reloc_calls == 2 and fake.nears[0] is not None and fake.nears[1] is None
    assert loop.counts["relocalized_near"] == 0 and loop.counts["relocalized"] == 1
    assert loop.current_pose().tolist() == [5.0, 6.0, 0.5]


@pytest.mark.parametrize("lossless", [False, True])
def test_scans_arriving_faster_than_mapped(lossless):
    # 150 scans handed over at once, each with its odometry (a log of ROBOTLASER1 lines
    # drained from a replay's queue): a live loop keeps the newest 64 waiting and counts the
    # rest dropped; a lossless one (a replay as fast as the mapper goes) maps them all
    loop = MappingLoop(cfg(min_travel=0.0, min_turn=0.0, scan_max_rate=1000.0), devices={},
                       lossless=lossless)
    world = get_world("corridor")
    for i in range(150):
        s = scan_at(world, 0.05 * i, i, (i + 1) * 10_000_000)
        x, y, th = world.trajectory(0.05 * i)
        s.pose_odom = (float(x), float(y), float(th))
        loop.handle("replay", s)
    loop.process(final=True)
    if lossless:
        assert loop.counts["scans"] == 150 and loop.counts["scans_dropped"] == 0
    else:
        assert loop.counts["scans"] == 64 and loop.counts["scans_dropped"] == 86
