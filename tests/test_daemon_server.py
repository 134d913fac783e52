"""The query socket and signals of a device-less cgamapd: commands, errors, watch, TCP when
configured, SIGHUP reload (good and bad config), set-pose + checkpoint round trip."""

from __future__ import annotations

import json
import shutil
import signal
import socket
import time

import pytest
import yaml
from cgamap.daemon.server import stream
from daemon_stack import DaemonProc, short_dir, wait_until


@pytest.fixture
def daemon(tmp_path):
    run = short_dir()
    procs: list[DaemonProc] = []

    def make(cfg: dict) -> DaemonProc:
        d = DaemonProc(cfg, tmp_path, run)
        procs.append(d)
        d.wait_ready()
        return d

    yield make
    for d in procs:
        d.stop()
    shutil.rmtree(run, ignore_errors=True)


def test_commands_and_errors(daemon):
    d = daemon({"checkpoint": {"interval": 60.0}})
    assert d.ask("version")["class"] == "version"
    assert d.ask("status")["devices"] == []
    err = d.ask("no-such-command")
    assert err["class"] == "error" and "status" in err["commands"]
    assert d.ask("set-pose", x=1.5, y=-2.0)["class"] == "error"  # theta missing
    assert d.ask("set-pose", x=1.5, y=-2.0, theta=0.25)["pose"] == [1.5, -2.0, 0.25]
    assert d.ask("relocalize")["ok"] is False  # no scan yet: a clear refusal
    # a hint must be a pose, with a positive radius and turn; radius and turn need one
    for bad in ({"near": [1.0, 2.0]}, {"near": [1.0, "x", 0.0]}, {"near": [1e9, 0.0, 0.0]},
                {"near": [0.0, 0.0, 0.0], "radius": -1.0},
                {"near": [0.0, 0.0, 0.0], "turn": 7.0}, {"radius": 2.0}):
        err = d.ask("relocalize", **bad)
        assert err["class"] == "error" and err["error"].startswith("relocalize: "), (bad, err)
    hinted = d.ask("relocalize", near=[0.0, 0.0, 0.0], radius=3.0)
    assert hinted["class"] == "relocalize" and hinted["ok"] is False  # still no scan
    ck = d.ask("checkpoint")
    assert ck["class"] == "checkpoint"
    assert d.checkpoint()["loop"]["pose"].tolist() == [1.5, -2.0, 0.25]
    with socket.socket(socket.AF_UNIX) as s:  # plain words and bad JSON on a raw socket
        s.settimeout(5)
        s.connect(str(d.socket))
        s.sendall(b"status\n{not json\n")
        f = s.makefile("rb")
        assert json.loads(f.readline())["class"] == "status"
        assert "bad request" in json.loads(f.readline())["error"]


def test_watch_streams_pose_events(daemon):
    d = daemon({})
    events = []
    gen = stream(d.socket, timeout=10.0, interval=0.2)
    events.append(next(gen))
    d.ask("set-pose", x=3.0, y=0.0, theta=0.0)
    for obj in gen:
        events.append(obj)
        if obj["class"] == "pose":
            break
    gen.close()
    assert events[0]["class"] == "watch"
    assert events[-1]["pose"][0] == 3.0


def test_tcp_only_when_configured(daemon):
    d = daemon({"server": {"tcp": True, "tcp_port": 0}})
    assert d.ask("status")["class"] == "status"
    # the listener is on 127.0.0.1 (the default); find the port from /proc/net/tcp
    port = None
    for line in open("/proc/net/tcp").read().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        host, p = local.split(":")
        if state == "0A" and host == "0100007F":
            with socket.socket() as s:
                s.settimeout(1)
                try:
                    s.connect(("127.0.0.1", int(p, 16)))
                    s.sendall(b"version\n")
                    if b'"proto"' in s.recv(4096):
                        port = int(p, 16)
                        break
                except OSError:
                    continue
    assert port is not None


def test_sighup_reloads_what_is_safe(daemon):
    d = daemon({"checkpoint": {"interval": 60.0}})
    cfg = yaml.safe_load(d.cfg_path.read_text())
    cfg["checkpoint"]["interval"] = 7.5
    d.cfg_path.write_text(yaml.safe_dump(cfg))
    d.proc.send_signal(signal.SIGHUP)
    assert wait_until(lambda: d.ask("status")["checkpoint"]["interval_s"] == 7.5, 10)
    d.cfg_path.write_text("checkpoint: {interval: -1}\n")  # a broken edit is refused
    d.proc.send_signal(signal.SIGHUP)
    time.sleep(0.5)
    assert d.ask("status")["checkpoint"]["interval_s"] == 7.5
    assert "reload" in d.log_text() and d.proc.poll() is None
    assert d.terminate()[0] == 0


def test_cli_without_daemon_is_one_clear_line(tmp_path):
    import subprocess
    import sys

    code = "import sys; from cgamap.daemon.cli import main; sys.exit(main())"
    for args in (["status"], ["map", "export", "--format", "json"], ["watch", "--count", "1"]):
        out = subprocess.run([sys.executable, "-c", code, *args, "--socket",
                              str(tmp_path / "none.sock")], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 69, out.stderr
        assert len(out.stderr.strip().splitlines()) == 1 and "cannot connect" in out.stderr


def test_cli_watch_lines(daemon):
    import subprocess
    import sys

    d = daemon({})
    code = "import sys; from cgamap.daemon.cli import main; sys.exit(main())"
    out = subprocess.run([sys.executable, "-c", code, "watch", "--socket", str(d.socket),
                          "--count", "2", "--interval", "0.1"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    lines = [json.loads(x) for x in out.stdout.splitlines()]
    assert [x["class"] for x in lines] == ["watch", "status"]
