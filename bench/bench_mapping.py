"""2D mapping on the real Intel log: map build with --odom-noise high, then 200 relocalisation
trials on the built map (the figures of ``cgamap map build`` / ``cgamap relocalize``)."""

from __future__ import annotations

import numpy as np

from .intel import LOG, build, missing, scans


def run() -> dict:
    from cgamap.mapping.offline import build_map, relocalize_trials, revisit_agreement

    if missing():
        return missing()
    res = build(0)
    log = list(scans())
    out = {"log": LOG, "odom_noise": "high", "seed": 0, "build": res.report,
           # raw-point ICP at the revisits (scans 50 and more apart, within 1 m and 45 deg)
           "icp_agreement_revisits": revisit_agreement(log, res.poses)}
    # relocalised poses are in the map's frame: scored against the reference after the
    # build's rigid alignment (the ATE gauge), as `cgamap relocalize` does, and the same
    # answers against the map's own trajectory (``vs_map_trajectory``), which separates
    # relocalisation from the map's residual error against the reference
    out["relocalize"] = relocalize_trials(res.map, log, 200, seed=0,
                                          alignment=res.report["alignment_to_reference"],
                                          also={"vs_map_trajectory": res.poses})
    out["relocalize_unaligned"] = relocalize_trials(res.map, log, 200, seed=0)
    # the same log with the recorded (corrected) odometry: the mapper's own floor
    clean = build_map(log, np.array([s.pose_odom for s in log]))
    keys = ("ate_trans_m", "ate_rot_deg", "rpe_trans_m", "rpe_rot_deg", "ms_per_scan_median")
    out["build_odom_noise_none"] = {k: clean.report[k] for k in keys}
    return out


if __name__ == "__main__":
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    print(json.dumps(run(), indent=2))
