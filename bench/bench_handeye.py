"""Hand-eye accuracy: our motor-algebra solver next to OpenCV's five, same problems, same run.

20 pose pairs per problem (head turned up to 45 degrees about random axes, target 0.8 m
ahead), Gaussian noise per axis on both measured poses (rotation vector and translation) at
three levels, ``seeds`` problems each.  Reported: median and p95 of the rotation error (deg)
and the translation error (mm) of head_T_cam, and the mean solve time per method (ms).

Usage: python -m bench.bench_handeye [--seeds N]
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


def run(seeds: int = 100, n_poses: int = 20) -> dict:
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
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    result = run(a.seeds)
    print(json.dumps(result, indent=2) if a.json else format_table(result))
    print(f"total {time.perf_counter() - t0:.1f} s")
