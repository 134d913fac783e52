"""Pose-pair files (input of ``calib hand-eye``) and calibration files (its output).

Pairs file, JSON or YAML: ``{"pairs": [{"base_T_head": 4x4, "cam_T_target": 4x4, "pan": rad,
"tilt": rad}, ...]}`` in metres; the joint angles are optional.  ``base_T_head`` is the head
(gripper) pose in the base frame, ``cam_T_target`` the target pose in the camera frame, as
OpenCV's ``calibrateHandEye`` takes them.

Calibration file, YAML, read by the daemon's config (``devices.<pantilt>.hand_eye``):
``head_T_cam`` (4x4 rows) at the top level, beside ``method``, ``t_eye`` / ``R_eye`` /
``q_eye`` (the camera chain's T_eye and fixed rotation, DESIGN.md), residuals, uncertainty.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from cgamap.cga import quaternion_from_matrix
from cgamap.drivers.yaml_errors import yaml_error_text
from cgamap.mapping.fileio import backup_path, write_text_atomic  # noqa: F401 (calib.cli)

from .handeye import mount_motor
from .se3 import rpy_from_matrix


class PairsFileError(ValueError):
    """A pairs file that cannot be used; the message names the file and the place."""


@dataclass
class PairSet:
    base_T_head: np.ndarray  # (n, 4, 4)
    cam_T_target: np.ndarray  # (n, 4, 4)
    pan: np.ndarray | None = None  # (n,) rad, when every pair has it
    tilt: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.base_T_head)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _matrix(value, where: str) -> np.ndarray:
    # Check the nesting before numpy sees it: a YAML alias bomb nests lists deeply and
    # np.asarray would try to build the whole thing.
    rows = value if isinstance(value, list) else None
    flat = rows is not None and len(rows) == 16 and all(_is_number(v) for v in rows)
    nested = (rows is not None and len(rows) == 4
              and all(isinstance(r, list) and len(r) == 4 and all(_is_number(v) for v in r)
                      for r in rows))
    if not (flat or nested):
        shape = (f"{len(rows)} rows" if rows is not None else type(value).__name__)
        raise PairsFileError(f"{where}: expected a 4x4 matrix (4 lists of 4 numbers), "
                             f"got {shape}")
    m = np.asarray(value, dtype=float).reshape(4, 4)
    if not np.all(np.isfinite(m)):
        raise PairsFileError(f"{where}: non-finite value")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise PairsFileError(f"{where}: last row must be [0, 0, 0, 1]")
    R = m[:3, :3]
    if (np.abs(R).max() > 1.0 + 1e-3 or np.abs(R.T @ R - np.eye(3)).max() > 1e-3
            or np.linalg.det(R) < 0):
        raise PairsFileError(f"{where}: upper-left 3x3 is not a rotation matrix")
    if np.abs(m[:3, 3]).max() > 100.0:
        raise PairsFileError(f"{where}: translation over 100 m (millimetres instead of metres?)")
    return m


def _angle(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise PairsFileError(f"{where}: expected a number (radians)")
    return float(value)


def parse_pairs(data, source: str = "pairs") -> PairSet:
    """Validate a loaded pairs document; errors name ``source`` and the offending entry."""
    if not isinstance(data, dict) or "pairs" not in data:
        raise PairsFileError(f"{source}: expected a mapping with a 'pairs' list")
    items = data["pairs"]
    if not isinstance(items, list) or not items:
        raise PairsFileError(f"{source}: 'pairs' must be a non-empty list")
    H, C, pan, tilt = [], [], [], []
    for k, item in enumerate(items):
        where = f"{source}: pairs[{k}]"
        if not isinstance(item, dict):
            raise PairsFileError(f"{where}: expected a mapping")
        for key in ("base_T_head", "cam_T_target"):
            if key not in item:
                raise PairsFileError(f"{where}: missing '{key}'")
        H.append(_matrix(item["base_T_head"], f"{where}.base_T_head"))
        C.append(_matrix(item["cam_T_target"], f"{where}.cam_T_target"))
        pan.append(_angle(item["pan"], f"{where}.pan") if "pan" in item else None)
        tilt.append(_angle(item["tilt"], f"{where}.tilt") if "tilt" in item else None)
    meta = {k: v for k, v in data.items() if k != "pairs"}
    return PairSet(
        np.array(H), np.array(C),
        None if None in pan else np.array(pan, float),
        None if None in tilt else np.array(tilt, float), meta)


def load_pairs(path: str | Path) -> PairSet:
    """Read a JSON or YAML pairs file (by extension; anything else is tried as both)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise PairsFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise PairsFileError(f"{path}: not a text (JSON or YAML) file: undecodable byte at "
                             f"offset {exc.start}") from None
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            data = json.loads(text)
        else:  # YAML is a superset of JSON
            data = yaml.safe_load(text)
    except json.JSONDecodeError as exc:
        raise PairsFileError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno}: "
                             f"{exc.msg}") from None
    except yaml.YAMLError as exc:
        raise PairsFileError(f"{path}: {yaml_error_text(exc, 'invalid YAML')}") from None
    return parse_pairs(data, str(path))


