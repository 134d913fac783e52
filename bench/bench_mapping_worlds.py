"""2D mapping beyond the Intel lab: `cgamap map build` on simulated logs of places unlike it
(``drivers/sim/world.py``): a 60 m x 36 m hall whose walls are mostly beyond 25 m, a campus
loop whose only lines are building facades 10-40 m off, a 150 m corridor driven there
and back, and a 100 m x 48 m office floor whose corridors one lap drives once each way
(``one_lap``: seeds 0-3 mapped over that lap alone, where every revisit looks the other
way).  Each log (two laps, a 180-beam scan a second, LMS-like noise, written as CARMEN
and read back) is mapped with ``--odom-noise high``; the ATE is against the simulation's
truth.  The hall and the campus are also mapped with the extraction limited to 25 m (the
default until the limit became the sensor's reach).  The hall during a fair (``expo``: 24
visitors standing at booths, 4 carts parked for three minutes at a time) is mapped over
three laps with and without the free-space clearing (:mod:`cgamap.mapping.free_space`):
``phantoms`` are map segments more than 0.25 m from every wall of the empty hall,
``stale`` those not seen in the last lap (what people and carts left behind)."""

from __future__ import annotations

import contextlib
import io
import json
import tempfile
from pathlib import Path

WORLDS = ("hall", "campus", "long_corridor", "office")
KEYS = ("scans_processed", "segments", "ms_per_scan_median", "ms_per_scan_p95",
        "final_optimisation_ms", "loop_closures", "sweep_closures", "ate_trans_m",
        "ate_rot_deg")


def _build(log: Path, out: Path) -> dict:
    from cgamap.daemon.cli import main

    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["map", "build", "--log", str(log), "--out", str(out), "--odom-noise",
                   "high", "--seed", "0", "--quiet"])
    if rc:
        raise RuntimeError(f"map build exited {rc}")
    rep = json.loads((out / "report.json").read_text())
    return {k: rep[k] for k in KEYS} | {"odometry_ate_m": rep["odometry"]["ate_trans_m"]}


def _limited(log: Path) -> dict:
    from cgamap.drivers.carmen import read_scans
    from cgamap.mapping.offline import build_map, log_odometry
    from cgamap.mapping.segments import SegmentParams
    from cgamap.mapping.slam2d import MapperParams

    scans = read_scans(log)
    res = build_map(scans, log_odometry(scans, "high", 0)[0],  # as map build takes it
                    MapperParams(segments=SegmentParams(range_max=25.0)))
    return {k: res.report[k] for k in ("ate_trans_m", "ate_rot_deg", "loop_closures")}


def _phantoms(res, world, static) -> dict:
    import numpy as np
    from cgamap.mapping.evaluation import apply_pose
    from cgamap.mapping.matching import segment_distances

    m, n = res.map, len(res.poses)
    T = res.report["alignment_to_reference"]
    ends = [apply_pose(T, np.column_stack([p, np.zeros(len(p))]))[:, :2] for p in (m.a, m.b)]
    mid = 0.5 * (ends[0] + ends[1])
    ph = segment_distances(mid, static[:, :2], static[:, 2:]).min(axis=1) > 0.25
    # not seen in the last lap: by none of the graph nodes (the scans that were mapped) of it
    last_lap = np.searchsorted(res.node_scan, n - round(world.path_length / world.speed))
    stale = ph & (m.last_seen < last_lap)
    length = np.hypot(*(ends[1] - ends[0]).T)
    return {"segments": len(m), "phantoms": int(ph.sum()),
            "phantom_length_m": round(float(length[ph].sum()), 1),
            "stale": int(stale.sum()), "stale_length_m": round(float(length[stale].sum()), 1)}


def _one_lap(name: str, seeds: range = range(4)) -> dict:
    """ATE and loop closures per odometry seed (high noise) over one lap of ``name``."""
    from cgamap.drivers.sim.scanlog import simulated_scans
    from cgamap.drivers.sim.world import get_world
    from cgamap.mapping.offline import build_map, log_odometry

    scans = simulated_scans(get_world(name), laps=1.0)
    reps = [build_map(scans, log_odometry(scans, "high", s)[0]).report for s in seeds]
    return {"seeds": list(seeds), "ate_trans_m": [r["ate_trans_m"] for r in reps],
            "loop_closures": [r["loop_closures"] for r in reps],
            "online_ate_trans_m": [r["online"]["ate_trans_m"] for r in reps]}


def _expo() -> dict:
    from dataclasses import replace

    from cgamap.drivers.sim.scanlog import simulated_scans
    from cgamap.drivers.sim.world import get_world
    from cgamap.mapping.offline import build_map, log_odometry
    from cgamap.mapping.slam2d import MapperParams

    w = get_world("expo")
    scans = simulated_scans(w, laps=3.0)
    odo = log_odometry(scans, "high", 0)[0]
    out = {"laps": 3, "path_m": round(w.path_length, 1), "movers": len(w.movers)}
    for clear in (True, False):
        MP = MapperParams()
        MP = replace(MP, map=replace(MP.map, clear=replace(MP.map.clear, enabled=clear)))
        res = build_map(scans, odo, MP)
        out["clearing" if clear else "no_clearing"] = {
            k: res.report[k] for k in ("ate_trans_m", "ms_per_scan_median")} | {
            "online_ate_trans_m": res.report["online"]["ate_trans_m"]} | _phantoms(
            res, w, get_world("hall").segments)
    return out


def run() -> dict:
    from cgamap.drivers.carmen import write_carmen
    from cgamap.drivers.sim.scanlog import simulated_scans
    from cgamap.drivers.sim.world import get_world

    out: dict = {"odom_noise": "high", "seed": 0, "laps": 2, "beams": 180}
    with tempfile.TemporaryDirectory() as tmp:
        for name in WORLDS:
            w = get_world(name)
            log = Path(tmp) / f"{name}.log"
            write_carmen(log, simulated_scans(w))
            fig = {"path_m": round(w.path_length, 1), **_build(log, Path(tmp) / name)}
            if name in ("hall", "campus"):
                fig["range_max_25m"] = _limited(log)
            if name == "office":
                fig["one_lap"] = _one_lap(name)
            out[name] = fig
    out["expo"] = _expo()
    return out
