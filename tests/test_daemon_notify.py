"""sd_notify: datagrams reach a fake notify socket, path and abstract forms."""

from __future__ import annotations

import os
import socket

from cgamap.daemon import notify


def test_not_under_systemd(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert notify.ready() is False


def test_path_socket(tmp_path, monkeypatch):
    path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind(str(path))
        s.settimeout(5)
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        assert notify.ready("mapping")
        assert s.recv(4096).decode().split("\n") == ["READY=1", "STATUS=mapping"]
        notify.watchdog()
        assert s.recv(4096) == b"WATCHDOG=1"


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
