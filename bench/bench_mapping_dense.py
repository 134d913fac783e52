"""2D mapping of a dense run (the simulated loop world, two laps, a 361-beam scan every 5 cm,
high odometry noise): the per-scan time and the finishing pass's cost when every scan has
dozens of neighbours, with the pair cap (``NeighbourParams.max_pairs``) as it runs and the
number of pairs it would take without it."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

STEP_M = 0.05
LAPS = 2
BEAMS = 361


def dense_run(step: float = STEP_M, laps: float = LAPS, beams: int = BEAMS):
    """Scans (LaserScan-like records with ``pose_ref``) and the true poses along the loop."""
    from cgamap.drivers.sim.world import NoiseModel, get_world

    w = get_world("loop")
    n = int(w.path_length * laps / step)
    X = np.column_stack(w.trajectory(np.arange(n) * step / w.speed))
    inc = np.pi / beams
    ang = -np.pi / 2 + inc * np.arange(beams)
    rng = np.random.default_rng(0)
    noise = NoiseModel(sigma=0.01)
    scans = [SimpleNamespace(ranges=noise.apply(w.raycast(x, y, th, ang, 30.0), rng),
                             angle_min=-np.pi / 2, angle_increment=inc, stamp_ns=k * 10 ** 8,
                             pose_ref=(x, y, th)) for k, (x, y, th) in enumerate(X)]
    return scans, X


def run() -> dict:
    from dataclasses import replace

    from cgamap.mapping.odometry import add_odometry_noise
    from cgamap.mapping.offline import build_map
    from cgamap.mapping.segments import extract_segments
    from cgamap.mapping.slam2d import MapperParams, neighbour_pairs, round_params

    scans, X = dense_run()
    P = MapperParams()
    res = build_map(scans, add_odometry_noise(X, "high", 0), P)
    keys = ("scans_processed", "ms_per_scan_median", "ms_per_scan_p95",
            "final_optimisation_ms", "loop_closures", "sweep_closures", "ate_trans_m",
            "ate_rot_deg")
    out = {"world": "loop", "step_m": STEP_M, "laps": LAPS, "beams": BEAMS,
           **{k: res.report[k] for k in keys}}
    segs = [extract_segments(s.ranges, s.angle_min, s.angle_increment, P.segments)
            for s in scans]
    kept = [(s.a, s.b) for s in segs]
    coarse = round_params(P.neighbours, 0)
    out["pairs_coarse_round"] = int(len(neighbour_pairs(res.poses, kept, coarse)))
    out["pairs_coarse_round_uncapped"] = int(len(neighbour_pairs(
        res.poses, kept, replace(coarse, max_pairs=0))))
    return out
