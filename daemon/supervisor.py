"""Device supervision: one thread per device, a bounded queue from each to the mapping loop.

A device source is anything with ``open()``, ``read(timeout) -> message | list | None`` and
``close()`` (optionally ``errors``: an ErrorCounters or dict).  A worker opens it, reads, and
puts messages on its queue; any exception closes the source and restarts it after a delay that
doubles from ``backoff_initial`` up to ``backoff_max`` (reset by the first message after a
restart).  A source silent for ``stall_s`` is treated as failed.  Queues are bounded: a lossy
queue (scans, frames) drops its oldest entry when full and counts it; a lossless queue
(odometry, pan-tilt) makes the device thread wait for room instead.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

log = logging.getLogger(__name__)


class DeviceSource(Protocol):
    def open(self) -> None: ...
    def read(self, timeout: float) -> Any: ...
    def close(self) -> None: ...


class Bus:
    """The per-device bounded queues, with one condition the mapping loop waits on."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.queues: dict[str, BoundedQueue] = {}

    def add(self, name: str, maxlen: int, lossy: bool) -> BoundedQueue:
        q = BoundedQueue(self.cond, maxlen, lossy)
        self.queues[name] = q
        return q

    def wait(self, timeout: float) -> None:
        with self.cond:
            if not any(q.items for q in self.queues.values()):
                self.cond.wait(timeout)

    def drain(self) -> list[tuple[str, Any]]:
        """Everything queued, as (device name, message), in arrival order per device."""
        out = []
        with self.cond:
            for name, q in self.queues.items():
                while q.items:
                    out.append((name, q.items.popleft()))
            self.cond.notify_all()  # wake lossless producers waiting for room
        return out


class BoundedQueue:
    def __init__(self, cond: threading.Condition, maxlen: int, lossy: bool):
        self.cond = cond
        self.maxlen = max(1, maxlen)
        self.lossy = lossy
        self.items: collections.deque = collections.deque()
        self.dropped = 0
        self.high_water = 0

    def put(self, item: Any, stop: threading.Event) -> bool:
        """Queue ``item``; False if ``stop`` was set while waiting for room (lossless)."""
        with self.cond:
            while len(self.items) >= self.maxlen:
                if self.lossy:
                    self.items.popleft()  # the oldest scan is the least useful one
                    self.dropped += 1
                    break
                if stop.is_set():
                    return False
                self.cond.wait(0.1)
            self.items.append(item)
            self.high_water = max(self.high_water, len(self.items))
            self.cond.notify_all()
        return True


@dataclass
class Health:
    """What ``status`` reports per device."""

    name: str
    role: str
    state: str = "starting"  # starting, opening, running, backoff, stopped, disabled
    restarts: int = 0
    messages: int = 0
    last_message_mono: float | None = None
    rate_hz: float = 0.0
    last_error: str | None = None
    errors: dict[str, int] = field(default_factory=dict)
    since_mono: float = field(default_factory=time.monotonic)

    def as_dict(self, queue: BoundedQueue | None = None) -> dict:
        now = time.monotonic()
        age = None if self.last_message_mono is None else round(now - self.last_message_mono, 3)
        rate = self.rate_hz if age is not None and age < 5.0 else 0.0
        d = {"name": self.name, "role": self.role, "state": self.state,
             "restarts": self.restarts, "messages": self.messages, "last_message_age_s": age,
             "rate_hz": round(rate, 2), "last_error": self.last_error,
             "errors": dict(self.errors), "state_for_s": round(now - self.since_mono, 2)}
        if queue is not None:
            d["queue"] = {"length": len(queue.items), "max": queue.maxlen,
                          "dropped": queue.dropped, "lossy": queue.lossy}
        return d


def _counters(source: Any) -> dict[str, int]:
    errs = getattr(source, "errors", None)
    if errs is None:
        return {}
    if hasattr(errs, "as_dict"):
        return errs.as_dict()
    return dict(errs) if isinstance(errs, dict) else {}


