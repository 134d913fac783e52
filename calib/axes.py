"""Pan/tilt axis calibration: each joint's axis as a CGA line, from the camera's motions.

The camera's pose in the (fixed) target frame follows the product of exponentials of the two
joints: T(pan, tilt) = S_pan(pan) S_tilt(tilt) T0, where S_L(q) is the motor turning by q about
the line L (M = T_p R(q) ~T_p for a line through p), L_pan the pan axis and L_tilt the tilt axis
at pan = 0, both in the target frame.  The two lines and T0 are fitted by least squares on all
observed poses (so no pose pair has to move one joint alone); the common perpendicular of the
two axes gives the axes point (T_axis of the camera chain, DESIGN.md), its length the axes'
offset, and the angle between them the residual non-orthogonality.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from cgamap.cga import Multivector, line_from_point_direction, motor_to_matrix, rotor, translator

from .se3 import inv, make_pose, so3_exp, so3_log


class AxisCalibrationError(ValueError):
    """Not enough joint motion (or parallel axes) to calibrate the axes."""


def joint_motor(point: np.ndarray, direction: np.ndarray, angle: np.ndarray) -> Multivector:
    """Motors (...) turning by ``angle`` about the line through ``point`` along ``direction``:
    T_p R ~T_p (seed eqs. 4-7)."""
    angle = np.asarray(angle, float)
    d = np.broadcast_to(direction, angle.shape + (3,))
    p = np.broadcast_to(point, angle.shape + (3,))
    return translator(p) * rotor(d, angle) * translator(-p)


def screw_axis(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Screw axes of rigid motions (..., 4, 4): (point closest to the origin, unit direction,
    angle, slide along the axis).  With t_perp the translation across the axis,
    p = (t_perp + cot(angle/2) d x t_perp) / 2."""
    w = so3_log(T[..., :3, :3])
    th = np.linalg.norm(w, axis=-1)
    if np.any(th < 1e-9):
        raise AxisCalibrationError("a motion without rotation has no screw axis")
    d = w / th[..., None]
    t = T[..., :3, 3]
    slide = np.einsum("...i,...i->...", d, t)
    tp = t - slide[..., None] * d
    p = 0.5 * (tp + (1.0 / np.tan(th / 2))[..., None] * np.cross(d, tp))
    return p, d, th, slide


def screw_line(T: np.ndarray) -> Multivector:
    """The screw axis of rigid motions as OPNS CGA lines (the line the motion turns about)."""
    p, d, _, _ = screw_axis(T)
    return line_from_point_direction(p, d)


def _perp_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


@dataclass
class _Params:
    p1: np.ndarray
    d1: np.ndarray
    p2: np.ndarray
    d2: np.ndarray
    T0: np.ndarray

    def moved(self, x: np.ndarray) -> _Params:
        """Minimal update (14): each line turns by 2 angles and shifts by 2 offsets across
        itself; T0 by a rotation vector and a translation."""
        out = []
        for (p, d), o in (((self.p1, self.d1), 0), ((self.p2, self.d2), 4)):
            u, v = _perp_basis(d)
            d_new = d + x[o] * u + x[o + 1] * v
            d_new /= np.linalg.norm(d_new)
            out += [p + x[o + 2] * u + x[o + 3] * v, d_new]
        T0 = make_pose(so3_exp(x[8:11]) @ self.T0[:3, :3], self.T0[:3, 3] + x[11:14])
        return _Params(*out, T0)


