"""The stereo twin: the 3D scene rendered as a rectified, textured left/right pair.

Vectorised ray casting against the scene's rectangles (``world3d``) from both optical
centres; each surface is painted with value noise in its own surface coordinates (metres),
so the texture sticks to the surface and both views see the same pattern.  Octaves finer than
about two pixels at the hit's distance are faded out (a cheap anti-aliasing that keeps SGBM
from matching aliasing).  The synthetic grabber feeds the pair through the same SGBM path as
the real cameras and attaches the true depth of the left image.
"""

from __future__ import annotations

import time
from functools import lru_cache

import numpy as np
from cgamap.cga import Multivector, motor_to_matrix

from ..messages import PanTiltState
from ..stereo import StereoFrame, StereoGrabber, register_backend, sgbm_frame
from ..stereo_calib import StereoCalibration, rectified_calibration
from ..stereo_points import CameraMount, camera_motor
from ..stereo_sgbm import SgbmParams, make_matcher
from .world3d import Scene3D, get_scene

OCTAVES = (0.02, 0.045, 0.1, 0.25)          # value-noise cell sizes, metres
OCTAVE_WEIGHTS = (0.35, 0.3, 0.2, 0.15)
KIND_BRIGHTNESS = {"floor": 0.55, "wall": 0.7, "tread": 0.6, "riser": 0.45, "top": 0.65,
                   "box": 0.5, "furniture": 0.5, "pillar": 0.6}


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) per integer lattice point and seed."""
    h = (ix.astype(np.uint32) * np.uint32(0x8DA6B343)) ^ (iy.astype(np.uint32)
                                                           * np.uint32(0xD8163841))
    h ^= seed.astype(np.uint32) * np.uint32(0xCB1AB31F)
    h ^= h >> np.uint32(13)
    h *= np.uint32(0x5BD1E995)
    h ^= h >> np.uint32(15)
    return (h & np.uint32(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def value_noise(a: np.ndarray, b: np.ndarray, seed: np.ndarray, cell: float) -> np.ndarray:
    """Smoothly interpolated lattice noise at surface coordinates (a, b) metres."""
    x, y = a / cell, b / cell
    ix, iy = np.floor(x), np.floor(y)
    fx, fy = x - ix, y - iy
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)  # smoothstep
    ix, iy = ix.astype(np.int64), iy.astype(np.int64)
    v00 = _hash01(ix, iy, seed)
    v10 = _hash01(ix + 1, iy, seed)
    v01 = _hash01(ix, iy + 1, seed)
    v11 = _hash01(ix + 1, iy + 1, seed)
    return (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy


def shade(scene: Scene3D, idx: np.ndarray, a: np.ndarray, b: np.ndarray,
          footprint: np.ndarray) -> np.ndarray:
    """Grey level in [0, 1] of hits on quads ``idx`` at surface coordinates (a, b);
    ``footprint`` is the size of one pixel on the surface (metres) for anti-aliasing."""
    bright = np.array([KIND_BRIGHTNESS.get(k, 0.6) for k in scene.kinds] + [0.85])
    seed = np.where(idx >= 0, idx + 1, 0)
    tex = np.zeros_like(a)
    wsum = np.zeros_like(a)
    for cell, w in zip(OCTAVES, OCTAVE_WEIGHTS, strict=True):  # four octaves, vectorised
        fade = np.clip((cell / np.maximum(footprint, 1e-9) - 2.0) / 2.0, 0.0, 1.0) * w
        tex += fade * value_noise(a, b, seed * 7 + int(cell * 1000), cell)
        wsum += fade
    tex = np.where(wsum > 0, tex / np.maximum(wsum, 1e-12), 0.5)
    g = bright[idx] * (0.35 + 0.9 * tex)
    return np.where(idx >= 0, g, bright[-1])  # sky / nothing: flat


@lru_cache(maxsize=8)
def _pixel_rays(fx: float, fy: float, cx: float, cy: float, w: int, h: int) -> np.ndarray:
    """(h*w, 3) optical-frame ray directions with z = 1 through every pixel centre."""
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(h * w)], axis=-1)
    d.setflags(write=False)
    return d


def camera_rays(K, D, size: tuple[int, int]) -> np.ndarray:
    """(h*w, 3) optical-frame rays with z = 1 through every pixel of a real (distorted)
    camera with matrix K and OpenCV distortion D: renders raw, unrectified views."""
    import cv2

    w, h = size
    v, u = np.mgrid[0:h, 0:w]
    pix = np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)[:, None, :]
    xy = cv2.undistortPointsIter(pix, np.asarray(K, float), np.asarray(D, float), None, None,
                                 (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10))
    xy = xy.reshape(-1, 2)
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


def _raycast_pinhole(scene: Scene3D, origin: np.ndarray, Rm: np.ndarray,
                     calib: StereoCalibration, w: int, h: int, dirs: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``Scene3D.raycast`` for a pinhole image, with a depth buffer: a quad wholly in front of
    the camera is tested only against the pixels of its projected bounding box (a loop over
    quads, vectorised over pixels); quads reaching behind the camera against all pixels."""
    d = dirs.reshape(h, w, 3)
    t_buf = np.full((h, w), np.inf)
    idx = np.full((h, w), -1, dtype=np.int64)
    a_buf = np.zeros((h, w))
    b_buf = np.zeros((h, w))
    n = scene.normals
    lu = np.linalg.norm(scene.eu, axis=1)
    lv = np.linalg.norm(scene.ev, axis=1)
    for q in range(len(scene)):  # tens of quads; each step is vectorised over its pixels
        c0 = scene.corner[q]
        corners = np.stack([c0, c0 + scene.eu[q], c0 + scene.ev[q],
                            c0 + scene.eu[q] + scene.ev[q]]) - origin
        cam = corners @ Rm                       # (4, 3) in the optical frame
        if np.all(cam[:, 2] > 1e-3):
            u = calib.fx * cam[:, 0] / cam[:, 2] + calib.cx
            v = calib.fy * cam[:, 1] / cam[:, 2] + calib.cy
            u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, w)
            v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, h)
            if u0 >= u1 or v0 >= v1:
                continue
        elif np.all(cam[:, 2] <= 0):
            continue                             # wholly behind the camera
        else:
            u0, u1, v0, v1 = 0, w, 0, h
        dd = d[v0:v1, u0:u1]
        wq = c0 - origin
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wq @ n[q]) / (dd @ n[q])
            a = t * (dd @ (scene.eu[q] / lu[q])) - wq @ (scene.eu[q] / lu[q])
            b = t * (dd @ (scene.ev[q] / lv[q])) - wq @ (scene.ev[q] / lv[q])
            win = ((t > 1e-6) & (a >= 0) & (a <= lu[q]) & (b >= 0) & (b <= lv[q])
                   & (t < t_buf[v0:v1, u0:u1]))
        t_buf[v0:v1, u0:u1][win] = t[win]
        idx[v0:v1, u0:u1][win] = q
        a_buf[v0:v1, u0:u1][win] = a[win]
        b_buf[v0:v1, u0:u1][win] = b[win]
    return t_buf.ravel(), idx.ravel(), a_buf.ravel(), b_buf.ravel()