class DeviceWorker(threading.Thread):
    """Runs one device: open, read, queue; restart with capped exponential backoff."""

    def __init__(self, name: str, role: str, factory: Callable[[], DeviceSource],
                 queue: BoundedQueue, read_timeout: float = 0.5, backoff_initial: float = 0.2,
                 backoff_max: float = 1.0, stall_s: float = 5.0):
        super().__init__(name=f"dev-{name}", daemon=True)
        self.factory = factory
        self.queue = queue
        self.health = Health(name, role)
        self.read_timeout = read_timeout
        self.backoff_initial = backoff_initial
        self.backoff_max = backoff_max
        self.stall_s = stall_s
        self.stop_event = threading.Event()
        self._source: DeviceSource | None = None
        self._lock = threading.Lock()
        self.restart_requested = threading.Event()

    def _set_state(self, state: str) -> None:
        if self.health.state != state:
            self.health.state = state
            self.health.since_mono = time.monotonic()

    def stop(self) -> None:
        self.stop_event.set()

    def restart(self) -> None:
        """Close and reopen the device (e.g. after a config reload)."""
        self.restart_requested.set()

    def _on_message(self, msg: Any) -> None:
        now = time.monotonic()
        h = self.health
        if h.last_message_mono is not None:
            dt = max(now - h.last_message_mono, 1e-6)
            h.rate_hz = 1.0 / dt if h.rate_hz == 0.0 else 0.9 * h.rate_hz + 0.1 / dt
        h.last_message_mono = now
        h.messages += 1
        self.queue.put(msg, self.stop_event)

    def _run_once(self) -> None:
        """Open the source and read until it fails, stalls or we are stopped."""
        self._set_state("opening")
        source = self.factory()
        with self._lock:
            self._source = source
        try:
            source.open()
            self._set_state("running")
            last = time.monotonic()
            got_any = False
            while not self.stop_event.is_set() and not self.restart_requested.is_set():
                out = source.read(self.read_timeout)
                self.health.errors = _counters(source)
                if out is None:
                    if time.monotonic() - last > self.stall_s:
                        raise TimeoutError(f"no message for {self.stall_s:.1f} s")
                    continue
                if isinstance(out, EndOfStream):
                    self._set_state("finished")
                    self.stop_event.set()
                    return
                for msg in out if isinstance(out, list) else [out]:
                    self._on_message(msg)
                last = time.monotonic()
                if not got_any:
                    got_any = True
                    self._backoff = self.backoff_initial  # healthy again: reset the delay
        finally:
            with self._lock:
                self._source = None
            try:
                source.close()
            except Exception as exc:  # noqa: BLE001 - a failing close must not stop us
                log.debug("%s: close failed: %s", self.health.name, exc)

    def run(self) -> None:
        self._backoff = self.backoff_initial
        first = True
        while not self.stop_event.is_set():
            if not first:
                self.health.restarts += 1
            first = False
            self.restart_requested.clear()
            try:
                self._run_once()
                if self.stop_event.is_set() or self.restart_requested.is_set():
                    continue
            except Exception as exc:  # noqa: BLE001 - any device failure means restart
                msg = f"{type(exc).__name__}: {exc}"[:200]
                if msg != self.health.last_error:
                    log.warning("device %s failed: %s; retry in %.1f s", self.health.name, msg,
                                self._backoff)
                self.health.last_error = msg
            self._set_state("backoff")
            if self.stop_event.wait(self._backoff):
                break
            self._backoff = min(self._backoff * 2.0, self.backoff_max)
        if self.health.state != "finished":
            self._set_state("stopped")


class EndOfStream:
    """Returned by a replay source's ``read`` when the recording is exhausted."""


END = EndOfStream()


class Supervisor:
    """Owns the device workers and the bus."""

    def __init__(self, backoff_initial: float = 0.2, backoff_max: float = 1.0,
                 stall_s: float = 5.0):
        self.bus = Bus()
        self.workers: dict[str, DeviceWorker] = {}
        self.disabled: dict[str, Health] = {}
        self.backoff_initial = backoff_initial
        self.backoff_max = backoff_max
        self.stall_s = stall_s

    def add(self, name: str, role: str, factory: Callable[[], DeviceSource], queue_len: int,
            lossy: bool, read_timeout: float = 0.5) -> DeviceWorker:
        q = self.bus.add(name, queue_len, lossy)
        w = DeviceWorker(name, role, factory, q, read_timeout, self.backoff_initial,
                         self.backoff_max, self.stall_s)
        self.workers[name] = w
        return w

    def add_disabled(self, name: str, role: str) -> None:
        self.disabled[name] = Health(name, role, state="disabled")

    def start(self) -> None:
        for w in self.workers.values():
            w.start()

    def stop(self, timeout: float = 1.0) -> None:
        for w in self.workers.values():
            w.stop()
        deadline = time.monotonic() + timeout
        for w in self.workers.values():
            w.join(max(0.0, deadline - time.monotonic()))

    def health(self) -> list[dict]:
        out = [w.health.as_dict(w.queue) for w in self.workers.values()]
        return out + [h.as_dict() for h in self.disabled.values()]

    def running(self, names: Iterable[str] | None = None) -> bool:
        return any(w.health.state == "running" for n, w in self.workers.items()
                   if names is None or n in names)

    def all_running(self) -> bool:
        """Every device has delivered a message since it was (re)opened."""
        return all(w.health.state in ("running", "finished") and w.health.messages > 0
                   for w in self.workers.values())

    def all_finished(self) -> bool:
        return bool(self.workers) and all(w.health.state in ("finished", "stopped")
                                          for w in self.workers.values())
