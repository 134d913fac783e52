"""Regression tests for QA findings that have no better home."""

from __future__ import annotations

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