def render_view(scene: Scene3D, H_GC: np.ndarray, calib: StereoCalibration,
                size: tuple[int, int], offset: float = 0.0,
                rays: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Grey image in [0, 1] and depth z (NaN = nothing) of a camera at pose H_GC (optical
    frame x right, y down, z forward), shifted by ``offset`` metres along its x.  ``rays``
    (h*w, 3, z = 1) replace the pinhole rays of ``calib`` (e.g. ``camera_rays``)."""
    w, h = size
    d_c = _pixel_rays(calib.fx, calib.fy, calib.cx, calib.cy, w, h) if rays is None else rays
    Rm = H_GC[:3, :3]
    origin = H_GC[:3, 3] + Rm[:, 0] * offset
    dirs = d_c @ Rm.T
    if rays is None:  # pinhole: test each quad only against the pixels it can cover
        t, idx, a, b = _raycast_pinhole(scene, origin, Rm, calib, w, h, dirs)
    else:
        t, idx, a, b = scene.raycast(origin, dirs)  # t along a z = 1 ray is the depth z
    # One pixel spans about z/fx metres, more on surfaces seen at a grazing angle.
    n = scene.normals[np.maximum(idx, 0)]
    cosang = np.abs(np.einsum("ij,ij->i", n, dirs)) / np.linalg.norm(dirs, axis=1)
    footprint = np.where(idx >= 0, t / calib.fx / np.maximum(cosang, 0.05), 1.0)
    img = shade(scene, idx, a, b, footprint)
    depth = np.where(idx >= 0, t, np.nan)
    return img.reshape(h, w), depth.reshape(h, w)


def _to8(img: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """An 8-bit image of a [0, 1] rendering, with Gaussian sensor noise in grey levels."""
    return np.clip(img * 255.0 + rng.normal(0.0, noise, img.shape), 0, 255).astype(np.uint8)


def render_raw_pair(scene: Scene3D, H_GC: np.ndarray, K1, D1, K2, D2, R, T,
                    size: tuple[int, int], noise: float = 1.0,
                    rng: np.random.Generator | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unrectified 8-bit pair of a real rig (cv2.stereoCalibrate convention: a point x in the
    left camera frame is R x + T in the right one), and the raw left view's true depth."""
    rng = rng or np.random.default_rng(0)
    R, T = np.asarray(R, float).reshape(3, 3), np.asarray(T, float).reshape(3)
    H_12 = np.eye(4)  # right camera -> left camera frame: x1 = R^T (x2 - T)
    H_12[:3, :3], H_12[:3, 3] = R.T, -R.T @ T
    f = rectified_calibration(float(np.asarray(K1)[0, 0]), 0, 0, 0)  # fx for anti-aliasing
    left, depth = render_view(scene, H_GC, f, size, rays=camera_rays(K1, D1, size))
    right, _ = render_view(scene, H_GC @ H_12, f, size, rays=camera_rays(K2, D2, size))
    return _to8(left, noise, rng), _to8(right, noise, rng), depth


def render_pair(scene: Scene3D, M_GC: Multivector | np.ndarray, calib: StereoCalibration,
                size: tuple[int, int] = (640, 400), noise: float = 1.0,
                rng: np.random.Generator | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rectified 8-bit left/right images and the left view's true depth (metres, NaN = none).

    The right camera sits ``calib.baseline`` along the left camera's +x; ``noise`` is the
    standard deviation of the sensor noise in grey levels.
    """
    H = motor_to_matrix(M_GC) if isinstance(M_GC, Multivector) else np.asarray(M_GC, float)
    rng = rng or np.random.default_rng(0)
    left, depth = render_view(scene, H, calib, size)
    right, _ = render_view(scene, H, calib, size, offset=calib.baseline)
    return _to8(left, noise, rng), _to8(right, noise, rng), depth


def default_calibration(size: tuple[int, int] = (640, 400), fx: float = 450.0,
                        baseline: float = 0.075) -> StereoCalibration:
    """An OAK-D-like rectified pair: 640x400, fx 450 px, 7.5 cm baseline."""
    w, h = size
    return rectified_calibration(fx, (w - 1) / 2.0, (h - 1) / 2.0, baseline, size=(w, h))


class SyntheticGrabber(StereoGrabber):
    """Frames of the simulated world along its trajectory (``fps`` frames per simulated
    second), rendered, matched with SGBM, with the true depth and robot pose attached.

    ``pan``/``tilt`` are fixed head angles (radians) or callables of the simulated time.
    """

    model = "synthetic"

    def __init__(self, world: str = "corridor", size=(640, 400), fx: float = 450.0,
                 baseline: float = 0.075, fps: float = 5.0, pan=0.0, tilt=0.0,
                 mount: CameraMount | dict | None = None, sgbm: SgbmParams | dict | None = None,
                 noise: float = 1.0, seed: int = 0, t0: float = 0.0, pose=None, **_ignored):
        self.scene = get_scene(world)
        self.size = (int(size[0]), int(size[1]))
        self.calib = default_calibration(self.size, fx, baseline)
        self.fps = float(fps)
        self.pan, self.tilt = pan, tilt
        self.mount = mount if isinstance(mount, CameraMount) else CameraMount.from_dict(
            mount or {"t_axis": (0.1, 0.0, 1.0), "t_eye": (0.05, baseline / 2, 0.05)})
        self.params = sgbm if isinstance(sgbm, SgbmParams) else SgbmParams.from_dict(sgbm)
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self.t0 = t0
        self.fixed_pose = pose  # (x, y, theta) to hold the robot still, else the trajectory
        self.seq = 0
        self._matcher = None

    def pose_at(self, t: float) -> tuple[float, float, float]:
        if self.fixed_pose is not None:
            return tuple(float(v) for v in self.fixed_pose)
        if self.scene.world is None:
            return (0.0, 0.0, 0.0)
        return self.scene.world.trajectory(t)

    def camera_motor_at(self, t: float) -> tuple[Multivector, tuple, float, float]:
        pan = self.pan(t) if callable(self.pan) else float(self.pan)
        tilt = self.tilt(t) if callable(self.tilt) else float(self.tilt)
        pose = self.pose_at(t)
        return camera_motor(pose, pan, tilt, self.mount), pose, pan, tilt

    def grab(self, timeout: float = 5.0) -> StereoFrame:
        t = self.t0 + self.seq / self.fps
        M, pose, pan, tilt = self.camera_motor_at(t)
        left, right, depth = render_pair(self.scene, M, self.calib, self.size, self.noise,
                                         self.rng)
        if self._matcher is None:
            self._matcher = make_matcher(self.params)
        stamp = time.monotonic_ns()
        pt = PanTiltState(seq=self.seq, stamp_ns=stamp, pan=pan, tilt=tilt)
        frame = sgbm_frame(self.seq, stamp, left, right, self.calib, self.params,
                           matcher=self._matcher, ground_truth=depth, pantilt=pt,
                           pose_ref=pose)
        frame.meta.update({"sim_time": t, "world": self.scene.name})
        self.seq += 1
        return frame


def open_synthetic(device: str | None = None, **config) -> SyntheticGrabber:
    """The ``synthetic`` stereo backend: ``device`` is a world name (default corridor)."""
    return SyntheticGrabber(device or "corridor", **config)


register_backend("synthetic", open_synthetic)
