"""CLI of the running daemon: ``cgamap status|watch|map export|map optimize|record|demo`` and
the socket mode of ``cgamap relocalize``.

The socket is ``--socket``, else $CGAMAP_SOCKET, else /run/cgamap/cgamapd.sock (systemd's
RuntimeDirectory).  ``cgamap record`` writes the daemon's device messages (a raw ``watch``)
to MCAP; with ``--config`` it opens the devices itself (when no daemon runs).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

from cgamap.daemon.cli import UsageError
from cgamap.daemon.export import FORMATS

DEFAULT_SOCKET = "/run/cgamap/cgamapd.sock"
REPLY_TIMEOUT = 10.0  # s: a daemon that does not answer a query within this is stuck
OPTIMIZE_TIMEOUT = 600.0  # s: the finishing pass over 20 000 nodes takes minutes, not hours


def socket_path(args: argparse.Namespace) -> str:
    return getattr(args, "socket", None) or os.environ.get("CGAMAP_SOCKET") or DEFAULT_SOCKET


def _ask(args: argparse.Namespace, cmd: str, timeout: float = REPLY_TIMEOUT, **kw) -> dict:
    from cgamap.daemon.server import DaemonUnavailable, request

    where = socket_path(args)
    try:
        reply = request(where, cmd, timeout=timeout, **kw)
    except DaemonUnavailable as exc:
        raise UsageError(f"{cmd}: {exc}", code=69) from None  # EX_UNAVAILABLE
    except TimeoutError:
        raise UsageError(f"{cmd}: {where}: no reply within {timeout:g} s (daemon "
                         "stuck, or not cgamapd)", code=69) from None
    except OSError as exc:
        raise UsageError(f"{cmd}: {where}: {exc.strerror or exc}", code=69) from None
    except ValueError:  # JSONDecodeError, UnicodeDecodeError
        raise UsageError(f"{cmd}: {where}: the reply is not cgamapd's JSON", code=69) from None
    if not isinstance(reply, dict):
        raise UsageError(f"{cmd}: {where}: the reply is not cgamapd's JSON", code=69)
    if reply.get("class") == "error":
        error = str(reply["error"])
        error = error[len(cmd) + 2:] if error.startswith(f"{cmd}: ") else error
        raise UsageError(f"{cmd}: {error}", code=1)
    return reply


def _positive(cmd: str, flag: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{cmd}: {flag}: must be a positive number, got {value}")


def _output_file(cmd: str, flag: str, path: Path) -> None:
    """Refuse an output path the writer would fail on (with a traceback) or that is a
    directory; the parent folder is created as the exporters do."""
    if path.is_dir():
        raise UsageError(f"{cmd}: {flag} {path}: is a directory")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{cmd}: {flag} {path}: cannot create its folder "
                         f"({exc.strerror or exc})") from None
    if not os.access(path.parent, os.W_OK):
        raise UsageError(f"{cmd}: {flag} {path}: folder is not writable")


def _add_socket(p: argparse.ArgumentParser) -> None:
    p.add_argument("--socket", help=f"daemon socket (default $CGAMAP_SOCKET or {DEFAULT_SOCKET})")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="the daemon's devices, pose and maps")
    _add_socket(p)
    p.add_argument("--json", action="store_true", help="the raw JSON reply")
    p.set_defaults(func=run_status)

    p = sub.add_parser("watch", help="stream the daemon's poses and map changes (JSON lines)")
    _add_socket(p)
    p.add_argument("--raw", action="store_true", help="also every device message")
    p.add_argument("--count", type=int, default=0, help="stop after this many lines (0: never)")
    p.add_argument("--interval", type=float, default=1.0, help="status every N s")
    p.set_defaults(func=run_watch)

    map_group = _map_group(sub)
    p = map_group.add_parser("export", help="write the daemon's map (png, pgm+yaml, ply, json)")
    _add_socket(p)
    p.add_argument("--format", "-f", choices=FORMATS, required=True)
    p.add_argument("--output", "-o", help="file (default: map.<format>)")
    p.add_argument("--resolution", type=float, default=None, help="m per pixel (png, pgm)")
    p.set_defaults(func=run_map_export)

    p = map_group.add_parser("optimize", help="run the finishing pass on the daemon's map now")
    _add_socket(p)
    p.add_argument("--timeout", type=float, default=OPTIMIZE_TIMEOUT,
                   help=f"seconds to wait for the reply (default {OPTIMIZE_TIMEOUT:g})")
    p.set_defaults(func=run_map_optimize)

    if "relocalize" not in sub.choices:
        p = sub.add_parser("relocalize", help="ask the daemon to relocalise the robot")
        _add_socket(p)
        p.set_defaults(func=relocalize_via_daemon)
    else:  # cmd_mapping's offline relocalize: give it the socket for its daemon mode
        p = sub.choices["relocalize"]
        if not any("--socket" in a.option_strings for a in p._actions):  # noqa: SLF001
            _add_socket(p)

    p = sub.add_parser("set-pose", help="tell the daemon where the robot is (x y theta_deg)")
    _add_socket(p)
    p.add_argument("x", type=float)
    p.add_argument("y", type=float)
    p.add_argument("theta_deg", type=float)
    p.set_defaults(func=run_set_pose)

    p = sub.add_parser("checkpoint", help="ask the daemon to write a checkpoint now")
    _add_socket(p)
    p.set_defaults(func=lambda a: _print(_ask(a, "checkpoint")))

    p = sub.add_parser("record", help="record every device's messages to an MCAP file")
    _add_socket(p)
    p.add_argument("output", help="MCAP file to write")
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until Ctrl-C)")
    p.add_argument("--config", help="open the devices of this config directly (no daemon)")
    p.set_defaults(func=run_record)

    if "demo" not in sub.choices:
        p = sub.add_parser("demo", help="the simulated robot end to end: twins, cgamapd, maps")
        p.add_argument("--duration", type=float, default=None, help="seconds of driving")
        p.add_argument("--out", default="out", help="output folder (default: out/)")
        p.add_argument("--config", help="simulated robot config (default: config/sim.yaml)")
        p.add_argument("--world", help="simulated world (default: from the config)")
        p.add_argument("--no-camera", action="store_true", help="2D only (faster)")
        p.set_defaults(func=run_demo)


def _map_group(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """The ``map`` group of cmd_mapping (MAP_SUBPARSERS), else one of our own."""
    mod = sys.modules.get("cgamap.daemon.cmd_mapping")
    group = getattr(mod, "MAP_SUBPARSERS", None)
    if group is not None:
        return group
    if "map" in sub.choices:
        parser = sub.choices["map"]
        for action in parser._actions:  # noqa: SLF001 - argparse keeps them nowhere else
            if isinstance(action, argparse._SubParsersAction):
                return action
    p = sub.add_parser("map", help="maps")
    return p.add_subparsers(dest="map_command", metavar="ACTION", required=True)


def _print(obj: dict) -> int:
    print(json.dumps(obj, indent=1))
    return 0


def run_map_optimize(args: argparse.Namespace) -> int:
    """``{"cmd": "optimize"}``: the daemon's reply (edges, nodes, ms, max_shift_m) as JSON."""
    _positive("optimize", "--timeout", args.timeout)
    return _print(_ask(args, "optimize", timeout=args.timeout))


