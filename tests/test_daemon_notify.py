"""sd_notify: datagrams reach a fake notify socket, path and abstract forms."""

from __future__ import annotations

import os
import socket
import time

import pytest
from cgamap.daemon import notify


def test_not_under_systemd(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert notify.ready() is False


@pytest.fixture
def manager(tmp_path, monkeypatch):
    """A fake service manager: a datagram socket at a path, named by $NOTIFY_SOCKET."""
    path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind(str(path))
        s.settimeout(5)
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        yield s


def test_path_socket(manager):
    assert notify.ready("mapping")
    assert manager.recv(4096).decode().split("\n") == ["READY=1", "STATUS=mapping"]
    notify.watchdog()
    assert manager.recv(4096) == b"WATCHDOG=1"


def test_abstract_socket(monkeypatch):
    name = f"cgamap-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind("\0" + name)
        s.settimeout(5)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert notify.stopping()
        assert s.recv(4096) == b"STOPPING=1"


def test_watchdog_period(monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    assert notify.watchdog_period() == 1.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert notify.watchdog_period() is None


def test_extending_asks_for_more_start_time_while_busy(manager, monkeypatch):
    with notify.extending(step=0.2):
        time.sleep(0.35)
    manager.setblocking(False)
    got = []
    while True:
        try:
            got.append(manager.recv(4096))
        except BlockingIOError:
            break
    # one at the start, then one every 50 ms while the block ran
    assert len(got) >= 4 and set(got) == {b"EXTEND_TIMEOUT_USEC=200000"}
    time.sleep(0.15)                                  # and none once it is over
    with pytest.raises(BlockingIOError):
        manager.recv(4096)
    monkeypatch.delenv("NOTIFY_SOCKET")
    with notify.extending(step=0.2):
        pass                                        # not under systemd: nothing to do
