"""Helpers for the daemon's end-to-end tests: twins, a config, cgamapd as a subprocess with a
fake notify socket, and clean teardown (nothing left running)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from cgamap.daemon.demo import NotifyListener
from cgamap.daemon.server import DaemonUnavailable, request
from cgamap.daemon.store import CheckpointStore
from cgamap.daemon.twins import Twin, start_twin


def short_dir() -> Path:
    """A short temp dir for sockets (AF_UNIX paths are limited to 108 bytes)."""
    return Path(tempfile.mkdtemp(prefix="cgd-"))


class DaemonProc:
    """cgamapd run as systemd would: NOTIFY_SOCKET, WATCHDOG_USEC, SIGTERM to stop."""

    def __init__(self, cfg: dict, workdir: Path, run_dir: Path, extra: list[str] | None = None):
        self.workdir = workdir
        self.run_dir = run_dir
        cfg = dict(cfg)
        cfg["paths"] = {"state_dir": str(workdir / "state"), "runtime_dir": str(run_dir)}
        self.cfg_path = workdir / "cgamapd.yaml"
        self.cfg_path.write_text(yaml.safe_dump(cfg))
        self.socket = run_dir / "cgamapd.sock"
        self.state_dir = workdir / "state"
        self.notify = NotifyListener(run_dir / f"notify-{os.getpid()}-{time.monotonic_ns()}")
        env = dict(os.environ, NOTIFY_SOCKET=str(self.notify.path), WATCHDOG_USEC="500000")
        for k in ("STATE_DIRECTORY", "RUNTIME_DIRECTORY"):
            env.pop(k, None)
        self.log_path = workdir / "cgamapd.log"
        self.log = open(self.log_path, "a")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "cgamap.daemon.main", "-c", str(self.cfg_path),
             *(extra or [])], env=env, stdout=self.log, stderr=self.log)

    def wait_ready(self, timeout: float = 60.0) -> None:
        if not self.notify.wait_for("READY=1", timeout):
            raise AssertionError(f"no READY=1; log:\n{self.log_text()}")

    def ask(self, cmd: str, **kw) -> dict:
        return request(self.socket, cmd, timeout=10.0, **kw)

    def log_text(self) -> str:
        self.log.flush()
        return self.log_path.read_text()[-4000:]

    def terminate(self, timeout: float = 10.0) -> tuple[int, float]:
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        rc = self.proc.wait(timeout)
        return rc, time.monotonic() - t0

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.notify.close()
        self.log.close()

    def checkpoint(self) -> dict | None:
        return CheckpointStore(self.state_dir).load()


def wait_until(pred, timeout: float = 20.0, step: float = 0.1):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        with contextlib.suppress(DaemonUnavailable, OSError, KeyError):
            last = pred()
            if last:
                return last
        time.sleep(step)
    return last


def stack_config(laser: Twin | None, base: Twin | None, camera_world: str | None = None,
                 epoch_ns: int | None = None, laser_url: str | None = None,
                 checkpoint: float = 1.0) -> dict:
    devices: dict = {}
    if laser is not None or laser_url is not None:
        devices["laser"] = {"role": "laser", "model": "hokuyo",
                            "url": laser_url or laser.url, "queue": 8}
    if base is not None:
        devices["base"] = {"role": "odometry", "model": "modbus-base", "url": base.url,
                           "rate": 50.0, "params": {"wheel_radius": 0.05, "track": 0.30,
                                                    "ticks_per_rev": 4096}}
    if camera_world is not None:
        devices["head"] = {"role": "pantilt", "model": "dynamixel",
                           "url": "serial:///nonexistent/pantilt", "enabled": False,
                           "axis_point": [0.1, 0.0, 1.0], "eye_offset": [0.05, 0.0375, 0.05]}
        devices["camera"] = {"role": "camera", "model": "sim-stereo",
                             "url": f"sim://{camera_world}", "rate": 1.0,
                             "params": {"size": [320, 200], "fx": 225.0, "epoch_ns": epoch_ns}}
    return {"log_level": "info", "checkpoint": {"interval": checkpoint},
            "supervisor": {"backoff_initial": 0.1, "backoff_max": 1.0, "ready_timeout": 2.0},
            "devices": devices,
            "mapping": {"params3d": {"max_depth": 6.0, "stride": 2}}}


__all__ = ["DaemonProc", "Twin", "short_dir", "stack_config", "start_twin", "wait_until"]
