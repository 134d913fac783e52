"""A lost robot's relocalisation with and without a hint (the daemon's ``lost_radius``):
100 scans per simulated place, each relocalised over the whole map and near a hint that is
the true pose off by about 1 m and 10 deg (normal, per axis), within 3 m and 30 deg.  Each
answer is right (within 0.2 m and 3 deg), wrong, or refused as ambiguous (a look-alike place
scoring within 0.05, as the daemon refuses it for a lost robot); near a hint, a pose that
fits under the daemon's ``LOST_SCORE`` of the scan is ``weak`` (not taken).  ``kidnapped``: the hint
10 m off in a random direction (the robot was carried away): any answer near it is wrong,
and a wrong jump is what the near-first try must not make.  The map is built from
full-circle scans at the true poses (``tests/synth2d.scanned_map``)."""

from __future__ import annotations

import time

import numpy as np

WORLDS = ("loop", "long_corridor", "office")
HINT_SIGMA = (1.0, np.deg2rad(10.0))     # m, rad per axis
NEAR = (3.0, np.deg2rad(30.0))           # the daemon's lost_radius default and LOST_TURN


def _place(name: str, trials: int = 100) -> dict:
    from cgamap.daemon.loop import LOST_SCORE, RELOC_AMBIGUITY
    from cgamap.drivers.sim.world import get_world
    from cgamap.mapping.posegraph import wrap
    from cgamap.mapping.relocalize import DistanceField, relocalize, rivals
    from cgamap.mapping.segments import segments_from_scan
    from synth2d import scan, scanned_map  # bench/run.py puts tests/ on sys.path

    w = get_world(name)
    t = np.linspace(0, w.path_length / w.speed, 300, endpoint=False)
    poses = np.column_stack(w.trajectory(t))
    lmap = scanned_map(w, poses[::2])
    field = DistanceField(lmap)
    rng = np.random.default_rng(1)
    out = {k: {"right": 0, "wrong": 0, "ambiguous": 0, "not_found": 0, "weak": 0, "ms": []}
           for k in ("global", "near", "kidnapped")}
    for i in rng.choice(len(poses) - 1, trials, replace=False):
        p = 0.5 * (poses[i] + poses[i + 1])
        seg = segments_from_scan(scan(w, p, n=180, sigma=0.01, seed=int(i)))
        hint = p + np.r_[rng.normal(0, HINT_SIGMA[0], 2), rng.normal(0, HINT_SIGMA[1])]
        away = rng.uniform(0, 2 * np.pi)
        far = p + np.r_[10.0 * np.cos(away), 10.0 * np.sin(away), 0.0]
        for key, near in (("global", None), ("near", (hint, *NEAR)),
                          ("kidnapped", (far, *NEAR))):
            t0 = time.perf_counter()
            r = relocalize(lmap, seg, field, near=near)
            out[key]["ms"].append((time.perf_counter() - t0) * 1e3)
            if not r.found:
                out[key]["not_found"] += 1
            elif near is not None and r.score < LOST_SCORE:
                out[key]["weak"] += 1
            elif rivals(r.hypotheses, r.hypotheses[0], RELOC_AMBIGUITY, 0.5):
                out[key]["ambiguous"] += 1
            elif (np.hypot(*(r.pose[:2] - p[:2])) < 0.2
                  and abs(wrap(r.pose[2] - p[2])) < np.deg2rad(3.0)):
                out[key]["right"] += 1
            else:
                out[key]["wrong"] += 1
    for v in out.values():
        v["median_ms"] = round(float(np.median(v.pop("ms"))), 2)
    return {"trials": trials, "segments": len(lmap), **out}


def run() -> dict:
    return {"hint_sigma": [HINT_SIGMA[0], round(float(np.degrees(HINT_SIGMA[1])), 1)],
            "near": [NEAR[0], round(float(np.degrees(NEAR[1])), 1)],
            **{name: _place(name) for name in WORLDS}}
