"""Recorded stereo sequences: the folder layout, its writer, and the replay grabber.

Layout of a recording folder (what ``cgamap stereo --out DIR`` writes; ``left/`` and
``right/`` with one calibration file is all a replay needs)::

    calibration.yaml        # stereo_calib format (rectified fields, or raw K1..T + size)
    frames.jsonl            # optional: one JSON object per frame (seq, stamp_ns, pose, pan, tilt)
    left/000000.png         # left image (rectified when the calibration is rectified)
    right/000000.png
    disparity/000000.png    # optional: 16-bit, disparity x 256, 0 = none
    depth/000000.npy        # optional: float32 metres (depth backends; ground truth)
    points/000000.npy       # optional: (n, 3) float32 points, left optical frame (or global)

Replay pushes every pair through the same rectify + SGBM path as the live cameras.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .messages import PanTiltState
from .stereo import StereoFrame, StereoGrabber, frame_points, frame_points_global, sgbm_frame
from .stereo_calib import (
    StereoCalibration,
    calibration_text,
    load_calibration,
    rectified_calibration,
)
from .stereo_points import CameraMount
from .stereo_sgbm import SgbmParams, make_matcher

DISPARITY_SCALE = 256.0  # 16-bit PNG disparity: value / 256 pixels (KITTI convention)
IMAGE_EXT = (".png", ".pgm", ".ppm", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def encode_disparity(disp: np.ndarray) -> np.ndarray:
    """Disparity (pixels, NaN = none) as uint16 (x256, 0 = none)."""
    d = np.nan_to_num(np.asarray(disp, dtype=np.float64), nan=0.0)
    return np.clip(np.round(d * DISPARITY_SCALE), 0, 65535).astype(np.uint16)


def decode_disparity(raw: np.ndarray) -> np.ndarray:
    d = raw.astype(np.float32) / DISPARITY_SCALE
    d[raw == 0] = np.nan
    return d


#: How a recording's files reach the disk: ``write_file(path, data)``.
WriteFile = Callable[[Path, bytes], object]


def png_bytes(img: np.ndarray) -> bytes:
    """``img`` as a PNG file's bytes (8- or 16-bit, grey or BGR)."""
    import cv2

    try:
        ok, buf = cv2.imencode(".png", img)
    except cv2.error:   # e.g. a channel count PNG has not: a bad frame, not an OpenCV fault
        ok = False
    if not ok:
        raise ValueError(f"stereo recording: OpenCV cannot encode a {img.dtype} image of shape "
                         f"{img.shape} as PNG")
    return buf.tobytes()


def npy_bytes(arr: np.ndarray) -> bytes:
    """``arr`` as a ``.npy`` file's bytes (``np.load`` reads them back)."""
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


class SequenceWriter:
    """Writes frames into a recording folder (the layout above).

    Every file of a frame is encoded in memory first and then handed whole to ``write_file``.
    Drivers may not import ``mapping``, so the crash-safe writer is passed in from above:
    ``cgamap stereo`` gives ``mapping.fileio.write_bytes_atomic`` (temp file, fsync, rename),
    so a frame cut short by a full disk or a kill is never left under its final name.  The
    default, ``Path.write_bytes``, writes in place (tests, scratch folders).  ``frames.jsonl``
    gets a frame's line only after all of the frame's files are written."""

    def __init__(self, out: str | Path, save_points: bool = True, stride: int = 1,
                 max_depth: float = np.inf, global_frame: bool = False,
                 mount: CameraMount | None = None, write_file: WriteFile = Path.write_bytes):
        self.out = Path(out)
        self.global_frame = global_frame
        self.mount = mount
        self.save_points = save_points
        self.stride = stride
        self.max_depth = max_depth
        self.write_file = write_file
        self._calib_written = False
        self.count = 0

    def encode(self, frame: StereoFrame) -> tuple[dict, dict[str, bytes]]:
        """A frame's index record and its files (path relative to the folder -> bytes)."""
        name = f"{frame.seq:06d}"
        rec: dict = {"seq": frame.seq, "stamp_ns": frame.stamp_ns}
        files: dict[str, bytes] = {}

        def put(sub: str, ext: str, data: bytes) -> None:
            rec[sub] = f"{sub}/{name}{ext}"
            files[rec[sub]] = data

        put("left", ".png", png_bytes(frame.left))
        if frame.right is not None:
            put("right", ".png", png_bytes(frame.right))
        if frame.disparity is not None:
            put("disparity", ".png", png_bytes(encode_disparity(frame.disparity)))
        depth = frame.depth if frame.depth is not None else frame.ground_truth
        if depth is not None:
            put("depth", ".npy", npy_bytes(np.asarray(depth, dtype=np.float32)))
        if self.save_points:
            if self.global_frame:
                pts = frame_points_global(frame, self.mount, max_depth=self.max_depth,
                                          stride=self.stride)
            else:
                pts = frame_points(frame, max_depth=self.max_depth, stride=self.stride)
            put("points", ".npy", npy_bytes(pts.astype(np.float32)))
            rec["n_points"] = int(len(pts))
            rec["points_frame"] = "global" if self.global_frame else "camera"
        if frame.pose_ref is not None:
            rec["pose"] = [float(v) for v in frame.pose_ref]
        if frame.pantilt is not None:
            rec["pan"], rec["tilt"] = float(frame.pantilt.pan), float(frame.pantilt.tilt)
            rec["pantilt_stamp_ns"] = frame.pantilt.stamp_ns
        return rec, files

    def write(self, frame: StereoFrame) -> dict:
        """Write one frame; returns its index record (also appended to frames.jsonl)."""
        rec, files = self.encode(frame)
        self.out.mkdir(parents=True, exist_ok=True)
        if not self._calib_written:
            c = frame.calib  # images are stored rectified: store the rectified calibration
            rect = rectified_calibration(c.fx, c.cx, c.cy, c.baseline, fy=c.fy, size=c.size,
                                         doffs=c.doffs, R_rect=c.R_rect)
            self.write_file(self.out / "calibration.yaml", calibration_text(rect).encode())
            self._calib_written = True
        for rel, data in files.items():
            (self.out / rel).parent.mkdir(exist_ok=True)
            self.write_file(self.out / rel, data)
        with open(self.out / "frames.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")
        self.count += 1
        return rec


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT)


