"""``cgamapd``: the mapping daemon's entry point.

    cgamapd [--config FILE] [--replay FILE] [--state-dir DIR] [--socket PATH]
    cgamapd --check-config FILE

Exit codes follow sysexits.h where systemd cares: 78 (EX_CONFIG) for a bad configuration,
0 after a clean SIGTERM/SIGINT shutdown with a final checkpoint.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import stat
import sys
from pathlib import Path

from cgamap.daemon import config as config_mod

DEFAULT_CONFIG = "/etc/cgamap/robot.yaml"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cgamapd", description="cgamap mapping daemon")
    p.add_argument("--config", "-c", default=None,
                   help=f"YAML config (default: $CONFIGURATION_DIRECTORY/robot.yaml or "
                        f"{DEFAULT_CONFIG})")
    p.add_argument("--check-config", metavar="FILE", help="validate FILE and exit (78 if bad)")
    p.add_argument("--replay", metavar="FILE",
                   help="take input from an MCAP recording or a CARMEN log, not devices")
    p.add_argument("--replay-rate", type=float, default=0.0,
                   help="replay speed factor (0: as fast as the mapper goes)")
    p.add_argument("--exit-after-replay", action="store_true",
                   help="checkpoint and exit when the replay is exhausted")
    p.add_argument("--state-dir", help="override paths.state_dir")
    p.add_argument("--socket", help="override the query socket path")
    p.add_argument("--log-level", choices=config_mod.LOG_LEVELS, help="override log_level")
    return p


def default_config_path() -> str:
    import os

    d = os.environ.get("CONFIGURATION_DIRECTORY", "").split(":")[0]
    return f"{d}/robot.yaml" if d else DEFAULT_CONFIG


EX_USAGE, EX_NOINPUT, EX_CANTCREAT = 64, 66, 73  # sysexits.h
MCAP_MAGIC = b"\x89MCAP0\r\n"


class StartupError(Exception):
    """A problem found before the daemon starts: one line, exit ``code``."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


def check_replay(path: str) -> None:
    """The replay input must be a readable, complete recording with messages in it: the
    supervisor would otherwise retry a missing or cut file forever (and replay its start
    again each time)."""
    import gzip
    import zlib

    p = Path(path)
    if p.is_dir():
        raise StartupError(f"--replay {path}: is a directory, not a recording", EX_NOINPUT)
    if not p.is_file():
        raise StartupError(f"--replay {path}: no such file", EX_NOINPUT)
    try:
        with open(p, "rb") as f:
            head = f.read(2)
        if not head:
            raise StartupError(f"--replay {path}: empty file", EX_NOINPUT)
        if head == b"\x89M":  # MCAP: a complete recording ends with the magic again
            with open(p, "rb") as f:
                f.seek(max(0, p.stat().st_size - 8))
                if f.read(8) != MCAP_MAGIC:
                    raise StartupError(f"--replay {path}: MCAP recording is incomplete (cut "
                                       "short: no end magic)", EX_NOINPUT)
        if head == b"\x1f\x8b":  # gzipped CARMEN log: the whole stream must be intact
            with gzip.open(p, "rb") as f:
                while f.read(1 << 20):
                    pass
    except StartupError:
        raise
    except OSError as exc:
        raise StartupError(f"--replay {path}: cannot read ({exc.strerror or exc})",
                           EX_NOINPUT) from None
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise StartupError(f"--replay {path}: damaged gzip file ({exc})", EX_NOINPUT) from None
    from cgamap.daemon.recording import read_messages

    try:
        found = next(iter(read_messages(p)), None) is not None
    except Exception as exc:  # noqa: BLE001 - any reader failure is "not a recording"
        raise StartupError(f"--replay {path}: cannot read as MCAP or CARMEN log "
                           f"({type(exc).__name__}: {exc})"[:300], EX_NOINPUT) from None
    if not found:
        raise StartupError(f"--replay {path}: no device messages in it (not an MCAP "
                           "recording or a CARMEN log?)", EX_NOINPUT)


def replay_mount(path: str) -> tuple[float, float, float] | None:
    """The laser mount (x, y, yaw) a replayed CARMEN log states (``stated_mount`` of its
    scans' laser and odometry poses: a ROBOTLASER1 log of a laser off the robot's centre ->
    that offset; an FLASER log -> zeros).  None when the log states none (an MCAP recording,
    poses missing, or laser poses corrected apart from the odometry): the configuration's
    mount stands."""
    from cgamap.daemon.recording import is_mcap, read_messages
    from cgamap.drivers.messages import LaserScan
    from cgamap.mapping.odometry import stated_mount

    if is_mcap(path):
        return None
    ref, odo = [], []
    for msg in read_messages(path):
        if isinstance(msg, LaserScan) and msg.pose_ref is not None and msg.pose_odom is not None:
            ref.append(msg.pose_ref)
            odo.append(msg.pose_odom)
    m = stated_mount(odo, ref) if ref else None
    return None if m is None else (float(m[0]), float(m[1]), float(m[2]))