def _model(par: _Params, pan: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    M = joint_motor(par.p1, par.d1, pan) * joint_motor(par.p2, par.d2, tilt)
    return motor_to_matrix(M) @ par.T0


def _residuals(par: _Params, pan, tilt, T_obs, w_rot: float) -> np.ndarray:
    """Compared where the camera measures well: the target's pose in the camera frame
    (cam_T_target; its position there is accurate across the view, while the camera's
    position in the target frame mixes in the rotation error times the distance)."""
    C_obs, C_mod = inv(T_obs), inv(_model(par, pan, tilt))
    rot = so3_log(C_obs[:, :3, :3] @ np.swapaxes(C_mod[:, :3, :3], 1, 2))
    return np.concatenate([w_rot * rot, C_obs[:, :3, 3] - C_mod[:, :3, 3]], -1).reshape(-1)


@dataclass
class AxisCalibration:
    pan_point: np.ndarray  # a point on the pan axis (target frame, or base frame if known)
    pan_direction: np.ndarray
    tilt_point: np.ndarray  # the tilt axis at pan = 0
    tilt_direction: np.ndarray
    angle_deg: float  # between the axes
    offset_m: float  # length of the common perpendicular
    axis_point: np.ndarray  # midpoint of the common perpendicular
    rms_rot_deg: float  # fit residuals of cam_T_target
    rms_trans_m: float
    frame: str = "target"

    @property
    def non_orthogonality_deg(self) -> float:
        return self.angle_deg - 90.0

    def lines(self) -> tuple[Multivector, Multivector]:
        """The two axes as OPNS CGA lines."""
        return (line_from_point_direction(self.pan_point, self.pan_direction),
                line_from_point_direction(self.tilt_point, self.tilt_direction))

    def as_dict(self) -> dict:
        f = lambda v: [float(x) for x in v]  # noqa: E731
        return {"frame": self.frame, "pan_point": f(self.pan_point),
                "pan_direction": f(self.pan_direction), "tilt_point": f(self.tilt_point),
                "tilt_direction": f(self.tilt_direction), "angle_deg": float(self.angle_deg),
                "non_orthogonality_deg": float(self.non_orthogonality_deg),
                "offset_m": float(self.offset_m), "axis_point": f(self.axis_point),
                "rms_rot_deg": float(self.rms_rot_deg), "rms_trans_m": float(self.rms_trans_m)}


def common_perpendicular(p1, d1, p2, d2) -> tuple[np.ndarray, np.ndarray]:
    """Feet of the common perpendicular of two non-parallel lines."""
    n = np.cross(d1, d2)
    nn = n @ n
    if nn < 1e-12:
        raise AxisCalibrationError("the pan and tilt axes come out parallel")
    r = p2 - p1
    s = np.cross(r, d2) @ n / nn
    t = np.cross(r, d1) @ n / nn
    return p1 + s * d1, p2 + t * d2


def calibrate_axes(cam_T_target, pan, tilt, base_T_target: np.ndarray | None = None,
                   min_range_deg: float = 2.0, iters: int = 50) -> AxisCalibration:
    """Fit both joint axes from the target's pose at known joint angles.

    Initial guess: the screw axes of the camera's motions between the two poses that differ
    most in one joint and least in the other (with ``base_T_target``, directions along base z
    and y); the fit then refines lines and T0 by Levenberg-Marquardt.  With ``base_T_target``
    the result is expressed in the base frame."""
    C = np.asarray(cam_T_target, float)
    pan, tilt = np.asarray(pan, float), np.asarray(tilt, float)
    for name, q in (("pan", pan), ("tilt", tilt)):
        if np.degrees(np.ptp(q)) < min_range_deg:
            raise AxisCalibrationError(f"the {name} joint moves less than {min_range_deg} deg")
    T_obs = inv(C)  # target_T_cam
    # Screw axes of the camera's motions with the largest pan / tilt spread (CGA lines).
    p1, d1 = _axis_between(T_obs, pan, tilt)
    p2, d2 = _axis_between(T_obs, tilt, pan)
    if base_T_target is not None:  # directions known up to the mount: base z and y
        Rt = base_T_target[:3, :3].T
        d1, d2 = Rt @ np.array([0, 0, 1.0]), Rt @ np.array([0, 1.0, 0])
    best = None
    for s2 in (1.0, -1.0):  # the tilt direction's sign is not known without the base frame
        par = _Params(p1, d1, p2, s2 * d2, np.eye(4))
        # T0 from the first pose with the current axes.
        M0 = _model(par, pan[:1], tilt[:1])[0]
        par.T0 = inv(M0) @ T_obs[0]
        par, cost = _lm(par, pan, tilt, T_obs, iters)
        if best is None or cost < best[1]:
            best = (par, cost)
        if base_T_target is not None:
            break
    par = best[0]
    r = _residuals(par, pan, tilt, T_obs, 1.0).reshape(-1, 6)
    rms_rot = float(np.degrees(np.sqrt(np.mean(np.sum(r[:, :3] ** 2, -1)))))
    rms_t = float(np.sqrt(np.mean(np.sum(r[:, 3:] ** 2, -1))))
    c1, c2 = common_perpendicular(par.p1, par.d1, par.p2, par.d2)
    p1, d1, p2, d2 = c1, par.d1, c2, par.d2
    frame = "target"
    if base_T_target is not None:
        R, t = base_T_target[:3, :3], base_T_target[:3, 3]
        p1, p2, d1, d2 = R @ p1 + t, R @ p2 + t, R @ d1, R @ d2
        frame = "base"
    # Signed: both directions point along positive joint rotation (nominally 90 deg).
    angle = float(np.degrees(np.arccos(np.clip(d1 @ d2, -1.0, 1.0))))
    return AxisCalibration(p1, d1, p2, d2, angle, float(np.linalg.norm(c1 - c2)),
                           0.5 * (p1 + p2), rms_rot, rms_t, frame)


def _axis_between(T_obs, q, other) -> tuple[np.ndarray, np.ndarray]:
    """Screw axis (point, direction) of the camera's motion between the two poses that differ
    most in ``q`` and least in ``other``: a rough initial line for that joint."""
    n = len(q)
    i, j = np.triu_indices(n, 1)
    score = np.abs(q[i] - q[j]) - 3.0 * np.abs(other[i] - other[j])
    k = np.argmax(score)
    p, d, _, _ = screw_axis(T_obs[j[k]] @ inv(T_obs[i[k]]))  # motion in the target frame
    return p, d * np.sign(q[j[k]] - q[i[k]])


def _lm(par: _Params, pan, tilt, T_obs, iters: int) -> tuple[_Params, float]:
    w_rot = 0.5  # metres per radian: weighs rotation against translation residuals
    r = _residuals(par, pan, tilt, T_obs, w_rot)
    cost = r @ r
    lam = 1e-3
    h = 1e-7
    for _ in range(iters):
        J = np.stack([(_residuals(par.moved(h * e), pan, tilt, T_obs, w_rot)
                       - _residuals(par.moved(-h * e), pan, tilt, T_obs, w_rot)) / (2 * h)
                      for e in np.eye(14)], -1)
        JtJ, g = J.T @ J, J.T @ r
        for _ in range(10):
            step = -np.linalg.solve(JtJ + lam * (np.diag(np.diag(JtJ)) + 1e-12 * np.eye(14)), g)
            cand = par.moved(step)
            rc = _residuals(cand, pan, tilt, T_obs, w_rot)
            if rc @ rc < cost:
                break
            lam *= 10
        else:
            break
        done = cost - rc @ rc < 1e-14 * max(cost, 1e-300)
        par, r, cost, lam = cand, rc, rc @ rc, max(lam / 10, 1e-12)
        if done:
            break
    return par, float(cost)
