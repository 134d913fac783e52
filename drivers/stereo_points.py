"""Disparity to 3D points, and the camera chain that carries them to the global frame.

Reprojection of a rectified pair: z = fx b / (d + doffs), x = (u - cx) z / fx,
y = (v - cy) z / fy, in the left camera's optical frame C (x right, y down, z forward).
The points then reach the global frame G through the camera chain of DESIGN.md (seed 000
eqs. 17-22, PRL 20-25, corrected): one motor M_GC applied to all points at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from cgamap.cga import (
    Multivector,
    apply_points,
    camera_chain,
    motor_from_pose,
    motor_to_matrix,
    rotor,
    translator,
)

from .pantilt import pan_tilt_rotors
from .stereo_calib import StereoCalibration

# Fixed rotation from the head frame (x forward, y left, z up) to the optical frame
# (x right, y down, z forward): columns are the optical axes written in the head frame.
R_HEAD_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def disparity_to_depth(disp: np.ndarray, calib: StereoCalibration,
                       min_disparity: float = 0.5) -> np.ndarray:
    """Depth z (metres) per pixel; NaN where the disparity is missing or below the minimum."""
    d = np.asarray(disp, dtype=np.float64) + calib.doffs
    with np.errstate(invalid="ignore", divide="ignore"):
        z = calib.fx * calib.baseline / d
    z[~(d >= min_disparity)] = np.nan
    return z


def depth_to_points(depth: np.ndarray, calib: StereoCalibration, max_depth: float = np.inf,
                    stride: int = 1, organised: bool = False) -> np.ndarray:
    """Back-project a depth image (metres, NaN = none) to points in the optical frame.

    Returns (n, 3) valid points, or (h, w, 3) with NaN holes when ``organised``; points are in
    the raw left camera frame (a raw calibration's rectifying rotation R_rect is undone).
    ``stride`` subsamples rows and columns (every stride-th pixel).
    """
    z = np.asarray(depth, dtype=np.float64)[::stride, ::stride]
    h, w = z.shape
    v, u = np.mgrid[0:h * stride:stride, 0:w * stride:stride]
    x = (u - calib.cx) * z / calib.fx
    y = (v - calib.cy) * z / calib.fy
    pts = np.stack([x, y, z], axis=-1)
    if calib.R_rect is not None:  # back from the rectified to the raw left camera frame
        pts = pts @ np.asarray(calib.R_rect)
    ok = np.isfinite(z) & (z > 0) & (z <= max_depth)
    if organised:
        pts[~ok] = np.nan
        return pts
    return pts[ok]


def disparity_to_points(disp: np.ndarray, calib: StereoCalibration, max_depth: float = np.inf,
                        stride: int = 1, min_disparity: float = 0.5,
                        organised: bool = False) -> np.ndarray:
    """Reproject a disparity image (pixels, NaN = none) to (n, 3) optical-frame points."""
    depth = disparity_to_depth(disp, calib, min_disparity=min_disparity)
    return depth_to_points(depth, calib, max_depth=max_depth, stride=stride,
                           organised=organised)


@dataclass
class CameraMount:
    """Where the camera sits on the robot (DESIGN.md camera chain).

    ``t_axis``: the pan-tilt axis point in the base frame B (metres); ``t_eye``: the left
    camera's optical centre in the tilted head frame (x forward, y left, z up).  Pan turns
    about the base's +z (counter-clockwise), tilt about the panned head's +y (positive tilt
    pitches the camera down).
    """

    t_axis: tuple[float, float, float] = (0.0, 0.0, 0.5)
    t_eye: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Rotation of the optical frame in the head frame (columns: the optical x, y, z axes in
    # head coordinates), e.g. from a hand-eye calibration's head_T_cam; None: the nominal
    # R_HEAD_OPTICAL (optical z along the head's x).
    R_eye: tuple[tuple[float, float, float], ...] | None = None

    @classmethod
    def from_dict(cls, d: dict | None) -> CameraMount:
        d = dict(d or {})
        R = d.get("R_eye")
        return cls(t_axis=tuple(float(v) for v in d.get("t_axis", cls.t_axis)),
                   t_eye=tuple(float(v) for v in d.get("t_eye", cls.t_eye)),
                   R_eye=None if R is None else tuple(tuple(float(v) for v in row) for row in R))

    @classmethod
    def from_head_T_cam(cls, t_axis, head_T_cam) -> CameraMount:
        """Mount from the axis point and a hand-eye result (4x4 head_T_cam, rows)."""
        H = np.asarray(head_T_cam, dtype=float)
        return cls(t_axis=tuple(float(v) for v in t_axis),
                   t_eye=tuple(float(v) for v in H[:3, 3]),
                   R_eye=tuple(tuple(float(v) for v in row) for row in H[:3, :3]))

    @property
    def rotation(self) -> np.ndarray:
        return R_HEAD_OPTICAL if self.R_eye is None else np.asarray(self.R_eye, dtype=float)


def camera_motor(pose: tuple[float, float, float] | Multivector = (0.0, 0.0, 0.0),
                 pan: float = 0.0, tilt: float = 0.0,
                 mount: CameraMount | None = None) -> Multivector:
    """M_GC of the left camera's optical frame (eqs. 17-22 as corrected in DESIGN.md).

    ``pose`` is the robot's planar pose (x, y, theta) or its motor M_GB = T_pos R_pos (a motor
    is split into its translation and rotation parts).
    """
    mount = mount or CameraMount()
    if isinstance(pose, Multivector):
        H = motor_to_matrix(pose)
        T_pos = translator(H[:3, 3])
        R_pos = motor_from_pose(np.zeros(3), H[:3, :3])
    else:
        x, y, th = (float(v) for v in pose)
        T_pos = translator(np.array([x, y, 0.0]))
        R_pos = rotor(np.array([0.0, 0.0, 1.0]), th)
    R_pan, R_tilt = pan_tilt_rotors(pan, tilt)
    R_eye = motor_from_pose(np.zeros(3), mount.rotation)
    return camera_chain(T_pos, R_pos, R_pan, R_tilt, np.asarray(mount.t_axis, dtype=float),
                        np.asarray(mount.t_eye, dtype=float), R_eye=R_eye)


def camera_matrix_chain(pose: tuple[float, float, float], pan: float = 0.0, tilt: float = 0.0,
                        mount: CameraMount | None = None) -> np.ndarray:
    """The same chain as 4x4 homogeneous matrices: H_GB H_B,axis H_pan H_tilt H_eye H_opt
    (used to check ``camera_motor``)."""
    mount = mount or CameraMount()

    def rz(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    def ry(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])

    def h(R=None, t=(0.0, 0.0, 0.0)):
        out = np.eye(4)
        out[:3, :3] = np.eye(3) if R is None else R
        out[:3, 3] = t
        return out

    x, y, th = pose
    return (h(rz(th), (x, y, 0.0)) @ h(t=mount.t_axis) @ h(rz(pan)) @ h(ry(tilt))
            @ h(t=mount.t_eye) @ h(mount.rotation))


def points_to_global(points_c: np.ndarray, M_GC: Multivector) -> np.ndarray:
    """Carry (..., 3) optical-frame points to the global frame with one motor (fast path)."""
    return apply_points(M_GC, points_c)
