"""2D mapping on a third real log, the MIT CSAIL building (see :mod:`bench.extra_data`: not
fetchable here, read from the cache when someone put it there): 406 scans of 361 beams a
metre apart (a sparser log than Intel's, with a building that is not all right angles).
``map build`` as a user runs it, with the log's own increments (no noise) and ``high`` noise
on seeds 0-3, scored against the log's corrected poses, and relocalisation (200 trials) on
the seed-0 map against the reference and against the map's own trajectory.  Skipped, with
the reason, when the log is absent."""

from __future__ import annotations

import numpy as np

from .extra_data import CSAIL, CSAIL_SHA256, checked, extra_dir, missing, relocalize_on

RUNS = (("none", 0), ("high", 0), ("high", 1), ("high", 2), ("high", 3))
KEYS = ("ate_trans_m", "ate_rot_deg", "ate_trans_max_m", "rpe_trans_m", "rpe_rot_deg",
        "ms_per_scan_median", "ms_per_scan_p95", "final_optimisation_ms", "loop_closures",
        "segments")


def run() -> dict:
    from cgamap.drivers.carmen import read_scans
    from cgamap.mapping.offline import build_map, log_odometry

    if missing(CSAIL):
        return missing(CSAIL)
    scans = list(read_scans(extra_dir() / CSAIL))
    out: dict = {"log": CSAIL, **checked(CSAIL, CSAIL_SHA256), "scans": len(scans),
                 "runs": {}}
    first = None
    for preset, seed in RUNS:
        res = build_map(scans, log_odometry(scans, preset, seed)[0])
        rep = res.report
        out["runs"][f"{preset}_seed{seed}"] = {
            **{k: rep[k] for k in KEYS},
            "icp_agreement": {k: rep["icp_agreement"][k].get("trans_median_m")
                              for k in ("estimate", "reference")}}
        if preset == "high" and first is None:
            first = res
    high = [v["ate_trans_m"] for k, v in out["runs"].items() if k.startswith("high")]
    out["high_mean_ate_m"] = round(float(np.mean(high)), 4)
    out["relocalize_high_seed0"] = relocalize_on(first, scans)
    return out


if __name__ == "__main__":
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    print(json.dumps(run(), indent=2))
