"""2D mapping on the real Intel log across odometry-noise seeds: the spread of the trajectory
error (one seed can be lucky), what the finishing neighbour pass adds, where the error comes
from (the noise preset's translation and rotation terms apart, and no noise), and the error
against the independent Kümmerle et al. relations next to the log's own reference poses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .intel import LOG, build, missing
from .intel import scans as intel_scans

RELATIONS = "laser/intel.relations"
SEEDS = (0, 1, 2, 3)


def run() -> dict:
    from cgamap.mapping.evaluation import affine_fit, load_relations, relations_error
    from cgamap.mapping.finishing import NeighbourParams
    from cgamap.mapping.line_adjust import AdjustParams
    from cgamap.mapping.odometry import ODOM_NOISE_PRESETS, add_odometry_noise
    from cgamap.mapping.offline import build_map
    from cgamap.mapping.slam2d import MapperParams
    from conftest import data_dir  # bench/run.py puts tests/ on sys.path

    if missing():
        return missing()
    scans = list(intel_scans())
    odo0 = np.array([s.pose_odom for s in scans])
    keys = ("ate_trans_m", "ate_rot_deg", "rpe_trans_m", "rpe_rot_deg", "ms_per_scan_median",
            "final_optimisation_ms", "loop_closures", "sweep_closures", "slips_recovered")
    out: dict = {"log": LOG, "odom_noise": "high", "seeds": {}}
    ref = np.array([s.pose_ref for s in scans])

    def affine(poses) -> dict:
        # how much of the error is one linear distortion of the whole map (see README)
        f = affine_fit(poses, ref)
        return {"ate_affine_m": round(f["ate_affine_m"], 4),
                "stretch": [round(v, 5) for v in f["stretch"]],
                "stretch_axis_deg": round(f["stretch_axis_deg"], 1)}

    first = None
    for seed in SEEDS:
        res = build(seed)
        out["seeds"][str(seed)] = {**{k: res.report[k] for k in keys},
                                   "affine": affine(res.poses),
                                   # each scan's pose as given when it came in (the live pose)
                                   "online_ate_trans_m": res.report["online"]["ate_trans_m"]}
        first = first or res
    ate = np.array([v["ate_trans_m"] for v in out["seeds"].values()])
    rot = np.array([v["ate_rot_deg"] for v in out["seeds"].values()])
    out["ate_trans_m"] = {"mean": round(float(ate.mean()), 4), "max": float(ate.max())}
    out["ate_rot_deg"] = {"mean": round(float(rot.mean()), 3), "max": float(rot.max())}
    out["ate_affine_m"] = {"mean": round(float(np.mean(
        [v["affine"]["ate_affine_m"] for v in out["seeds"].values()])), 4)}
    off = build_map(scans, add_odometry_noise(odo0, "high", SEEDS[0]),
                    MapperParams(neighbours=NeighbourParams(enabled=False)))
    out["seed0_without_neighbour_pass"] = {k: off.report[k] for k in keys}
    bare = build_map(scans, add_odometry_noise(odo0, "high", SEEDS[0]),
                     MapperParams(adjust=AdjustParams(enabled=False)))
    out["seed0_without_line_adjustment"] = {
        **{k: bare.report[k] for k in keys},
        "icp_agreement": bare.report["icp_agreement"]["estimate"]}
    # the error budget: the high preset's translation terms alone (length bias and noise)
    # and its rotation terms alone (turn noise, heading drift), then no noise at all -- the
    # log's own increments, which are the reference's, so along a corridor where the walls
    # leave the position open the estimate follows the reference by construction
    hi = ODOM_NOISE_PRESETS["high"]
    budget = {"translation_only": replace(hi, rot_rel=0.0, rot_abs=0.0, rot_per_m=0.0,
                                          drift_per_m=0.0),
              "rotation_only": replace(hi, trans_bias=0.0, trans_rel=0.0, trans_abs=0.0),
              "none": "none"}
    out["seed0_error_budget"] = {}
    for name, noise in budget.items():
        got = build_map(scans, add_odometry_noise(odo0, noise, SEEDS[0]))
        out["seed0_error_budget"][name] = {
            **{k: got.report[k] for k in ("ate_trans_m", "ate_rot_deg", "slips_recovered")},
            "affine": affine(got.poses)}
    # the reference is SLAM output: which of estimate and reference follows the raw ranges
    out["icp_agreement_seed0"] = first.report["icp_agreement"]
    rel_path = data_dir() / RELATIONS
    if rel_path.exists():
        rel = load_relations(rel_path)
        est = relations_error(first.stamps, first.poses, rel)
        ref = relations_error(first.stamps, np.array([s.pose_ref for s in scans]), rel,
                              offset=est["clock_offset_s"])
        out["relations_seed0"] = {"estimate": est, "reference": ref,
                                  "without_line_adjustment":
                                      relations_error(bare.stamps, bare.poses, rel)}
        per_seed = [relations_error(build(s).stamps, build(s).poses, rel) for s in SEEDS]
        out["relations_seeds_mean"] = {
            k: round(float(np.mean([r[k] for r in per_seed])), 4)
            for k in ("trans_mean_m", "rot_mean_deg")}
    return out


if __name__ == "__main__":
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    print(json.dumps(run(), indent=2))
