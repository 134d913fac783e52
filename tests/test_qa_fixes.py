"""Regression tests for QA findings that have no better home."""

from __future__ import annotations

import json
import os
import shutil
import socket

import numpy as np
import pytest
from cgamap.daemon.server import QueryServer
from daemon_stack import short_dir


@pytest.fixture
def sockdir():
    d = short_dir()
    yield str(d)
    shutil.rmtree(d, ignore_errors=True)


class _App:
    def command(self, req):
        return {"ok": True}

    def watch(self, req, send, stop):
        pass


@pytest.mark.parametrize("kind", ["file", "dir", "symlink"])
def test_socket_path_holding_another_file_is_refused_and_kept(kind, sockdir):
    d = sockdir
    path = os.path.join(d, "q.sock")
    if kind == "file":
        with open(path, "w") as f:
            f.write("precious")
    elif kind == "dir":
        os.mkdir(path)
    else:
        os.symlink(os.path.join(d, "elsewhere"), path)
    srv = QueryServer(_App(), path)
    with pytest.raises(RuntimeError, match="not a socket"):
        srv.start()
    assert os.path.lexists(path)
    if kind == "file":
        with open(path) as f:
            assert f.read() == "precious"


def test_stale_socket_is_replaced(sockdir):
    d = sockdir
    path = os.path.join(d, "q.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(path)
    s.close()                               # a socket file nobody listens on
    srv = QueryServer(_App(), path)
    srv.start()
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as c:
            c.settimeout(2.0)
            c.connect(path)
    finally:
        srv.stop()


def test_replay_read_error_ends_the_replay_instead_of_restarting(monkeypatch):
    """QA: an error partway through a replay restarted it from the start forever."""
    import threading

    import numpy as np
    from cgamap.daemon import recording
    from cgamap.daemon.devices import ReplaySource
    from cgamap.daemon.supervisor import BoundedQueue, DeviceWorker
    from cgamap.drivers.messages import LaserScan

    def broken(path):
        for i in range(3):
            yield LaserScan(seq=i, stamp_ns=i * 10**8, angle_min=0.0, angle_increment=0.01,
                            ranges=np.ones(5))
        raise ValueError("chunk 4: bad CRC")
    monkeypatch.setattr(recording, "read_messages", broken)
    q = BoundedQueue(threading.Condition(), 100, lossy=False)
    w = DeviceWorker("replay", "laser", lambda: ReplaySource("rec.mcap", roles=("laser",)), q,
                     backoff_initial=0.01, backoff_max=0.01)
    w.start()
    w.join(timeout=10.0)
    assert not w.is_alive()
    assert [m.seq for m in q.items] == [0, 1, 2]          # no duplicates from a restart
    assert w.health.state == "finished" and w.health.restarts == 0
    assert w.health.errors == {"replay_errors": 1}


def _daemon(tmp_path, sockdir):
    from cgamap.daemon import config as config_mod
    from cgamap.daemon.service import Daemon

    cfg = config_mod.validate({"devices": {}}, tmp_path)
    return Daemon(cfg, state_dir=str(tmp_path / "state"),
                  socket_path=os.path.join(sockdir, "d.sock"))


def test_set_pose_refuses_huge_coordinates(tmp_path, sockdir):
    """QA: x = 1e308 was accepted and poisoned the trajectory (map export failed forever)."""
    d = _daemon(tmp_path, sockdir)
    for bad in ({"x": 1e308, "y": 0, "theta": 0}, {"x": 0, "y": -2e6, "theta": 0},
                {"x": 0, "y": 0, "theta": float("nan")}):
        r = d.command({"cmd": "set-pose", **bad})
        assert r["class"] == "error" and "set-pose" in r["error"], r
    r = d.command({"cmd": "set-pose", "x": 1.0, "y": -2.0, "theta": 7.0})
    assert r["class"] == "pose"
    assert r["pose"][:2] == [1.0, -2.0] and abs(r["pose"][2] - (7.0 - 2 * np.pi)) < 1e-4


def test_checkpoint_failures_counted_and_shutdown_failure_is_nonzero(tmp_path, sockdir):
    import signal
    import threading

    d = _daemon(tmp_path, sockdir)

    def fail(payload):
        raise OSError(28, "No space left on device")
    d.store.save = fail
    assert d.checkpoint("interval")["class"] == "error"
    st = d.command({"cmd": "status"})
    assert st["checkpoint"]["failures"] == 1 and "No space" in st["checkpoint"]["last_error"]
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    threading.Timer(0.3, d.stop_event.set).start()
    try:
        assert d.run() == 74
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    assert d.checkpoint_failures >= 2


def test_binary_map_json_is_a_map_format_error(tmp_path):
    from cgamap.mapping.mapio import MapFormatError, load_map

    p = tmp_path / "g.json"
    p.write_bytes(bytes(range(256)) * 12)
    with pytest.raises(MapFormatError, match="g.json: not a JSON map"):
        load_map(p)


def _room_log(path, n: int = 12) -> None:
    """A CARMEN log of ``n`` FLASER scans in a 8 m x 5 m room, robot creeping along x."""
    ang = np.radians(np.arange(-90, 91))
    lines = []
    for k in range(n):
        x, y, th = 2.0 + 0.05 * k, 2.0, 0.0
        c, s = np.cos(ang + th), np.sin(ang + th)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (8 - x) / c, np.where(c < 0, -x / c, np.inf))
            ty = np.where(s > 0, (5 - y) / s, np.where(s < 0, -y / s, np.inf))
        r = np.minimum(tx, ty)
        lines.append(f"FLASER 181 {' '.join(f'{v:.3f}' for v in r)} {x} {y} {th} {x} {y} {th} "
                     f"{k * 0.1:.2f} host {k * 0.1:.2f}")
    path.write_text("\n".join(lines) + "\n")


