"""Device sources for the supervisor, built from the config's device entries.

Each source has ``open()``, ``read(timeout)`` and ``close()`` (see ``supervisor``).  Drivers are
imported lazily so that a build without one (or without its library) still starts the others;
the missing one fails on open and is reported in its health.  The drivers' own reconnect logic
is switched off: restarting is the supervisor's job, with backoff and counted restarts.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

log = logging.getLogger(__name__)

LASER_CLASSES = {
    "lms2xx": ("cgamap.drivers.lms2xx", "Lms2xxDriver"),
    "hokuyo": ("cgamap.drivers.hokuyo", "HokuyoDriver"),
    "cola": ("cgamap.drivers.cola", "ColaDriver"),
}
CAMERA_BACKENDS = {"oak": "depthai", "sim-stereo": "synthetic"}


def _import(module: str, name: str):
    import importlib

    return getattr(importlib.import_module(module), name)


class LaserSource:
    """A laser driver (LMS2xx, Hokuyo, CoLa) behind the supervisor's interface."""

    def __init__(self, model: str, url: str, timeout: float, params: dict):
        self.model, self.url, self.timeout, self.params = model, url, timeout, params
        self.driver = None

    @property
    def errors(self):
        return None if self.driver is None else self.driver.errors

    def open(self) -> None:
        cls = _import(*LASER_CLASSES[self.model])
        self.driver = cls(self.url, self.timeout, reconnect=False, **self.params)
        self.driver.open()

    def read(self, timeout: float):
        return self.driver.read_scan(timeout)

    def close(self) -> None:
        if self.driver is not None:
            self.driver.close()


class PacedSource:
    """A polled device (Modbus base, pan-tilt, camera) read at ``rate`` Hz on deadlines."""

    def __init__(self, make: Callable[[], Any], read: Callable[[Any, float], Any], rate: float,
                 open_name: str = "open"):
        self.make, self._read, self.period = make, read, 1.0 / rate
        self.dev: Any = None
        self.open_name = open_name
        self._due = 0.0

    @property
    def errors(self):
        return getattr(self.dev, "errors", None)

    def open(self) -> None:
        self.dev = self.make()
        getattr(self.dev, self.open_name)()
        self._due = time.monotonic()

    def read(self, timeout: float):
        wait = self._due - time.monotonic()
        if wait > timeout:
            time.sleep(timeout)
            return None
        if wait > 0:
            time.sleep(wait)
        self._due = max(self._due + self.period, time.monotonic() - self.period)
        return self._read(self.dev, timeout)

    def close(self) -> None:
        if self.dev is not None:
            self.dev.close()


def _modbus(dev: dict) -> Callable[[], Any]:
    def make():
        from cgamap.drivers.modbus_base import ModbusBase, ModbusBaseConfig

        return ModbusBase(ModbusBaseConfig.from_dict(dev))

    return make


def _pantilt(dev: dict) -> Callable[[], Any]:
    def make():
        from cgamap.drivers.pantilt import PanTilt, PanTiltConfig

        return PanTilt(PanTiltConfig.from_dict({**dev["params"], "url": dev["url"]}))

    return make


def _pantilt_read(d: Any, timeout: float):
    return d.read_state()


class SimClockGrabber:
    """The synthetic stereo grabber on the simulation's clock: frame time = now - epoch, so
    frames and the laser twin (whose clock starts at ``epoch``) see the same robot pose."""

    def __init__(self, grabber: Any, epoch_ns: int | None):
        self.g = grabber
        self.epoch_ns = epoch_ns if epoch_ns is not None else time.monotonic_ns()

    def open(self) -> None:
        self.g.open()

    def grab(self, timeout: float):
        now = time.monotonic_ns()
        self.g.t0 = (now - self.epoch_ns) / 1e9 - self.g.seq / self.g.fps
        frame = self.g.grab(timeout)
        frame.stamp_ns = now
        return frame

    def close(self) -> None:
        self.g.close()


