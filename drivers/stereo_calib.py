"""Stereo calibration: the file format, its loader, and rectification maps.

Two YAML forms are accepted (both plain YAML; OpenCV ``FileStorage`` files with
``%YAML:1.0`` and ``!!opencv-matrix`` nodes are read through ``cv2.FileStorage``):

* full (from a stereo calibration), pixels and metres::

      K1: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]   # left camera matrix
      D1: [k1, k2, p1, p2, k3]                     # left distortion (OpenCV order)
      K2: ...; D2: ...                             # right camera
      R: 3x3; T: [tx, ty, tz]                      # x_right = R x_left + T (cv2.stereoCalibrate)
      size: [width, height]

* already rectified (Middlebury, PCL test pairs, the synthetic camera, OAK output)::

      fx: 368.53; fy: 368.53; cx: 318.11; cy: 224.33; baseline: 0.8387
      size: [640, 480]          # optional
      doffs: 0.0                # optional: cx_right - cx_left offset added to disparity
      R_rect: 3x3               # optional: raw left camera -> rectified rotation (else I)

After rectification every pair is described by (fx, fy, cx, cy, baseline, doffs):
depth z = fx * baseline / (d + doffs) for disparity d in pixels of the left image.  Points
are given in the raw left camera's optical frame (the rectifying rotation is undone), so the
camera chain applies whether or not the images needed rectification.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .yaml_errors import yaml_error_text


class CalibrationFileError(ValueError):
    """A calibration file that cannot be read or parsed; the message names the file."""


@dataclass
class StereoCalibration:
    """A stereo pair's calibration; rectified intrinsics are derived on demand."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float                        # metres between the optical centres
    size: tuple[int, int] | None = None    # (width, height) of the images
    doffs: float = 0.0
    # Raw (unrectified) calibration; None when the pair is already rectified.
    K1: np.ndarray | None = None
    D1: np.ndarray | None = None
    K2: np.ndarray | None = None
    D2: np.ndarray | None = None
    R: np.ndarray | None = None
    T: np.ndarray | None = None
    # Rotation from the raw left camera frame to the rectified one (cv2.stereoRectify R1):
    # rectified points x_rect = R_rect x_raw; None when the pair is already rectified.
    R_rect: np.ndarray | None = None
    _maps: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def rectified(self) -> bool:
        """True when images need no remapping (no raw calibration attached)."""
        return self.K1 is None

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix of the rectified left image."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        """Plain-YAML form (the rectified fields, plus the raw ones when present)."""
        out: dict = {"fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx),
                     "cy": float(self.cy), "baseline": float(self.baseline),
                     "doffs": float(self.doffs)}
        if self.size is not None:
            out["size"] = [int(self.size[0]), int(self.size[1])]
        for name in ("R_rect", "K1", "D1", "K2", "D2", "R", "T"):
            val = getattr(self, name)
            if val is not None:
                out[name] = np.asarray(val, dtype=float).tolist()
        return out

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Remap a raw pair to the rectified geometry (identity for rectified calibrations)."""
        if self.rectified:
            return left, right
        import cv2

        if self._maps is None:
            raise RuntimeError("stereo calibration: rectification maps missing")
        m1x, m1y, m2x, m2y = self._maps
        return (cv2.remap(left, m1x, m1y, cv2.INTER_LINEAR),
                cv2.remap(right, m2x, m2y, cv2.INTER_LINEAR))


def rectified_calibration(fx: float, cx: float, cy: float, baseline: float,
                          fy: float | None = None, size: tuple[int, int] | None = None,
                          doffs: float = 0.0, R_rect=None) -> StereoCalibration:
    """Calibration of an already rectified pair (e.g. the PCL car pair or the OAK output);
    ``R_rect`` the rotation from the raw left camera to the rectified one, if not identity."""
    return StereoCalibration(fx=float(fx), fy=float(fx if fy is None else fy), cx=float(cx),
                             cy=float(cy), baseline=float(baseline), size=size, doffs=float(doffs),
                             R_rect=None if R_rect is None else
                             np.asarray(R_rect, dtype=float).reshape(3, 3))


