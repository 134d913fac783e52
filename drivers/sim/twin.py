"""Plumbing shared by the device twins: the twin thread's life cycle, fault requests, and the
``cgamap sim-device`` serve-until-signal loop; small helpers of the pty twins.

:class:`TwinControl` is a base for twins that run their device in one thread (``_run``): it
holds the lock, the truncate counter and stall deadline that the fault methods set and the
thread reads, and a queue of requests (unplug, replug) that the thread executes between two
I/O steps, so that a test thread never closes a device the twin thread is using.
:class:`ScanTwin` adds the state of the twins that ray-cast scans from a simulated world.

:func:`serve_until_signal` is the body of a twin module's ``main(args)``: start, print where
to connect as the first stdout line, serve until SIGINT/SIGTERM, stop; optionally SIGUSR1
unplugs for a while and SIGUSR2 stalls.  :func:`flip_bytes` (line noise) serves the pty twins
of the Modbus base and the Dynamixel bus.
"""

from __future__ import annotations

import collections
import random
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Self

import numpy as np

from .world import NoiseModel, World, get_world


class TwinControl:
    """Life cycle and fault requests of a twin served by one thread.

    A subclass implements ``_run`` (the thread: loop while ``_running``, calling
    :meth:`_serve_requests` each turn) and, to be unpluggable, ``_unplug``/``_replug``; it
    releases its device in ``stop()`` after ``super().stop()``.
    """

    _thread_name = "twin"
    _join_s = 5.0   # how long stop() waits for the thread

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._truncate = 0
        self._stall_until = 0.0
        self._requests: collections.deque[tuple[str, threading.Event]] = collections.deque()
        self._running = False
        self._thread: threading.Thread | None = None

    # -- faults (thread-safe) ----------------------------------------------------------------
    def truncate(self, count: int = 1) -> None:
        """Cut the next ``count`` scan telegrams short."""
        with self._lock:
            self._truncate += count

    def stall(self, seconds: float) -> None:
        """Hang: no output and no answers for ``seconds`` (input received meanwhile is lost)."""
        with self._lock:
            self._stall_until = time.monotonic() + seconds

    def unplug(self) -> None:
        """Pull the plug (the twin's ``_unplug``), done by the twin thread between I/O steps."""
        self._request("unplug")

    def replug(self) -> None:
        """Plug back in (the twin's ``_replug``): the device returns as after power-on."""
        self._request("replug")

    def _take_truncate(self) -> bool:
        """Whether to cut the telegram being sent (consumes one pending truncation)."""
        with self._lock:
            cut = self._truncate > 0
            if cut:
                self._truncate -= 1
        return cut

    def _request(self, what: str) -> None:
        """Have the twin thread ``_do(what)`` and wait for it (directly if not running)."""
        if not self._running:
            self._do(what)
            return
        done = threading.Event()
        self._requests.append((what, done))
        if not done.wait(5.0):
            raise TimeoutError(f"twin did not {what}")

    def _serve_requests(self) -> None:
        """Called by the twin thread: execute the pending requests."""
        while self._requests:
            what, done = self._requests.popleft()
            self._do(what)
            done.set()

    def _do(self, what: str) -> None:
        if what == "unplug":
            self._unplug()
        elif what == "replug":
            self._replug()

    def _unplug(self) -> None:
        raise NotImplementedError

    def _replug(self) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        raise NotImplementedError

    # -- life cycle ------------------------------------------------------------------------
    def start(self) -> Self:
        self._running = True
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """End the twin thread (subclasses then close their device)."""
        self._running = False
        if self._thread is not None:
            self._thread.join(self._join_s)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ScanTwin(TwinControl):
    """A :class:`TwinControl` that ray-casts scans from a simulated world (the SICK and Hokuyo
    twins): the world, its noise, the random stream for noise and faults, the device clock's
    ``time_scale``, and what was sent."""

    def __init__(self, world: str | World, *, seed: int, fault_rate: float, time_scale: float,
                 noise: NoiseModel | None) -> None:
        super().__init__()
        self.world = get_world(world) if isinstance(world, str) else world
        self.rng = np.random.default_rng(seed)
        self.fault_rate = float(fault_rate)
        self.time_scale = float(time_scale)
        self.noise = noise if noise is not None else NoiseModel(sigma=0.01, dropout=0.002)
        # per streamed scan telegram, the twin's record of it (the SICK twins: its values as a
        # key and whether it left intact; the Hokuyo twin: a SentScan)
        self.sent: collections.deque[Any] = collections.deque(maxlen=200000)
        # ground truth per generated scan: (device counter, sim time, x, y, theta)
        self.truth: collections.deque[tuple[int, float, float, float, float]] = \
            collections.deque(maxlen=200000)
        self.stats: collections.Counter[str] = collections.Counter()


@dataclass
class SignalFaults:
    """What SIGUSR1 and SIGUSR2 do to a twin served by :func:`serve_until_signal`."""

    unplug: Callable[[], None]
    replug: Callable[[], None]
    stall: Callable[[float], None]
    unplug_s: float = 2.0    # SIGUSR1: unplug, replug this long after
    stall_s: float = 2.0     # SIGUSR2: stall this long


def serve_until_signal(start: Callable[[], str], stop: Callable[[], None], *,
                       banner: str | None = None, faults: SignalFaults | None = None) -> int:
    """Serve a twin from the main thread of ``cgamap sim-device NAME``; returns 0.

    ``start()`` starts the twin and returns the pty path or host:port, printed as the first
    stdout line (flushed); ``banner`` goes to stderr.  Serves until SIGINT/SIGTERM, then calls
    ``stop()``.  With ``faults``, SIGUSR1 unplugs the twin for ``unplug_s`` and SIGUSR2 stalls
    it: both are executed by this loop, not in the signal handler, so that a stop signal during
    an unplug ends the wait and no replug outlives ``stop()``.
    """
    done = threading.Event()
    actions: collections.deque[str] = collections.deque()
    signal.signal(signal.SIGINT, lambda *_: done.set())
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    if faults is not None:
        signal.signal(signal.SIGUSR1, lambda *_: actions.append("unplug"))
        signal.signal(signal.SIGUSR2, lambda *_: actions.append("stall"))
    where = start()
    try:
        print(where, flush=True)
        if banner:
            print(banner, file=sys.stderr, flush=True)
        while not done.wait(0.1):
            while actions and faults is not None:
                if actions.popleft() == "unplug":
                    faults.unplug()
                    if done.wait(faults.unplug_s):
                        break
                    faults.replug()
                else:
                    faults.stall(faults.stall_s)
    finally:
        stop()
    sys.stdout.flush()
    return 0


def flip_bytes(data: bytes, rate: float, rng: random.Random) -> bytes:
    """Line noise: each byte inverted with probability ``rate`` (one draw per byte)."""
    return bytes(b ^ 0xFF if rng.random() < rate else b for b in data)
