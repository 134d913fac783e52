"""The ``depthai`` stereo backend: an OAK camera through the depthai v3 API.

The mono pair (CAM_B left, CAM_C right) feeds a StereoDepth node on the device with the
ROBOTICS preset; the host receives depth (uint16 millimetres, aligned to the rectified left
view) and the rectified left image.  Intrinsics and baseline are read from the device's calibration.

depthai is imported only when a grabber is opened: building a ``dai.Pipeline()`` searches for
a device and blocks for seconds (DESIGN.md), so nothing here runs at import time.  Device
discovery runs in a worker thread with a timeout, so a missing or wedged USB stack cannot hang
the caller.
"""

from __future__ import annotations

import datetime
import logging
import os
import threading
from typing import Any

import numpy as np

from .stereo import StereoFrame, StereoGrabber
from .stereo_calib import StereoCalibration, rectified_calibration

log = logging.getLogger(__name__)


class DeviceNotFound(RuntimeError):
    """No OAK device is attached (or none answered in time)."""


def _import_depthai():
    try:
        import depthai as dai
    except ImportError as exc:  # optional on machines without cameras
        raise DeviceNotFound(f"depthai: the depthai package is not installed ({exc})") from exc
    return dai


def list_devices(timeout: float = 5.0) -> list[dict[str, str]]:
    """OAK devices visible now, as dicts (device_id, name, state); [] when none answer
    within ``timeout`` seconds."""
    result: list = []

    def work():
        try:
            dai = _import_depthai()
            for info in dai.Device.getAllAvailableDevices():
                result.append({"device_id": info.deviceId, "name": info.name,
                               "state": str(info.state)})
        except Exception as exc:  # discovery problems mean "no device" to the caller
            log.warning("depthai discovery failed: %s", exc)

    t = threading.Thread(target=work, name="depthai-discovery", daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive():
        log.warning("depthai discovery did not finish within %.1f s", timeout)
        return []
    return list(result)


def calibration_from_handler(handler: Any, size: tuple[int, int]) -> StereoCalibration:
    """Calibration of the rectified-left view from a ``dai.CalibrationHandler``.

    depthai rectifies both views onto the right camera's (CAM_C) intrinsics, and rotates the
    left view by the stored left rectification rotation (its ``H = M_right R1 M_left^-1``;
    unverified on a device here).  Intrinsics are scaled to ``size``; the baseline CAM_B-CAM_C
    is reported in centimetres and returned in metres.
    """
    dai = _import_depthai()
    w, h = int(size[0]), int(size[1])
    K = np.array(handler.getCameraIntrinsics(dai.CameraBoardSocket.CAM_C, w, h))
    baseline_cm = handler.getBaselineDistance(dai.CameraBoardSocket.CAM_B,
                                              dai.CameraBoardSocket.CAM_C)
    try:
        R1 = np.array(handler.getStereoLeftRectificationRotation(), dtype=float)
        R1 = R1 if R1.shape == (3, 3) and np.allclose(R1 @ R1.T, np.eye(3), atol=1e-4) \
            else None
    except RuntimeError:  # no stereo rectification stored
        R1 = None
    return rectified_calibration(K[0, 0], K[0, 2], K[1, 2], abs(baseline_cm) / 100.0,
                                 fy=K[1, 1], size=(w, h), R_rect=R1)


def _stamp_ns(msg: Any) -> int:
    """depthai host timestamps are on the host's steady clock (CLOCK_MONOTONIC on Linux),
    the same clock as ``time.monotonic_ns()``."""
    ts: datetime.timedelta = msg.getTimestamp()
    return (ts.days * 86_400 + ts.seconds) * 1_000_000_000 + ts.microseconds * 1000


def frame_from_messages(depth_msg: Any, left_msg: Any, calib: StereoCalibration,
                        seq: int) -> StereoFrame:
    """A StereoFrame from a depth ImgFrame (uint16 mm, 0 = none) and the rectified left."""
    depth_mm = np.asarray(depth_msg.getFrame())
    depth = depth_mm.astype(np.float32) / 1000.0
    depth[depth_mm == 0] = np.nan
    left = np.asarray(left_msg.getCvFrame()) if left_msg is not None else np.zeros(
        depth.shape, np.uint8)
    return StereoFrame(seq=seq, stamp_ns=_stamp_ns(depth_msg), calib=calib, left=left,
                       depth=depth, device_stamp=int(depth_msg.getSequenceNum()))


class DepthaiGrabber(StereoGrabber):
    """OAK stereo depth.  ``device``: "" / "auto" for the first device, else a device id,
    USB name or IP address."""

    model = "depthai"

    def __init__(self, device: str = "", size=(640, 400), fps: float = 15.0,
                 preset: str = "ROBOTICS", discovery_timeout: float = 5.0,
                 subpixel: bool = True, lr_check: bool = True, **_ignored):
        self.device = "" if device in (None, "", "auto") else str(device)
        self.size = (int(size[0]), int(size[1]))
        self.fps = float(fps)
        self.preset = preset
        self.discovery_timeout = float(discovery_timeout)
        self.subpixel = subpixel
        self.lr_check = lr_check
        self.pipeline = None
        self.calib: StereoCalibration | None = None
        self._q_depth = None
        self._q_left = None
        self.seq = 0

    def open(self) -> None:
        if self.pipeline is not None:
            return
        devices = list_devices(self.discovery_timeout)
        if self.device:
            devices = [d for d in devices if self.device in (d["device_id"], d["name"])] or (
                [{"device_id": self.device}] if self.device.count(".") == 3 else [])
        if not devices:
            want = f" matching {self.device!r}" if self.device else ""
            raise DeviceNotFound(f"depthai: no OAK device found{want} (searched "
                                 f"{self.discovery_timeout:.0f} s; check USB access and udev)")
        dai = _import_depthai()
        # Bound the library's own search too (it defaults to about 11 s when nothing answers).
        os.environ.setdefault("DEPTHAI_SEARCH_TIMEOUT", str(int(self.discovery_timeout * 1000)))
        if self.device:
            pipeline = dai.Pipeline(dai.Device(dai.DeviceInfo(self.device)))
        else:
            pipeline = dai.Pipeline()
        try:
            left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
            right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
            out_l = left.requestOutput(self.size, type=dai.ImgFrame.Type.GRAY8, fps=self.fps)
            out_r = right.requestOutput(self.size, type=dai.ImgFrame.Type.GRAY8, fps=self.fps)
            preset = getattr(dai.node.StereoDepth.PresetMode, self.preset)
            stereo = pipeline.create(dai.node.StereoDepth).build(out_l, out_r,
                                                                 presetMode=preset)
            stereo.setLeftRightCheck(self.lr_check)
            stereo.setSubpixel(self.subpixel)
            # Depth in the rectified left view: the same geometry as the host SGBM path.
            stereo.setDepthAlign(
                dai.StereoDepthConfig.AlgorithmControl.DepthAlign.RECTIFIED_LEFT)
            self._q_depth = stereo.depth.createOutputQueue(maxSize=4, blocking=False)
            self._q_left = stereo.rectifiedLeft.createOutputQueue(maxSize=4, blocking=False)
            handler = pipeline.getDefaultDevice().readCalibration()
            self.calib = calibration_from_handler(handler, self.size)
            pipeline.start()
        except Exception:
            try:
                pipeline.stop()
            except Exception:  # not started yet
                pass
            raise
        self.pipeline = pipeline

    def grab(self, timeout: float = 5.0) -> StereoFrame:
        if self.pipeline is None:
            self.open()
        wait = datetime.timedelta(seconds=timeout)
        depth_msg = self._q_depth.get(wait)
        if depth_msg is None:
            raise TimeoutError(f"depthai: no depth frame within {timeout:.1f} s")
        left_msg = self._q_left.get(wait)
        # Pair by the device's sequence numbers (the two queues may drift by a frame).
        for _ in range(8):
            if left_msg is None or left_msg.getSequenceNum() >= depth_msg.getSequenceNum():
                break
            left_msg = self._q_left.get(wait)
        frame = frame_from_messages(depth_msg, left_msg, self.calib, self.seq)
        self.seq += 1
        return frame

    def close(self) -> None:
        if self.pipeline is not None:
            try:
                self.pipeline.stop()
            finally:
                self.pipeline = None
