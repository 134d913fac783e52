"""Trajectory error against reference poses: ATE after rigid alignment, RPE over distance."""

from __future__ import annotations

import numpy as np
from cgamap.cga import angle_diff
from scipy.spatial import cKDTree

from .odometry import compose_pose2d, relative
from .scan_icp import IcpParams, icp, scan_points


def align_rigid_2d(est: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    """(x, y, theta) of the rigid motion that best maps est positions onto ref (Kabsch)."""
    pe, pr = est[:, :2], ref[:, :2]
    ce, cr = pe.mean(0), pr.mean(0)
    A = (pe - ce).T @ (pr - cr)
    th = np.arctan2(A[0, 1] - A[1, 0], A[0, 0] + A[1, 1])
    c, s = np.cos(th), np.sin(th)
    t = cr - np.array([[c, -s], [s, c]]) @ ce
    return float(t[0]), float(t[1]), float(th)


def apply_pose(T, poses: np.ndarray) -> np.ndarray:
    """(n, 3) poses moved by the rigid motion T = (x, y, theta): T composed with each."""
    return compose_pose2d(T, poses)


def ate(est: np.ndarray, ref: np.ndarray) -> dict:
    """Absolute trajectory error: RMS translation (m) and rotation (deg) after alignment."""
    T = align_rigid_2d(est, ref)
    al = apply_pose(T, est)
    dt = np.linalg.norm(al[:, :2] - ref[:, :2], axis=-1)
    dr = angle_diff(al[:, 2], ref[:, 2])
    return {"ate_trans_m": float(np.sqrt(np.mean(dt ** 2))),
            "ate_rot_deg": float(np.degrees(np.sqrt(np.mean(dr ** 2)))),
            "ate_trans_max_m": float(dt.max())}


def affine_fit(est: np.ndarray, ref: np.ndarray) -> dict:
    """How much of the trajectory error a linear distortion explains: the RMS translation
    error after the best affine map of est positions onto ref (``ate_affine_m``), and that
    map's principal stretches (``stretch``: largest, smallest; 1 = none) with the direction
    of the largest in ref's frame (``stretch_axis_deg``, 0-180).  A map that is right but for
    a wheel-scale error has equal stretches; one whose corridors along x and along y came out
    differently long has unequal ones, which a rigid alignment leaves in the ATE."""
    pe, pr = est[:, :2] - est[:, :2].mean(0), ref[:, :2] - ref[:, :2].mean(0)
    M, *_ = np.linalg.lstsq(pe, pr, rcond=None)     # pr ~ pe @ M
    U, S, _ = np.linalg.svd(M.T)                     # ref-frame axes of the stretch
    rms = float(np.sqrt(np.mean(np.sum((pe @ M - pr) ** 2, axis=-1))))
    return {"ate_affine_m": rms, "stretch": [float(S[0]), float(S[1])],
            "stretch_axis_deg": float(np.degrees(np.arctan2(U[1, 0], U[0, 0])) % 180.0)}


def odometry_model(odo: np.ndarray, ref: np.ndarray, min_step: float = 0.2) -> dict:
    """The odometry's error between consecutive poses against the reference's, in the terms
    the mapper calibrates (``odometry_calibration``): ``scale`` such that a reference step's
    length is ``scale`` times the odometry's (least squares over steps of ``min_step`` metres
    or more), ``drift_deg_per_m`` such that its turn is the odometry's less ``drift`` per
    metre driven; and what neither explains, per step: ``turn_residual_deg_rms`` and
    ``length_residual_m_rms`` (after the scale)."""
    raw, true = relative(odo[:-1], odo[1:]), relative(ref[:-1], ref[1:])
    d, dt = np.hypot(raw[:, 0], raw[:, 1]), np.hypot(true[:, 0], true[:, 1])
    run = d >= min_step
    scale = float(d[run] @ dt[run] / (d[run] @ d[run])) if run.any() else 1.0
    turn = angle_diff(raw[:, 2], true[:, 2])         # odometry's turn less the reference's
    drift = float(d @ turn / (d @ d)) if d @ d > 0 else 0.0
    return {"scale": round(scale, 5), "drift_deg_per_m": round(float(np.degrees(drift)), 4),
            "turn_residual_deg_rms": round(float(np.degrees(np.sqrt(np.mean(
                (turn - drift * d) ** 2)))), 4) if len(d) else 0.0,
            "length_residual_m_rms": round(float(np.sqrt(np.mean(
                (scale * d[run] - dt[run]) ** 2))), 4) if run.any() else 0.0,
            "steps": int(len(d))}


def rpe(est: np.ndarray, ref: np.ndarray, distance: float = 1.0) -> dict:
    """Relative pose error over ``distance`` metres of (reference) travel: RMS of the
    difference between estimated and reference relative motions."""
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref[:, :2], axis=0),
                                                              axis=-1))])
    i = np.arange(len(ref))
    j = np.searchsorted(travel, travel + distance)
    ok = j < len(ref)
    i, j = i[ok], j[ok]
    if not len(i):
        return {"rpe_trans_m": float("nan"), "rpe_rot_deg": float("nan"), "rpe_pairs": 0}
    re, rr = relative(est[i], est[j]), relative(ref[i], ref[j])
    dt = np.linalg.norm(re[:, :2] - rr[:, :2], axis=-1)
    dr = angle_diff(re[:, 2], rr[:, 2])
    return {"rpe_trans_m": float(np.sqrt(np.mean(dt ** 2))),
            "rpe_rot_deg": float(np.degrees(np.sqrt(np.mean(dr ** 2)))),
            "rpe_pairs": int(len(i))}


