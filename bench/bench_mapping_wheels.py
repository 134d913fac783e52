"""2D mapping with a real robot's own wheel odometry (``map build --odom-noise wheels``).

The Intel and MIT CSAIL corrected logs are GMapping's output (their NEFF lines): the laser
lines' odometry fields are the corrected poses, but the ODOM lines keep the wheels' readings,
restarted at each scan's corrected pose.  For each log: the wheels' error against the
reference steps in the calibration's terms (``evaluation.odometry_model``) beside the noise
presets', and builds with the wheels.  A build's outcome hangs on discrete decisions (which
loop closures, which slips), so the Intel build is repeated with the odometry moved by 1e-9
(``jitter`` seeds; 0 is ``map build`` itself): the spread is what one input can give.
The Intel builds are repeated with far closure jumps held for a second scan
(``builds_confirm_jump_1m``).  On CSAIL the readings are not of the scans' times
(``at_scan_time``), so its wheel steps miss up to a reading's interval of motion each:
one build, to show what that does."""

from __future__ import annotations

import numpy as np

from .extra_data import CSAIL, extra_dir
from .extra_data import missing as missing_extra
from .intel import LOG, missing

JITTERS = (0, 1, 2, 3)
KEYS = ("ate_trans_m", "ate_rot_deg", "rpe_trans_m", "rpe_rot_deg", "loop_closures",
        "slips_recovered", "ms_per_scan_median")


def _log(path, jitters, relocalize: bool, held: bool = False) -> dict:
    from dataclasses import replace

    from cgamap.drivers.carmen import read_scans_and_wheels
    from cgamap.mapping.evaluation import odometry_model
    from cgamap.mapping.offline import build_map, log_odometry, relocalize_trials
    from cgamap.mapping.slam2d import LoopParams, MapperParams

    scans, w = read_scans_and_wheels(path)
    ref = np.array([s.pose_ref for s in scans], float)
    odo, _ = log_odometry(scans, "wheels", 0, (w.at, w.start))
    out: dict = {"scans": len(scans), "rebased": w.rebased, "at_scan_time": w.at_scan_time,
                 "odometry_model": {"wheels": odometry_model(odo, ref), **{
                     p: odometry_model(log_odometry(scans, p, 0)[0], ref)
                     for p in ("low", "high")}},
                 "builds": {}}
    def jittered(j: int) -> np.ndarray:
        return odo + np.random.default_rng(j).standard_normal(odo.shape) * 1e-9 if j else odo

    def spread(builds: dict) -> dict:
        ates = [b["ate_trans_m"] for b in builds.values()]
        return {"mean": round(float(np.mean(ates)), 4), "min": min(ates), "max": max(ates)}

    first = None
    for j in jitters:
        res = build_map(scans, jittered(j))
        rep = res.report
        out["builds"][f"jitter{j}"] = {**{k: rep[k] for k in KEYS},
                                       "odometry_calibration": rep.get("odometry_calibration"),
                                       "online_ate_m": rep["online"]["ate_trans_m"]}
        if first is None:
            first = res
    out["ate_m"] = spread(out["builds"])
    if relocalize:
        out["relocalize_jitter0"] = relocalize_trials(
            first.map, scans, 200, seed=0, alignment=first.report["alignment_to_reference"],
            also={"vs_map_trajectory": first.poses})
    if held:
        # far jumps held for a second scan (``LoopParams.confirm_jump``, off by default):
        # the same inputs; see docs/mapping-2d.md, *A far jump held for a second scan*
        P = MapperParams(loop=replace(LoopParams(), confirm_jump=1.0))
        out["builds_confirm_jump_1m"] = {}
        for j in jitters:
            rep = build_map(scans, jittered(j), P).report
            out["builds_confirm_jump_1m"][f"jitter{j}"] = {
                "ate_trans_m": rep["ate_trans_m"], "online_ate_m": rep["online"]["ate_trans_m"],
                **{k: v for k, v in rep["closure_attempts"].items()
                   if k.startswith("held") or k == "witnessed"}}
        out["ate_m_confirm_jump_1m"] = spread(out["builds_confirm_jump_1m"])
    return out


def run() -> dict:
    from conftest import data_dir

    out: dict = {}
    out["intel"] = missing() or _log(data_dir() / LOG, JITTERS, relocalize=True, held=True)
    out["csail"] = missing_extra(CSAIL) or _log(extra_dir() / CSAIL, (0,), relocalize=False)
    return out


if __name__ == "__main__":
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    print(json.dumps(run(), indent=2))
