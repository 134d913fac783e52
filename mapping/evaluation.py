"""Trajectory error against reference poses: ATE after rigid alignment, RPE over distance."""

from __future__ import annotations

import numpy as np
from cgamap.cga import angle_diff

from .odometry import compose_pose2d, relative


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
