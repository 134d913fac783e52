"""The stereo camera grabber: one frame type, one interface, backends chosen by config/URL.

Backends (``open_grabber``): ``depthai`` (an OAK, StereoDepth on the device), ``opencv`` (two
cameras or one side-by-side UVC camera, rectified and matched on the host with StereoSGBM),
and ``replay`` (a recorded folder of image pairs + calibration, same path).  The simulator's
``synthetic`` camera (``drivers.sim.stereo_render``: the simulated 3D world rendered as a
textured pair, same SGBM path, ground truth attached) registers itself when imported: a
driver does not depend on the simulator.
Every backend yields ``StereoFrame``s; ``frame_points`` / ``points_from_stereo_pair`` turn
them into points, and ``stereo_points.camera_motor`` carries the points to the global frame.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
from cgamap.cga import Multivector

from .messages import PanTiltState
from .stereo_calib import (
    StereoCalibration,
    as_calibration,
    load_calibration,
    rectified_calibration,
    save_calibration,
)
from .stereo_points import (
    CameraMount,
    camera_motor,
    depth_to_points,
    disparity_to_depth,
    disparity_to_points,
    points_to_global,
)
from .stereo_sgbm import SgbmParams, compute_disparity

__all__ = [
    "StereoFrame", "StereoGrabber", "StereoCalibration", "SgbmParams", "load_calibration",
    "save_calibration", "rectified_calibration", "points_from_stereo_pair", "frame_points",
    "frame_motor", "frame_points_global", "CameraMount",
    "nearest_pantilt", "interpolate_pantilt", "pair_with_pantilt", "open_grabber", "BACKENDS",
    "register_backend",
]


@dataclass
class StereoFrame:
    """One stereo frame in the rectified geometry of its calibration.

    ``disparity`` in pixels (float32, NaN = no match) and/or ``depth`` in metres (NaN = none);
    ``left`` (and ``right`` when the backend has it) the rectified images; ``ground_truth`` the
    true depth of the left image (synthetic backend only).
    """

    seq: int
    stamp_ns: int
    calib: StereoCalibration
    left: np.ndarray
    right: np.ndarray | None = None
    disparity: np.ndarray | None = None
    depth: np.ndarray | None = None
    ground_truth: np.ndarray | None = None
    device_stamp: int | None = None
    pantilt: PanTiltState | None = None
    pose_ref: tuple[float, float, float] | None = None  # robot pose (x, y, theta), if known
    meta: dict = field(default_factory=dict)

    def depth_image(self) -> np.ndarray:
        """Depth in metres (from ``depth`` or derived from ``disparity``)."""
        if self.depth is not None:
            return self.depth
        if self.disparity is None:
            raise ValueError("stereo frame has neither depth nor disparity")
        return disparity_to_depth(self.disparity, self.calib)


class StereoGrabber:
    """Backend interface: ``open()``, ``grab(timeout)`` -> StereoFrame, ``close()``;
    iterable and a context manager.  Nothing touches a device before ``open()``."""

    model = "abstract"

    def open(self) -> None:
        """Acquire the device (no-op for file and synthetic sources)."""

    def grab(self, timeout: float = 5.0) -> StereoFrame:
        raise NotImplementedError

    def close(self) -> None:
        """Release the device."""

    def __enter__(self) -> StereoGrabber:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def frames(self, count: int | None = None, timeout: float = 5.0) -> Iterator[StereoFrame]:
        """Up to ``count`` frames (all available when None); stops at end of a sequence."""
        n = 0
        while count is None or n < count:
            try:
                frame = self.grab(timeout=timeout)
            except StopIteration:
                return
            yield frame
            n += 1


def frame_points(frame: StereoFrame, max_depth: float = np.inf, stride: int = 1) -> np.ndarray:
    """(n, 3) points of a frame in the left camera's optical frame (shared by all backends)."""
    if frame.disparity is not None:
        return disparity_to_points(frame.disparity, frame.calib, max_depth=max_depth,
                                   stride=stride)
    return depth_to_points(frame.depth_image(), frame.calib, max_depth=max_depth, stride=stride)


def frame_motor(frame: StereoFrame, mount: CameraMount | None = None,
                pose: tuple[float, float, float] | Multivector | None = None) -> Multivector:
    """M_GC of a frame: the camera chain from the robot pose (``pose``, else the frame's
    ``pose_ref``, else the origin) and the frame's paired pan-tilt state (else level)."""
    pose = pose if pose is not None else (frame.pose_ref or (0.0, 0.0, 0.0))
    pan = frame.pantilt.pan if frame.pantilt is not None else 0.0
    tilt = frame.pantilt.tilt if frame.pantilt is not None else 0.0
    return camera_motor(pose, pan, tilt, mount)


def frame_points_global(frame: StereoFrame, mount: CameraMount | None = None,
                        pose: tuple[float, float, float] | Multivector | None = None,
                        max_depth: float = np.inf, stride: int = 1) -> np.ndarray:
    """(n, 3) points of a frame in the global frame: reprojection, then one motor for all."""
    pts = frame_points(frame, max_depth=max_depth, stride=stride)
    return points_to_global(pts, frame_motor(frame, mount, pose))


