"""The daemon's on-demand finishing pass (``{"cmd": "optimize"}``): trajectory error before and
after on the real Intel log (noisy odometry), and on a long simulated run the cost split into
what holds the map thread (snapshot, apply) and what runs beside it (the pass itself), with
the per-scan store's size.  Measures, never asserts."""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np


def _cfg(**mapping) -> dict:
    from cgamap.daemon import config as config_mod

    return config_mod.validate({"devices": {}, "mapping": {
        "map3d": False, "min_travel": 0.0, "min_turn": 0.0, "scan_max_rate": 1e6, **mapping}})


def _timed_pass(loop) -> dict:
    """optimize_begin / run / optimize_end with each part timed."""
    t0 = time.perf_counter()
    job = loop.optimize_begin()
    t1 = time.perf_counter()
    job.run()
    t2 = time.perf_counter()
    got = loop.optimize_end(job)
    t3 = time.perf_counter()
    return {**got, "snapshot_ms": round(1e3 * (t1 - t0), 2),
            "compute_ms": round(1e3 * (t2 - t1), 1), "apply_ms": round(1e3 * (t3 - t2), 2)}


def _intel(seeds=(0, 1)) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from cgamap.daemon.loop import MappingLoop
    from cgamap.mapping.evaluation import ate
    from cgamap.mapping.odometry import add_odometry_noise

    from .intel import missing
    from .intel import scans as intel_scans

    if missing():
        return missing()
    scans = list(intel_scans())
    ref_all = np.array([s.pose_ref for s in scans])
    index = {s.stamp_ns: k for k, s in enumerate(scans)}
    out = {}
    for seed in seeds:
        odo = add_odometry_noise(np.array([s.pose_odom for s in scans]), "high", seed)
        loop = MappingLoop(_cfg())
        for s, o in zip(scans, odo, strict=True):
            loop.handle("laser", dataclasses.replace(s, pose_odom=tuple(o)))
            loop.process(final=True)
        ref = ref_all[[index[int(r[0])] for r in loop.trajectory]]
        m = loop.mapper.m
        before = ate(_rows(loop), ref)  # every mapped scan's pose, nodes and tracked ones
        got = _timed_pass(loop)
        after = ate(_rows(loop), ref)
        out[f"seed_{seed}"] = {
            "scans": len(ref), "nodes": m.count,
            "ate_online_m": round(before["ate_trans_m"], 4),
            "ate_after_m": round(after["ate_trans_m"], 4),
            "ate_rot_online_deg": round(before["ate_rot_deg"], 3),
            "ate_rot_after_deg": round(after["ate_rot_deg"], 3), **got}
    return out


def _long_run(laps: int = 12, max_nodes: int = 20_000) -> dict:
    """The simulated loop world driven ``laps`` times (noisy odometry): the pass's cost as
    the graph grows, and the kept segments' memory."""
    from cgamap.daemon.loop import MappingLoop
    from cgamap.drivers.messages import LaserScan, OdometryPose
    from cgamap.drivers.sim.world import get_world
    from cgamap.mapping.evaluation import ate
    from cgamap.mapping.odometry import add_odometry_noise

    w = get_world("loop")
    t = np.arange(0, laps * w.path_length / w.speed, 0.6 / w.speed)
    truth = np.column_stack(w.trajectory(t))
    odo = add_odometry_noise(truth, "high", seed=5)
    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    loop = MappingLoop(_cfg(params2d={"max_nodes": max_nodes}))
    t0 = time.perf_counter()
    for k, (p, o) in enumerate(zip(truth, odo, strict=True)):
        stamp = int(k * 1e8) + 1
        r = w.raycast(*p, angles, 30.0)
        r = np.where(np.isfinite(r), r + np.random.default_rng(k).normal(0, 0.01, r.shape), np.nan)
        loop.handle("base", OdometryPose(stamp_ns=stamp - 1, x=o[0], y=o[1], theta=o[2]))
        loop.handle("laser", LaserScan(seq=k, stamp_ns=stamp, angle_min=float(angles[0]),
                                       angle_increment=float(angles[1] - angles[0]), ranges=r))
        loop.process(odometry_live=False)
    feed_s = time.perf_counter() - t0
    m = loop.mapper.m
    kept = sum(a.nbytes + b.nbytes for a, b in m.scans)
    ref = truth[[int(r[0]) // 10 ** 8 for r in loop.trajectory]]
    live = _kept(loop)  # the rows of the kept nodes' scans (and those tracked from them)
    before = ate(_rows(loop)[live], ref[live])["ate_trans_m"]
    got = _timed_pass(loop)
    return {"scans": len(truth), "nodes": m.count, "max_nodes": max_nodes,
            "feed_s": round(feed_s, 1), "kept_segments_bytes": int(kept),
            "kept_bytes_per_node": round(kept / max(m.count, 1), 1),
            "map_segments": len(loop.segments()),
            "ate_online_m": round(before, 4),
            "ate_after_m": round(ate(_rows(loop)[live], ref[live])["ate_trans_m"], 4), **got}


def _kept(loop) -> np.ndarray:
    """Which trajectory rows are at or after the oldest kept graph node's scan."""
    stamps = np.array([r[0] for r in loop.trajectory])
    return stamps >= loop.mapper.node_stamps[0]


def _rows(loop) -> np.ndarray:
    """The daemon's trajectory: each mapped scan's pose (a node's, or tracked from one)."""
    return np.array([r[2:5] for r in loop.trajectory])


def run() -> dict:
    out = {"intel": _intel(), "sim_loop_12_laps": _long_run(),
           "sim_loop_12_laps_max_nodes_400": _long_run(max_nodes=400)}
    if os.environ.get("CGAMAP_BENCH_LONG") == "1":
        # the daemon's 20 000-node limit reached: about 2 min of mapping, 4-5 min of pass
        out["sim_loop_245_laps"] = _long_run(laps=245)
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))