def run_status(args: argparse.Namespace) -> int:
    st = _ask(args, "status")
    if args.json:
        return _print(st)
    try:
        return _print_status(st)
    except (KeyError, TypeError, ValueError) as exc:
        raise UsageError(f"status: {socket_path(args)}: unexpected reply (missing or bad "
                         f"{exc}); see --json", code=1) from None


def _print_status(st: dict) -> int:
    x, y, th = st["pose"]
    q = st.get("quality")
    print(f"pose        {x:.3f} {y:.3f} {math.degrees(th):.1f} deg   match quality "
          f"{'-' if q is None else f'{q:.2f}'}{'  LOST' if st.get('lost') else ''}")
    print(f"map         {st['map']['segments']} segments, {st['map']['planes']} planes "
          f"(version {st['map']['version']})")
    c = st["counts"]
    late = c.get("scans_out_of_order", 0)
    print(f"scans       {c.get('scans', 0)} mapped, {c.get('scans_skipped', 0)} skipped "
          f"(standing{f', {late} stamped out of order' if late else ''}), "
          f"{c.get('scans_in', 0)} received; frames {c.get('frames', 0)}")
    ck = st["checkpoint"]
    print(f"checkpoint  {ck['saves']} saves to {ck['dir']} every {ck['interval_s']:g} s")
    print(f"{'device':10s} {'state':9s} {'rate':>7s} {'age':>7s} {'restarts':>8s} "
          f"{'dropped':>7s}  errors")
    for d in st["devices"]:
        age = d.get("last_message_age_s")
        errs = {k: v for k, v in (d.get("errors") or {}).items() if v}
        print(f"{d['name']:10s} {d['state']:9s} {d['rate_hz']:6.1f}/s "
              f"{'-' if age is None else f'{age:6.2f}s':>7s} {d['restarts']:8d} "
              f"{d.get('queue', {}).get('dropped', 0):7d}  "
              f"{errs or ''}{'  ' + d['last_error'] if d.get('last_error') else ''}")
    return 0


