"""The daemon: wires config, supervisor, mapping loop, store, query server and sd_notify.

The main thread runs the mapping loop and owns time: it drains the device queues, feeds the
loop, pings the watchdog from the loop itself (a hung loop gets restarted by systemd),
checkpoints at the configured interval, and handles the signals (SIGTERM/SIGINT: checkpoint
and exit well within 2 s; SIGHUP: reload what is safe to change while running).  Query
threads read and change the loop under one lock.
"""

from __future__ import annotations

import collections
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from cgamap.daemon import config as config_mod
from cgamap.daemon import notify
from cgamap.daemon.devices import ReplaySource, build_source
from cgamap.daemon.loop import MappingLoop
from cgamap.daemon.server import (
    HINT_RADIUS_M,
    HINT_TURN,
    POSE_LIMIT_M,
    QueryServer,
    handler_table,
    hint_problem,
)
from cgamap.daemon.store import CheckpointStore
from cgamap.daemon.supervisor import Supervisor
from cgamap.mapping.jit import warm_up

log = logging.getLogger("cgamapd")

LOSSY_ROLES = ("laser", "camera")  # the newest scan/frame matters; odometry never dropped


class Daemon:
    def __init__(self, cfg: dict, config_path: str | None = None, replay: str | None = None,
                 replay_rate: float = 0.0, state_dir: str | None = None,
                 socket_path: str | None = None, exit_after_replay: bool = False,
                 laser_mount: tuple[float, float, float] | None = None):
        self.cfg = cfg
        self.config_path = config_path
        self.replay = replay
        self.replay_rate = replay_rate
        self.exit_after_replay = exit_after_replay
        state, sock = config_mod.resolve_paths(cfg)
        self.state_dir = Path(state_dir) if state_dir else state
        self.socket_path = Path(socket_path) if socket_path else sock
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.reload_requested = False
        self.checkpoint_requested = False
        self.store = CheckpointStore(self.state_dir)
        # a replayed log's own laser mount (``main.replay_mount``) over the configured one
        self.laser_mount = laser_mount
        self.loop = self._new_loop()
        self.supervisor = self._build_supervisor(cfg)
        self.server: QueryServer | None = None
        self.started_mono = time.monotonic()
        self.last_checkpoint_mono = time.monotonic()
        self.taps: list[collections.deque] = []
        self.tap_cond = threading.Condition(self.lock)
        self.loaded_from: str | None = None
        self.checkpoint_failures = 0
        self.last_checkpoint_error: str | None = None
        self.optimize_thread: threading.Thread | None = None  # the periodic pass, if running
        self._periodic_at = -1  # scans mapped when the last periodic pass started

    # -- construction -----------------------------------------------------------------------
    def _new_loop(self) -> MappingLoop:
        """The mapping loop: a replay as fast as the mapper goes loses no scan (its source
        waits for room, and the loop maps a waiting scan rather than drop it)."""
        return MappingLoop(self.cfg, laser_mount=self.laser_mount,
                           lossless=bool(self.replay) and self.replay_rate == 0)

    def _build_supervisor(self, cfg: dict) -> Supervisor:
        sv = cfg["supervisor"]
        sup = Supervisor(sv["backoff_initial"], sv["backoff_max"])
        if self.replay:
            src = Path(self.replay)
            sup.add("replay", "replay",
                    lambda: ReplaySource(str(src), roles=(), rate=self.replay_rate),
                    256, lossy=False)
            return sup
        for name, dev in cfg["devices"].items():
            if not dev["enabled"]:
                sup.add_disabled(name, dev["role"])
                continue
            sup.add(name, dev["role"], build_source(name, dev), dev["queue"] if
                    dev["role"] in LOSSY_ROLES else max(dev["queue"], 256),
                    lossy=dev["role"] in LOSSY_ROLES, read_timeout=min(dev["timeout"], 0.5))
        return sup

    # -- the run ---------------------------------------------------------------------------
    def run(self) -> int:
        notify.status("compiling the mapper's kernels")
        # about 30 s uncached on a 2-core machine (once per install): before the first scan,
        # with the start-up timeout extended while it lasts
        with notify.extending():
            log.info("mapper kernels ready in %.1f s", warm_up())
            notify.status("loading checkpoint")
            self._load_checkpoint()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stop_event.set())
        signal.signal(signal.SIGHUP, self._on_hup)
        srv = self.cfg["server"]
        self.server = QueryServer(self, self.socket_path, srv["socket_mode"],
                                  (srv["tcp_host"], srv["tcp_port"]) if srv["tcp"] else None,
                                  srv["max_clients"])
        try:
            self.server.start()
        except (OSError, RuntimeError) as exc:
            log.error("query socket: %s", exc)
            return 73  # EX_CANTCREAT
        notify.status("opening devices")
        self.supervisor.start()
        rc = 0
        try:
            self._main_loop()
        finally:
            notify.stopping()
            t0 = time.monotonic()
            self.server.stop()
            self.supervisor.stop(timeout=0.6)
            with self.lock:
                self._drain()
                self.loop.process(final=True)
                if self.checkpoint("shutdown")["class"] == "error":
                    rc = 74  # EX_IOERR: the map of this run was not saved
            log.info("stopped in %.2f s", time.monotonic() - t0)
        return rc

    def _main_loop(self) -> None:
        wd = notify.watchdog_period()
        next_wd = time.monotonic()
        next_status = time.monotonic()
        odometry_names = [n for n, w in self.supervisor.workers.items()
                          if w.health.role == "odometry"]
        # READY once every device streams, or after ready_timeout with what there is: a device
        # that never appears must not hold the service in "activating" until systemd kills it
        ready_at = time.monotonic() + self.cfg["supervisor"]["ready_timeout"]
        ready = False
        last_optimize = time.monotonic()
        while not self.stop_event.is_set():
            if not ready and (self.supervisor.all_running() or time.monotonic() >= ready_at):
                ready = True
                running = sum(w.health.state == "running"
                              for w in self.supervisor.workers.values())
                log.info("cgamapd ready: socket %s, state %s, %d/%d devices streaming",
                         self.socket_path, self.state_dir, running, len(self.supervisor.workers))
                notify.ready(self.status_line())
            self.supervisor.bus.wait(0.05)
            with self.lock:
                self._drain()
                live = self.supervisor.running(odometry_names) if odometry_names else False
                self.loop.process(odometry_live=live)
            now = time.monotonic()
            if wd is not None and now >= next_wd:
                notify.watchdog()
                next_wd = now + wd
            if self.reload_requested:
                self.reload_requested = False
                self.reload()
            if (self.checkpoint_requested
                    or now - self.last_checkpoint_mono >= self.cfg["checkpoint"]["interval"]):
                self.checkpoint_requested = False
                with self.lock:
                    self.checkpoint("interval")
            if now >= next_status:
                next_status = now + 2.0
                notify.status(self.status_line())
            every = self.cfg["mapping"].get("optimize_every_s", 0.0)  # SIGHUP may change it
            if every and now - last_optimize >= every:
                last_optimize = now
                self._optimize_in_background()
            if self.replay and self.supervisor.all_finished():
                with self.lock:
                    self._drain()
                    self.loop.process(final=True)
                if self.exit_after_replay:
                    log.info("replay finished: %d scans", self.loop.counts["scans"])
                    return

    def _drain(self) -> None:
        for name, msg in self.supervisor.bus.drain():
            self.loop.handle(name, msg)
            if self.taps:
                for tap in self.taps:
                    tap.append((name, msg))
        if self.taps:
            self.tap_cond.notify_all()

    def _on_hup(self, *_: Any) -> None:
        self.reload_requested = True

    def status_line(self) -> str:
        s = self.loop.status()
        running = sum(w.health.state == "running" for w in self.supervisor.workers.values())
        x, y, th = s["pose"]
        return (f"{running}/{len(self.supervisor.workers)} devices, pose {x:.2f} {y:.2f} "
                f"{np.degrees(th):.0f}deg, {s['map']['segments']} segments, "
                f"{s['map']['planes']} planes")

    # -- persistence -------------------------------------------------------------------------
    def _load_checkpoint(self) -> None:
        try:
            payload = self.store.load()
        except OSError as exc:
            log.warning("cannot read checkpoints in %s: %s", self.state_dir, exc)
            return
        if payload is None:
            log.info("no checkpoint in %s: starting an empty map", self.state_dir)
            return
        try:
            self.loop.load_state(payload["loop"])
            self.loaded_from = payload.get("_file")
            log.info("loaded checkpoint %s", self.loaded_from)
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("checkpoint %s does not fit this build (%s): empty map",
                        payload.get("_file"), exc)
            self.loop = self._new_loop()

    def checkpoint(self, reason: str) -> dict:
        try:
            path = self.store.save({"reason": reason, "loop": self.loop.state(),
                                    "config": self.config_path})
        except Exception as exc:  # noqa: BLE001 - a failed checkpoint must not stop mapping
            log.error("checkpoint failed: %s: %s", type(exc).__name__, exc)
            self.checkpoint_failures += 1
            self.last_checkpoint_error = f"{reason}: {type(exc).__name__}: {exc}"[:200]
            return {"class": "error", "error": f"checkpoint failed: {exc}"}
        finally:
            self.last_checkpoint_mono = time.monotonic()
        return {"class": "checkpoint", "path": str(path), "reason": reason,
                "duration_s": round(self.store.last_save_s or 0.0, 4)}

    # -- SIGHUP ---------------------------------------------------------------------------
    def reload(self) -> None:
        """Re-read the config: log level, checkpoint interval, loss thresholds, the periodic
        optimisation and backoff apply at once; a device whose URL or parameters changed is
        restarted; added or removed devices and role changes need a restart (logged)."""
        notify.reloading()
        if not self.config_path:
            return
        try:
            new = config_mod.load(self.config_path)
        except config_mod.ConfigError as exc:
            log.error("reload: %s: %s (keeping the running config)", self.config_path, exc)
            notify.ready("mapping (reload failed)")
            return
        logging.getLogger().setLevel(new["log_level"].upper())
        with self.lock:
            self.cfg["checkpoint"] = new["checkpoint"]
            self.cfg["log_level"] = new["log_level"]
            self.loop.lost_quality = new["mapping"]["lost_quality"]
            self.loop.lost_after = new["mapping"]["lost_after"]
            self.loop.lost_radius = new["mapping"]["lost_radius"]
            self.cfg["mapping"]["optimize_every_s"] = new["mapping"]["optimize_every_s"]
            for w in self.supervisor.workers.values():
                w.backoff_initial = new["supervisor"]["backoff_initial"]
                w.backoff_max = new["supervisor"]["backoff_max"]
            if not self.replay:
                old_devs, new_devs = self.cfg["devices"], new["devices"]
                if set(old_devs) != set(new_devs):
                    log.warning("reload: devices added or removed; restart cgamapd to apply")
                for name in set(old_devs) & set(new_devs):
                    o, n = old_devs[name], new_devs[name]
                    if o == n or name not in self.supervisor.workers:
                        continue
                    if o["role"] != n["role"]:
                        log.warning("reload: %s changed role; restart cgamapd to apply", name)
                        continue
                    w = self.supervisor.workers[name]
                    w.factory = build_source(name, n)
                    old_devs[name] = n
                    w.restart()
                    log.info("reload: restarting device %s with its new settings", name)
        log.info("configuration reloaded from %s", self.config_path)
        notify.ready(self.status_line())

    # -- queries ---------------------------------------------------------------------------
    def command(self, req: dict) -> dict:
        fn = handler_table(self).get(req["cmd"])
        if fn is None:
            return {"class": "error", "error": f"unknown command {req['cmd']!r}",
                    "commands": sorted(handler_table(self)) + ["watch"]}
        try:
            return fn(req)
        except (ValueError, TypeError, KeyError) as exc:
            return {"class": "error", "error": f"{req['cmd']}: {exc}"}
        except Exception as exc:  # noqa: BLE001 - a failing query must not cost the client
            log.exception("command %s failed", req["cmd"])
            return {"class": "error", "error": f"{req['cmd']}: internal error: {exc}"}

    def cmd_version(self, req: dict) -> dict:
        from cgamap.daemon.cli import package_version

        return {"class": "version", "release": package_version(), "proto": 1}

    def cmd_status(self, req: dict) -> dict:
        with self.lock:
            s = self.loop.status()
            s["loaded_from"] = self.loaded_from
        s.update({"class": "status", "uptime_s": round(time.monotonic() - self.started_mono, 2),
                  "devices": self.supervisor.health(), "replay": self.replay,
                  "checkpoint": {"saves": self.store.saves, "dir": str(self.state_dir),
                                 "last_duration_s": self.store.last_save_s,
                                 "last_saved_at": self.store.last_saved_at,
                                 "failures": self.checkpoint_failures,
                                 "last_error": self.last_checkpoint_error,
                                 "interval_s": self.cfg["checkpoint"]["interval"]}})
        for d in s["devices"]:
            d["rate_hz"] = round(self.loop.rate(d["name"]), 2) or d["rate_hz"]
        return s

    def cmd_map(self, req: dict) -> dict:
        with self.lock:
            out = self.loop.map_json()
        return {"class": "map", **out}

    def cmd_trajectory(self, req: dict) -> dict:
        with self.lock:
            traj = list(self.loop.trajectory)
        cols = ["stamp_ns", "device_stamp", "x", "y", "theta", "quality"]
        return {"class": "trajectory", "columns": cols, "rows": traj}

    def cmd_relocalize(self, req: dict) -> dict:
        """Relocalise on the latest scan; with ``near`` [x, y, theta] (a hint, as a person
        gives one on a map) only within ``radius`` metres and ``turn`` radians of it
        (default ``HINT_RADIUS_M``, ``HINT_TURN``)."""
        near = None
        if "near" in req:
            hint = req["near"]
            if not isinstance(hint, list) or len(hint) != 3:
                raise ValueError("near must be [x, y, theta]")
            pose = [float(v) for v in hint]
            radius = float(req.get("radius", HINT_RADIUS_M))
            turn = float(req.get("turn", HINT_TURN))
            problem = hint_problem(pose, radius, turn)
            if problem:
                raise ValueError(problem)
            near = (np.array(pose), radius, turn)
        elif "radius" in req or "turn" in req:
            raise ValueError("radius and turn need near")
        with self.lock:
            return {"class": "relocalize", **self.loop.relocalize(near=near)}

    def cmd_checkpoint(self, req: dict) -> dict:
        with self.lock:
            return self.checkpoint("request")

    def cmd_optimize(self, req: dict) -> dict:
        """The finishing pass over the kept nodes (MappingLoop.optimize): computed here,
        in the query thread, on a snapshot while the main thread keeps mapping, then applied
        under the lock between two scans.  A second request while one runs is an error."""
        return {"class": "optimize", **self.optimize()}

    def optimize(self) -> dict:
        """One pass (MappingLoop.optimize) under the daemon's lock, abandoned on shutdown."""
        return self.loop.optimize(self.lock, self.stop_event.is_set,
                                  stopping="the daemon is stopping; nothing applied")

    def _optimize_in_background(self) -> None:
        """The periodic pass (mapping.optimize_every_s) in its own thread; skipped while a
        pass (periodic or requested) is running, and when no scan was mapped since the last
        periodic one (a robot standing for days needs no pass an hour)."""
        with self.lock:
            scans = self.loop.counts["scans"]
            if self.loop.optimizing or self.loop.mapper is None or scans == self._periodic_at:
                return
            self._periodic_at = scans

        def run() -> None:
            try:
                got = self.optimize()
                log.info("periodic optimisation: %d edges over %d nodes, max shift %.3f m, "
                         "%.0f ms", got["edges"], got["nodes"], got["max_shift_m"], got["ms"])
            except ValueError as exc:
                log.info("periodic optimisation skipped: %s", exc)
            except Exception:  # noqa: BLE001 - the map stays as it was
                log.exception("periodic optimisation failed")

        self.optimize_thread = threading.Thread(target=run, name="optimize", daemon=True)
        self.optimize_thread.start()

    def cmd_set_pose(self, req: dict) -> dict:
        pose = [float(req[k]) for k in ("x", "y", "theta")]
        if not all(np.isfinite(pose)):
            raise ValueError("x, y, theta must be finite")
        if max(abs(pose[0]), abs(pose[1])) > POSE_LIMIT_M:
            raise ValueError(f"x, y must be within +-{POSE_LIMIT_M:g} m")
        pose[2] = float(np.arctan2(np.sin(pose[2]), np.cos(pose[2])))
        with self.lock:
            self.loop.set_pose(pose)
            return {"class": "pose", "pose": self.loop.pose_list()}

    def watch(self, req: dict, send, stopping: threading.Event) -> None:
        """Stream events (pose, planes) and a status every ``interval`` s; with ``raw`` every
        device message too (as recorded JSON)."""
        from cgamap.daemon.recording import TOPICS, to_record

        interval = float(req.get("interval", 1.0))
        raw = bool(req.get("raw", False))
        tap: collections.deque = collections.deque(maxlen=4096)
        with self.lock:
            seq = self.loop.event_seq
            if raw:
                self.taps.append(tap)
        if not send({"class": "watch", "enable": True, "raw": raw}):
            return
        next_status = 0.0
        try:
            while not stopping.is_set() and not self.stop_event.is_set():
                with self.lock:
                    if raw and not tap:
                        self.tap_cond.wait(0.1)
                    events = [e for e in self.loop.events if e["seq"] > seq]
                    msgs = list(tap)
                    tap.clear()
                if events:
                    seq = events[-1]["seq"]
                for e in events:
                    if not send(e):
                        return
                for name, msg in msgs:
                    spec = TOPICS.get(type(msg))
                    if spec is None:
                        continue
                    if not send({"class": "raw", "device": name, "topic": spec[0],
                                 "schema": spec[1], "stamp_ns": msg.stamp_ns,
                                 "body": to_record(msg)}):
                        return
                now = time.monotonic()
                if now >= next_status:
                    next_status = now + interval
                    if not send(self.cmd_status({})):
                        return
                if not raw:
                    time.sleep(0.05)
        finally:
            with self.lock:
                self.taps = [t for t in self.taps if t is not tap]

