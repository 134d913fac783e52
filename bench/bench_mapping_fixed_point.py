"""Where the Intel build goes when it follows only itself: ``map build`` run again with its
own finished trajectory as the odometry, round after round, from the high-noise seed 0 and
from the log's own (noise-free) odometry.  Per round: the ATE against the log's reference
poses, the error over the Kümmerle et al. relations, consecutive poses against raw-point ICP,
and how far the two runs are from each other.

The log's increments are the reference's: the noise-free run starts on the reference and
its ATE is low by construction.  If the two runs meet each other while both leave the
reference, the build's own answer is noise-free, and what the ATE still measures is where
that answer and the reference disagree; the relations and the ICP agreement (independent of
the reference) say which of the two they side with."""

from __future__ import annotations

import numpy as np

from .intel import build, missing
from .intel import scans as intel_scans

RELATIONS = "laser/intel.relations"
ROUNDS = 4  # the build, then three rebuilds from its own trajectory (~55 s each)


def run() -> dict:
    from cgamap.mapping.evaluation import ate, load_relations, relations_error
    from cgamap.mapping.offline import build_map, log_odometry
    from conftest import data_dir  # bench/run.py puts tests/ on sys.path

    if missing():
        return missing()
    scans = list(intel_scans())
    ref = np.array([s.pose_ref for s in scans])
    stamps = np.array([s.stamp_ns for s in scans]) * 1e-9
    rel_path = data_dir() / RELATIONS
    relations = load_relations(rel_path) if rel_path.exists() else None

    def figures(res) -> dict:
        out = {"ate_trans_m": res.report["ate_trans_m"], "ate_rot_deg": res.report["ate_rot_deg"]}
        icp = res.report["icp_agreement"]["estimate"]
        out["icp_trans_median_m"] = icp["trans_median_m"]
        out["icp_rot_median_deg"] = icp["rot_median_deg"]
        if relations is not None:
            r = relations_error(stamps, res.poses, relations)
            out["relations_trans_mean_m"] = round(r["trans_mean_m"], 4)
            out["relations_rot_mean_deg"] = round(r["rot_mean_deg"], 3)
        return out

    runs = {"high_seed0": build(0), "noise_free": None}
    out: dict = {"rounds": ROUNDS, "runs": {k: [] for k in runs}, "apart_m": []}
    odo = {"high_seed0": None, "noise_free": log_odometry(scans, "none", 0)[0]}
    if relations is not None:
        r = relations_error(stamps, ref, relations)
        out["reference_relations_trans_mean_m"] = round(r["trans_mean_m"], 4)
    for _ in range(ROUNDS):
        poses = {}
        for name in runs:
            res = runs[name] if runs[name] is not None else build_map(scans, odo[name])
            out["runs"][name].append(figures(res))
            poses[name] = res.poses
            odo[name], runs[name] = res.poses, None  # the next round starts from this one
        # the two runs against each other, aligned as the ATE aligns a run on the reference
        out["apart_m"].append(round(ate(poses["high_seed0"], poses["noise_free"])
                                    ["ate_trans_m"], 4))
    return out