def run_watch(args: argparse.Namespace) -> int:
    from cgamap.daemon.server import DaemonUnavailable, stream

    if args.count < 0:
        raise UsageError(f"watch: --count: must be >= 0, got {args.count}")
    _positive("watch", "--interval", args.interval)
    # the daemon sends a status every --interval: silence far beyond that is a stuck peer
    quiet = max(REPLY_TIMEOUT, 3 * args.interval)
    where = socket_path(args)
    n = 0
    try:
        for obj in stream(where, timeout=quiet, raw=args.raw, interval=args.interval):
            print(json.dumps(obj, separators=(",", ":")), flush=True)
            n += 1
            if args.count and n >= args.count:
                break
    except DaemonUnavailable as exc:
        raise UsageError(f"watch: {exc}", code=69) from None
    except TimeoutError:
        raise UsageError(f"watch: {where}: nothing from the daemon for {quiet:g} s", 69) \
            from None
    except ValueError:
        raise UsageError(f"watch: {where}: a line that is not cgamapd's JSON", 69) from None
    return 0


def run_map_export(args: argparse.Namespace) -> int:
    import cv2
    from cgamap.daemon.export import export

    out = Path(args.output or f"map.{args.format}")
    if args.resolution is not None:
        _positive("map export", "--resolution", args.resolution)
        if args.resolution < 0.001:  # a finer grid than 1 mm is an image too big to write
            raise UsageError(f"map export: --resolution: {args.resolution} m per pixel is "
                             "finer than 1 mm")
    if args.format in ("png", "pgm") and out.suffix.lower() != f".{args.format}":
        raise UsageError(f"map export: --output {out}: a {args.format} file needs the "
                         f".{args.format} extension")
    _output_file("map export", "--output", out)
    reply = _ask(args, "map")
    kw = {}
    if args.format == "png":
        if args.resolution:
            kw["resolution"] = args.resolution
        rows = _ask(args, "trajectory")["rows"]
        if rows:  # the path the robot took, under the map
            import numpy as np

            kw["trajectory"] = np.asarray(rows, dtype=float)[:, 2:5]
    elif args.format == "pgm" and args.resolution:
        kw["resolution"] = args.resolution
    try:
        with warnings.catch_warnings():  # a failure is reported below in one line
            warnings.simplefilter("ignore", RuntimeWarning)
            files = export(reply, args.format, out, **kw)
    except OSError as exc:
        raise UsageError(f"map export: --output {out}: {exc.strerror or exc}", 1) from None
    except (ValueError, MemoryError, cv2.error) as exc:
        raise UsageError(f"map export: {type(exc).__name__}: {exc}"[:200], 1) from None
    print(" ".join(str(f) for f in files))
    return 0


