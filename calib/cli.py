"""``cgamap calib``: hand-eye calibration of the camera on the pan-tilt head.

``cgamap calib hand-eye --pairs FILE [--method M] [--out calib.yaml] [--json]`` solves for
head_T_cam; ``cgamap calib collect --sim | --pantilt URL --camera URL`` records the pose pairs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

from .handeye import METHODS, DegenerateMotionError
from .pairs import PairsFileError


class CalibUsageError(Exception):
    """Bad input to a calib command: the CLI prints it as one line and exits with 2."""

    exit_code = 2


def _usage_error(msg: str) -> CalibUsageError:
    return CalibUsageError(msg)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calib", help="hand-eye calibration (camera on the pan-tilt head)")
    csub = p.add_subparsers(dest="calib_command", metavar="CALIB_COMMAND")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    he = csub.add_parser("hand-eye", help="solve head_T_cam from recorded pose pairs")
    he.add_argument("--pairs", required=True, metavar="FILE",
                    help="pose pairs (JSON or YAML): {pairs: [{base_T_head, cam_T_target, "
                         "pan, tilt}, ...]}")
    he.add_argument("--method", default="motor", choices=METHODS,
                    help="motor (ours, default) or one of OpenCV's five for comparison")
    he.add_argument("--out", metavar="FILE", help="write the calibration YAML here")
    he.add_argument("--json", action="store_true", help="print one JSON object")
    he.add_argument("--axes", action="store_true",
                    help="also calibrate the pan and tilt axes (needs pan/tilt in the pairs)")
    he.set_defaults(func=cmd_hand_eye)

    from .collect import add_arguments

    co = csub.add_parser("collect", help="drive the pan-tilt, detect the target, record pairs")
    add_arguments(co)
    co.set_defaults(func=cmd_collect)


def _fmt_vec(v, scale=1.0, fmt="{:+.4f}") -> str:
    return " ".join(fmt.format(float(x) * scale) for x in v)


def cmd_hand_eye(args: argparse.Namespace) -> int:
    from .handeye import solve
    from .pairs import calibration_document, load_pairs, write_calibration

    if args.out:
        _check_output("calib hand-eye", "--out", args.out)
        if Path(args.out).exists() and Path(args.out).resolve() == Path(args.pairs).resolve():
            raise _usage_error(f"calib hand-eye: --out {args.out}: is the --pairs file; "
                               "write the calibration to another file")
    try:
        pairs = load_pairs(args.pairs)
    except PairsFileError as exc:
        raise _usage_error(f"calib hand-eye: {exc}") from None
    try:
        result = solve(pairs.base_T_head, pairs.cam_T_target, method=args.method,
                       pan=pairs.pan, tilt=pairs.tilt)
    except DegenerateMotionError as exc:
        raise _usage_error(f"calib hand-eye: {args.pairs}: {exc}") from None
    except ValueError as exc:
        raise _usage_error(f"calib hand-eye: {args.pairs}: {exc}") from None
    except RuntimeError as exc:  # a comparison solver that gave up
        err = _usage_error(f"calib hand-eye: {exc}")
        err.code = 1
        raise err from None
    axes = None
    if args.axes:
        axes = _axes_summary(pairs, result)
    doc = calibration_document(result, len(pairs), source=str(args.pairs), axes=axes)
    if args.out:
        try:
            write_calibration(args.out, doc)
        except OSError as exc:
            raise _usage_error(f"calib hand-eye: --out {args.out}: {exc.strerror or exc}"
                               ) from None
    if args.json:
        print(json.dumps(doc))
        return 0
    _print_report(doc, result)
    if args.out:
        print(f"wrote {args.out}")
    return 0


def _axes_summary(pairs, result) -> dict:
    from .axes import AxisCalibrationError, calibrate_axes

    if pairs.pan is None or pairs.tilt is None:
        raise _usage_error("calib hand-eye: --axes needs 'pan' and 'tilt' in every pair")
    try:
        ax = calibrate_axes(pairs.cam_T_target, pairs.pan, pairs.tilt,
                            base_T_target=result.base_T_target)
    except AxisCalibrationError as exc:
        raise _usage_error(f"calib hand-eye: --axes: {exc}") from None
    return ax.as_dict()


def _print_report(doc: dict, result) -> None:
    X = np.asarray(doc["head_T_cam"])
    n_in = int(np.sum(result.inliers)) if result.inliers is not None else doc["pairs"]
    out = sys.stdout
    print(f"hand-eye ({doc['method']}): {doc['pairs']} pose pairs, {n_in} used", file=out)
    print("head_T_cam:", file=out)
    for row in X:
        print("  [" + ", ".join(f"{v:+.6f}" for v in row) + "]", file=out)
    unc = doc.get("uncertainty")
    t_sig = f"  (1-sigma {_fmt_vec(unc['trans_mm_1sigma'], 1, '{:.2f}')} mm)" if unc else ""
    r_sig = f"  (1-sigma {_fmt_vec(unc['rot_deg_1sigma'], 1, '{:.3f}')} deg)" if unc else ""
    print(f"translation (m): {_fmt_vec(X[:3, 3])}{t_sig}", file=out)
    print(f"rotation RPY (deg): {_fmt_vec(doc['rpy_eye_deg'], 1, '{:+.3f}')}{r_sig}", file=out)
    print(f"quaternion (w x y z): {_fmt_vec(doc['q_eye'], 1, '{:+.6f}')}", file=out)
    print("motor M = T R: " + " ".join(f"{v:+.6f}{'' if k == '1' else '*' + k}"
                                       for k, v in doc["motor"].items()), file=out)
    if unc:
        print(f"noise estimate per axis: {unc['noise_rot_deg']:.3f} deg, "
              f"{unc['noise_trans_mm']:.2f} mm", file=out)
    res = doc.get("residuals")
    if res:
        print("pair  rot (deg)  trans (mm)", file=out)
        for k, (r, t, ok) in enumerate(zip(res["rot_deg"], res["trans_mm"], res["inliers"],
                                           strict=True)):
            print(f"{k:4d}  {r:9.4f}  {t:10.3f}{'' if ok else '  rejected'}", file=out)
    axes = doc.get("axes")
    if axes:
        print(f"axes: angle between pan and tilt {axes['angle_deg']:.3f} deg "
              f"(non-orthogonality {axes['non_orthogonality_deg']:+.3f} deg), "
              f"offset {axes['offset_m'] * 1e3:.2f} mm", file=out)
        if "axis_point" in axes:
            print(f"axis point (base frame, m): {_fmt_vec(axes['axis_point'])}", file=out)


def _check_output(cmd: str, flag: str, path: str) -> None:
    """Refuse an output file that cannot be written before the work that produces it."""
    p = Path(path)
    if p.is_dir():
        raise _usage_error(f"{cmd}: {flag} {path}: is a directory")
    parent = p.parent
    if not parent.is_dir():
        raise _usage_error(f"{cmd}: {flag} {path}: no such directory {str(parent)!r}")
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise _usage_error(f"{cmd}: {flag} {path}: not writable")


def _check_collect_args(args: argparse.Namespace) -> None:
    cmd = "calib collect"
    least = 3 if args.target == "chessboard" else 2  # OpenCV's chessboard finder needs > 2
    if args.cols < least or args.rows < least:
        raise _usage_error(f"{cmd}: --cols/--rows: a {args.target} needs at least {least} x "
                           f"{least} inner corners, got {args.cols} x {args.rows}")
    for flag, value in (("--square", args.square), ("--max-reproj", args.max_reproj),
                        ("--marker", args.marker)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise _usage_error(f"{cmd}: {flag}: must be a positive number, got {value}")
    for flag, value in (("--pan-range", args.pan_range), ("--tilt-range", args.tilt_range),
                        ("--settle", args.settle), ("--min-sharpness", args.min_sharpness)):
        if not (math.isfinite(value) and value >= 0):
            raise _usage_error(f"{cmd}: {flag}: must be a number >= 0, got {value}")
    if not all(math.isfinite(v) for v in args.axis_point):
        raise _usage_error(f"{cmd}: --axis-point: must be finite, got {args.axis_point}")
    if args.intrinsics and not Path(args.intrinsics).is_file():
        raise _usage_error(f"{cmd}: --intrinsics {args.intrinsics}: no such file")
    _check_output(cmd, "--out", args.out)
    if args.truth:
        _check_output(cmd, "--truth", args.truth)
        if Path(args.truth).resolve() == Path(args.out).resolve():
            raise _usage_error(f"{cmd}: --truth {args.truth}: is the --out file")


def cmd_collect(args: argparse.Namespace) -> int:
    from .collect import CollectError, run_collect
    from .pairs import backup_path

    _check_collect_args(args)
    previous = Path(args.out).is_file()
    try:
        code = run_collect(args)
    except CollectError as exc:
        err = _usage_error(f"calib collect: {exc}")
        err.exit_code = exc.exit_code
        raise err from None
    if previous and backup_path(args.out).is_file():
        print(f"calib collect: the previous {args.out} is kept as {backup_path(args.out)}",
              file=sys.stderr)
    return code
