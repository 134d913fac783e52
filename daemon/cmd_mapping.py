"""``cgamap map build`` and ``cgamap relocalize``: the 2D line mapper over recorded logs.

``map`` is a subcommand group; its subparsers object is the module global ``MAP_SUBPARSERS``
so other modules (e.g. ``map export``) can add to it after :func:`register` ran.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from cgamap.daemon.cli import UsageError

MAP_SUBPARSERS: argparse._SubParsersAction | None = None


def register(sub: argparse._SubParsersAction) -> None:
    global MAP_SUBPARSERS
    p = sub.add_parser("map", help="2D line maps: build from a log, ...")
    MAP_SUBPARSERS = p.add_subparsers(dest="map_command", metavar="MAP_COMMAND")
    p.set_defaults(func=lambda args: (p.print_help(sys.stderr), 2)[1])

    b = MAP_SUBPARSERS.add_parser("build", help="replay a CARMEN log through the 2D mapper")
    b.add_argument("--log", required=True, help="CARMEN log (.log, .clf, optionally .gz)")
    b.add_argument("--out", required=True,
                   help="output directory (created if missing; an earlier map.json in it is "
                        "kept as map.json.bak)")
    b.add_argument("--odom-noise", choices=["none", "low", "high", "wheels"], default="none",
                   help="corrupt the log's odometry with this preset "
                        "(cgamap.mapping.odometry.ODOM_NOISE_PRESETS); 'wheels' replays the "
                        "robot's own wheel odometry from the log's ODOM lines instead, with "
                        "no noise added (in a corrected log the laser lines' odometry fields "
                        "are the corrected poses, but its ODOM lines keep the wheels' steps)")
    b.add_argument("--seed", type=int, default=0, help="seed of the odometry noise")
    b.add_argument("--relations", metavar="FILE",
                   help="relative-pose ground truth (Kümmerle et al. 2009 format, e.g. "
                        "intel.relations): report the error over the relations whose two "
                        "instants are scans of the log")
    b.add_argument("--params", metavar="FILE",
                   help="YAML of 2D mapper parameters to change (the fields of "
                        "cgamap.mapping.slam2d.MapperParams, nested: e.g. 'segments: "
                        "{range_max: 30.0, min_points: 8}'), or a cgamapd config, whose "
                        "mapping.params2d is taken; recorded in map.json and report.json")
    b.add_argument("--no-loop-closure", action="store_true",
                   help="global-map matching only, no pose graph")
    b.add_argument("--lenient", action="store_true", help="skip malformed log lines")
    b.add_argument("--quiet", action="store_true", help="no progress on stderr")
    b.set_defaults(func=run_build)

    r = sub.add_parser("relocalize", help="relocalise scans in a map (Hough domain)")
    r.add_argument("--map", help="map.json written by 'cgamap map build'")
    r.add_argument("--log", help="CARMEN log whose scans are relocalised")
    r.add_argument("--trials", type=int, default=200,
                   help="number of random scans (at most the log's scan count)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--json", action="store_true", help="one JSON object on stdout")
    r.add_argument("--lenient", action="store_true", help="skip malformed log lines")
    r.add_argument("--near", nargs=3, type=float, metavar=("X", "Y", "THETA_DEG"),
                   help="daemon mode: a hint, only poses near it (as a 2D pose estimate)")
    r.add_argument("--radius", type=float, help="with --near: metres (default 2)")
    r.add_argument("--turn", type=float, help="with --near: degrees (default 30)")
    r.set_defaults(func=run_relocalize)


def _progress(label: str, quiet: bool):
    if quiet:
        return None

    if sys.stderr.isatty():
        def show(k: int, n: int) -> None:
            if k == n or k % 25 == 0:
                print(f"\r{label}: {k}/{n}", end="\n" if k == n else "", file=sys.stderr,
                      flush=True)
        return show

    # a log file or a pipe: a line per tenth, not one line run together by carriage returns
    def lines(k: int, n: int) -> None:
        step = max(n // 10, 1)
        if k == n or k % step == 0:
            print(f"{label}: {k}/{n}", file=sys.stderr, flush=True)
    return lines


def _read_log(path: str, lenient: bool, quiet: bool = False, wheels: bool = False):
    """The log's scans, the reader's stats, and with ``wheels`` its ODOM readings at the
    scans (:class:`cgamap.drivers.carmen.WheelReadings`; None without ODOM lines or
    ``wheels``)."""
    from cgamap.drivers.carmen import CarmenFormatError, CarmenStats, read_scans_and_wheels

    p = Path(path)
    if p.is_dir():
        raise UsageError(f"--log: {path}: is a directory (give the log file in it)")
    if not p.is_file():
        raise UsageError(f"--log: {path}: no such file")
    st = CarmenStats()
    try:
        scans, readings = read_scans_and_wheels(p, lenient=lenient, stats=st, wheels=wheels)
    except CarmenFormatError as exc:
        raise UsageError(f"--log: {exc}") from None
    except (OSError, EOFError) as exc:
        raise UsageError(f"--log: {path}: cannot read ({exc})") from None
    if not scans:
        raise UsageError(f"--log: {path}: no laser scans (FLASER/ROBOTLASER1) in the log")
    if st.duplicates and not quiet:
        print(f"--log: {st.duplicates} FLASER scans repeat ROBOTLASER1 scans (same time and "
              "ranges): read once", file=sys.stderr)
    if st.saturated_range is not None and not quiet:
        print(f"--log: {st.saturated_beams} readings of {st.saturated_range:g} m (the log's "
              "longest, repeated) taken as no return", file=sys.stderr)
    return scans, st, readings


def _read_relations(path: str) -> np.ndarray:
    from cgamap.mapping.evaluation import load_relations

    try:
        return load_relations(path)
    except OSError as exc:
        raise UsageError(f"--relations: {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise UsageError(f"--relations: {exc}") from None


def _relations_report(relations: np.ndarray, stamps: np.ndarray, poses: np.ndarray, scans,
                      odometry: np.ndarray) -> dict:
    """The estimate's error over the relations; the log's reference poses (when it has
    them) and the odometry scored the same way, for scale: a reference that is itself SLAM
    output is not ground truth."""
    from cgamap.mapping.evaluation import relations_error

    def rounded(d: dict) -> dict:
        return {k: round(v, 4) if isinstance(v, float) else v for k, v in d.items()}

    est = relations_error(stamps, poses, relations)
    out = {"estimate": rounded(est)}
    ref = [s.pose_ref for s in scans]
    if all(r is not None for r in ref):
        out["reference"] = rounded(relations_error(stamps, np.array(ref, float), relations,
                                                   offset=est["clock_offset_s"]))
    out["odometry"] = rounded(relations_error(stamps, odometry, relations,
                                              offset=est["clock_offset_s"]))
    return out


def _read_params(path: str):
    """``--params FILE``: (the mapper's parameters, the overrides the file gives), checked as
    the daemon checks its ``mapping.params2d`` (:func:`~cgamap.daemon.config.mapper_params`)."""
    from cgamap.daemon.config import YamlFileError, mapper_params, read_yaml

    try:
        doc = read_yaml(path, "parameter file")
    except YamlFileError as exc:
        raise UsageError(f"--params: {path}: {exc.key + ': ' if exc.key else ''}{exc}"
                         ) from None
    where = ""
    mapping = doc.get("mapping") if isinstance(doc, dict) else None
    if isinstance(mapping, dict):  # a cgamapd config: its 2D mapper's parameters
        doc, where = mapping.get("params2d"), "mapping.params2d."
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise UsageError(f"--params: {path}: {where or 'top level: '}expected a mapping of "
                         f"mapper parameters, got {type(doc).__name__}")
    try:
        return mapper_params(doc, where, mount_note="the laser's mount comes from the log "
                             "(its laser and odometry poses), not from here"), doc
    except ValueError as exc:
        raise UsageError(f"--params: {path}: {exc}") from None


def _segment_params(lmap):
    """The segment extraction a map was built with (``map build --params``, recorded in its
    metadata): relocalising in it must cut scans into segments the same way."""
    from cgamap.daemon.config import with_overrides
    from cgamap.mapping.segments import SegmentParams

    rec = lmap.metadata.get("params2d", {})
    if not isinstance(rec, dict):
        raise UsageError("--map: metadata.params2d: expected a mapping")
    got = rec.get("segments")
    if got is None:
        return None
    if not isinstance(got, dict):
        raise UsageError("--map: metadata.params2d.segments: expected a mapping")
    try:
        return with_overrides(SegmentParams(), got, "metadata.params2d.segments.",
                              "segment parameter")
    except ValueError as exc:
        raise UsageError(f"--map: {exc}") from None


def run_build(args: argparse.Namespace) -> int:
    from cgamap.mapping.fileio import write_text_atomic
    from cgamap.mapping.linemap import LineMap  # noqa: F401  (import check before work)
    from cgamap.mapping.mapio import save_map
    from cgamap.mapping.offline import WHEELS, build_map, log_odometry, wheel_steps
    from cgamap.mapping.render import export_occupancy, render_png
    from cgamap.mapping.slam2d import MapperParams

    params, overrides = _read_params(args.params) if args.params else (MapperParams(), {})
    wheels = args.odom_noise == WHEELS
    scans, st, readings = _read_log(args.log, args.lenient, args.quiet, wheels)
    relations = _read_relations(args.relations) if args.relations else None
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out: {out}: cannot create ({exc.strerror})") from None
    try:
        odo, mount = log_odometry(scans, args.odom_noise, args.seed,
                                  None if readings is None else (readings.at, readings.start))
    except ValueError as exc:
        if wheels:
            raise UsageError(f"--odom-noise wheels: {args.log}: {exc}") from None
        raise UsageError(f"--log: {exc}; cannot replay without odometry") from None
    if readings is not None and readings.at_scan_time < 0.5 and not args.quiet:
        print(f"map build: warning: {readings.at_scan_time:.0%} of the log's scans have an "
              "ODOM reading of their own time: the wheel steps miss the motion between the "
              "last reading and each scan", file=sys.stderr)
    if args.no_loop_closure:
        params = replace(params, loop=replace(params.loop, enabled=False))
    res = build_map(scans, odo, params, _progress("map build", args.quiet),
                    None if args.quiet else lambda line: print(f"map build: {line}",
                                                               file=sys.stderr, flush=True))
    meta = {"log": str(args.log), "odom_noise": args.odom_noise, "seed": args.seed,
            "scans": len(scans), "frame": "map = the log's first pose"}
    if overrides:
        meta["params2d"] = overrides
    if "alignment_to_reference" in res.report:
        meta["alignment_to_reference"] = res.report["alignment_to_reference"]
    if (res.report.get("reference_check") or {}).get("odometry_like"):
        meta["reference_odometry_like"] = True   # relocalize says so beside its rate
    _keep_previous(out / "map.json", args.quiet)
    save_map(res.map, out / "map.json", meta)
    render_png(res.map, out / "map.png", res.poses)
    export_occupancy(res.map, out / "map")
    rows = "".join(f"{t:.6f},{x:.4f},{y:.4f},{th:.5f}\n"
                   for t, (x, y, th) in zip(res.stamps, res.poses, strict=True))
    write_text_atomic(out / "trajectory.csv", "t,x,y,theta\n" + rows)
    report = {"log": str(args.log), "odom_noise": args.odom_noise, "seed": args.seed,
              "skipped_lines": st.skipped, **({"params2d": overrides} if overrides else {}),
              **res.report}
    if st.duplicates:
        report["duplicate_scans_dropped"] = st.duplicates
    if st.saturated_range is not None:
        report["no_return_reading_m"] = st.saturated_range
        report["no_return_readings"] = st.saturated_beams
    if mount is not None:
        report["laser_mount"] = [round(float(v), 5) for v in mount]
    if readings is not None:
        report["wheel_odometry"] = {
            "odom_lines": readings.readings, "rebased": readings.rebased,
            "unknown_steps": wheel_steps(readings.at, readings.start)[1],
            "at_scan_time": readings.at_scan_time}
    if relations is not None:
        report["relations"] = _relations_report(relations, res.stamps, res.poses, scans, odo)
    write_text_atomic(out / "report.json", json.dumps(report, indent=2) + "\n")
    if not args.quiet:
        keys = ("scans_processed", "segments", "ms_per_scan_median", "ate_trans_m",
                "ate_rot_deg", "rpe_trans_m", "rpe_rot_deg")
        line = " ".join(f"{k}={report[k]}" for k in keys if k in report)
        sq = report.get("squareness", {}).get("estimate", {}).get("rms_deg")
        if sq is not None:  # a log without reference poses still gets this one figure
            line += f" wall_squareness_deg={sq}"
        print(line, file=sys.stderr)
        chk = report.get("reference_check") or {}
        if chk.get("odometry_like"):
            on, rms = chk["on_axes"], chk["rms_deg"]
            print(f"map build: warning: the log's poses look like raw odometry, not a corrected "
                  f"trajectory (walls {rms['reference']}° RMS off the building's axes along "
                  f"them, {rms['estimate']}° along the estimate; {on['reference']:.0%} of the "
                  f"wall length near the axes against {on['estimate']:.0%}): the ATE is against "
                  "them, not against the truth", file=sys.stderr)
    print(out / "map.json")
    return 0


def _keep_previous(path: Path, quiet: bool) -> None:
    """An earlier map in the output folder is kept as ``<name>.bak`` (one generation): a
    rebuild into the same folder must not silently lose a map somebody worked for."""
    if not path.exists():
        return
    bak = path.with_name(path.name + ".bak")
    try:
        path.replace(bak)
    except OSError as exc:
        raise UsageError(f"--out: cannot keep the earlier {path} as {bak.name} "
                         f"({exc.strerror}); nothing written") from None
    if not quiet:
        print(f"map build: the earlier {path} is kept as {bak}", file=sys.stderr)


def run_relocalize(args: argparse.Namespace) -> int:
    if (args.radius is not None or args.turn is not None) and args.near is None:
        raise UsageError("relocalize: --radius and --turn need --near")
    if args.near is not None and (args.map is not None or args.log is not None):
        raise UsageError("relocalize: --near asks the running daemon; give neither --map "
                         "nor --log")
    if args.map is None and args.log is None:
        from cgamap.daemon.cmd_daemon import relocalize_via_daemon

        return relocalize_via_daemon(args)  # no map or log given: ask the running daemon
    if args.map is None or args.log is None:
        raise UsageError("relocalize: offline mode needs both --map and --log "
                         "(give neither to ask the running daemon)")
    if args.trials < 1:
        raise UsageError(f"--trials: must be >= 1, got {args.trials}")
    from cgamap.mapping.mapio import MapFormatError, load_map
    from cgamap.mapping.offline import relocalize_trials

    try:
        lmap = load_map(args.map)
    except MapFormatError as exc:
        raise UsageError(f"--map: {exc}") from None
    if len(lmap) < 2:
        raise UsageError(f"--map: {args.map}: the map has fewer than 2 segments")
    segment_params = _segment_params(lmap)
    scans, _, _ = _read_log(args.log, args.lenient)
    if any(s.pose_ref is None for s in scans):
        raise UsageError("--log: scans carry no reference poses to score against")
    align = _alignment(lmap.metadata.get("alignment_to_reference"))
    trials = args.trials
    if trials > len(scans):   # more would draw scans twice: the rate would count repeats
        print(f"relocalize: --trials {trials} capped to the log's {len(scans)} scans",
              file=sys.stderr)
        trials = len(scans)
    own = _build_trajectory(Path(args.map).with_name("trajectory.csv"), scans)
    # progress goes to stderr, so --json's stdout stays one object; short runs stay quiet
    res = relocalize_trials(lmap, scans, trials, args.seed, alignment=align,
                            segment_params=segment_params,
                            progress=_progress("relocalize", trials < 50),
                            also=None if own is None else {"vs_map_trajectory": own})
    if args.json:
        print(json.dumps(res))
    else:
        gauge = " (map frame aligned to the reference by the build's ATE alignment)" \
            if res["aligned_to_reference"] else ""
        print(f"{res['successes']}/{res['trials']} relocalised within 0.2 m and 3 deg of the "
              f"reference{gauge}: {100 * res['success_rate']:.1f} %, median "
              f"{res['median_ms']:.1f} ms, p95 {res['p95_ms']:.1f} ms")
        if lmap.metadata.get("reference_odometry_like"):
            print("relocalize: the build found the log's poses look like raw odometry: the "
                  "rate against them says little about the map", file=sys.stderr)
        if own is not None:
            v = res["vs_map_trajectory"]
            print(f"{v['successes']}/{res['trials']} within 0.2 m and 3 deg of the build's own "
                  f"trajectory (trajectory.csv): {100 * v['success_rate']:.1f} %")
    return 0


def _build_trajectory(path: Path, scans) -> np.ndarray | None:
    """The poses of ``map build``'s ``trajectory.csv`` beside the map, when it is this log's
    (a row per scan, the same stamps): relocalisation is then scored against the map's own
    trajectory too, which the map's ATE against the reference does not blur.  None when
    the file is absent; when it is unreadable or another log's, None with one line on
    stderr saying so (it is optional: the trials go on)."""
    if not path.is_file():
        return None
    try:
        rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        stamps = np.array([s.stamp_ns for s in scans], dtype=float) * 1e-9
        if rows.shape != (len(scans), 4) or not np.allclose(rows[:, 0], stamps, atol=1e-3):
            print(f"relocalize: {path} is not this log's trajectory ({len(rows)} rows, "
                  f"{len(scans)} scans): scored against the reference only", file=sys.stderr)
            return None
    except (OSError, ValueError) as exc:
        print(f"relocalize: {path}: unreadable ({exc}): scored against the reference only",
              file=sys.stderr)
        return None
    return rows[:, 1:]


def _alignment(value):
    """The map's rigid alignment onto the reference frame, if the map file carries one."""
    if value is None:
        return None
    try:
        x, y, th = (float(v) for v in value)
    except (TypeError, ValueError):
        raise UsageError("--map: metadata.alignment_to_reference: expected 3 numbers") from None
    return (x, y, th)
