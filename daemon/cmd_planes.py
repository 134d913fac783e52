"""``cgamap planes``: planes of a point cloud file or of one stereo pair.

    cgamap planes --cloud FILE.{ply,pcd,npy} [--method ransac|hough] [--json]
    cgamap planes --stereo LEFT RIGHT --calib FILE [--method ...] [--json]

Planes are printed largest first, in the cloud's own frame (for a stereo pair: the left
camera's optical frame). With ``--json`` the output is one object
``{"planes": [{"normal": [x, y, z], "rho": m, "inliers": n, ...}, ...]}``.

Depth cameras: their error grows with range squared, and an RGB-D camera reports depth in
steps (a Kinect: ~7 cm at 5 m). A fixed inlier band would slice one far wall into a stack of
fake planes, one per step. So the band widens by --range-noise * range^2; without the flag it
is 0.003 for a stereo pair and for an organised (width x height) cloud or one whose depth is
quantised (a depth camera in its own frame), else 0 (laser scans, merged maps).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from cgamap.daemon.cli import UsageError


def register(subparsers) -> None:
    p = subparsers.add_parser("planes", help="detect planes in a point cloud or a stereo pair",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--cloud", metavar="FILE", help="point cloud: .pcd, .ply or .npy")
    src.add_argument("--stereo", nargs=2, metavar=("LEFT", "RIGHT"),
                     help="a stereo image pair (needs --calib)")
    p.add_argument("--calib", metavar="FILE", help="stereo calibration file (with --stereo)")
    p.add_argument("--method", choices=("ransac", "hough"), default="ransac")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument("--threshold", type=float, default=0.02, help="inlier distance, m")
    p.add_argument("--range-noise", type=float, default=None,
                   help="extra threshold per squared range, 1/m (default: 0.003 for stereo "
                        "and for organised or depth-quantised clouds (a depth camera), else 0)")
    p.add_argument("--min-inliers", type=int, default=1000)
    p.add_argument("--normal-tol", type=float, default=0.0, metavar="DEG",
                   help="RANSAC: a point supports a plane only if its local normal is within "
                        "DEG of the plane's (0: off; e.g. 17 for stairs)")
    p.add_argument("--max-planes", type=int, default=10)
    p.add_argument("--max-depth", type=float, default=10.0,
                   help="stereo: drop points farther than this, m")
    p.add_argument("--seed", type=int, default=0, help="random seed (results repeat)")
    p.add_argument("--configurations", action="store_true",
                   help="also report corridors, stairways, doorways, workplaces")
    p.add_argument("--up", type=float, nargs=3, metavar=("X", "Y", "Z"), default=None,
                   help="the up direction in the cloud's frame (default 0 0 1 for files, "
                        "0 -1 0 for stereo: the OpenCV camera frame)")
    p.add_argument("--ply", metavar="OUT", help="write the planes as PLY quads")
    p.add_argument("--hough-png", metavar="OUT", help="write the theta-phi view of the planes")
    p.set_defaults(func=run)


def _positive(name: str, value: float) -> None:
    if not (value > 0 and np.isfinite(value)):
        raise UsageError(f"{name}: must be a positive number, got {value}")


def _input_file(flag: str, path: str) -> None:
    p = Path(path)
    if p.is_dir():
        raise UsageError(f"{flag} {path}: is a directory, not a file")
    if not p.is_file():
        raise UsageError(f"{flag} {path}: no such file")


def _output_file(flag: str, path: str | None, suffixes: tuple[str, ...]) -> None:
    """Refuse an output the export would fail on, before the (long) detection runs;
    ``suffixes``: the file name endings the writer needs (empty: any)."""
    if not path:
        return
    p = Path(path)
    if suffixes and p.suffix.lower() not in suffixes:
        raise UsageError(f"{flag} {path}: cannot export: expected a "
                         f"{' or '.join(suffixes)} file name")
    if p.is_dir():
        raise UsageError(f"{flag} {path}: cannot export: is a directory")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise UsageError(f"{flag} {path}: cannot export: no such directory {str(parent)!r}")
    if not os.access(parent, os.W_OK):
        raise UsageError(f"{flag} {path}: cannot export: directory {str(parent)!r} is not "
                         "writable")


def _load_cloud(path: str) -> np.ndarray:
    from cgamap.mapping.pcd import CloudFormatError, read_cloud

    _input_file("--cloud", path)
    try:
        return read_cloud(path)
    except CloudFormatError as exc:
        raise UsageError(f"--cloud {exc}") from None
    except (OSError, EOFError, ValueError) as exc:  # e.g. an empty or cut .npy
        raise UsageError(f"--cloud {path}: cannot read ({exc})") from None


def _stereo_points(left: str, right: str, calib: str | None, max_depth: float) -> np.ndarray:
    import cv2
    import yaml
    from cgamap.drivers.stereo import points_from_stereo_pair
    from cgamap.drivers.yaml_errors import yaml_error_text

    if not calib:
        raise UsageError("--stereo: needs --calib FILE")
    for flag, name in (("--stereo", left), ("--stereo", right), ("--calib", calib)):
        _input_file(flag, name)
    imgs = [cv2.imread(name, cv2.IMREAD_UNCHANGED) for name in (left, right)]
    for name, img in zip((left, right), imgs, strict=True):
        if img is None:
            raise UsageError(f"--stereo {name}: not an image OpenCV can read")
    if imgs[0].shape[:2] != imgs[1].shape[:2]:
        raise UsageError(f"--stereo: the images differ in size: {left} is "
                         f"{imgs[0].shape[1]}x{imgs[0].shape[0]}, {right} is "
                         f"{imgs[1].shape[1]}x{imgs[1].shape[0]}")
    try:
        return points_from_stereo_pair(imgs[0], imgs[1], calib, max_depth=max_depth)
    except yaml.YAMLError as exc:
        raise UsageError(f"--calib {calib}: {yaml_error_text(exc)}") from None
    except UnicodeDecodeError:
        raise UsageError(f"--calib {calib}: not a text (YAML) file") from None
    except (ValueError, KeyError, TypeError, OSError) as exc:
        raise UsageError(f"--calib {calib}: {exc}") from None


def run(args) -> int:
    from cgamap.mapping.pcd import finite_points
    from cgamap.mapping.planes import PlaneParams, detect_planes, range_noise_for

    _positive("--threshold", args.threshold)
    _positive("--min-inliers", args.min_inliers)
    _positive("--max-planes", args.max_planes)
    _positive("--max-depth", args.max_depth)
    if not 0 <= args.normal_tol < 90:
        raise UsageError(f"--normal-tol: must be in [0, 90) degrees, got {args.normal_tol}")
    if args.range_noise is not None and not (args.range_noise >= 0
                                             and np.isfinite(args.range_noise)):
        raise UsageError(f"--range-noise: must be a number >= 0, got {args.range_noise}")
    if args.up is not None and not (np.all(np.isfinite(args.up))
                                    and np.linalg.norm(args.up) > 0):
        raise UsageError(f"--up: must be a finite non-zero vector, got {args.up}")
    _output_file("--ply", args.ply, ())
    _output_file("--hough-png", args.hough_png, (".png",))
    t0 = time.perf_counter()
    if args.cloud:
        cloud = _load_cloud(args.cloud)
        range_noise = range_noise_for(cloud) if args.range_noise is None else args.range_noise
        source = f"--cloud {args.cloud}"
    else:
        cloud = _stereo_points(args.stereo[0], args.stereo[1], args.calib, args.max_depth)
        range_noise = 0.003 if args.range_noise is None else args.range_noise
        source = f"--stereo {args.stereo[0]} {args.stereo[1]}"
    pts = finite_points(cloud)
    if len(pts) < 3:
        raise UsageError(f"{source}: fewer than 3 finite points"
                         + ("" if args.cloud else f" within --max-depth {args.max_depth:g} m"))
    t1 = time.perf_counter()
    prm = PlaneParams(threshold=args.threshold, range_noise=range_noise,
                      min_inliers=args.min_inliers, max_planes=args.max_planes,
                      normal_tol=np.radians(args.normal_tol))
    planes = detect_planes(pts, args.method, prm, seed=args.seed)
    t2 = time.perf_counter()
    configs = []
    if args.configurations:
        from cgamap.mapping.configurations import find_configurations

        up = args.up or ((0.0, 0.0, 1.0) if args.cloud else (0.0, -1.0, 0.0))
        configs = find_configurations(planes, up=up)
    _exports(args, planes)
    if args.json:
        out = {"planes": [p.to_dict() for p in planes], "points": int(len(pts)),
               "method": args.method, "range_noise": range_noise,
               "seconds": {"load": round(t1 - t0, 4), "detect": round(t2 - t1, 4)}}
        if args.configurations:
            out["configurations"] = [c.to_dict() for c in configs]
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    band = f", band {args.threshold:g} m + {range_noise:g} r^2" if range_noise else ""
    print(f"{len(planes)} planes in {len(pts)} points ({args.method}{band}, "
          f"{1000 * (t2 - t1):.0f} ms)")
    for i, p in enumerate(planes):
        t, ph, r = p.hough
        n = p.normal
        print(f"{i:2d}  n=({n[0]:+.4f} {n[1]:+.4f} {n[2]:+.4f})  rho={p.rho:.4f} m  "
              f"theta={np.degrees(t):6.2f} phi={np.degrees(ph):7.2f} deg  inliers={p.inliers}  "
              f"rms={1000 * p.rms:.1f} mm  area={p.area:.2f} m2")
    for c in configs:
        shown = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in c.params.items()
                 if k not in ("corners",) and not isinstance(v, list)}
        print(f"{c.kind}: planes {c.planes} {shown}")
    return 0


def _exports(args, planes) -> None:
    if not (args.ply or args.hough_png):
        return
    from cgamap.mapping.planemap import PlaneMap

    pm = PlaneMap()
    pm.planes = []
    for p in planes:  # one map plane per detected plane, no merging
        pm._add(_as_map_plane(p))
    import cv2

    for flag, path, save in (("--ply", args.ply, pm.save_ply),
                             ("--hough-png", args.hough_png, pm.save_hough_png)):
        if not path:
            continue
        try:
            save(path)
        except OSError as exc:
            raise UsageError(f"{flag} {path}: cannot export: {exc.strerror or exc}") from None
        except cv2.error as exc:
            raise UsageError(f"{flag} {path}: cannot export: {exc.err or exc}") from None


def _as_map_plane(p):
    from cgamap.mapping.planemap import MapPlane

    return MapPlane(p.normal, p.rho, p.extent, inliers=p.inliers, corners=p.corners)


