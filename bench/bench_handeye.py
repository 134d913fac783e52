"""Hand-eye accuracy: our motor-algebra solver next to OpenCV's five, same problems, same run.

20 pose pairs per problem (head turned up to 45 degrees about random axes, target 0.8 m
ahead), Gaussian noise per axis on both measured poses (rotation vector and translation) at
three levels, ``seeds`` problems each.  Reported: median and p95 of the rotation error (deg)
and the translation error (mm) of head_T_cam, and the mean solve time per method (ms).  Then
the whole ``calib collect --sim`` path (rendered chessboard, detection, solvePnP) for
``sim_seeds`` hidden mounts, every solver on the same pairs.

Usage: python -m bench.bench_handeye [--seeds N] [--sim-seeds N] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from cgamap.calib.handeye import METHODS, solve
from cgamap.calib.se3 import pose_errors
from cgamap.calib.synthetic import make_problem

LEVELS = {"noise-free": (0.0, 0.0), "0.1deg/1mm": (0.1, 0.001), "1deg/5mm": (1.0, 0.005)}


def run(seeds: int = 100, n_poses: int = 20, sim_seeds: int = 10) -> dict:
    out: dict = {"poses": n_poses, "seeds": seeds, "levels": {}}
    for level, (s_rot, s_t) in LEVELS.items():
        errs = {m: [] for m in METHODS}
        times = {m: 0.0 for m in METHODS}
        for seed in range(seeds):
            p = make_problem(np.random.default_rng(seed), n_poses, s_rot, s_t)
            for m in METHODS:
                t0 = time.perf_counter()
                r = solve(p.base_T_head, p.cam_T_target, method=m)
                times[m] += time.perf_counter() - t0
                errs[m].append(pose_errors(r.head_T_cam, p.head_T_cam))
        table = {}
        for m in METHODS:
            e = np.array(errs[m])
            table[m] = {
                "rot_deg_median": float(np.median(e[:, 0])),
                "rot_deg_p95": float(np.percentile(e[:, 0], 95)),
                "trans_mm_median": float(1e3 * np.median(e[:, 1])),
                "trans_mm_p95": float(1e3 * np.percentile(e[:, 1], 95)),
                "ms_per_solve": 1e3 * times[m] / seeds,
            }
        cv = [m for m in METHODS if m != "motor"]
        table["best_opencv"] = {k: min(table[m][k] for m in cv) for k in table["motor"]
                                if k != "ms_per_solve"}
        table["motor_at_or_below_best_opencv"] = all(
            table["motor"][k] <= v for k, v in table["best_opencv"].items())
        out["levels"][level] = table
    if sim_seeds:
        out["sim_pipeline"] = run_sim_pipeline(sim_seeds, n_poses)
    return out


def run_sim_pipeline(seeds: int = 10, n_poses: int = 20) -> dict:
    """The whole collect path on the simulated rig (rendered chessboard, corner detection,
    solvePnP, joints on the Dynamixel grid), then every solver on the same pairs."""
    import math

    from cgamap.calib.collect import DirectJoints, SimSource, collect, pose_set
    from cgamap.calib.sim import default_rig

    errs = {m: [] for m in METHODS}
    fails = {m: 0 for m in METHODS}
    t_collect = 0.0
    for seed in range(seeds):
        rig = default_rig(seed)
        t0 = time.perf_counter()
        rep = collect(SimSource(rig, seed, DirectJoints()), rig.board,
                      pose_set(n_poses, math.radians(12), math.radians(8)), rig.axis_point,
                      1.0, 100.0)
        t_collect += time.perf_counter() - t0
        p = rep.pairs
        for m in METHODS:
            try:
                r = solve(p.base_T_head, p.cam_T_target, method=m, pan=p.pan, tilt=p.tilt)
            except (RuntimeError, ValueError):
                fails[m] += 1
                continue
            errs[m].append(pose_errors(r.head_T_cam, rig.head_T_cam))
    out: dict = {"seeds": seeds, "poses": n_poses, "ms_per_collect": 1e3 * t_collect / seeds}
    for m in METHODS:
        e = np.array(errs[m]).reshape(-1, 2)
        out[m] = {"failed": fails[m]}
        if len(e):
            out[m].update({
                "rot_deg_median": float(np.median(e[:, 0])),
                "rot_deg_max": float(np.max(e[:, 0])),
                "trans_mm_median": float(1e3 * np.median(e[:, 1])),
                "trans_mm_max": float(1e3 * np.max(e[:, 1]))})
    return out


def format_table(res: dict) -> str:
    lines = []
    for level, table in res["levels"].items():
        lines.append(f"{level} ({res['poses']} poses, {res['seeds']} seeds)")
        lines.append("| method | rot median (deg) | rot p95 (deg) | trans median (mm) | "
                     "trans p95 (mm) | ms/solve |")
        lines.append("|---|---|---|---|---|---|")
        for m in METHODS:
            r = table[m]
            lines.append(f"| {m} | {r['rot_deg_median']:.4g} | {r['rot_deg_p95']:.4g} | "
                         f"{r['trans_mm_median']:.4g} | {r['trans_mm_p95']:.4g} | "
                         f"{r['ms_per_solve']:.2f} |")
        lines.append("")
    sim = res.get("sim_pipeline")
    if sim:
        lines.append(f"sim pipeline (rendered chessboard, PnP; {sim['seeds']} seeds)")
        lines.append("| method | rot median (deg) | rot max (deg) | trans median (mm) | "
                     "trans max (mm) | failed |")
        lines.append("|---|---|---|---|---|---|")
        for m in METHODS:
            r = sim[m]
            if "rot_deg_median" in r:
                lines.append(f"| {m} | {r['rot_deg_median']:.4g} | {r['rot_deg_max']:.4g} | "
                             f"{r['trans_mm_median']:.4g} | {r['trans_mm_max']:.4g} | "
                             f"{r['failed']} |")
            else:
                lines.append(f"| {m} | - | - | - | - | {r['failed']} |")
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--sim-seeds", type=int, default=10)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    result = run(a.seeds, sim_seeds=a.sim_seeds)
    print(json.dumps(result, indent=2) if a.json else format_table(result))
    print(f"total {time.perf_counter() - t0:.1f} s")