def relocalize_via_daemon(args: argparse.Namespace) -> int:
    """Socket mode of ``cgamap relocalize``: the daemon relocalises on its latest scan.
    ``cmd_mapping`` calls this when neither --map nor --log is given."""
    from cgamap.daemon.server import HINT_RADIUS_M, HINT_TURN, hint_problem

    kw: dict = {}
    near = getattr(args, "near", None)
    if near is not None:
        radius, turn = getattr(args, "radius", None), getattr(args, "turn", None)
        kw = {"near": [near[0], near[1], math.radians(near[2])],
              "radius": HINT_RADIUS_M if radius is None else radius,
              "turn": HINT_TURN if turn is None else math.radians(turn)}
        problem = hint_problem(kw["near"], kw["radius"], kw["turn"])
        if problem:  # its field, named as the flag is
            raise UsageError(f"relocalize: --{problem}")
    reply = _ask(args, "relocalize", **kw)
    if not reply.get("ok"):
        raise UsageError(f"relocalize: {reply.get('error', 'failed')}", code=1)
    x, y, th = reply["pose"]
    if getattr(args, "json", False):
        print(json.dumps(reply))
    else:
        print(f"relocalised: {x:.3f} {y:.3f} {math.degrees(th):.1f} deg "
              f"(score {reply.get('score', 0):.2f})")
    return 0


def run_set_pose(args: argparse.Namespace) -> int:
    for name, value in (("x", args.x), ("y", args.y)):
        if not (math.isfinite(value) and abs(value) <= 1e6):
            raise UsageError(f"set-pose: {name}: must be a finite position within 1000 km, "
                             f"got {value}")
    if not math.isfinite(args.theta_deg):
        raise UsageError(f"set-pose: theta_deg: must be finite, got {args.theta_deg}")
    reply = _ask(args, "set-pose", x=args.x, y=args.y, theta=math.radians(args.theta_deg))
    x, y, th = reply["pose"]
    print(f"pose set: {x:.3f} {y:.3f} {math.degrees(th):.1f} deg")
    return 0


def run_record(args: argparse.Namespace) -> int:
    from cgamap.daemon.recording import McapRecorder

    out = Path(args.output)
    if not (math.isfinite(args.duration) and args.duration >= 0):
        raise UsageError(f"record: --duration: must be a number of seconds >= 0 (0: until "
                         f"Ctrl-C), got {args.duration}")
    if out.exists() and not out.is_dir():  # never overwrite an earlier recording
        raise UsageError(f"record: {out}: exists; give a new file name")
    _output_file("record", "output", out)
    if args.config:  # a bad config must not leave an empty recording behind
        _load_config("record", args.config)
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    deadline = time.monotonic() + args.duration if args.duration > 0 else math.inf
    rec = None
    try:
        with open(out, "wb") as f:
            rec = McapRecorder(f)
            try:
                if args.config:
                    _record_devices(args.config, rec, stop, deadline)
                else:
                    _record_daemon(args, rec, stop, deadline)
            finally:
                rec.finish()
    except UsageError:
        if rec is None or rec.count == 0:  # nothing recorded: leave no empty file
            out.unlink(missing_ok=True)
        raise
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    print(f"{out}: {rec.count} messages")
    return 0


