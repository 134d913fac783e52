"""The ``opencv`` stereo backend: two cameras, or one side-by-side UVC stereo camera, through
``cv2.VideoCapture``; rectified with a stereo calibration file and matched with StereoSGBM.

Device URL: ``"0,1"`` (left and right camera indices or paths/URLs, comma-separated) or
``"sbs:0"`` (one camera delivering left|right side by side in one frame; also any video file,
e.g. ``"sbs:/path/rec.avi"``).  A bare ``"0"`` is read as side-by-side.
"""

from __future__ import annotations

import time

from .stereo import StereoFrame, StereoGrabber, sgbm_frame
from .stereo_calib import StereoCalibration, as_calibration
from .stereo_sgbm import SgbmParams, make_matcher


def parse_device(url: str) -> tuple[str, list[int | str]]:
    """("sbs" | "pair", sources) of an opencv device URL; numeric sources become indices."""
    url = url.strip()
    mode = "pair" if "," in url else "sbs"
    if url.startswith("sbs:"):
        mode, url = "sbs", url[4:]
    parts = [p.strip() for p in url.split(",")] if mode == "pair" else [url]
    if mode == "pair" and len(parts) != 2:
        raise ValueError(f"opencv stereo device {url!r}: expected 'LEFT,RIGHT' or 'sbs:SRC'")
    if any(not p for p in parts):
        raise ValueError(f"opencv stereo device {url!r}: empty source")
    return mode, [int(p) if p.isdigit() else p for p in parts]


class OpenCVGrabber(StereoGrabber):
    """Host-side stereo from UVC cameras (or video files) via OpenCV capture."""

    model = "opencv"

    def __init__(self, device: str = "0,1", calibration=None,
                 sgbm: SgbmParams | dict | None = None, size=None, fps: float | None = None,
                 **_ignored):
        self.mode, self.sources = parse_device(device)
        if calibration is None:
            raise ValueError("opencv stereo: a calibration file is required "
                             "(config 'calibration' or --calib)")
        self.calib: StereoCalibration = as_calibration(calibration)
        self.params = sgbm if isinstance(sgbm, SgbmParams) else SgbmParams.from_dict(sgbm)
        self.size = tuple(size) if size else self.calib.size  # per-eye (width, height)
        self.fps = fps
        self.caps: list = []
        self.seq = 0
        self._matcher = None

    def open(self) -> None:
        import cv2

        for src in self.sources:
            cap = cv2.VideoCapture(src)
            if not cap.isOpened():
                self.close()
                raise RuntimeError(f"opencv stereo: cannot open capture source {src!r}")
            if self.size and isinstance(src, int):
                w = self.size[0] * (2 if self.mode == "sbs" else 1)
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.size[1])
            if self.fps and isinstance(src, int):
                cap.set(cv2.CAP_PROP_FPS, self.fps)
            self.caps.append(cap)

    def close(self) -> None:
        for cap in self.caps:
            cap.release()
        self.caps = []

    def _read(self):
        if not self.caps:
            self.open()
        if self.mode == "pair":
            # grab() both first, then retrieve: the two exposures are as close as USB allows
            ok = all(cap.grab() for cap in self.caps)
            stamp = time.monotonic_ns()
            frames = [cap.retrieve()[1] for cap in self.caps] if ok else [None, None]
            if not ok or any(f is None for f in frames):
                raise StopIteration
            return frames[0], frames[1], stamp
        ok, img = self.caps[0].read()
        stamp = time.monotonic_ns()
        if not ok or img is None:
            raise StopIteration
        half = img.shape[1] // 2
        return img[:, :half], img[:, half:2 * half], stamp

    def grab(self, timeout: float = 5.0) -> StereoFrame:
        left, right, stamp = self._read()
        if self._matcher is None:
            self._matcher = make_matcher(self.params)
        frame = sgbm_frame(self.seq, stamp, left, right, self.calib, self.params,
                           matcher=self._matcher)
        self.seq += 1
        return frame