class ReplayGrabber(StereoGrabber):
    """Replays a recording folder through the rectify + SGBM path (``use_recorded=True``
    loads stored disparity/depth instead of matching again)."""

    model = "replay"

    def __init__(self, folder: str | Path, calibration: str | Path | None = None,
                 sgbm: SgbmParams | dict | None = None, loop: bool = False,
                 use_recorded: bool = False, **_ignored):
        self.folder = Path(folder)
        self.calibration_path = Path(calibration) if calibration else None
        self.params = sgbm if isinstance(sgbm, SgbmParams) else SgbmParams.from_dict(sgbm)
        self.loop = loop
        self.use_recorded = use_recorded
        self.records: list[dict] = []
        self.calib: StereoCalibration | None = None
        self.index = 0
        self._matcher = None

    def open(self) -> None:
        if not self.folder.is_dir():
            raise FileNotFoundError(f"stereo replay: no such folder {self.folder}")
        cpath = self.calibration_path or self.folder / "calibration.yaml"
        if not cpath.exists():
            raise FileNotFoundError(f"stereo replay: calibration file {cpath} not found")
        self.calib = load_calibration(cpath)
        index = self.folder / "frames.jsonl"
        if index.exists():
            self.records = [json.loads(line) for line in index.read_text().splitlines()
                            if line.strip()]
        else:
            lefts = _list_images(self.folder / "left") if (self.folder / "left").is_dir() \
                else []
            rights = _list_images(self.folder / "right") if (self.folder / "right").is_dir() \
                else []
            if len(lefts) != len(rights):
                raise ValueError(f"stereo replay: {len(lefts)} left but {len(rights)} right "
                                 f"images in {self.folder}")
            self.records = [{"seq": i, "left": str(a.relative_to(self.folder)),
                             "right": str(b.relative_to(self.folder))}
                            for i, (a, b) in enumerate(zip(lefts, rights, strict=True))]
        if not self.records:
            raise ValueError(f"stereo replay: no image pairs in {self.folder}")
        self.index = 0

    def __len__(self) -> int:
        return len(self.records)

    def grab(self, timeout: float = 5.0) -> StereoFrame:
        import cv2

        if self.calib is None:
            self.open()
        if self.index >= len(self.records):
            if not self.loop:
                raise StopIteration
            self.index = 0
        rec = self.records[self.index]
        self.index += 1
        left = cv2.imread(str(self.folder / rec["left"]), cv2.IMREAD_UNCHANGED)
        right = cv2.imread(str(self.folder / rec["right"]), cv2.IMREAD_UNCHANGED) \
            if "right" in rec else None
        if left is None or (right is None and "right" in rec):
            raise ValueError(f"stereo replay: cannot read images of frame {rec.get('seq')}")
        stamp = int(rec.get("stamp_ns", time.monotonic_ns()))
        seq = int(rec.get("seq", self.index - 1))
        extra: dict = {}
        if "pose" in rec:
            extra["pose_ref"] = tuple(rec["pose"])
        if "pan" in rec:
            extra["pantilt"] = PanTiltState(seq=seq, stamp_ns=int(rec.get("pantilt_stamp_ns",
                                                                          stamp)),
                                            pan=rec["pan"], tilt=rec["tilt"])
        if "depth" in rec and (self.folder / rec["depth"]).exists():
            depth = np.load(self.folder / rec["depth"])
            if right is None or self.use_recorded:
                extra["depth"] = depth
            else:
                extra["ground_truth"] = depth
        if self.use_recorded or right is None:
            disp = None
            if "disparity" in rec:
                disp = decode_disparity(cv2.imread(str(self.folder / rec["disparity"]),
                                                   cv2.IMREAD_UNCHANGED))
            if disp is None and "depth" not in extra:
                raise ValueError(f"stereo replay: frame {seq} has no right image and no "
                                 "recorded disparity or depth")
            return StereoFrame(seq=seq, stamp_ns=stamp, calib=self.calib, left=left,
                               right=right, disparity=disp, **extra)
        if self._matcher is None:
            self._matcher = make_matcher(self.params)
        return sgbm_frame(seq, stamp, left, right, self.calib, self.params,
                          matcher=self._matcher, **extra)
