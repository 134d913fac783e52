"""cgamapd end to end: twins + daemon subprocess, READY on a fake notify socket, drive, query,
pose error against the simulation's truth, CLI exports and recording, SIGTERM, checkpoint,
restart from the checkpoint, replay of the recording."""

from __future__ import annotations

import json
import math
import shutil
import stat
import subprocess
import sys

import numpy as np
import pytest
from cgamap.daemon.demo import Driver, map_error, truth_error
from cgamap.daemon.export import read_ply_counts
from cgamap.daemon.recording import read_messages
from cgamap.drivers.messages import LaserScan, WheelTicks
from cgamap.drivers.sim.world import get_world
from cgamap.mapping.evaluation import apply_pose
from daemon_stack import DaemonProc, short_dir, stack_config, start_twin, wait_until

GEOM = {"wheel_radius": 0.05, "track_width": 0.30}


def same_view(world, alignment, pose_a, pose_b) -> float:
    """Share of a 270 degree laser fan's beams (0.25 degree steps) that see the same range
    (within 0.15 m + 2 %) from two map-frame poses, ``alignment`` moving them into the world.
    The 'loop' world's corridors and corners look alike from several places (half a turn
    round its block, or one corner seen from its other corridor), so a relocalisation may
    rightly land at any of them: it is judged by what the robot would see there."""
    to_world = np.asarray(alignment, dtype=float)
    fan = np.deg2rad(np.arange(-135.0, 135.01, 0.25))
    ra, rb = (world.raycast(*apply_pose(to_world, np.asarray(p, dtype=float)), fan, 30.0)
              for p in (pose_a, pose_b))
    return float(np.mean(np.abs(ra - rb) < 0.15 + 0.02 * ra))


def cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    # not `-m cgamap.daemon.cli`: that would load cli twice (two UsageError classes)
    code = "import sys; from cgamap.daemon.cli import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture
def stack(tmp_path):
    laser = start_twin("hokuyo", world="loop")
    base = start_twin("modbus-base")
    run = short_dir()
    daemons: list[DaemonProc] = []
    # drive from the start: the laser twin's robot moves on the twin's clock from its start
    driver = Driver(base.url, get_world("loop"), laser.started_ns, GEOM)
    driver.start()

    def daemon(**kw) -> DaemonProc:
        cfg = stack_config(laser, base, camera_world="loop", epoch_ns=laser.started_ns)
        d = DaemonProc(cfg, tmp_path, run, **kw)
        daemons.append(d)
        return d

    try:
        yield daemon, driver, tmp_path
    finally:
        driver.stop_event.set()
        if driver.is_alive():
            driver.join(5)
        for d in daemons:
            d.stop()
        laser.stop()
        base.stop()
        shutil.rmtree(run, ignore_errors=True)


