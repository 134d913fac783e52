"""``cgamap stereo``: grab stereo frames from a camera, the simulated world or a recording and
write them to a folder (left/right PNG, 16-bit disparity PNG, depth .npy, points .npy,
calibration YAML, frames.jsonl; layout in ``drivers/stereo_replay.py``)."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import yaml
from cgamap.daemon.cli import UsageError

MAX_DISPARITIES = 1024
MAX_BLOCK = 51


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo", help="grab stereo frames and write images, disparity, points")
    p.add_argument("--model", required=True,
                   choices=["depthai", "opencv", "synthetic", "replay"],
                   help="backend: OAK camera, OpenCV cameras, simulated world, recording")
    p.add_argument("--device", default="",
                   help="depthai: device id/IP ('' = first); opencv: 'L,R' indices or "
                        "'sbs:SRC'; synthetic: world name (corridor, room, loop, stairs, "
                        "corridor-boxes); replay: recording folder")
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--count", type=int, default=1, help="frames to grab (default 1)")
    p.add_argument("--calib", help="stereo calibration YAML (opencv; replay override)")
    p.add_argument("--num-disparities", type=int, default=64, help="SGBM search range")
    p.add_argument("--block-size", type=int, default=5, help="SGBM block size (odd)")
    p.add_argument("--max-depth", type=float, default=20.0, help="drop points beyond (m)")
    p.add_argument("--stride", type=int, default=1, help="keep every n-th pixel for points")
    p.add_argument("--no-points", action="store_true", help="do not write points .npy")
    p.add_argument("--global-frame", action="store_true",
                   help="points in the global frame (camera chain from the frame's robot pose "
                        "and pan-tilt state) instead of the left camera's optical frame")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait per frame")
    p.set_defaults(func=run)


def _grabber(args: argparse.Namespace):
    from cgamap.drivers.stereo import open_grabber

    config: dict = {"sgbm": {"num_disparities": args.num_disparities,
                             "block_size": args.block_size}}
    if args.calib:
        config["calibration"] = args.calib
    if args.model == "depthai":
        config = {"discovery_timeout": min(args.timeout, 10.0)}
    if args.model == "replay" and not args.device:
        raise UsageError("stereo: --device: give the recording folder to replay")
    if args.model == "synthetic":
        config["seed"] = 0
    try:
        if args.model == "synthetic":   # the simulator's camera, not a driver backend
            from cgamap.drivers.sim.stereo_render import open_synthetic

            return open_synthetic(args.device, **config)
        return open_grabber(args.model, args.device, config)
    except (ValueError, FileNotFoundError, OSError) as exc:
        raise UsageError(f"stereo: {exc}") from None


def _check_out(args: argparse.Namespace) -> bool:
    """The output folder must be creatable and must not already hold a recording: the
    writer appends to frames.jsonl and numbers frames from 0, so it would overwrite one.
    Returns True when the folder is new (created here)."""
    out = Path(args.out)
    created = not out.exists()
    if args.model == "replay" and args.device and Path(args.device).resolve() == out.resolve():
        raise UsageError(f"stereo: --out {args.out}: is the recording being replayed; "
                         "choose another folder")
    if out.exists() and not out.is_dir():
        raise UsageError(f"stereo: --out {args.out}: exists and is not a folder")
    if (out / "frames.jsonl").exists():
        raise UsageError(f"stereo: --out {args.out}: already holds a recording "
                         "(frames.jsonl); choose a new folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"stereo: --out {args.out}: cannot create ({exc.strerror or exc})"
                         ) from None
    if not os.access(out, os.W_OK):
        raise UsageError(f"stereo: --out {args.out}: folder is not writable")
    return created


def _check_args(args: argparse.Namespace) -> None:
    if args.count < 1:
        raise UsageError("stereo: --count: must be at least 1")
    if args.stride < 1:
        raise UsageError("stereo: --stride: must be at least 1")
    # OpenCV itself only fails (or allocates for minutes) on values beyond the image
    if not 16 <= args.num_disparities <= MAX_DISPARITIES:
        raise UsageError(f"stereo: --num-disparities: must be 16..{MAX_DISPARITIES} (a "
                         f"multiple of 16, below the image width), got {args.num_disparities}")
    if not 1 <= args.block_size <= MAX_BLOCK:
        raise UsageError(f"stereo: --block-size: must be odd, 1..{MAX_BLOCK}, got "
                         f"{args.block_size}")
    if not args.max_depth > 0:  # inf is fine: keep every point
        raise UsageError(f"stereo: --max-depth: must be positive, got {args.max_depth}")
    if not (args.timeout > 0 and math.isfinite(args.timeout)):
        raise UsageError(f"stereo: --timeout: must be a positive number, got {args.timeout}")
    if args.calib:
        if Path(args.calib).is_dir():
            raise UsageError(f"stereo: --calib {args.calib}: is a directory, not a file")
        if not Path(args.calib).is_file():
            raise UsageError(f"stereo: --calib {args.calib}: no such file")
    if args.model == "replay" and args.device and not Path(args.device).is_dir():
        raise UsageError(f"stereo: --device {args.device}: no such folder (a recording to replay)")


def run(args: argparse.Namespace) -> int:
    import cv2
    from cgamap.drivers.stereo_depthai import DeviceNotFound
    from cgamap.drivers.stereo_replay import SequenceWriter
    from cgamap.mapping.fileio import write_bytes_atomic

    _check_args(args)
    grabber = _grabber(args)
    created = _check_out(args)
    mount = getattr(grabber, "mount", None) if args.global_frame else None
    # crash-safe files: a frame cut short (full disk, kill) never stands under its final name
    writer = SequenceWriter(args.out, save_points=not args.no_points, stride=args.stride,
                            max_depth=args.max_depth, global_frame=args.global_frame,
                            mount=mount, write_file=write_bytes_atomic)
    try:
        return _grab(args, grabber, writer, cv2, DeviceNotFound)
    finally:
        if created and writer.count == 0:  # leave no empty folder behind a failure
            try:
                Path(args.out).rmdir()
            except OSError:
                pass


def _grab(args: argparse.Namespace, grabber, writer, cv2, DeviceNotFound) -> int:
    from cgamap.drivers.stereo_sgbm import SgbmRangeError

    try:
        grabber.open()
    except DeviceNotFound as exc:
        raise UsageError(f"stereo: {exc}", code=1) from None
    except (ValueError, FileNotFoundError, RuntimeError, yaml.YAMLError) as exc:
        raise UsageError(f"stereo: {_input_problem(args, exc)}", code=1) from None
    try:
        for frame in grabber.frames(count=args.count, timeout=args.timeout):
            rec = writer.write(frame)
            depth = frame.depth_image()
            med = float(np.nanmedian(depth)) if np.isfinite(depth).any() else float("nan")
            print(f"frame {frame.seq}: {rec.get('n_points', 0)} points, "
                  f"median depth {med:.2f} m -> {args.out}/{rec['left']}", flush=True)
    except TimeoutError as exc:
        raise UsageError(f"stereo: {exc}", code=1) from None
    except SgbmRangeError as exc:
        raise UsageError(f"stereo: --num-disparities {args.num_disparities}: {exc}",
                         code=1) from None
    except (ValueError, yaml.YAMLError) as exc:
        raise UsageError(f"stereo: {_input_problem(args, exc)}", code=1) from None
    except cv2.error as exc:  # e.g. more disparities than the image is wide
        raise UsageError(f"stereo: OpenCV refused the frame: {exc.err or exc} (check "
                         "--num-disparities and --block-size against the image size)",
                         code=1) from None
    except BrokenPipeError:  # stdout's reader went away: cgamap's main ends quietly
        raise
    except OSError as exc:  # e.g. the disk filled up while writing
        raise UsageError(f"stereo: --out {args.out}: cannot write ({exc.strerror or exc})",
                         code=1) from None
    finally:
        grabber.close()
    if writer.count == 0:
        print(f"cgamap: stereo: no frames from --model {args.model} --device "
              f"{args.device or '(default)'}", file=sys.stderr)
        return 1
    return 0


def _input_problem(args: argparse.Namespace, exc: Exception) -> str:
    """One line for a damaged input (a recording's frames.jsonl or calibration YAML)."""
    from cgamap.drivers.stereo_calib import CalibrationFileError
    from cgamap.drivers.stereo_replay import RecordingIndexError
    from cgamap.drivers.yaml_errors import yaml_error_text

    where = f"--device {args.device}: " if args.device else ""
    # both name the file and the problem (the index error its line number)
    if isinstance(exc, (CalibrationFileError, RecordingIndexError)):
        return f"{where}{exc}"
    if isinstance(exc, json.JSONDecodeError):
        return f"{where}frames.jsonl is damaged (line {exc.lineno}: {exc.msg})"
    if isinstance(exc, UnicodeDecodeError):
        return f"{where}a text file of the recording is not text"
    if isinstance(exc, yaml.YAMLError):
        return f"{where}calibration {yaml_error_text(exc)}"
    return str(exc)