def test_map_cli_log_dir_backup_and_trial_cap(tmp_path, capsys):
    from cgamap.daemon.cli import main

    assert main(["map", "build", "--log", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "is a directory" in err and len(err.strip().splitlines()) == 1
    log = tmp_path / "room.log"
    _room_log(log)
    out = tmp_path / "m"
    assert main(["map", "build", "--log", str(log), "--out", str(out), "--quiet"]) == 0
    first = (out / "map.json").read_text()
    capsys.readouterr()
    assert main(["map", "build", "--log", str(log), "--out", str(out)]) == 0
    assert (out / "map.json.bak").read_text() == first
    assert "kept as" in capsys.readouterr().err
    rc = main(["relocalize", "--map", str(out / "map.json"), "--log", str(log), "--trials",
               "500", "--json"])
    assert rc == 0
    out_, err = capsys.readouterr()
    assert json.loads(out_)["trials"] == 12
    assert "capped to the log's 12 scans" in err


_SPAM = """
import argparse, sys
from cgamap.daemon import cli

def spam(args):
    if args.peer:
        raise BrokenPipeError(32, "Broken pipe")
    for _ in range(10**6):
        print("x" * 100)

def parser():
    p = argparse.ArgumentParser()
    p.add_argument("-v", "--verbose", action="count", default=0)
    s = p.add_subparsers().add_parser("spam")
    s.add_argument("--peer", action="store_true")
    s.set_defaults(func=spam)
    return p

cli.build_parser = parser
sys.exit(cli.main(sys.argv[1:]))
"""


def test_closed_stdout_ends_quietly_with_exit_0():
    """`cgamap ... | head`: exit 0, nothing on stderr (main catches BrokenPipeError once)."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", _SPAM, "spam"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.read(1000)
    proc.stdout.close()
    try:
        err = proc.stderr.read()
        assert proc.wait(timeout=30) == 0, err
    finally:
        proc.kill()
    assert err == b""
    # a broken pipe that is not stdout (a peer's socket) is one line, not exit 0
    out = subprocess.run([sys.executable, "-c", _SPAM, "spam", "--peer"], capture_output=True,
                         timeout=30)
    assert out.returncode == 74 and out.stderr.decode().count("\n") == 1, out.stderr