def _record_daemon(args, rec, stop: threading.Event, deadline: float) -> None:
    from cgamap.daemon.server import DaemonUnavailable, connect

    try:
        s = connect(socket_path(args), timeout=1.0)
    except DaemonUnavailable as exc:
        raise UsageError(f"record: {exc} (or give --config to open the devices)", 69) \
            from None
    with s:
        s.sendall(b'{"cmd": "watch", "raw": true, "interval": 5}\n')
        # recv with our own line buffer: a buffered reader is unusable after one timeout
        # ("cannot read from timed out object"), and a quiet second is normal here
        s.settimeout(0.5)
        buf = b""
        while not stop.is_set() and time.monotonic() < deadline:
            if b"\n" not in buf:
                try:
                    chunk = s.recv(1 << 16)
                except TimeoutError:
                    continue
                if not chunk:
                    break
                buf += chunk
                continue
            line, buf = buf.split(b"\n", 1)
            if not line.strip():
                continue
            obj = json.loads(line)
            if obj.get("class") == "raw":
                rec.write_json(obj["topic"], obj["schema"], obj["body"], obj["stamp_ns"])
            elif obj.get("class") == "pose" and obj.get("pose"):
                rec.write_pose(time.monotonic_ns(), *obj["pose"])


def _record_devices(config_path: str, rec, stop: threading.Event, deadline: float) -> None:
    from cgamap.daemon.devices import build_source
    from cgamap.daemon.supervisor import Supervisor

    cfg = _load_config("record", config_path)
    sup = Supervisor(cfg["supervisor"]["backoff_initial"], cfg["supervisor"]["backoff_max"])
    for name, dev in cfg["devices"].items():
        if dev["enabled"] and dev["role"] != "camera":
            sup.add(name, dev["role"], build_source(name, dev), 1024, lossy=False)
    sup.start()
    try:
        while not stop.is_set() and time.monotonic() < deadline:
            sup.bus.wait(0.1)
            for _name, msg in sup.bus.drain():
                rec.write(msg)
    finally:
        sup.stop()


def _load_config(cmd: str, path) -> dict:
    from cgamap.daemon import config as config_mod

    try:
        return config_mod.load(path)
    except config_mod.ConfigError as exc:
        raise UsageError(f"{cmd}: {path}: {exc}", config_mod.EX_CONFIG) from None


def run_demo(args: argparse.Namespace) -> int:
    from cgamap.daemon import config as config_mod
    from cgamap.daemon.demo import default_config
    from cgamap.daemon.demo import run_demo as demo

    cfg_path = Path(args.config) if args.config else default_config()
    try:
        cfg = config_mod.load(cfg_path)
    except config_mod.ConfigError as exc:
        raise UsageError(f"demo: {cfg_path}: {exc}", config_mod.EX_CONFIG) from None
    if args.duration is not None:
        _positive("demo", "--duration", args.duration)
    try:
        duration = args.duration or float(cfg["sim"].get("duration", 60))
    except (TypeError, ValueError):
        raise UsageError(f"demo: {cfg_path}: sim.duration: expected a number", 78) from None
    if args.world is not None:
        from cgamap.drivers.sim.world import WORLDS

        if args.world not in WORLDS:
            raise UsageError(f"demo: --world {args.world!r}: unknown world (choose from "
                             f"{', '.join(sorted(WORLDS))})")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"demo: --out {out}: exists and is not a folder")
    report = demo(out, duration, cfg_path, args.world, camera=not args.no_camera)
    t = report.get("truth", {})
    print(f"\npose error vs truth: ATE {t.get('ate_trans_m', float('nan')):.3f} m / "
          f"{t.get('ate_rot_deg', float('nan')):.2f} deg over {t.get('path_length_m', 0):.1f} m"
          f"; {report['segments']} segments, {report['planes']} planes")
    print(f"wrote {out / 'map.png'}, {out / 'map3d.ply'}, {out / 'report.md'}")
    return 0 if report.get("daemon_exit") == 0 and report.get("checkpoint_ok") else 1
