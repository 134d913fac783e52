"""``cgamap calib collect``: drive the pan-tilt through poses that excite both joints, grab a
frame at each, find the target, solve its pose and record the pose pairs.

Each pose: move the joints, read back the measured angles, grab, detect the target, skip
blurred frames (variance of the Laplacian over the target below ``--min-sharpness``) and poor
fits (RMS reprojection above ``--max-reproj``), then record base_T_head (the head's forward
kinematics at the measured angles) with cam_T_target (solvePnP).  ``--sim`` runs on the
simulated rig of ``calib/sim.py`` with its joints on the Dynamixel twin, driven through the
pan-tilt driver (``--sim-joints direct`` skips the bus); the hardware path opens the pan-tilt
driver and the camera grabber by URL.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from cgamap.mapping.fileio import write_text_atomic

from .pairs import PairSet, save_pairs
from .sim import SimRig, default_rig, pan_tilt_head_pose
from .targets import make_target, solve_pnp

DXL_TICK = 2 * math.pi / 4096  # Dynamixel X-series position resolution


class CollectError(Exception):
    """Bad arguments or an unusable device for ``calib collect``; one line for the user."""

    exit_code = 2


class TooFewPosesError(CollectError):
    """The run saw fewer than 3 usable poses: nothing is written (exit 1, not a usage error)."""

    exit_code = 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_argument_group("source")
    src.add_argument("--sim", action="store_true", help="use the simulated rig (no hardware)")
    src.add_argument("--seed", type=int, default=0, help="--sim: hidden mount and noise seed")
    src.add_argument("--truth", metavar="FILE", help="--sim: also write the hidden true mount")
    src.add_argument("--sim-joints", choices=("twin", "direct"), default="twin",
                     help="--sim: drive the Dynamixel twin through the pan-tilt driver (twin, "
                          "default) or set the joint angles directly (direct, faster)")
    src.add_argument("--sim-blur", type=int, nargs="*", default=[], help=argparse.SUPPRESS)
    src.add_argument("--pantilt", metavar="URL",
                     help="pan-tilt device, e.g. serial:///dev/ttyUSB0?baudrate=57600")
    src.add_argument("--camera", metavar="URL",
                     help="camera grabber as MODEL://DEVICE, e.g. depthai://, opencv://0,1")
    src.add_argument("--intrinsics", metavar="FILE",
                     help="camera calibration (stereo calibration YAML); default: the frame's")
    src.add_argument("--axis-point", type=float, nargs=3, default=[0.10, 0.0, 0.90],
                     metavar=("X", "Y", "Z"), help="pan-tilt axes point in the base frame (m)")
    src.add_argument("--settle", type=float, default=0.5, help="seconds to wait after a move")
    tg = p.add_argument_group("target")
    tg.add_argument("--target", default="chessboard", choices=("chessboard", "charuco"))
    tg.add_argument("--cols", type=int, default=9, help="inner corners along a row")
    tg.add_argument("--rows", type=int, default=6, help="inner corners along a column")
    tg.add_argument("--square", type=float, default=0.03, help="square size (m)")
    tg.add_argument("--marker", type=float, help="ChArUco marker size (m), default 0.75 square")
    tg.add_argument("--dictionary", default="DICT_4X4_50", help="ChArUco ArUco dictionary")
    ps = p.add_argument_group("poses and quality")
    ps.add_argument("--poses", type=int, default=20, help="number of poses to visit")
    ps.add_argument("--pan-range", type=float, default=12.0, help="pan within +- this (deg)")
    ps.add_argument("--tilt-range", type=float, default=10.0, help="tilt within +- this (deg)")
    ps.add_argument("--max-reproj", type=float, default=1.0, help="max RMS reprojection (px)")
    ps.add_argument("--min-sharpness", type=float, default=100.0,
                    help="min variance of the Laplacian over the target (blur check)")
    ps.add_argument("--out", default="pairs.json", metavar="FILE",
                    help="pairs file to write (.json, else YAML)")
    ps.add_argument("--json", action="store_true", help="print a JSON summary")


def pose_set(n: int, pan_max: float, tilt_max: float) -> np.ndarray:
    """(n, 2) joint angles (rad) covering [-pan_max, pan_max] x [-tilt_max, tilt_max]: the
    four corners first (both joints excited at once), then a golden-ratio lattice."""
    corners = np.array([[-1, -1], [1, 1], [1, -1], [-1, 1]], float)
    k = np.arange(max(n - 4, 0))
    lattice = np.stack([np.mod(k * 0.6180339887498949 + 0.5, 1.0) * 2 - 1,
                        (k + 0.5) / max(len(k), 1) * 2 - 1], -1)
    u = np.concatenate([corners, lattice])[:n]
    return u * np.array([pan_max, tilt_max])


# ---- joint and camera sources ---------------------------------------------------------------

class DirectJoints:
    """Joint angles without a bus: goals land on the Dynamixel position grid."""

    def move(self, pan: float, tilt: float) -> tuple[float, float]:
        return round(pan / DXL_TICK) * DXL_TICK, round(tilt / DXL_TICK) * DXL_TICK

    def close(self) -> None:
        pass


class HeadJoints:
    """The pan-tilt driver (``cgamap.drivers.pantilt``): move, wait until the servos report
    the goal and stand still, return the measured angles.  With ``twin=True`` a Dynamixel bus
    twin is started on a pty first, so --sim drives the same byte path as the robot."""

    def __init__(self, url: str | None, settle: float, twin: bool = False):
        try:
            from cgamap.drivers.pantilt import PanTilt, PanTiltConfig, PanTiltError
        except ImportError:
            raise CollectError("the pan-tilt driver (cgamap.drivers.pantilt) is not available "
                               "in this build") from None
        self._error = PanTiltError
        self.settle = settle
        self.twin = None
        if twin:
            from cgamap.drivers.sim.dynamixel import DynamixelBusTwin

            self.twin = DynamixelBusTwin()
            url = self.twin.start()
        try:
            # profile velocity 0: the servos' own velocity limit (fast, fine for calibration)
            self.head = PanTilt(PanTiltConfig(url=url, profile_velocity=0.0)).open()
            if not self.head.torque(True):
                raise PanTiltError(f"{url}: torque could not be enabled")
        except (PanTiltError, OSError, ValueError) as exc:
            self.close()
            raise CollectError(f"--pantilt: {exc}") from None

    def move(self, pan: float, tilt: float) -> tuple[float, float]:
        try:
            self.head.move(pan, tilt)
        except self._error as exc:
            raise CollectError(f"pan-tilt: {exc}") from None
        st = self.head.wait_until_reached(pan, tilt, tol=0.01, timeout=10.0)
        if st is None:
            raise CollectError(f"pan-tilt: goal ({pan:.3f}, {tilt:.3f}) rad not reached in 10 s")
        # The moving flag drops within the servo's moving threshold: read until two reads agree.
        prev = (st.pan, st.tilt)
        for _ in range(50):
            time.sleep(0.02)
            st = self.head.read_state() or st
            if (st.pan, st.tilt) == prev:
                break
            prev = (st.pan, st.tilt)
        if self.settle > 0 and self.twin is None:
            time.sleep(self.settle)  # let the head stop swinging before the exposure
            st = self.head.read_state() or st
        return float(st.pan), float(st.tilt)

    def close(self) -> None:
        head = getattr(self, "head", None)
        if head is not None:
            head.close()
        if self.twin is not None:
            self.twin.stop()
            self.twin = None


class SimSource:
    """The simulated rig: the camera renders the target from the hidden true mount at the
    angles the joints report."""

    def __init__(self, rig: SimRig, seed: int, joints):
        self.rig = rig
        self.joints = joints
        self.rng = np.random.default_rng(seed + 1)
        self.pose = (0.0, 0.0)
        self.index = 0

    def intrinsics(self) -> tuple[np.ndarray, np.ndarray]:
        return self.rig.K, np.zeros(5)

    def move(self, pan: float, tilt: float) -> tuple[float, float]:
        self.pose = self.joints.move(pan, tilt)
        return self.pose

    def grab(self) -> np.ndarray:
        img = self.rig.render(*self.pose, self.rng, index=self.index)
        self.index += 1
        return img

    def close(self) -> None:
        self.joints.close()


class HardwareSource:
    """Pan-tilt driver + camera grabber, opened by URL (both imported lazily, so a build or a
    machine without them fails here with one clear line)."""

    def __init__(self, pantilt_url: str, camera_url: str, intrinsics: str | None,
                 settle: float):
        from cgamap.drivers.stereo import load_calibration, open_grabber

        model, sep, device = camera_url.partition("://")
        if not sep:
            raise CollectError(f"--camera {camera_url!r}: expected MODEL://DEVICE "
                               "(depthai://, opencv://0,1, synthetic://corridor)")
        try:
            self._calib = load_calibration(intrinsics) if intrinsics else None
        except (OSError, ValueError, KeyError) as exc:
            raise CollectError(f"--intrinsics {intrinsics}: {exc}") from None
        config = {"calibration": intrinsics} if intrinsics else {}
        self.joints = HeadJoints(pantilt_url, settle)
        try:
            if model == "synthetic":    # the simulator's camera: no driver imports drivers.sim
                from cgamap.drivers.sim.stereo_render import open_synthetic

                self.camera = open_synthetic(device, **config)
            else:
                self.camera = open_grabber(model, device, config)
            self.camera.open()
        except (ValueError, OSError, RuntimeError, ImportError) as exc:
            self.joints.close()
            raise CollectError(f"--camera {camera_url!r}: {exc}") from None

    def intrinsics(self) -> tuple[np.ndarray, np.ndarray] | None:
        return (self._calib.K, np.zeros(5)) if self._calib is not None else None

    def move(self, pan: float, tilt: float) -> tuple[float, float]:
        return self.joints.move(pan, tilt)

    def grab(self) -> np.ndarray:
        import cv2

        frame = self.camera.grab(timeout=5.0)
        if self._calib is None:
            self._calib = frame.calib  # the rectified left camera's intrinsics
        img = frame.left
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img

    def close(self) -> None:
        self.camera.close()
        self.joints.close()


# ---- the loop -----------------------------------------------------------------------------

@dataclass
class CollectReport:
    pairs: PairSet
    visited: int = 0
    skipped: list = field(default_factory=list)  # (index, reason)


def collect(source, target, joints: np.ndarray, axis_point, max_reproj: float,
            min_sharpness: float, log=None) -> CollectReport:
    """Visit ``joints`` (n, 2), keep the frames that pass the checks, return the pairs."""
    H, C, pans, tilts, skipped = [], [], [], [], []
    K_dist = source.intrinsics()
    for k, (pan_cmd, tilt_cmd) in enumerate(joints):
        pan, tilt = source.move(float(pan_cmd), float(tilt_cmd))
        img = source.grab()
        if K_dist is None:
            K_dist = source.intrinsics()
        det = target.detect(img)
        reason = None
        if det is None:
            reason = "target not found"
        elif det.sharpness < min_sharpness:
            reason = f"blurred (sharpness {det.sharpness:.0f} < {min_sharpness:.0f})"
        else:
            cam_T_target, rms = solve_pnp(det, *K_dist)
            if rms > max_reproj:
                reason = f"reprojection {rms:.2f} px > {max_reproj:.2f}"
        if reason:
            skipped.append((k, reason))
            if log:
                log(f"pose {k:3d} pan {math.degrees(pan):+6.2f} tilt {math.degrees(tilt):+6.2f}"
                    f" deg: skipped, {reason}")
            continue
        H.append(pan_tilt_head_pose(pan, tilt, axis_point))
        C.append(cam_T_target)
        pans.append(pan)
        tilts.append(tilt)
        if log:
            log(f"pose {k:3d} pan {math.degrees(pan):+6.2f} tilt {math.degrees(tilt):+6.2f} deg:"
                f" {len(det.image_points)} points, reprojection {rms:.3f} px")
    meta = {"target": {"kind": target.kind, "cols": target.cols, "rows": target.rows,
                       "square": target.square},
            "axis_point": [float(v) for v in axis_point]}
    if K_dist is not None:
        meta["intrinsics"] = {"K": np.asarray(K_dist[0]).tolist()}
    pairs = PairSet(np.array(H).reshape(-1, 4, 4), np.array(C).reshape(-1, 4, 4),
                    np.array(pans), np.array(tilts), meta)
    return CollectReport(pairs, len(joints), skipped)


def run_collect(args: argparse.Namespace) -> int:
    if args.poses < 3:
        raise CollectError(f"--poses {args.poses}: need at least 3")
    try:
        target = make_target(args.target, args.cols, args.rows, args.square, args.marker,
                             args.dictionary)
    except ValueError as exc:
        raise CollectError(str(exc)) from None
    if args.sim:
        if args.pantilt or args.camera:
            raise CollectError("--sim excludes --pantilt/--camera")
        rig = default_rig(args.seed, board=target)
        rig.motion_blur = set(args.sim_blur)
        joints = (DirectJoints() if args.sim_joints == "direct"
                  else HeadJoints(None, args.settle, twin=True))
        source = SimSource(rig, args.seed, joints)
        axis_point = rig.axis_point
    elif args.pantilt and args.camera:
        source = HardwareSource(args.pantilt, args.camera, args.intrinsics, args.settle)
        axis_point = np.asarray(args.axis_point, float)
    else:
        raise CollectError("give --sim, or both --pantilt URL and --camera URL")
    joints = pose_set(args.poses, math.radians(args.pan_range), math.radians(args.tilt_range))
    log = None if args.json else (lambda s: print(s, flush=True))
    try:
        report = collect(source, target, joints, axis_point, args.max_reproj,
                         args.min_sharpness, log)
    finally:
        source.close()
    report.pairs.meta["source"] = "sim" if args.sim else f"{args.pantilt} {args.camera}"
    report.pairs.meta["skipped"] = [{"pose": k, "reason": r} for k, r in report.skipped]
    n = len(report.pairs)
    if n < 3:   # hand-eye needs 3 poses: an empty file would only replace a useful one
        reasons = Counter(r for _, r in report.skipped)
        why = ", ".join(f"{c} x {r}" for r, c in reasons.most_common(3)) or "none skipped"
        raise TooFewPosesError(f"only {n} usable poses of {report.visited} (need 3; {why}); "
                               f"check the target and the lighting; {args.out} not written")
    try:
        save_pairs(args.out, report.pairs)
        if args.sim and args.truth:
            write_text_atomic(args.truth, json.dumps(
                {"head_T_cam": rig.head_T_cam.tolist(),
                 "axis_point": rig.axis_point.tolist(),
                 "base_T_target": rig.base_T_target.tolist()}, indent=1) + "\n")
    except OSError as exc:
        raise CollectError(f"cannot write: {exc}") from None
    summary = {"out": args.out, "pairs": n, "visited": report.visited,
               "skipped": report.pairs.meta["skipped"]}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"recorded {n} of {report.visited} poses to {args.out}"
              f" ({len(report.skipped)} skipped)")
    return 0