def test_end_to_end(stack):
    daemon, driver, tmp = stack
    d = daemon()
    d.wait_ready()
    assert stat.S_IMODE(d.socket.stat().st_mode) == 0o660
    # READY waits for the devices to stream (up to supervisor.ready_timeout)
    first = {x["name"]: x["messages"] for x in d.ask("status")["devices"]}
    assert first["laser"] > 0 and first["base"] > 0
    assert wait_until(lambda: d.ask("status")["counts"].get("scans", 0) >= 60, 90), \
        d.log_text()
    st = d.ask("status")
    states = {x["name"]: x["state"] for x in st["devices"]}
    assert states["laser"] == "running" and states["base"] == "running"
    assert states["head"] == "disabled"
    assert wait_until(lambda: d.ask("status")["map"]["planes"] >= 1, 60), d.log_text()
    # the walls mapped by now depend on where the twin's robot was when mapping began (later
    # on a busy machine: the walls behind it out of sight): wait for the ones the exports need
    assert wait_until(lambda: d.ask("status")["map"]["segments"] >= 5, 60), d.log_text()

    # the CLI against the socket: status, exports, a short recording
    sock = str(d.socket)
    out = cli("status", "--socket", sock)
    assert out.returncode == 0 and "laser" in out.stdout, out.stderr
    for fmt in ("png", "pgm", "ply", "json"):
        res = cli("map", "export", "--socket", sock, "--format", fmt, "-o", str(tmp / f"m.{fmt}"))
        assert res.returncode == 0, res.stderr
    assert (tmp / "m.png").stat().st_size > 1000 and (tmp / "m.yaml").exists()
    assert read_ply_counts(tmp / "m.ply")[1] >= 5
    assert len(json.loads((tmp / "m.json").read_text())["segments"]) >= 4
    rec = cli("record", "--socket", sock, "--duration", "3", str(tmp / "run.mcap"))
    assert rec.returncode == 0, rec.stderr
    msgs = list(read_messages(tmp / "run.mcap"))
    assert sum(isinstance(m, LaserScan) for m in msgs) >= 20
    assert sum(isinstance(m, WheelTicks) for m in msgs) >= 20

    # pose error against the simulation's truth (twin clock in every scan)
    print("pipeline errors:", {k: v for k, v in d.ask("status")["counts"].items()
                               if k.startswith("errors")})
    err = truth_error(d.ask("trajectory")["rows"], get_world("loop"))
    print("pose error vs truth:", {k: v for k, v in err.items() if not k.startswith("_")})
    assert err["poses"] >= 60
    assert err["ate_trans_m"] < 0.15 and err["ate_rot_deg"] < 3.0
    walls = map_error(d.ask("map")["segments"], get_world("loop"), err["alignment"])
    print("map vs true walls:", walls)
    assert walls["wall_dist_p95_m"] < 0.15  # no ghost walls
    # relocalise while the base still drives: stopped, the odometry would stand while the
    # twin's robot moves on, and the tracked pose would fall behind the scan relocalised
    before = d.ask("status")["pose"]
    reloc = d.ask("relocalize")
    print("relocalize on demand:", reloc, "tracked:", before)
    assert reloc["class"] == "relocalize"
    if reloc["ok"]:  # found: where tracking has the robot, or where it would see the same
        near = abs(reloc["pose"][0] - before[0]) + abs(reloc["pose"][1] - before[1]) < 1.0
        assert near or same_view(get_world("loop"), err["alignment"], before,
                                 reloc["pose"]) > 0.9, (reloc, before)
    # the CLI's socket mode: `cgamap relocalize` with neither --map nor --log asks the daemon
    res = cli("relocalize", "--socket", str(d.socket), "--json")
    if res.returncode == 0:
        assert json.loads(res.stdout)["class"] == "relocalize"
    else:  # "not found" is a daemon answer, reported as one line with exit code 1
        assert res.returncode == 1 and res.stderr.startswith("cgamap: relocalize:"), res.stderr
    # ... and with a hint (a 2D pose estimate): the answer lies within its radius
    x, y, th = d.ask("status")["pose"]
    res = cli("relocalize", "--socket", str(d.socket), "--json", "--near", str(x), str(y),
              str(math.degrees(th)), "--radius", "2", "--turn", "20")
    if res.returncode == 0:
        got = json.loads(res.stdout)["pose"]
        print("hinted relocalisation:", got, "hint:", (x, y, th))
        assert math.hypot(got[0] - x, got[1] - y) < 2.5, (got, (x, y))
    else:
        assert res.returncode == 1 and res.stderr.startswith("cgamap: relocalize:"), res.stderr
    driver.stop_event.set()
    driver.join(5)
    final_map = d.ask("map")
    final_scans = d.ask("status")["counts"]["scans"]

    rc, took = d.terminate()
    print(f"SIGTERM to exit: {took:.2f} s")
    assert rc == 0, d.log_text()
    msgs = d.notify.messages
    assert "READY=1" in msgs and "WATCHDOG=1" in msgs and "STOPPING=1" in msgs
    assert msgs.index("READY=1") < msgs.index("STOPPING=1")
    ck = d.checkpoint()
    assert ck is not None and ck["reason"] == "shutdown"
    # written after the last scan mapped (the map lives on until then: fusing and ageing may
    # have taken segments since final_map, so compare the scans, not the segment counts)
    assert ck["loop"]["counts"]["scans"] >= final_scans
    assert len(ck["loop"]["map2d"]["map"]["a"]) > 0 and len(final_map["segments"]) > 0

    # a new daemon on the same state directory starts from the checkpoint
    d2 = daemon()
    d2.wait_ready()
    st2 = d2.ask("status")
    # (the twin's world keeps moving, so the map may already have grown since)
    assert st2["loaded_from"] and st2["map"]["segments"] >= len(ck["loop"]["map2d"]["map"]["a"])
    assert d2.terminate()[0] == 0


