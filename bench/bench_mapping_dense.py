"""2D mapping of a dense run (the simulated loop world, two laps, a 361-beam scan every 5 cm,
high odometry noise): the per-scan time and the finishing pass's cost, with the pair cap
(``NeighbourParams.max_pairs``) as it runs and the number of pairs it would take without it;
with the node gate (``MapperParams.node_travel``: the scans between nodes tracked only) and
with every scan a node, when each has dozens of neighbours."""

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

    from cgamap.mapping.finishing import neighbour_pairs, round_params
    from cgamap.mapping.odometry import add_odometry_noise
    from cgamap.mapping.offline import build_map
    from cgamap.mapping.segments import extract_segments
    from cgamap.mapping.slam2d import MapperParams

    scans, X = dense_run()
    odo = add_odometry_noise(X, "high", 0)
    keys = ("scans_processed", "graph_nodes", "ms_per_scan_median", "ms_per_scan_p95",
            "final_optimisation_ms", "loop_closures", "sweep_closures", "ate_trans_m",
            "ate_rot_deg")
    out: dict = {"world": "loop", "step_m": STEP_M, "laps": LAPS, "beams": BEAMS}
    # the defaults (a node every 0.5 m or 0.2 rad, the scans between tracked), and every
    # scan a node (as before the node gate)
    for name, P in (("nodes_gated", MapperParams()),
                    ("every_scan_a_node", MapperParams(node_travel=0.0, node_turn=0.0))):
        res = build_map(scans, odo, P)
        got = {k: res.report[k] for k in keys}
        segs = [extract_segments(scans[k].ranges, scans[k].angle_min,
                                 scans[k].angle_increment, P.segments) for k in res.node_scan]
        kept = [(s.a, s.b) for s in segs]
        coarse = round_params(P.neighbours, 0)
        nodes = res.poses[res.node_scan]
        got["pairs_coarse_round"] = int(len(neighbour_pairs(nodes, kept, coarse)))
        got["pairs_coarse_round_uncapped"] = int(len(neighbour_pairs(
            nodes, kept, replace(coarse, max_pairs=0))))
        out[name] = got
    return out
