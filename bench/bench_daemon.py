"""Daemon figures: checkpoint cost by map size, query round trip, log replay throughput and
pose error on the real Intel log (against the log's corrected poses).  Measures, never asserts."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import yaml


def _checkpoint_cost() -> dict:
    from cgamap.daemon import config as config_mod
    from cgamap.daemon.loop import MappingLoop
    from cgamap.daemon.store import CheckpointStore

    out = {}
    with tempfile.TemporaryDirectory() as d:
        for n in (500, 2000, 8000):
            loop = MappingLoop(config_mod.validate({}))
            lm = loop.mapper.m.map
            rng = np.random.default_rng(0)
            for f in fields(lm):
                v = getattr(lm, f.name)
                if isinstance(v, np.ndarray):
                    setattr(lm, f.name, rng.normal(size=(n,) + v.shape[1:]).astype(v.dtype))
            store = CheckpointStore(d)
            times = []
            for _ in range(5):
                store.save({"loop": loop.state()})
                times.append(store.last_save_s)
            t0 = time.perf_counter()
            store.load()
            out[f"segments_{n}"] = {"save_ms_median": round(1e3 * float(np.median(times)), 2),
                                    "load_ms": round(1e3 * (time.perf_counter() - t0), 2),
                                    "bytes": store.current.stat().st_size}
    return out


def _daemon(cfg: dict, work: Path, run: Path, extra: list[str]) -> subprocess.Popen:
    cfg = dict(cfg, paths={"state_dir": str(work / "state"), "runtime_dir": str(run)})
    (work / "c.yaml").write_text(yaml.safe_dump(cfg))
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
    return subprocess.Popen([sys.executable, "-m", "cgamap.daemon.main", "-c",
                             str(work / "c.yaml"), *extra], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _query_latency() -> dict:
    from cgamap.daemon.server import DaemonUnavailable, request

    work, run = Path(tempfile.mkdtemp()), Path(tempfile.mkdtemp(prefix="cgb-"))
    p = _daemon({"checkpoint": {"interval": 60.0}}, work, run, [])
    try:
        sock = run / "cgamapd.sock"
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                request(sock, "version")
                break
            except DaemonUnavailable:
                time.sleep(0.05)
        t = []
        for _ in range(100):
            t0 = time.perf_counter()
            request(sock, "status")
            t.append(time.perf_counter() - t0)
        return {"status_roundtrip_ms_median": round(1e3 * float(np.median(t)), 3),
                "status_roundtrip_ms_p95": round(1e3 * float(np.percentile(t, 95)), 3)}
    finally:
        p.send_signal(signal.SIGTERM)
        p.wait(10)
        shutil.rmtree(work, ignore_errors=True)
        shutil.rmtree(run, ignore_errors=True)


def _replay_intel(max_scans: int = 400) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from cgamap.daemon.store import CheckpointStore
    from cgamap.mapping.evaluation import ate, rpe
    from conftest import data_dir, head_of_log

    log = data_dir() / "laser" / "intel-corrected.log.gz"
    if not log.exists():
        return {"skipped": f"{log} not found"}
    work, run = Path(tempfile.mkdtemp()), Path(tempfile.mkdtemp(prefix="cgb-"))
    try:
        part = head_of_log(log, work / "intel-part.log", max_scans)
        t0 = time.perf_counter()
        p = _daemon({"checkpoint": {"interval": 600.0}}, work, run,
                    ["--replay", str(part), "--exit-after-replay"])
        rc = p.wait(300)
        wall = time.perf_counter() - t0
        ck = CheckpointStore(work / "state").load()
        counts = ck["loop"]["counts"]
        from cgamap.daemon.recording import read_messages
        from cgamap.drivers.messages import LaserScan

        ref_at = {m.stamp_ns: m.pose_ref for m in read_messages(part)
                  if isinstance(m, LaserScan) and m.pose_ref is not None}
        traj = np.asarray(ck["loop"]["trajectory"], dtype=float)
        traj = np.array([r for r in traj if int(r[0]) in ref_at]).reshape(-1, 6)
        ref = np.array([ref_at[int(r[0])] for r in traj]).reshape(-1, 3)
        out = {"exit": rc, "scans": counts.get("scans", 0), "wall_s": round(wall, 2),
               "scans_per_s": round(counts.get("scans", 0) / wall, 1),
               "segments": len(ck["loop"]["map2d"]["map"]["a"])}
        if len(traj) == len(ref) and len(ref) > 3:
            # the daemon's per-scan poses (odometry from the FLASER lines, corrected by the 2D
            # mapper) against the log's reference poses, over the first max_scans scans
            out.update({k: round(v, 4) for k, v in ate(traj[:, 2:5], ref).items()})
            out.update({k: round(v, 4) for k, v in rpe(traj[:, 2:5], ref).items()})
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)
        shutil.rmtree(run, ignore_errors=True)


def _sim_stack(duration: float = 15.0) -> dict:
    """The demo stack (Hokuyo + base twins, no camera) for a short drive."""
    from cgamap.daemon.demo import run_demo

    out = Path(tempfile.mkdtemp())
    try:
        rep = run_demo(out, duration, camera=False, progress=lambda *_: None)
        t = rep.get("truth", {})
        return {"duration_s": duration, "path_m": round(t.get("path_length_m", 0.0), 2),
                "ate_trans_m": t.get("ate_trans_m"), "ate_rot_deg": t.get("ate_rot_deg"),
                "rpe_trans_m": t.get("rpe_trans_m"), "scans_mapped": rep["counts"].get("scans"),
                "scans_received": rep["counts"].get("scans_in"),
                "scan_ms": (rep.get("timing_ms") or {}).get("scan_ms"),
                "daemon_cpu_fraction": rep.get("daemon_cpu_fraction"),
                "sigterm_to_exit_s": rep.get("stop_s")}
    finally:
        shutil.rmtree(out, ignore_errors=True)


def run() -> dict:
    return {"checkpoint": _checkpoint_cost(), "query": _query_latency(),
            "replay_intel": _replay_intel(), "sim_stack": _sim_stack()}


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))