def from_raw(K1, D1, K2, D2, R, T, size: tuple[int, int], alpha: float = 0.0) -> StereoCalibration:
    """Rectify a raw stereo calibration with ``cv2.stereoRectify`` (zero-disparity principal
    points, so doffs = 0) and keep the remap tables for ``StereoCalibration.rectify``."""
    import cv2

    K1, K2, R = (np.asarray(a, dtype=float).reshape(3, 3) for a in (K1, K2, R))
    D1, D2 = (np.asarray(a, dtype=float).ravel() for a in (D1, D2))
    T = np.asarray(T, dtype=float).reshape(3)
    w, h = int(size[0]), int(size[1])
    R1, R2, P1, P2, _Q, _, _ = cv2.stereoRectify(
        K1, D1, K2, D2, (w, h), R, T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha)
    m1 = cv2.initUndistortRectifyMap(K1, D1, R1, P1, (w, h), cv2.CV_32FC1)
    m2 = cv2.initUndistortRectifyMap(K2, D2, R2, P2, (w, h), cv2.CV_32FC1)
    fx = P1[0, 0]
    baseline = abs(P2[0, 3] / P2[0, 0])
    return StereoCalibration(fx=fx, fy=P1[1, 1], cx=P1[0, 2], cy=P1[1, 2], baseline=baseline,
                             size=(w, h), doffs=P2[0, 2] - P1[0, 2], K1=K1, D1=D1, K2=K2, D2=D2,
                             R=R, T=T, R_rect=R1, _maps=(m1[0], m1[1], m2[0], m2[1]))


def calibration_from_dict(d: dict) -> StereoCalibration:
    """Build a calibration from either YAML form (see the module docstring)."""
    size = (tuple(int(v) for v in np.asarray(d["size"]).ravel())
            if d.get("size") is not None else None)
    if all(k in d for k in ("K1", "D1", "K2", "D2", "R", "T")):
        if size is None:
            raise ValueError("stereo calibration: 'size' is required with K1/D1/K2/D2/R/T")
        return from_raw(d["K1"], d["D1"], d["K2"], d["D2"], d["R"], d["T"], size)
    missing = [k for k in ("fx", "cx", "cy", "baseline") if k not in d]
    if missing:
        raise ValueError(f"stereo calibration: missing {', '.join(missing)} "
                         "(need fx, cx, cy, baseline or K1, D1, K2, D2, R, T, size)")
    return rectified_calibration(d["fx"], d["cx"], d["cy"], d["baseline"], fy=d.get("fy"),
                                 size=size, doffs=d.get("doffs", 0.0), R_rect=d.get("R_rect"))


def _read_filestorage(path: Path) -> dict:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        out: dict = {}
        root = fs.root()
        for key in root.keys():
            node = fs.getNode(key)
            if node.isMap() and node.mat() is not None:  # an opencv-matrix
                out[key] = node.mat()
            elif node.isSeq():
                out[key] = [node.at(i).real() for i in range(node.size())]
            elif node.isReal() or node.isInt():
                out[key] = node.real()
            else:
                mat = node.mat()
                if mat is not None:
                    out[key] = mat
        return out
    finally:
        fs.release()


def load_calibration(path: str | Path) -> StereoCalibration:
    """Read a stereo calibration file (YAML, either form; or an OpenCV FileStorage YAML)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise CalibrationFileError(f"stereo calibration {path}: not a YAML text file (binary "
                                   f"data at byte {exc.start})") from None
    if text.lstrip().startswith("%YAML:1.0"):
        import cv2

        try:
            data = _read_filestorage(path)
        except (cv2.error, SystemError) as exc:   # SystemError: cv2's parse error surfacing
            why = str(exc.__cause__ or exc).strip().splitlines()[-1]
            raise CalibrationFileError(f"stereo calibration {path}: OpenCV cannot parse it "
                                       f"({why})") from None
    else:
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise CalibrationFileError(f"stereo calibration {path}: calibration "
                                       f"{yaml_error_text(exc)}") from None
    if not isinstance(data, dict):
        raise ValueError(f"stereo calibration {path}: expected a mapping of fields")
    try:
        return calibration_from_dict(data)
    except ValueError as exc:
        if str(path) in str(exc):
            raise
        raise CalibrationFileError(f"stereo calibration {path}: {exc}") from None


def calibration_text(calib: StereoCalibration) -> str:
    """A calibration as plain YAML (re-readable by ``load_calibration``): the file's content,
    for a caller that writes it crash-safely (``mapping.fileio.write_text_atomic``)."""
    return yaml.safe_dump(calib.to_dict(), sort_keys=False)


def save_calibration(calib: StereoCalibration, path: str | Path) -> None:
    """Write ``calibration_text(calib)`` to ``path`` in place (scratch and test files).  Not
    crash-safe: drivers may not import ``mapping.fileio``, so callers keeping a file that
    matters write ``calibration_text`` with ``write_text_atomic`` themselves."""
    Path(path).write_text(calibration_text(calib))


def as_calibration(calib) -> StereoCalibration:
    """Accept a StereoCalibration, a dict of YAML fields, or a path to a calibration file."""
    if isinstance(calib, StereoCalibration):
        return calib
    if isinstance(calib, dict):
        return calibration_from_dict(calib)
    if isinstance(calib, (str, Path)):
        return load_calibration(calib)
    raise TypeError(f"stereo calibration: cannot use {type(calib).__name__}")
