"""Pictures of a line map: PNG of segments + trajectory (OpenCV), and an occupancy image
(PGM + YAML) in the ROS map_server convention."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from .fileio import write_bytes_atomic, write_text_atomic
from .linemap import LineMap

log = logging.getLogger(__name__)
MAX_SIDE_PX = 10000  # 300 MB for an RGB image at the cap; beyond it the resolution coarsens


def write_image_atomic(path: str | Path, img: np.ndarray, kind: str = "image") -> None:
    """Encode ``img`` by the file name's extension (``cv2.imencode``) and write it atomically
    (``fileio.write_bytes_atomic``): a failed or interrupted export leaves the previous picture
    whole.  Raises OSError naming the file when OpenCV cannot encode it."""
    ok, buf = cv2.imencode(Path(path).suffix, img)
    if not ok:
        raise OSError(f"{path}: could not write {kind}")
    write_bytes_atomic(path, buf.tobytes())


def _frame(points: np.ndarray, resolution: float, border: float):
    """Lower-left corner, size (px) and resolution (m/px) of the picture of ``points``.

    An extent that would need more than MAX_SIDE_PX pixels a side (a far-off trajectory point,
    say) is drawn at a coarser resolution, with a warning, rather than overflowing int or
    allocating terabytes."""
    if not (np.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number of metres, not {resolution}")
    if not np.all(np.isfinite(points)):
        raise ValueError("map or trajectory holds non-finite coordinates; cannot draw them")
    with np.errstate(over="ignore"):
        lo = points.min(0) - border
        hi = points.max(0) + border
        span = hi - lo
    if not np.all(np.isfinite(span)):
        raise ValueError("map or trajectory spans more than a float can hold; cannot draw it")
    need = float(np.max(span)) / resolution
    if need > MAX_SIDE_PX - 1:
        coarse = float(np.max(span)) / (MAX_SIDE_PX - 1)
        log.warning("map extent %.4g x %.4g m needs %.3g px a side at %g m/px; drawn at "
                    "%.4g m/px instead", *span, need, resolution, coarse)
        resolution = coarse
    size = np.minimum(np.ceil(span / resolution), MAX_SIDE_PX - 1).astype(int) + 1
    return lo, size, resolution


def _pix(p: np.ndarray, lo: np.ndarray, size: np.ndarray, resolution: float) -> np.ndarray:
    q = (p - lo) / resolution
    return np.column_stack([q[:, 0], size[1] - 1 - q[:, 1]]).round().astype(np.int32)


def render_png(lmap: LineMap, path: str | Path, trajectory: np.ndarray | None = None,
               reference: np.ndarray | None = None, resolution: float = 0.03,
               border: float = 1.0) -> None:
    """Map segments in black over white, the trajectory in blue (reference in light grey)."""
    pts = [lmap.a, lmap.b]
    for t in (trajectory, reference):
        if t is not None and len(t):
            pts.append(np.asarray(t)[:, :2])
    allp = np.concatenate(pts) if sum(len(p) for p in pts) else np.zeros((1, 2))
    lo, size, resolution = _frame(allp, resolution, border)
    img = np.full((size[1], size[0], 3), 255, np.uint8)
    if reference is not None and len(reference):
        cv2.polylines(img, [_pix(np.asarray(reference)[:, :2], lo, size, resolution)], False,
                      (200, 200, 200), 1, cv2.LINE_AA)
    if trajectory is not None and len(trajectory):
        cv2.polylines(img, [_pix(np.asarray(trajectory)[:, :2], lo, size, resolution)], False,
                      (220, 120, 0), 1, cv2.LINE_AA)
    if len(lmap):
        pa = _pix(lmap.a, lo, size, resolution)
        pb = _pix(lmap.b, lo, size, resolution)
        for p, q in zip(pa, pb, strict=True):  # one draw call per segment (segments, not points)
            cv2.line(img, tuple(int(v) for v in p), tuple(int(v) for v in q), (0, 0, 0), 2,
                     cv2.LINE_AA)
    write_image_atomic(path, img, "PNG")


def export_occupancy(lmap: LineMap, stem: str | Path, resolution: float = 0.05,
                     border: float = 1.0) -> tuple[Path, Path]:
    """Occupancy image ``stem.pgm`` and ``stem.yaml`` in the ROS map_server convention
    (negate 0: 0 = occupied, 254 = free, 205 = unknown; origin = world pose of the lower-left
    pixel).  A line map knows its walls, not the free space between them: walls are drawn
    occupied on an unknown background.  Returns both paths."""
    stem = Path(stem)
    allp = np.concatenate([lmap.a, lmap.b]) if len(lmap) else np.zeros((1, 2))
    lo, size, resolution = _frame(allp, resolution, border)
    img = np.full((size[1], size[0]), 205, np.uint8)
    if len(lmap):
        pa = _pix(lmap.a, lo, size, resolution)
        pb = _pix(lmap.b, lo, size, resolution)
        for p, q in zip(pa, pb, strict=True):
            cv2.line(img, tuple(int(v) for v in p), tuple(int(v) for v in q), 0, 1)
    pgm = stem.with_suffix(".pgm")
    yml = stem.with_suffix(".yaml")
    # each file atomic; the YAML last, so a map_server never reads a YAML naming a
    # half-written image
    write_image_atomic(pgm, img, "PGM")
    write_text_atomic(yml, f"image: {pgm.name}\nmode: trinary\nresolution: {resolution}\n"
                           f"origin: [{lo[0]:.4f}, {lo[1]:.4f}, 0.0]\nnegate: 0\n"
                           "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    return pgm, yml