def _camera(dev: dict) -> Callable[[], Any]:
    def make():
        backend = CAMERA_BACKENDS.get(dev["model"], dev["model"])
        parts = urlsplit(dev["url"])
        params = dict(dev["params"])
        epoch = params.pop("epoch_ns", None)
        if backend == "synthetic":   # the simulator's camera, built here: no driver imports it
            from cgamap.drivers.sim.stereo_render import open_synthetic

            where = parts.netloc or parts.path.strip("/") or "corridor"
            params.setdefault("fps", dev["rate"])
            return SimClockGrabber(open_synthetic(where, **params), epoch)
        from cgamap.drivers.stereo import open_grabber

        where = parts.netloc + parts.path if parts.scheme != "usb" else ""
        return open_grabber(backend, where, params)

    return make


def build_source(name: str, dev: dict) -> Callable[[], Any]:
    """A factory of fresh sources for one configured device (called on every (re)start)."""
    model, url = dev["model"], dev["url"]
    scheme = urlsplit(url).scheme
    if scheme == "sim" and not (dev["role"] == "camera" and model in ("sim-stereo", "synthetic")):
        def unresolved():
            raise RuntimeError(f"{url}: a sim:// URL is resolved by `cgamap demo` "
                               "(start the twin and give its pty or host:port)")
        return _Failing(unresolved)
    role = dev["role"]
    if role == "laser" and model in LASER_CLASSES:
        return lambda: LaserSource(model, url, dev["timeout"], dict(dev["params"]))
    if role == "odometry" and model == "modbus-base":
        return lambda: PacedSource(_modbus(dev), lambda d, t: d.read(), dev["rate"])
    if role == "pantilt":
        return lambda: PacedSource(_pantilt(dev), _pantilt_read, dev["rate"])
    if role == "camera":
        return lambda: PacedSource(_camera(dev), lambda d, t: d.grab(max(t, 1.0)), dev["rate"])
    if model == "carmen":
        path = urlsplit(url).path
        return lambda: ReplaySource(path, roles=(role,))
    raise RuntimeError(f"device {name}: no source for model {model!r}")


class _Failing:
    def __init__(self, fn):
        self.fn = fn

    def __call__(self):
        return self

    def open(self):
        self.fn()

    def read(self, timeout):
        return None

    def close(self):
        pass


class ReplaySource:
    """Messages from a recording (MCAP written by ``cgamap record``) or a CARMEN log.

    ``rate`` 0 replays as fast as the consumer takes them (the supervisor's lossless queue
    paces it); otherwise the recorded time gaps are replayed, scaled by 1/rate.  A read error
    partway through ends the replay (logged, counted in ``errors``): restarting would replay
    the start again and feed the map duplicate scans.
    """

    def __init__(self, path: str, roles: tuple[str, ...] = ("laser", "odometry"),
                 rate: float = 0.0):
        self.path, self.roles, self.rate = path, roles, rate
        self.it = None
        self.count = 0
        self.errors = {"replay_errors": 0}
        self._t0: tuple[int, float] | None = None

    def open(self) -> None:
        from cgamap.daemon.recording import read_messages

        self.it = iter(read_messages(self.path))

    def read(self, timeout: float):
        from cgamap.daemon.supervisor import END
        from cgamap.drivers.messages import LaserScan, OdometryPose, WheelTicks

        wanted = {"laser": (LaserScan,), "odometry": (OdometryPose, WheelTicks)}
        types = tuple(t for r in self.roles for t in wanted.get(r, ()))
        while True:
            try:
                msg = next(self.it)
            except StopIteration:
                return END
            except Exception as exc:  # noqa: BLE001 - whatever the reader raises, stop here
                self.errors["replay_errors"] += 1
                log.error("replay %s: read error after %d messages (%s: %s); replay ends here",
                          self.path, self.count, type(exc).__name__, exc)
                self.it = iter(())
                return END
            if types and not isinstance(msg, types):
                continue
            self.count += 1
            if self.rate > 0:
                now = time.monotonic()
                if self._t0 is None:
                    self._t0 = (msg.stamp_ns, now)
                due = self._t0[1] + (msg.stamp_ns - self._t0[0]) / 1e9 / self.rate
                if due > now:
                    time.sleep(due - now)
            return msg

    def close(self) -> None:
        self.it = None