def save_pairs(path: str | Path, pairs: PairSet) -> None:
    """Write a pairs file (JSON for .json, else YAML) atomically; a previous one is kept as
    ``<path>.bak``."""
    items = []
    for k in range(len(pairs)):
        item = {"base_T_head": pairs.base_T_head[k].tolist(),
                "cam_T_target": pairs.cam_T_target[k].tolist()}
        if pairs.pan is not None:
            item["pan"] = float(pairs.pan[k])
        if pairs.tilt is not None:
            item["tilt"] = float(pairs.tilt[k])
        items.append(item)
    doc = {**pairs.meta, "pairs": items}
    path = Path(path)
    text = (json.dumps(doc, indent=1) + "\n" if path.suffix.lower() == ".json"
            else yaml.safe_dump(doc, sort_keys=False))
    # a collection takes minutes on the robot: a re-run must not destroy the last one
    write_text_atomic(path, text, keep_previous=True)


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z), w >= 0, through the CGA core's conversion."""
    q = quaternion_from_matrix(R)
    return -q if q[0] < 0 else q


def calibration_document(result, n_pairs: int, source: str | None = None,
                         axes: dict | None = None) -> dict:
    """The calibration file's content for a ``HandEyeResult``."""
    X = np.asarray(result.head_T_cam)
    R = X[:3, :3]
    doc: dict = {
        "head_T_cam": [[float(v) for v in row] for row in X],
        "method": result.method,
        # Camera chain (DESIGN.md): T_eye moves from the axes point to the camera centre in
        # the tilted head frame; R_eye turns the head frame into the camera's optical frame.
        "t_eye": [float(v) for v in X[:3, 3]],
        "R_eye": [[float(v) for v in row] for row in R],
        "q_eye": [float(v) for v in quaternion_from_rotation(R)],
        "rpy_eye_deg": [float(v) for v in np.degrees(rpy_from_matrix(R))],
        "motor": mount_motor(X),
        "pairs": n_pairs,
    }
    if source:
        doc["source"] = source
    if result.residual_rot_deg is not None:
        doc["residuals"] = {
            "rot_deg": [round(float(v), 6) for v in result.residual_rot_deg],
            "trans_mm": [round(float(v) * 1e3, 4) for v in result.residual_trans_m],
            "inliers": [bool(v) for v in result.inliers],
        }
    if result.std_rot_deg is not None:
        doc["uncertainty"] = {
            "rot_deg_1sigma": [float(v) for v in result.std_rot_deg],
            "trans_mm_1sigma": [float(v) * 1e3 for v in result.std_trans_m],
            "noise_rot_deg": float(result.sigma_rot_deg),
            "noise_trans_mm": float(result.sigma_trans_m) * 1e3,
            "covariance": [[float(v) for v in row] for row in result.covariance],
        }
        if "head_noise_share" in result.info:
            doc["uncertainty"]["head_noise_share"] = float(result.info["head_noise_share"])
    if axes:
        doc["axes"] = axes
        if "axis_point" in axes:
            doc["axis_point"] = axes["axis_point"]
    return doc


def write_calibration(path: str | Path, doc: dict) -> None:
    header = ("# cgamap hand-eye calibration (cgamap calib hand-eye).  head_T_cam maps\n"
              "# left-camera (OpenCV) coordinates into the pan-tilt head frame; metres.\n")
    write_text_atomic(path, header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None),
                      keep_previous=True)
