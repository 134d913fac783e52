"""Simulated calibration rig: the pan-tilt head, the camera on it and a chessboard in view.

The rig holds the *true* mount (head_T_cam, hidden from the solver) and renders what the
camera sees at given joint angles: a pinhole projection of the planar target, drawn by warping
a texture of the board with the plane's homography (2x supersampled, then blurred and noised a
little).  Forward kinematics go through the CGA camera chain of DESIGN.md (seed eqs. 17-22):
base_T_cam = T_axis R_pan R_tilt T_eye R_eye.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from cgamap.cga import motor_to_matrix, rotor, translator
from cgamap.drivers.stereo_points import R_HEAD_OPTICAL as R_OPTICAL
from cgamap.drivers.stereo_points import CameraMount, camera_motor

from .se3 import make_pose, so3_exp
from .targets import ChessboardTarget

Z_AXIS = np.array([0.0, 0.0, 1.0])
Y_AXIS = np.array([0.0, 1.0, 0.0])


def pan_tilt_head_pose(pan, tilt, axis_point) -> np.ndarray:
    """base_T_head of the pan-tilt: T_axis R_pan R_tilt (pan about z, tilt about the head's
    y axis), through motors; (..., 4, 4)."""
    pan, tilt = np.broadcast_arrays(np.asarray(pan, float), np.asarray(tilt, float))
    M = translator(np.asarray(axis_point, float)) * rotor(Z_AXIS + 0 * pan[..., None], pan) \
        * rotor(Y_AXIS + 0 * tilt[..., None], tilt)
    return motor_to_matrix(M)


@dataclass
class SimRig:
    """The simulated head, camera and target.  ``head_T_cam`` is the truth to recover."""

    head_T_cam: np.ndarray
    axis_point: np.ndarray
    base_T_target: np.ndarray
    K: np.ndarray
    size: tuple[int, int] = (640, 480)
    board: object = field(default_factory=ChessboardTarget)  # anything with texture()
    noise_gray: float = 2.0
    blur_sigma: float = 0.6
    motion_blur: set = field(default_factory=set)  # frame indices rendered with heavy blur

    def base_T_cam(self, pan: float, tilt: float) -> np.ndarray:
        """Camera pose through the CGA camera chain (robot at the origin)."""
        mount = CameraMount.from_head_T_cam(self.axis_point, self.head_T_cam)
        return motor_to_matrix(camera_motor((0.0, 0.0, 0.0), pan, tilt, mount))

    def cam_T_target(self, pan: float, tilt: float) -> np.ndarray:
        C = np.linalg.inv(self.base_T_cam(pan, tilt)) @ self.base_T_target
        C[3] = (0.0, 0.0, 0.0, 1.0)
        return C

    def render(self, pan: float, tilt: float, rng: np.random.Generator,
               index: int | None = None) -> np.ndarray:
        """Grey image (h, w) uint8 of the target seen at these joint angles."""
        w, h = self.size
        ss = 2  # supersampling
        C = self.cam_T_target(pan, tilt)
        tex, A = self.board.texture()
        Ks = self.K.copy()
        Ks[:2] *= ss
        Ks[:2, 2] += 0.5 * (ss - 1)  # pixel centres of the finer grid
        Hplane = Ks @ np.column_stack([C[:3, 0], C[:3, 1], C[:3, 3]]) @ A
        big = cv2.warpPerspective(tex, Hplane, (w * ss, h * ss), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=110)
        img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        if C[2, 3] <= 0:  # target behind the camera: nothing to see
            img[:] = 110
        if self.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
        if index is not None and index in self.motion_blur:
            k = np.zeros((1, 25), np.float32)
            k[:] = 1.0 / 25
            img = cv2.filter2D(img, -1, k)
            img = cv2.GaussianBlur(img, (0, 0), 4.0)
        img = img + rng.normal(scale=self.noise_gray, size=img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def default_rig(seed: int = 0, target_distance: float = 1.0, board=None) -> SimRig:
    """The rig ``calib collect --sim`` uses: the nominal mount of config/hand_eye.yaml with a
    hidden error (up to 3 degrees, 1 cm) drawn from ``seed``; a 9x6 board of 30 mm squares
    ``target_distance`` ahead of the nominal camera centre, facing the robot."""
    rng = np.random.default_rng(seed)
    nominal = make_pose(R_OPTICAL, [0.06, 0.0375, 0.05])
    w = rng.normal(size=3)
    w *= np.radians(rng.uniform(1.0, 3.0)) / np.linalg.norm(w)
    head_T_cam = make_pose(so3_exp(w) @ nominal[:3, :3], nominal[:3, 3]
                           + rng.uniform(-0.01, 0.01, 3))
    axis_point = np.array([0.10, 0.0, 0.90])
    board = ChessboardTarget() if board is None else board
    # Target frame like the optical frame of a camera looking along base +x: x to the
    # camera's right (-y), y down (-z), z away from the robot (+x).
    R_t = R_OPTICAL
    centre = axis_point + nominal[:3, 3] + np.array([target_distance, 0.0, 0.0])
    origin = centre - R_t @ np.array([(board.cols - 1) * board.square / 2,
                                      (board.rows - 1) * board.square / 2, 0.0])
    K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
    return SimRig(head_T_cam=head_T_cam, axis_point=axis_point,
                  base_T_target=make_pose(R_t, origin), K=K, board=board)