def points_from_stereo_pair(left_img: np.ndarray, right_img: np.ndarray, calib,
                            sgbm: SgbmParams | dict | None = None, max_depth: float = np.inf,
                            stride: int = 1) -> np.ndarray:
    """(n, 3) points, in the left camera's optical frame (x right, y down, z forward, metres),
    from one stereo pair: rectify with the calibration, StereoSGBM disparity, reproject.

    ``calib``: a ``StereoCalibration``, a dict of its YAML fields, or a calibration file path
    (see ``stereo_calib``).  ``sgbm``: matcher parameters (``SgbmParams`` or
    a dict of its fields; default 64 disparities, block 5, 3-way mode).
    """
    calib = as_calibration(calib)
    params = sgbm if isinstance(sgbm, SgbmParams) else SgbmParams.from_dict(sgbm)
    left, right = calib.rectify(np.asarray(left_img), np.asarray(right_img))
    disp = compute_disparity(left, right, params)
    return disparity_to_points(disp, calib, max_depth=max_depth, stride=stride)


def _stamp(state: PanTiltState) -> int:
    return state.stamp_ns


def nearest_pantilt(stamp_ns: int, states: Sequence[PanTiltState],
                    max_gap_ns: int | None = None) -> PanTiltState | None:
    """The pan-tilt state nearest in time to ``stamp_ns`` (states sorted by stamp_ns);
    None when there is none within ``max_gap_ns``."""
    if not states:
        return None
    i = bisect.bisect_left(states, stamp_ns, key=_stamp)
    cands = [states[j] for j in (i - 1, i) if 0 <= j < len(states)]
    best = min(cands, key=lambda s: abs(s.stamp_ns - stamp_ns))
    if max_gap_ns is not None and abs(best.stamp_ns - stamp_ns) > max_gap_ns:
        return None
    return best


def interpolate_pantilt(stamp_ns: int, states: Sequence[PanTiltState],
                        max_gap_ns: int | None = 100_000_000) -> PanTiltState | None:
    """Pan and tilt at ``stamp_ns``, linearly interpolated between the two states around it
    (states sorted by stamp_ns); the nearest state when the stamp is outside their span or
    the two are more than ``max_gap_ns`` apart; None when none is within ``max_gap_ns``."""
    near = nearest_pantilt(stamp_ns, states, max_gap_ns)
    if near is None:
        return None
    i = bisect.bisect_right(states, stamp_ns, key=_stamp)
    if i == 0 or i == len(states):
        return near
    a, b = states[i - 1], states[i]
    span = b.stamp_ns - a.stamp_ns
    if span <= 0 or (max_gap_ns is not None and span > max_gap_ns):
        return near
    w = (stamp_ns - a.stamp_ns) / span
    return PanTiltState(seq=near.seq, stamp_ns=stamp_ns, pan=a.pan + w * (b.pan - a.pan),
                        tilt=a.tilt + w * (b.tilt - a.tilt), moving=a.moving or b.moving,
                        hardware_error=a.hardware_error | b.hardware_error)


def pair_with_pantilt(frame: StereoFrame, states: Sequence[PanTiltState],
                      max_gap_ns: int | None = 100_000_000,
                      interpolate: bool = False) -> StereoFrame:
    """Attach the pan-tilt state nearest in time (within ``max_gap_ns``, default 100 ms), or
    the one interpolated at the frame's stamp, to a frame (None when none is close enough)."""
    pick = interpolate_pantilt if interpolate else nearest_pantilt
    frame.pantilt = pick(frame.stamp_ns, states, max_gap_ns)
    return frame


def _depthai(device: str | None, **config) -> StereoGrabber:
    from .stereo_depthai import DepthaiGrabber

    return DepthaiGrabber(device or "", **config)


def _opencv(device: str | None, **config) -> StereoGrabber:
    from .stereo_opencv import OpenCVGrabber

    return OpenCVGrabber(device or "0,1", **config)


def _replay(device: str | None, **config) -> StereoGrabber:
    from .stereo_replay import ReplayGrabber

    return ReplayGrabber(device or ".", **config)


#: backend name -> ``factory(device, **config)``.  The drivers' own backends; others (the
#: simulator's ``synthetic``) add themselves with :func:`register_backend`, so that no driver
#: depends on them.
BACKENDS: dict[str, Callable[..., StereoGrabber]] = {
    "depthai": _depthai, "opencv": _opencv, "replay": _replay}


def register_backend(name: str, factory: Callable[..., StereoGrabber]) -> None:
    """Make ``open_grabber(name, device, config)`` call ``factory(device, **config)``."""
    BACKENDS[name] = factory


def open_grabber(model: str, device: str | None = None, config: dict | None = None
                 ) -> StereoGrabber:
    """Make (not open) a grabber.  ``model`` is a backend name; ``device`` its URL:

    * depthai: ``""`` / ``"auto"`` (first device) or a device id / IP;
    * opencv: ``"0,1"`` (two cameras), ``"0"`` or ``"sbs:0"`` (one side-by-side camera), or
      video file paths; needs ``config["calibration"]`` (a file path) unless rectified;
    * replay: a folder of recorded pairs (see ``stereo_replay``);
    * synthetic, once ``cgamap.drivers.sim.stereo_render`` is imported: a world name
      (``"corridor"``, ``"stairs"``, …).
    ``config`` carries backend settings (``sgbm``, ``calibration``, ``size``, ``fps``, …).
    """
    make = BACKENDS.get(model)
    if make is None:
        raise ValueError(f"stereo: unknown model {model!r} (choose from {', '.join(BACKENDS)})")
    return make(device, **dict(config or {}))


def sgbm_frame(seq: int, stamp_ns: int, left: np.ndarray, right: np.ndarray,
               calib: StereoCalibration, params: SgbmParams, matcher=None,
               **extra) -> StereoFrame:
    """Host-side path shared by the opencv, synthetic and replay backends: rectify, match."""
    left_r, right_r = calib.rectify(left, right)
    disp = compute_disparity(left_r, right_r, params, matcher=matcher)
    return StereoFrame(seq=seq, stamp_ns=stamp_ns, calib=calib, left=left_r, right=right_r,
                       disparity=disp, **extra)
