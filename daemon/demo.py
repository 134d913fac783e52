"""``cgamap demo``: the simulated robot end to end.

Starts the twins (Hokuyo laser and Modbus base as processes speaking their wire protocols; a
pan-tilt twin when one is installed; the stereo camera rendered inside the daemon), runs
``cgamapd`` on ``config/sim.yaml`` with the sim:// URLs resolved, drives the base along the
simulated world's path (feed-forward wheel speeds from the path, so odometry is a realistic,
drifting guess), shows progress, then writes into the output folder: the 2D map PNG, the 3D
map PLY, the map JSON, and a report of the pose error against the simulation's truth.

Truth: the Hokuyo twin's scans carry its millisecond clock (SCIP timestamps), and the twin
senses the world at ``world.trajectory(clock)``; the daemon logs each mapped scan's device
stamp with its pose, so every estimated pose has an exact true pose.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from cgamap.daemon import config as config_mod
from cgamap.daemon.export import export
from cgamap.daemon.server import request
from cgamap.daemon.twins import Twin, start_twin, twin_available
from cgamap.mapping.fileio import write_text_atomic
from cgamap.mapping.jit import warm_up

REPO = Path(__file__).resolve().parents[1]
SIM_TWINS = {"hokuyo": "hokuyo", "lms2xx": "lms2xx", "modbus-base": "modbus-base",
             "dynamixel": "dynamixel-pantilt"}


def default_config() -> Path:
    return REPO / "config" / "sim.yaml"


class NotifyListener:
    """A fake systemd notify socket: collects the daemon's datagrams."""

    def __init__(self, path: Path):
        self.path = path
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.messages.extend(data.decode(errors="replace").split("\n"))

    def wait_for(self, field: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if field in self.messages:
                return True
            time.sleep(0.05)
        return False

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()


def path_speeds(world: Any, t: float, wheel_radius: float, track: float,
                dt: float = 0.05) -> tuple[float, float]:
    """Wheel speeds (rad/s) that drive the world's path at time t (central differences)."""
    p0 = np.array(world.trajectory(max(t - dt, 0.0)))
    p1 = np.array(world.trajectory(t + dt))
    h = (t + dt) - max(t - dt, 0.0)
    v = math.hypot(*(p1[:2] - p0[:2])) / h
    w = math.remainder(p1[2] - p0[2], 2 * math.pi) / h
    return (v - w * track / 2) / wheel_radius, (v + w * track / 2) / wheel_radius


class Driver(threading.Thread):
    """The driving script: feed-forward wheel set-points along the world's path at 20 Hz."""

    def __init__(self, url: str, world: Any, epoch_ns: int, geom: dict):
        super().__init__(daemon=True, name="demo-driver")
        self.url, self.world, self.epoch_ns, self.geom = url, world, epoch_ns, geom
        self.stop_event = threading.Event()
        self.commands = 0
        self.error: str | None = None
        # the twins' clock (ms) when the wheels were told to stop: the twin's robot goes on
        # along the path, so later scans and the stopped odometry disagree
        self.stopped_ms: float | None = None

    def run(self) -> None:
        from cgamap.drivers.modbus_base import ModbusBase, ModbusBaseConfig

        base = ModbusBase(ModbusBaseConfig(url=self.url, allow_setpoints=True))
        try:
            base.open()
            r, b = self.geom["wheel_radius"], self.geom["track_width"]
            while not self.stop_event.wait(0.05):
                t = (time.monotonic_ns() - self.epoch_ns) / 1e9
                wl, wr = path_speeds(self.world, t, r, b)
                base.set_wheel_speeds(wl, wr)
                self.commands += 1
            self.stopped_ms = (time.monotonic_ns() - self.epoch_ns) / 1e6
            base.set_wheel_speeds(0.0, 0.0)
        except Exception as exc:  # noqa: BLE001 - reported in the demo's output
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            base.close()


def truth_error(rows: list, world: Any, until_ms: float | None = None) -> dict:
    """Pose error of the daemon's per-scan poses against the world path at the scans'
    device clock: ATE after rigid alignment, RPE over ~1 m, and the final pose error.
    ``until_ms``: score only scans stamped up to then (the drive's end: the simulated
    robot moves on along its path while the stopped wheels say it stands)."""
    from cgamap.mapping.evaluation import align_rigid_2d, apply_pose, ate, rpe

    arr = np.asarray([r for r in rows if r[1] >= 0], dtype=float).reshape(-1, 6)
    late = arr[:, 1] > until_ms if until_ms is not None else np.zeros(len(arr), bool)
    arr = arr[~late]
    if len(arr) < 3:
        return {"poses": int(len(arr)), "error": "too few poses to score"}
    est = arr[:, 2:5]
    ref = np.stack(world.trajectory(arr[:, 1] / 1000.0), axis=-1)
    out: dict[str, Any] = {"poses": int(len(est)), "poses_after_drive": int(late.sum()),
                           **ate(est, ref)}
    with contextlib.suppress(ValueError, IndexError):
        out.update(rpe(est, ref, 1.0))
    T = align_rigid_2d(est, ref)
    al = apply_pose(T, est)
    d = al[-1] - ref[-1]
    out["final_trans_m"] = float(math.hypot(d[0], d[1]))
    out["final_rot_deg"] = float(abs(math.degrees(math.remainder(d[2], 2 * math.pi))))
    out["path_length_m"] = float(np.sum(np.linalg.norm(np.diff(ref[:, :2], axis=0), axis=1)))
    out["alignment"] = [float(v) for v in T]
    out["_aligned"] = al
    out["_ref"] = ref
    return out


def map_error(segments, world: Any, alignment) -> dict:
    """Distance of the map's segment end points (moved into the world frame by
    ``alignment``) to the nearest true wall: how far the 2D map is from the building."""
    seg = np.asarray(segments, dtype=float).reshape(-1, 4)
    if not len(seg):
        return {"map_segments": 0}
    x, y, th = alignment
    c, s = math.cos(th), math.sin(th)
    p = np.concatenate([seg[:, :2], seg[:, 2:]]) @ np.array([[c, s], [-s, c]]) + [x, y]
    w = world.segments
    a, ab = w[:, :2], w[:, 2:] - w[:, :2]
    t = np.clip(np.einsum("nmk,mk->nm", p[:, None] - a, ab) / np.einsum("mk,mk->m", ab, ab),
                0.0, 1.0)
    d = np.linalg.norm(p[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)
    return {"map_segments": int(len(seg)), "wall_dist_median_m": float(np.median(d)),
            "wall_dist_p95_m": float(np.percentile(d, 95)), "wall_dist_max_m": float(d.max())}


def resolve_config(cfg_path: Path, twins: dict[str, Twin], out: Path, run_dir: Path,
                   duration: float, epoch_ns: int) -> tuple[Path, dict]:
    raw = yaml.safe_load(cfg_path.read_text())
    raw.setdefault("paths", {})
    raw["paths"].update({"state_dir": str(out / "state"), "runtime_dir": str(run_dir)})
    for dev in raw.get("devices", {}).values():
        url = dev.get("url", "")
        if not url.startswith("sim://"):
            continue
        name = url[len("sim://"):]
        if name in twins:
            dev["url"] = twins[name].url
        elif dev.get("role") == "camera":
            # rendered inside the daemon, on the laser twin's clock (see devices.py)
            dev["url"] = f"sim://{raw.get('sim', {}).get('world', 'loop')}"
            dev.setdefault("params", {})["epoch_ns"] = epoch_ns
        else:
            dev["enabled"] = False  # no twin for it in this build
    path = out / "sim-resolved.yaml"
    write_text_atomic(path, yaml.safe_dump(raw, sort_keys=False))
    cfg = config_mod.load(path)
    return path, cfg


def _camera_local(cfg: dict) -> bool:
    cam = next((d for d in cfg["devices"].values() if d["role"] == "camera"), None)
    return cam is not None and cam["enabled"]


def run_demo(out: Path, duration: float = 60.0, cfg_path: Path | None = None,
             world_name: str | None = None, progress=print, camera: bool = True) -> dict:
    """Run the demo; returns the report (also written to ``out``)."""
    from cgamap.drivers.sim.world import get_world

    cfg_path = cfg_path or default_config()
    base_cfg = config_mod.load(cfg_path)
    sim = base_cfg["sim"]
    world_name = world_name or sim.get("world", "loop")
    world = get_world(world_name)
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_dir = Path(os.environ.get("XDG_RUNTIME_DIR") or "/tmp") / f"cgamap-demo-{os.getpid()}"
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in (out / "state").glob("*"):
        stale.unlink()
    twins: dict[str, Twin] = {}
    procs: list[subprocess.Popen] = []
    notify = None
    driver = None
    report: dict[str, Any] = {"world": world_name, "duration_s": duration}
    # the twins run in sessions of their own (a terminal's Ctrl-C must reach only the demo,
    # which stops them): a SIGTERM must unwind through the finally below as Ctrl-C does, or
    # a killed demo leaves its twins running
    previous = _exit_on_sigterm()
    try:
        # the twins' clock is the path's: the robot is on its way from the laser twin's
        # start.  Uncached, the daemon's kernels took 9 s to compile before it read a scan,
        # and the drive then ended before the loop closed (2-3 cm ATE instead of 1-3 mm):
        # compile (and cache) them here first, so the daemon only loads them
        progress("compiling the mapper's kernels (cached after the first run) ...")
        warm_up()
        need = {urlname[len("sim://"):] for urlname in
                (d["url"] for d in base_cfg["devices"].values()) if urlname.startswith("sim://")}
        for name in sorted(need):
            twin = SIM_TWINS.get(name, name)
            if twin in ("hokuyo", "lms2xx", "modbus-base", "dynamixel-pantilt") and \
                    twin_available(twin):
                progress(f"starting twin {twin} ...")
                twins[name] = start_twin(twin, world=world_name, seed=int(sim.get("seed", 0)))
                progress(f"  {twin} at {twins[name].where}")
        laser = next((twins[n] for n in ("hokuyo", "lms2xx") if n in twins), None)
        if laser is None or "modbus-base" not in twins:
            raise RuntimeError("the demo needs the laser and base twins")
        epoch = laser.started_ns
        resolved, cfg = resolve_config(cfg_path, twins, out, run_dir, duration, epoch)
        if not camera:
            for d in cfg["devices"].values():
                if d["role"] == "camera":
                    d["enabled"] = False
            raw = yaml.safe_load(resolved.read_text())
            for d in raw["devices"].values():
                if d.get("role") == "camera":
                    d["enabled"] = False
            write_text_atomic(resolved, yaml.safe_dump(raw, sort_keys=False))
        sock = config_mod.resolve_paths(cfg)[1]
        # drive from now on: the laser twin's robot moves on its own clock, so the base must
        # move with it before the daemon reads either
        base_dev = next(d for d in cfg["devices"].values() if d["role"] == "odometry")
        geom = {"wheel_radius": 0.05, "track_width": 0.30,
                **{("track_width" if k == "track" else k): v
                   for k, v in base_dev["params"].items()}}
        driver = Driver(twins["modbus-base"].url, world, epoch, geom)
        driver.start()
        notify = NotifyListener(run_dir / "notify")
        env = dict(os.environ, NOTIFY_SOCKET=str(notify.path), WATCHDOG_USEC="2000000")
        env.pop("STATE_DIRECTORY", None)
        env.pop("RUNTIME_DIRECTORY", None)
        log = open(out / "cgamapd.log", "w")  # noqa: SIM115 - closed with the process
        progress("starting cgamapd ...")
        t_daemon = time.monotonic()
        daemon = subprocess.Popen([sys.executable, "-m", "cgamap.daemon.main", "-c",
                                   str(resolved)], env=env, stdout=log, stderr=log)
        procs.append(daemon)
        if not notify.wait_for("READY=1", 60.0):
            raise RuntimeError(f"cgamapd did not report READY (see {out / 'cgamapd.log'})")
        progress(f"cgamapd ready (socket {sock}); driving for {duration:.0f} s through "
                 f"the simulated '{world_name}' world")
        t0 = time.monotonic()
        next_report = t0
        while time.monotonic() - t0 < duration:
            if daemon.poll() is not None:
                raise RuntimeError(f"cgamapd exited ({daemon.returncode}); see cgamapd.log")
            time.sleep(0.2)
            if time.monotonic() >= next_report:
                next_report += 5.0
                st = request(sock, "status")
                x, y, th = st["pose"]
                devs = " ".join(f"{d['name']}:{'ok' if d['state'] == 'running' else d['state']}"
                                for d in st["devices"])
                progress(f"[{time.monotonic() - t0:5.1f}/{duration:.0f} s] pose "
                         f"({x:6.2f}, {y:6.2f}, {math.degrees(th):5.0f} deg)  "
                         f"{st['map']['segments']:4d} segments  {st['map']['planes']:3d} "
                         f"planes  scans {st['counts'].get('scans', 0)}  {devs}")
        driver.stop_event.set()
        driver.join(2.0)
        status = request(sock, "status")
        map_reply = request(sock, "map")
        traj = request(sock, "trajectory")["rows"]
        err = truth_error(traj, world, driver.stopped_ms)
        aligned, ref = err.pop("_aligned", None), err.pop("_ref", None)
        # the map in the world frame (the daemon's map starts at its first pose)
        if "alignment" in err and map_reply["segments"]:
            from cgamap.mapping.evaluation import apply_pose

            seg = np.asarray(map_reply["segments"], float)
            T = err["alignment"]
            ends = np.concatenate([seg[:, :2], seg[:, 2:]])
            moved = apply_pose(T, np.column_stack([ends, np.zeros(len(ends))]))[:, :2]
            world_map = dict(map_reply, segments=np.concatenate(
                [moved[:len(seg)], moved[len(seg):]], axis=1).tolist())
        else:
            world_map = map_reply
        if "alignment" in err:
            err.update(map_error(map_reply["segments"], world, err["alignment"]))
        files = []
        files += export(world_map, "png", out / "map.png", trajectory=aligned, reference=ref)
        files += export(map_reply, "ply", out / "map3d.ply")
        from cgamap.daemon.export import render_3d_png

        files += render_3d_png(map_reply, out / "map3d.png")  # the daemon's map frame
        files += export(map_reply, "json", out / "map.json")
        files += export(map_reply, "pgm", out / "map.pgm")
        cpu_s = process_cpu_s(daemon.pid)
        # stop the daemon the way systemd does, and check its last checkpoint
        t_stop = time.monotonic()
        daemon.send_signal(signal.SIGTERM)
        rc = daemon.wait(10)
        stop_s = time.monotonic() - t_stop
        from cgamap.daemon.store import CheckpointStore

        ck = CheckpointStore(cfg["paths"]["state_dir"]).load()
        report.update({
            "truth": err, "segments": len(map_reply["segments"]),
            "planes": len(map_reply["planes"]), "counts": status["counts"],
            "configurations": sorted(c["kind"] for c in map_reply.get("configurations", [])),
            "timing_ms": status.get("timing_ms"),
            "devices": {d["name"]: {k: d[k] for k in ("state", "restarts", "messages")}
                        for d in status["devices"]},
            "driver_commands": driver.commands, "driver_error": driver.error,
            "daemon_exit": rc, "stop_s": round(stop_s, 3),
            "daemon_cpu_s": cpu_s, "daemon_cpu_fraction": None if cpu_s is None else
            round(cpu_s / max(time.monotonic() - t_daemon, 1e-9), 3),
            "checkpoint_ok": ck is not None and ck.get("reason") == "shutdown",
            "notify": sorted(set(m.split("=")[0] for m in notify.messages if m)),
            "files": [str(f) for f in files],
        })
        write_report(out, report)
        return report
    finally:
        if driver is not None:
            driver.stop_event.set()
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(5)
        for t in twins.values():
            t.stop()
        if notify is not None:
            notify.close()
        for f in run_dir.glob("*"):
            with contextlib.suppress(OSError):
                f.unlink()
        with contextlib.suppress(OSError):
            run_dir.rmdir()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _exit_on_sigterm():
    """SIGTERM raises SystemExit(143) in the main thread; returns the handler it replaced
    (None when not in the main thread, where handlers cannot be set)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    return signal.signal(signal.SIGTERM, stop)


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a live process (Linux /proc), else None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return round((int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), 2)
    except (OSError, ValueError, IndexError):
        return None


def write_report(out: Path, report: dict) -> None:
    write_text_atomic(out / "report.json", json.dumps(report, indent=1, default=float))
    t = report.get("truth", {})
    lines = [
        "# cgamap demo report", "",
        f"World `{report['world']}`, {report['duration_s']:.0f} s of driving; "
        f"{t.get('path_length_m', 0):.1f} m of path, {t.get('poses', 0)} mapped scans scored"
        f" ({t.get('poses_after_drive', 0)} more after the drive stopped: not scored).", "",
        "| pose error against the simulation's truth | value |", "|---|---|",
    ]
    for key, label in (("ate_trans_m", "ATE translation (m, RMS, rigidly aligned)"),
                       ("ate_rot_deg", "ATE rotation (deg, RMS)"),
                       ("ate_trans_max_m", "ATE translation max (m)"),
                       ("rpe_trans_m", "RPE translation over ~1 m (m)"),
                       ("rpe_rot_deg", "RPE rotation over ~1 m (deg)"),
                       ("final_trans_m", "final pose translation error (m)"),
                       ("final_rot_deg", "final pose rotation error (deg)"),
                       ("wall_dist_median_m", "map: segment end to true wall, median (m)"),
                       ("wall_dist_p95_m", "map: segment end to true wall, 95th pct (m)")):
        if key in t:
            lines.append(f"| {label} | {t[key]:.3f} |")
    kinds = report.get("configurations") or []
    found = ", ".join(f"{kinds.count(k)} {k}" for k in sorted(set(kinds))) or "none"
    lines += ["", f"Map: {report.get('segments')} segments, {report.get('planes')} planes; "
              f"plane configurations found: {found}. "
              f"Daemon exit code {report.get('daemon_exit')} after SIGTERM in "
              f"{report.get('stop_s')} s; final checkpoint "
              f"{'valid' if report.get('checkpoint_ok') else 'MISSING'}.", ""]
    tm = report.get("timing_ms") or {}
    c = report.get("counts") or {}
    lines += [f"Mapping: {c.get('scans', 0)} scans mapped of {c.get('scans_in', 0)} received "
              f"({tm.get('scan_ms', 0):.1f} ms each), {c.get('frames', 0)} stereo frames "
              f"({tm.get('frame_ms', 0):.0f} ms each); pipeline errors: "
              f"{sum(v for k, v in c.items() if k.startswith('errors'))}; daemon CPU "
              f"{report.get('daemon_cpu_s')} s ({report.get('daemon_cpu_fraction')} of one "
              "core).", ""]
    lines += ["Files: " + ", ".join(Path(f).name for f in report.get("files", [])), ""]
    write_text_atomic(out / "report.md", "\n".join(lines))