def load_relations(path) -> np.ndarray:
    """Relative-pose ground truth in the format of Kümmerle et al. (2009), "On measuring the
    accuracy of SLAM algorithms": one relation per line, ``t1 t2 x y z roll pitch yaw`` (the
    pose at t2 seen from the pose at t1).  Returns (n, 5): t1, t2, x, y, yaw.  Raises
    ValueError naming the line of a malformed relation."""
    rows = []
    with open(path) as f:
        for k, line in enumerate(f, 1):
            v = line.split()
            if not v or v[0].startswith("#"):
                continue
            try:
                if len(v) != 8:
                    raise ValueError(f"{len(v)} fields, expected 8")
                t1, t2, x, y, _, _, _, yaw = (float(u) for u in v)
            except ValueError as exc:
                raise ValueError(f"{path}:{k}: not a relation ({exc})") from None
            if not all(np.isfinite((t1, t2, x, y, yaw))):
                raise ValueError(f"{path}:{k}: not a relation (non-finite value)")
            rows.append((t1, t2, x, y, yaw))
    if not rows:
        raise ValueError(f"{path}: no relations")
    return np.array(rows)


def clock_offset(stamps: np.ndarray, times: np.ndarray, tol: float = 2e-3) -> float:
    """The shift s such that the most ``times`` fall within ``tol`` of some ``stamps + s``:
    a log re-timed to start near zero (as corrected logs often are) against relations kept
    in the original clock.  The mode of all pairwise differences, refined to the mean of
    the differences that agree with it."""
    stamps, times = np.sort(np.asarray(stamps, float)), np.unique(np.asarray(times, float))
    sub = times[:: max(1, len(times) // 500)]  # a few hundred instants fix the mode
    diff = (sub[:, None] - stamps[None, :]).ravel()
    keys = np.round(diff / tol).astype(np.int64)
    cells, counts = np.unique(keys, return_counts=True)

    def count_at(c: np.ndarray) -> np.ndarray:
        k = np.minimum(np.searchsorted(cells, c), len(cells) - 1)
        return np.where(cells[k] == c, counts[k], 0)

    # a cell with its neighbours: the true offset can sit on a cell border
    best = cells[np.argmax(counts + count_at(cells - 1) + count_at(cells + 1))]
    # refine: of the differences around the mode, the shift that matches the most instants
    cand = np.unique(diff[np.abs(keys - best) <= 1])
    cand = cand[:: max(1, len(cand) // 200)]

    def matched(s: float) -> int:
        t = times - s
        k = np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1)
        return int(np.sum(np.minimum(np.abs(stamps[k] - t), np.abs(stamps[k - 1] - t)) <= tol))

    score = np.array([matched(c) for c in cand])
    return float(np.median(cand[score == score.max()]))


def relations_error(stamps: np.ndarray, poses: np.ndarray, relations: np.ndarray,
                    tol: float = 2e-3, offset: float | None = None) -> dict:
    """Mean and median error of ``poses`` (n, 3) against relations (:func:`load_relations`)
    whose two instants both coincide (within ``tol`` s) with a scan's stamp; the stamps'
    clock offset is estimated (:func:`clock_offset`) unless given."""
    stamps = np.asarray(stamps, float)
    if offset is None:
        offset = clock_offset(stamps, relations[:, :2].ravel(), tol)
    order = np.argsort(stamps)
    st = stamps[order] + offset

    def nearest(t):
        k = np.clip(np.searchsorted(st, t), 1, len(st) - 1)
        k = np.where(np.abs(st[k - 1] - t) <= np.abs(st[k] - t), k - 1, k)
        return order[k], np.abs(st[k] - t)

    i, d1 = nearest(relations[:, 0])
    j, d2 = nearest(relations[:, 1])
    ok = (d1 <= tol) & (d2 <= tol) & (i != j)
    out = {"relations": int(ok.sum()), "relations_total": int(len(relations)),
           "clock_offset_s": float(offset)}
    if not ok.any():
        return out
    rel = relative(np.asarray(poses, float)[i[ok]], np.asarray(poses, float)[j[ok]])
    r = relations[ok]
    et = np.hypot(rel[:, 0] - r[:, 2], rel[:, 1] - r[:, 3])
    er = np.degrees(np.abs(angle_diff(rel[:, 2], r[:, 4])))
    out.update({"trans_mean_m": float(et.mean()), "trans_median_m": float(np.median(et)),
                "rot_mean_deg": float(er.mean()), "rot_median_deg": float(np.median(er))})
    return out


def revisit_pairs(poses: np.ndarray, min_gap: int = 50, radius: float = 1.0,
                  turn_deg: float = 45.0) -> np.ndarray:
    """(m, 2) pairs (earlier, later) of scans taken at least ``min_gap`` scans apart from
    within ``radius`` m and ``turn_deg`` of each other by ``poses``: for each later scan the
    nearest such earlier one.  Where a trajectory closed its loops, these are the pairs
    that say whether it closed them right."""
    poses = np.asarray(poses, float)
    tree = cKDTree(poses[:, :2])
    out = []
    for i, near in enumerate(tree.query_ball_point(poses[:, :2], radius)):
        j = np.array([k for k in near if k <= i - min_gap], dtype=int)
        if not len(j):
            continue
        j = j[np.degrees(np.abs(angle_diff(poses[j, 2], poses[i, 2]))) <= turn_deg]
        if len(j):
            out.append((int(j[np.argmin(np.hypot(*(poses[j, :2] - poses[i, :2]).T))]), i))
    return np.array(out, dtype=int).reshape(-1, 2)


def icp_agreement(scans, trajectories: dict, guess: np.ndarray,
                  params: IcpParams | None = None, max_pairs: int = 1000,
                  pairs: np.ndarray | None = None) -> dict:
    """How well each trajectory's consecutive relative poses (or those of ``pairs``, (m, 2)
    scan indices, e.g. :func:`revisit_pairs`) agree with raw-point ICP between the same scans
    (:mod:`.scan_icp`, started from ``guess``'s relative poses): median and RMS of the
    translation (m) and rotation (deg) differences per trajectory, and the ICP's own
    consistency (each pair matched both ways, the two results composed; identity when the
    matcher is precise).  A reference that is itself a SLAM output is not ground truth: this
    tells whether the estimate or the reference sits closer to what the ranges say.

    At most ``max_pairs`` pairs, evenly spread over the run (0: all): two ICPs per pair take
    ~12 ms, and a 12 000-scan log's pairs would take longer than its mapping."""
    n = len(scans)
    P = (np.column_stack([np.arange(n - 1), np.arange(1, n)]) if pairs is None
         else np.asarray(pairs, int).reshape(-1, 2))
    if max_pairs and len(P) > max_pairs:
        P = P[np.unique(np.linspace(0, len(P) - 1, max_pairs).round().astype(int))]
    need = np.unique(P.ravel())
    pts = {int(k): scan_points(scans[k].ranges, scans[k].angle_min, scans[k].angle_increment,
                               params) for k in need}
    z, back = [], []
    for a, k in P.tolist():
        g = relative(guess[a], guess[k])
        f = icp(pts[k], pts[a], g, params)
        b = icp(pts[a], pts[k], relative(g, np.zeros(3)), params)
        z.append(f if f is not None else np.full(3, np.nan))
        back.append(compose_pose2d(f, b) if f is not None and b is not None
                    else np.full(3, np.nan))
    Z = np.array(z).reshape(-1, 3)

    def figures(d: np.ndarray) -> dict:
        d = d[np.isfinite(d).all(axis=1)]
        if not len(d):
            return {"pairs": 0}
        t, r = np.hypot(d[:, 0], d[:, 1]), np.degrees(np.abs(angle_diff(d[:, 2], 0.0)))
        return {"pairs": int(len(d)), "trans_median_m": round(float(np.median(t)), 4),
                "trans_rms_m": round(float(np.sqrt(np.mean(t ** 2))), 4),
                "rot_median_deg": round(float(np.median(r)), 3),
                "rot_rms_deg": round(float(np.sqrt(np.mean(r ** 2))), 3)}

    out = {name: figures(relative(Z, relative(np.asarray(X)[P[:, 0]], np.asarray(X)[P[:, 1]])))
           for name, X in trajectories.items()}
    out["icp_both_ways"] = figures(np.array(back).reshape(-1, 3))
    return out


def wall_squareness(walls, poses: np.ndarray, min_length: float = 1.5,
                    window_deg: float = 8.0, block: int = 250) -> dict:
    """A yardstick that needs no reference poses: how square the walls come out in a
    building of right angles.  Each scan's walls (``walls[k]`` = (a, b) end points (m, 2) in
    its laser frame; those ``min_length`` m and longer) are turned by their scan's heading in
    ``poses``; the building's axes are the length-weighted mean direction modulo 90°, and a
    wall within ``window_deg`` of an axis deviates from it by what its scan's heading is off
    (plus its own fit noise).  Returns the axis (``axis_deg``, 0-90), the length-weighted
    RMS deviation (``rms_deg``), the share of wall length near an axis (``on_axes``; walls
    beyond the window, a building's own oblique ones, are left out), and the mean deviation
    of each ``block`` scans' walls (``block_deg``: a heading drift that a loop later shares
    out shows as blocks off zero; ``worst_block_deg`` the largest).

    Two trajectories of the same scans compare by it directly, whatever their frames: the
    one whose walls line up better has the truer headings, where a SLAM reference (not
    ground truth) may itself be off by a degree."""
    heading = np.asarray(poses, float)[:, 2]
    ang, w, which = [], [], []
    for k, (a, b) in enumerate(walls):
        d = np.asarray(b, float) - np.asarray(a, float)
        length = np.hypot(d[:, 0], d[:, 1])
        m = length >= min_length
        ang.append(np.arctan2(d[m, 1], d[m, 0]) + heading[k])
        w.append(length[m])
        which.append(np.full(int(m.sum()), k))
    a, w, which = np.concatenate(ang), np.concatenate(w), np.concatenate(which)
    if not len(a):
        return {"walls": 0}
    axis = float(np.angle(np.sum(w * np.exp(4j * a)))) / 4.0    # direction modulo 90 deg
    dev = (a - axis + np.pi / 4) % (np.pi / 2) - np.pi / 4
    near = np.abs(dev) <= np.radians(window_deg)
    wn, dn, kn = w[near], dev[near], which[near]
    blocks = []
    for k0 in range(0, len(heading), block):
        m = (kn >= k0) & (kn < k0 + block)
        if wn[m].sum() > 0:
            blocks.append(round(float(np.degrees(np.sum(wn[m] * dn[m]) / wn[m].sum())), 3))
    return {"walls": int(near.sum()),
            "axis_deg": round(float(np.degrees(axis)) % 90.0, 3),
            "rms_deg": round(float(np.degrees(np.sqrt(np.sum(wn * dn ** 2) / wn.sum()))), 3)
            if wn.sum() > 0 else None,
            "on_axes": round(float(wn.sum() / w.sum()), 3),
            "block_deg": blocks,
            "worst_block_deg": max((abs(b) for b in blocks), default=None)}


def reference_check(squareness: dict, min_on_axes: float = 0.5, share: float = 0.8,
                    margin_deg: float = 1.0) -> dict | None:
    """Whether a log's reference poses look like raw odometry rather than a corrected
    trajectory, from :func:`wall_squareness` of the ``estimate`` and the ``reference``
    (None without both).  A raw CARMEN log carries its odometry where a corrected one
    carries the corrected poses, and nothing in the file says which; an ATE against
    drifting odometry says nothing about the map.  In a square building (the estimate has
    ``min_on_axes`` of its wall length near the axes) a drifting heading turns walls off the
    axes: the reference is flagged when it keeps at most ``share`` of the estimate's wall
    length there and its RMS deviation exceeds the estimate's by ``margin_deg``.  Intel's
    reference (a SLAM solution, seed 0 of ``high``) keeps 1.0x of the estimate's share and is
    0.04 deg off its RMS, Killian Court's (a pose-graph solution) 0.3-0.4 deg off; Intel with
    the ``high`` preset's odometry as its poses keeps 0.24x, 3.0 deg off."""
    est, ref = squareness.get("estimate") or {}, squareness.get("reference") or {}
    if est.get("rms_deg") is None or ref.get("rms_deg") is None:
        return None
    judged = est["on_axes"] >= min_on_axes
    flag = bool(judged and ref["on_axes"] <= share * est["on_axes"]
                and ref["rms_deg"] >= est["rms_deg"] + margin_deg)
    return {"odometry_like": flag, "judged": bool(judged),
            "on_axes": {"estimate": est["on_axes"], "reference": ref["on_axes"]},
            "rms_deg": {"estimate": est["rms_deg"], "reference": ref["rms_deg"]}}