def test_replay_of_a_recording(stack):
    """Record the devices for a few seconds, then reproduce the run from the MCAP file."""
    daemon, driver, tmp = stack
    d = daemon()
    d.wait_ready()
    assert wait_until(lambda: d.ask("status")["counts"].get("scans", 0) >= 5, 60)
    rec = cli("record", "--socket", str(d.socket), "--duration", "4", str(tmp / "r.mcap"))
    assert rec.returncode == 0, rec.stderr
    assert d.terminate()[0] == 0
    run = short_dir()
    try:
        cfg = {"checkpoint": {"interval": 30.0}}
        (tmp / "replay").mkdir(exist_ok=True)
        r = DaemonProc(cfg, tmp / "replay", run, extra=["--replay", str(tmp / "r.mcap"),
                                                         "--exit-after-replay"])
        assert r.proc.wait(60) == 0, r.log_text()
        ck = r.checkpoint()
        assert ck["loop"]["counts"]["scans"] >= 5
        assert len(ck["loop"]["map2d"]["map"]["a"]) >= 2
        r.stop()
    finally:
        shutil.rmtree(run, ignore_errors=True)


def test_record_without_daemon(tmp_path):
    """`cgamap record --config` opens the devices itself when no daemon runs."""
    import yaml

    base = start_twin("modbus-base")
    try:
        cfg = {"devices": {"base": {"role": "odometry", "model": "modbus-base",
                                    "url": base.url, "rate": 50.0}}}
        (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
        res = cli("record", "--config", str(tmp_path / "c.yaml"), "--duration", "1.5",
                  str(tmp_path / "b.mcap"))
        assert res.returncode == 0, res.stderr
        ticks = [m for m in read_messages(tmp_path / "b.mcap") if isinstance(m, WheelTicks)]
        assert len(ticks) >= 20 and [t.seq for t in ticks] == sorted(t.seq for t in ticks)
    finally:
        base.stop()


def test_replay_of_a_real_carmen_log(tmp_path, shared_data):
    """cgamapd --replay on the first 200 scans of the Intel lab log (real data)."""
    from conftest import head_of_log

    part = head_of_log(shared_data("laser/intel-corrected.log.gz"), tmp_path / "intel-200.log",
                       200)
    _, ck = _replay_to_the_end(part, tmp_path)
    assert ck["reason"] == "shutdown" and ck["loop"]["counts"]["scans"] >= 150
    assert len(ck["loop"]["map2d"]["map"]["a"]) >= 10


def _replay_to_the_end(log, tmp_path) -> tuple[str, dict]:
    """``cgamapd --replay LOG --exit-after-replay`` (no laser mount configured) run to its
    end: the daemon's log text and its last checkpoint."""
    run = short_dir()
    try:
        r = DaemonProc({"checkpoint": {"interval": 30.0}}, tmp_path, run,
                       extra=["--replay", str(log), "--exit-after-replay"])
        assert r.proc.wait(120) == 0, r.log_text()
        text, ck = r.log_text(), r.checkpoint()
        r.stop()
        return text, ck
    finally:
        shutil.rmtree(run, ignore_errors=True)


def _mounted_log(path, mount, laps: float):
    """A simulated run written as ROBOTLASER1 with the laser at ``mount`` on the robot;
    returns the robot's and the laser's true poses."""
    from cgamap.drivers.carmen import write_carmen
    from cgamap.drivers.sim.scanlog import simulated_scans
    from cgamap.mapping.odometry import compose_pose2d, relative

    scans = simulated_scans(get_world("loop"), laps=laps)
    laser = np.array([s.pose_ref for s in scans])
    robot = compose_pose2d(laser, relative(np.asarray(mount, float), np.zeros(3)))
    write_carmen(path, scans, kind="ROBOTLASER1", robot_poses=robot)
    return robot, laser


def test_replay_mount_is_what_the_log_states(tmp_path):
    from cgamap.daemon.main import mount_note, replay_mount
    from cgamap.drivers.carmen import write_carmen
    from cgamap.drivers.sim.scanlog import simulated_scans

    mount = (0.25, -0.05, 0.03)
    _mounted_log(tmp_path / "m.clf", mount, 0.3)
    assert np.allclose(replay_mount(str(tmp_path / "m.clf")), mount, atol=1e-4)
    flaser = tmp_path / "f.log"  # laser poses are the odometry poses: no offset
    write_carmen(flaser, simulated_scans(get_world("loop"), laps=0.2))
    assert replay_mount(str(flaser)) == (0.0, 0.0, 0.0)
    cfg = {"devices": {"lms": {"role": "laser", "mount": {"x": 0.25, "y": -0.05,
                                                          "yaw": 0.03}}}}
    assert mount_note(cfg, mount) is None  # as configured: nothing to say
    assert "x 0.000 m" in mount_note(cfg, (0.0, 0.0, 0.0))
    assert "x 0.250 m, y -0.050 m, yaw 1.72 deg" in mount_note({"devices": {}}, mount)


def test_replay_drops_a_no_return_the_log_keeps_as_a_reading(tmp_path, caplog):
    # as `map build` does (an LMS's 8 m mode logs "nothing within 8 m" as 8.18 m)
    import logging

    from cgamap.daemon.recording import read_messages
    from cgamap.drivers.carmen import write_carmen
    from cgamap.drivers.messages import LaserScan
    from cgamap.drivers.sim.scanlog import simulated_scans

    scans = simulated_scans(get_world("loop"), laps=0.3)
    for s in scans:
        s.ranges = np.where(np.isnan(s.ranges) | (s.ranges > 8.18), 8.18, s.ranges)
    write_carmen(tmp_path / "lms8m.log", scans)
    with caplog.at_level(logging.INFO, logger="cgamap.daemon.recording"):
        got = [m for m in read_messages(tmp_path / "lms8m.log") if isinstance(m, LaserScan)]
    assert "readings of 8.18 m" in caplog.text
    assert len(got) == len(scans)
    assert all(np.nanmax(m.ranges) < 8.17 for m in got)
    assert sum(np.isnan(m.ranges).sum() for m in got) == sum((s.ranges >= 8.18).sum()
                                                             for s in scans)


def test_replay_of_a_log_with_the_laser_off_the_centre(tmp_path):
    """cgamapd --replay of a ROBOTLASER1 log whose laser sits 25 cm ahead of the robot's
    centre, with a configuration that has no laser mount: the log's own mount is used (and
    said in the log), so the daemon's pose is the robot's, not the laser's."""
    from cgamap.mapping.odometry import relative

    mount = (0.25, -0.05, 0.03)
    log = tmp_path / "mounted.clf"
    robot, _ = _mounted_log(log, mount, 0.6)
    text, ck = _replay_to_the_end(log, tmp_path)
    assert "put the laser at x 0.250 m, y -0.050 m, yaw 1.72 deg" in text, text
    # the map against the world's walls, its frame starting at the robot's first pose
    # (measured: median 1 cm; with the laser taken for the robot, 15 cm)
    m2 = ck["loop"]["map2d"]["map"]
    err = map_error(np.concatenate([np.asarray(m2["a"]), np.asarray(m2["b"])], 1),
                    get_world("loop"), robot[0])
    assert err["wall_dist_median_m"] < 0.04, err
    # and the robot's pose at the end (measured 3 cm; the laser's taken for it: 7 cm)
    want = relative(robot[0], robot[-1])
    got = np.asarray(ck["loop"]["pose"], float)
    assert np.hypot(*(got[:2] - want[:2])) < 0.05, (got, want)
    assert abs(np.angle(np.exp(1j * (got[2] - want[2])))) < np.deg2rad(1.0)


def test_3d_render_and_ply_of_a_small_map(tmp_path):
    from cgamap.daemon.export import export, ply_mesh, render_3d_png

    reply = {"segments": [[0, 0, 4, 0], [4, 0, 4, 3]], "planes": [
        {"corners": [[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]]}]}
    v, f, c = ply_mesh(reply, wall_height=2.0)
    assert f.shape == (3, 4) and v[f[0]][:, 2].tolist() == [0, 0, 2, 2]
    export(reply, "ply", tmp_path / "m.ply")
    assert read_ply_counts(tmp_path / "m.ply") == (12, 3)
    render_3d_png(reply, tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 1000


def test_map_error_measures_distance_to_true_walls():
    world = get_world("loop")
    exact = map_error(world.segments, world, (0.0, 0.0, 0.0))
    assert exact["wall_dist_max_m"] < 1e-9
    shifted = map_error(world.segments + [0.0, 0.5, 0.0, 0.5], world, (0.0, 0.0, 0.0))
    assert shifted["wall_dist_p95_m"] > 0.3
    assert map_error(world.segments, world, (0.0, -0.5, 0.0))["wall_dist_p95_m"] > 0.3


def test_same_view_accepts_look_alike_places_only():
    """Two relocalisations on demand seen under load: the robot half a turn round the block,
    and one corner seen from its other corridor.  Both see what the tracked pose sees; a pose
    0.3 m across the corridor or 1 m along it does not."""
    world = get_world("loop")
    cases = [((4.4691, 0.6482, 0.1109), (5.9747, 9.8232, 3.1367), (2.2319, 0.0281, -0.0094)),
             ((3.1035, 0.5306, 0.0378), (12.5148, 7.6332, 1.4009), (9.5184, -0.2077, -0.1704))]
    for alignment, tracked, found in cases:
        assert same_view(world, alignment, tracked, found) > 0.95
        assert same_view(world, alignment, tracked, tracked) == 1.0
    alignment, tracked, _ = cases[0]
    along = np.add(tracked, (1.0, 0.0, 0.0))
    assert same_view(world, alignment, tracked, along) < 0.8
    alignment, tracked, _ = cases[1]
    across = np.add(tracked, (0.3, 0.0, 0.0))
    assert same_view(world, alignment, tracked, across) < 0.5


def test_replay_of_a_log_of_scans_alone_loses_none(tmp_path):
    """A ROBOTLASER1 log carries each scan's odometry and has no ODOM lines, so the replay's
    queue holds hundreds of scans at a time: replayed as fast as the mapper goes, every one
    is mapped (before, all but the 64 newest of each batch were dropped: Killian Court's
    3 873 scans gave 993)."""
    log = tmp_path / "scans.clf"
    robot, _ = _mounted_log(log, (0.0, 0.0, 0.0), 6.0)
    assert len(robot) > 256 + 64
    _, ck = _replay_to_the_end(log, tmp_path)
    counts = ck["loop"]["counts"]
    assert counts["scans_in"] == len(robot) and counts.get("scans_dropped", 0) == 0, counts
    assert counts["scans"] + counts.get("scans_skipped", 0) == len(robot), counts
