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

Crash safety: a frame's files reach the disk (data and names fsynced) before its
``frames.jsonl`` line, and each line is one ``write`` followed by ``fsync``, so a crash or
power cut can leave at most the last line torn (cut short, no newline).  Replay drops such
a tail (counted in ``torn_tail``, one warning); a damaged line anywhere else is an error
naming its line number.
"""

from __future__ import annotations

import io
import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .fileio import fsync_dir, mkdir_synced, write_bytes_synced
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

log = logging.getLogger(__name__)

INDEX_NAME = "frames.jsonl"
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


class RecordingIndexError(ValueError):
    """A line of a recording's ``frames.jsonl`` other than a torn last one is damaged."""

    def __init__(self, path: Path, lineno: int, problem: str):
        super().__init__(f"{path.name} is damaged (line {lineno}: {problem})")
        self.path, self.lineno, self.problem = path, lineno, problem


#: the index fields that name a file of the frame (relative to the recording's folder)
FILE_FIELDS = ("left", "right", "disparity", "depth", "points")


def _parse_record(raw: bytes, lineno: int, path: Path) -> dict:
    """One index line as a record; :class:`RecordingIndexError` when it is not one."""
    try:
        rec = json.loads(raw)
    except UnicodeDecodeError:
        raise RecordingIndexError(path, lineno, "not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise RecordingIndexError(path, lineno, f"{exc.msg} (column {exc.colno})") from None
    if not isinstance(rec, dict):
        raise RecordingIndexError(path, lineno, f"a JSON {type(rec).__name__}, not an object")
    if not isinstance(rec.get("left"), str):
        raise RecordingIndexError(path, lineno, 'no "left" image path')
    for key in FILE_FIELDS:
        if key in rec and not isinstance(rec[key], str):
            raise RecordingIndexError(path, lineno, f'"{key}" is not a file path')
    # the fields replay reads, checked here so a bad one is named with its line, not a
    # KeyError or TypeError in the middle of a replay
    for key in ("seq", "stamp_ns", "pantilt_stamp_ns"):
        if key in rec and not _is_int(rec[key]):
            raise RecordingIndexError(path, lineno, f'"{key}" is not a whole number')
    if "pose" in rec and not (isinstance(rec["pose"], list) and len(rec["pose"]) == 3
                              and all(_is_number(v) for v in rec["pose"])):
        raise RecordingIndexError(path, lineno, '"pose" is not [x, y, theta]')
    if ("pan" in rec) != ("tilt" in rec) or not all(_is_number(rec[k]) for k in ("pan", "tilt")
                                                    if k in rec):
        raise RecordingIndexError(path, lineno, '"pan" and "tilt" must be numbers, both or '
                                  'neither')
    return rec


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _is_json(raw: bytes) -> bool:
    try:
        json.loads(raw)
    except ValueError:   # JSONDecodeError, UnicodeDecodeError
        return False
    return True


def read_index(path: str | Path) -> tuple[list[dict], int]:
    """The records of a ``frames.jsonl`` and how many torn lines were dropped (0 or 1).

    A last line with no newline that is not valid JSON is a write cut short by a crash: it
    is dropped (and a warning logged).  Any other damaged line raises
    :class:`RecordingIndexError` with its 1-based line number; blank lines are skipped."""
    path = Path(path)
    lines = path.read_bytes().split(b"\n")
    tail = lines.pop()          # b"" when the file ends with a newline, as a whole one does
    records = [_parse_record(raw, i, path) for i, raw in enumerate(lines, 1) if raw.strip()]
    if not tail.strip():
        return records, 0
    if _is_json(tail):          # whole but for its newline: a record (or damage) like any other
        records.append(_parse_record(tail, len(lines) + 1, path))
        return records, 0
    log.warning("%s: last line (%d) is torn, %d bytes cut short by a crash: dropped it, "
                "%d whole frames remain", path, len(lines) + 1, len(tail), len(records))
    return records, 1


def repair_index_tail(path: str | Path) -> int:
    """Make an existing ``frames.jsonl`` end on a whole line before more are appended: a torn
    last line (no newline, not JSON) is truncated away, a whole one missing only its newline
    gets it.  Returns the number of lines dropped (0 or 1)."""
    path = Path(path)
    with open(path, "rb+") as f:
        data = f.read()
        if not data or data.endswith(b"\n"):
            return 0
        cut = data.rfind(b"\n") + 1            # 0: the only line is the torn one
        if data[cut:].strip() and _is_json(data[cut:]):
            f.write(b"\n")
            dropped = 0
        else:
            f.truncate(cut)
            dropped = 1 if data[cut:].strip() else 0
            if dropped:
                log.warning("%s: truncated a torn last line (%d bytes) before appending",
                            path, len(data) - cut)
        f.flush()
        os.fsync(f.fileno())
    return dropped


def append_line(path: Path, line: bytes) -> None:
    """Append one whole line: a single ``write``, then ``fsync``.  If the write fails or
    comes up short (full disk), the file is cut back to where it was, so the index never
    keeps a partial line it could help; a power cut mid-write leaves at most a torn tail,
    which :func:`read_index` drops."""
    created = not path.exists()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        start = os.fstat(fd).st_size
        try:
            n = os.write(fd, line)
            if n != len(line):
                raise OSError(28, f"No space left on device (wrote {n} of {len(line)} bytes)",
                              str(path))
            os.fsync(fd)
        except BaseException:
            try:
                os.ftruncate(fd, start)
            except OSError:
                pass
            raise
    finally:
        os.close(fd)
    if created:  # the new file's directory entry must survive a power cut too
        fsync_dir(path.parent)


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

    Every file of a frame is encoded in memory first and then handed whole to ``write_file``,
    which must return only once the file is on the disk.  Drivers may not import ``mapping``,
    so the atomic writer is passed in from above: ``cgamap stereo`` gives
    ``mapping.fileio.write_bytes_atomic`` (temp file, fsync, rename), so a frame cut short by
    a full disk or a kill is never left under its final name.  The default,
    :func:`~.fileio.write_bytes_synced`, writes in place and fsyncs the file and a new file's
    folder (a frame cut short may leave a partial file, but no line names it).  Folders are
    made with their names fsynced (:func:`~.fileio.mkdir_synced`).  ``frames.jsonl`` gets a
    frame's line only after all of the frame's files are written, as one write and an fsync
    (:func:`append_line`), so a line never names a file that is not on the disk.  On a
    folder that already has an index, a torn last line is truncated first
    (:func:`repair_index_tail`), so appended lines never glue onto it."""

    def __init__(self, out: str | Path, save_points: bool = True, stride: int = 1,
                 max_depth: float = np.inf, global_frame: bool = False,
                 mount: CameraMount | None = None,
                 write_file: WriteFile = write_bytes_synced):
        self.out = Path(out)
        self.global_frame = global_frame
        self.mount = mount
        self.save_points = save_points
        self.stride = stride
        self.max_depth = max_depth
        self.write_file = write_file
        self._calib_written = False
        self.count = 0
        self.torn_tail = 0    # torn lines truncated from an existing index
        if (self.out / INDEX_NAME).is_file():
            self.torn_tail = repair_index_tail(self.out / INDEX_NAME)

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
        mkdir_synced(self.out)
        if not self._calib_written:
            c = frame.calib  # images are stored rectified: store the rectified calibration
            rect = rectified_calibration(c.fx, c.cx, c.cy, c.baseline, fy=c.fy, size=c.size,
                                         doffs=c.doffs, R_rect=c.R_rect)
            self.write_file(self.out / "calibration.yaml", calibration_text(rect).encode())
            self._calib_written = True
        for rel, data in files.items():
            mkdir_synced((self.out / rel).parent)
            self.write_file(self.out / rel, data)
        append_line(self.out / INDEX_NAME, (json.dumps(rec) + "\n").encode())
        self.count += 1
        return rec


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT)


class ReplayGrabber(StereoGrabber):
    """Replays a recording folder through the rectify + SGBM path (``use_recorded=True``
    loads stored disparity/depth instead of matching again).

    ``torn_tail`` counts the torn last index line dropped at ``open`` (0 or 1); a frame whose
    files are missing or unreadable raises ``ValueError`` naming the frame and the file."""

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
        self.torn_tail = 0
        self._matcher = None

    def open(self) -> None:
        if not self.folder.is_dir():
            raise FileNotFoundError(f"stereo replay: no such folder {self.folder}")
        cpath = self.calibration_path or self.folder / "calibration.yaml"
        if not cpath.exists():
            raise FileNotFoundError(f"stereo replay: calibration file {cpath} not found")
        self.calib = load_calibration(cpath)
        index = self.folder / INDEX_NAME
        self.torn_tail = 0
        if index.exists():
            self.records, self.torn_tail = read_index(index)
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

    def _file(self, rec: dict, key: str, seq: int) -> Path:
        """The path of a frame's file; ValueError (one line) naming both when it is gone."""
        path = self.folder / rec[key]
        if not path.is_file():
            raise ValueError(f"stereo replay: {self.folder}: frame {seq}: {key} file "
                             f"{rec[key]} is missing")
        return path

    def _image(self, rec: dict, key: str, seq: int) -> np.ndarray:
        import cv2

        img = cv2.imread(str(self._file(rec, key, seq)), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"stereo replay: {self.folder}: frame {seq}: {key} file "
                             f"{rec[key]} is not a readable image")
        return img

    def _array(self, rec: dict, key: str, seq: int) -> np.ndarray:
        path = self._file(rec, key, seq)
        try:
            return np.load(path)
        except (OSError, ValueError, EOFError) as exc:
            raise ValueError(f"stereo replay: {self.folder}: frame {seq}: {key} file "
                             f"{rec[key]} is not a readable .npy array ({exc})") from None

    def grab(self, timeout: float = 5.0) -> StereoFrame:
        if self.calib is None:
            self.open()
        if self.index >= len(self.records):
            if not self.loop:
                raise StopIteration
            self.index = 0
        rec = self.records[self.index]
        self.index += 1
        seq = int(rec.get("seq", self.index - 1))
        left = self._image(rec, "left", seq)
        right = self._image(rec, "right", seq) if "right" in rec else None
        stamp = int(rec.get("stamp_ns", time.monotonic_ns()))
        extra: dict = {}
        if "pose" in rec:
            extra["pose_ref"] = tuple(rec["pose"])
        if "pan" in rec:
            extra["pantilt"] = PanTiltState(seq=seq, stamp_ns=int(rec.get("pantilt_stamp_ns",
                                                                          stamp)),
                                            pan=rec["pan"], tilt=rec["tilt"])
        # depth is optional (ground truth) unless it is all that stands in for the matching
        needs_depth = (right is None or self.use_recorded) and "disparity" not in rec
        if "depth" in rec and (needs_depth or (self.folder / rec["depth"]).exists()):
            depth = self._array(rec, "depth", seq)
            if right is None or self.use_recorded:
                extra["depth"] = depth
            else:
                extra["ground_truth"] = depth
        if self.use_recorded or right is None:
            disp = None
            if "disparity" in rec:
                disp = decode_disparity(self._image(rec, "disparity", seq))
            if disp is None and "depth" not in extra:
                raise ValueError(f"stereo replay: frame {seq} has no right image and no "
                                 "recorded disparity or depth")
            return StereoFrame(seq=seq, stamp_ns=stamp, calib=self.calib, left=left,
                               right=right, disparity=disp, **extra)
        if self._matcher is None:
            self._matcher = make_matcher(self.params)
        return sgbm_frame(seq, stamp, left, right, self.calib, self.params,
                          matcher=self._matcher, **extra)