def mount_note(cfg: dict, mount: tuple[float, float, float]) -> str | None:
    """A line to log when a replayed log's laser mount differs from the configured one."""
    from cgamap.daemon.loop import configured_mount

    old = configured_mount(cfg["devices"]) or (0.0, 0.0, 0.0)
    if max(abs(o - m) for o, m in zip(old, mount, strict=True)) <= 1e-3:
        return None
    return (f"replay: the log's laser poses put the laser at x {mount[0]:.3f} m, "
            f"y {mount[1]:.3f} m, yaw {math.degrees(mount[2]):.2f} deg from the robot's "
            f"centre; used in place of the configuration's ({old[0]:.3f} m, {old[1]:.3f} m, "
            f"{math.degrees(old[2]):.2f} deg)")


def check_paths(state_dir: Path, socket_path: Path) -> None:
    """The state directory must be usable (else the maps would silently not be saved) and
    the socket path must not be some other file (the server unlinks a stale socket)."""
    if state_dir.exists() and not state_dir.is_dir():
        raise StartupError(f"state directory {state_dir}: exists and is not a directory",
                           EX_CANTCREAT)
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StartupError(f"state directory {state_dir}: cannot create "
                           f"({exc.strerror or exc})", EX_CANTCREAT) from None
    if not os.access(state_dir, os.W_OK | os.X_OK):
        raise StartupError(f"state directory {state_dir}: not writable", EX_CANTCREAT)
    if socket_path.is_symlink() or (socket_path.exists()
                                    and not stat.S_ISSOCK(socket_path.stat().st_mode)):
        raise StartupError(f"socket {socket_path}: a file that is not a socket is there; "
                           "refusing to replace it", EX_CANTCREAT)


def lock_state_dir(state_dir: Path) -> int:
    """Hold an exclusive lock on the state directory for the daemon's life: a second cgamapd
    on the same directory would overwrite the first one's checkpoints (and remove its
    in-flight temp files).  Returns the lock file's descriptor (closed at exit)."""
    import fcntl

    lock = state_dir / "cgamapd.lock"
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise StartupError(f"state directory {state_dir}: cannot create {lock.name} "
                           f"({exc.strerror or exc})", EX_CANTCREAT) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        other = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise StartupError(f"state directory {state_dir}: in use by another cgamapd "
                           f"(pid {other})", EX_CANTCREAT) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    path = args.check_config or args.config or default_config_path()
    try:
        cfg = config_mod.load(path)
    except config_mod.ConfigError as exc:
        where = f"{path}: {exc}" if exc.path else exc.problem  # file-level: names the file
        print(f"cgamapd: {where}", file=sys.stderr)
        return config_mod.EX_CONFIG
    if args.check_config:
        print(f"cgamapd: {path}: ok ({len(cfg['devices'])} devices)")
        return 0
    try:
        if not (math.isfinite(args.replay_rate) and args.replay_rate >= 0):
            raise StartupError(f"--replay-rate: must be a number >= 0, got {args.replay_rate}",
                               EX_USAGE)
        mount, note = None, None
        if args.replay:
            check_replay(args.replay)
            mount = replay_mount(args.replay)
            note = mount_note(cfg, mount) if mount is not None else None
        state, sock = config_mod.resolve_paths(cfg)
        state = Path(args.state_dir) if args.state_dir else state
        check_paths(state, Path(args.socket) if args.socket else sock)
        lock_fd = lock_state_dir(state)
    except StartupError as exc:
        print(f"cgamapd: {exc}", file=sys.stderr)
        return exc.code
    level = (args.log_level or cfg["log_level"]).upper()
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")  # journald adds the time
    if note:
        logging.getLogger("cgamapd").warning("%s", note)
    from cgamap.daemon.service import Daemon

    daemon = Daemon(cfg, config_path=path, replay=args.replay, replay_rate=args.replay_rate,
                    state_dir=args.state_dir, socket_path=args.socket,
                    exit_after_replay=args.exit_after_replay, laser_mount=mount)
    try:
        return daemon.run()
    finally:
        os.close(lock_fd)


if __name__ == "__main__":
    sys.exit(main())
