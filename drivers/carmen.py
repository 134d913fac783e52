"""CARMEN log reader: FLASER / RLASER / ODOM / ROBOTLASER1 lines as typed messages.

Old CARMEN format (see ../shared/reference/lasers.md §4.3), one message per line:

    ODOM x y theta tv rv accel ipc_timestamp host logger_timestamp
    FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp
    ROBOTLASER1 type start_angle fov ang_res max_range accuracy remission_mode n r_1..r_n
                n_rem rem.. laser_x laser_y laser_th robot_x robot_y robot_th tv rv
                fwd_safety side_safety turn_axis ipc_timestamp host logger_timestamp

FLASER/RLASER carry no angles: 180° field of view, first beam at -pi/2, step pi/n for n = 180
or 360, pi/(n-1) for n = 181 or 361 (DESIGN.md).  ROBOTLASER1 beam k is at start_angle +
k * ang_res, as CARMEN and the tools that read its logs take it (the fov field is rounded and
not always (n - 1) * ang_res: a 180-beam scan with fov pi would spread the beams 0.6 % too
wide).  Ranges at or above the sensor maximum mean "no return" and become NaN.
``stamp_ns`` is the line's ipc timestamp in ns.

``pose_ref`` is the line's laser pose; ``pose_odom`` its odometry pose (FLASER odom_x ..,
ROBOTLASER1 robot_x ..), which is the robot's: a laser mounted off the robot's centre is
offset from it (``mapping.offline.log_odometry`` finds the offset and carries the odometry
to the laser).
"""

from __future__ import annotations

import gzip
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .messages import LaserScan, OdometryPose

# Ranges at or above this mean "no return" for SICK LMS logs (81.83 / 81.91 in CARMEN logs).
DEFAULT_MAX_RANGE = 81.0


class CarmenFormatError(ValueError):
    """A malformed line; the message names file:line."""


@dataclass
class CarmenStats:
    """What the reader saw: message counts and skipped lines (lenient mode)."""

    lines: int = 0
    scans: int = 0
    odometry: int = 0
    skipped: int = 0
    ignored: int = 0  # well-formed lines of other types (PARAM, NEFF, comments, ...)
    first_error: str | None = None
    by_type: dict[str, int] = field(default_factory=dict)
    # a no-return value the logger wrote as a plain reading (:func:`saturation_range`)
    saturated_range: float | None = None
    saturated_beams: int = 0
    # FLASER lines that repeat a ROBOTLASER1 line's scan (same time, same ranges): a log
    # written with both messages per scan (:func:`read_scans` keeps one)
    duplicates: int = 0

    @property
    def both_scan_kinds(self) -> bool:
        """Whether the log held FLASER and ROBOTLASER1 lines: a logger that may have written
        each scan twice (:class:`RepeatIndex` tells)."""
        return bool(self.by_type.get("FLASER") and self.by_type.get("ROBOTLASER1"))


def beam_geometry(n: int) -> tuple[float, float]:
    """(angle_min, angle_increment) of an n-beam FLASER scan over 180° (DESIGN.md)."""
    if n in (181, 361):
        return -math.pi / 2, math.pi / (n - 1)
    return -math.pi / 2, math.pi / n


def _open(path: Path):
    with open(path, "rb") as fh:
        magic = fh.read(2)
    if magic == b"\x1f\x8b":
        return gzip.open(path, "rt", encoding="ascii", errors="replace")
    return open(path, encoding="ascii", errors="replace")


def _stamp_ns(seconds: float) -> int:
    return int(round(seconds * 1e9))


def _ranges(raw: list[str], max_range: float) -> np.ndarray:
    r = np.array(raw, dtype=float)
    return np.where((r >= max_range) | (r <= 0) | ~np.isfinite(r), np.nan, r)


def _parse_flaser(tok: list[str], seq: int, max_range: float, frame: str) -> LaserScan:
    n = int(tok[1])
    if n <= 0 or len(tok) < 2 + n + 9:
        raise ValueError(f"expected {n} ranges + 9 fields, got {len(tok) - 2} fields")
    ranges = _ranges(tok[2:2 + n], max_range)
    x, y, th, ox, oy, oth = (float(v) for v in tok[2 + n:2 + n + 6])
    t = float(tok[2 + n + 6])
    amin, inc = beam_geometry(n)
    return LaserScan(
        seq=seq, stamp_ns=_stamp_ns(t), angle_min=amin, angle_increment=inc, ranges=ranges,
        range_min=0.0, range_max=max_range, frame=frame,
        pose_ref=(x, y, th), pose_odom=(ox, oy, oth),
    )


def _parse_robotlaser(tok: list[str], seq: int) -> LaserScan:
    start, fov, res, maxr = (float(v) for v in tok[2:6])
    n = int(tok[8])
    ranges_raw = tok[9:9 + n]
    k = 9 + n
    n_rem = int(tok[k])
    k += 1 + n_rem
    if len(tok) < k + 14 or len(ranges_raw) != n:
        raise ValueError("ROBOTLASER1 line too short")
    lx, ly, lth, rx, ry, rth = (float(v) for v in tok[k:k + 6])
    t = float(tok[k + 11])
    inc = res if res > 0 or n <= 1 else fov / (n - 1)
    return LaserScan(
        seq=seq, stamp_ns=_stamp_ns(t), angle_min=start, angle_increment=inc,
        ranges=_ranges(ranges_raw, maxr), range_min=0.0, range_max=maxr,
        pose_ref=(lx, ly, lth), pose_odom=(rx, ry, rth),
    )


def _parse_odom(tok: list[str], seq: int) -> OdometryPose:
    if len(tok) < 8:
        raise ValueError("ODOM needs x y theta tv rv accel timestamp")
    x, y, th, tv, rv = (float(v) for v in tok[1:6])
    t = float(tok[7])
    return OdometryPose(stamp_ns=_stamp_ns(t), x=x, y=y, theta=th, tv=tv, rv=rv, seq=seq)


def read_carmen(
    path: str | Path,
    *,
    lenient: bool = False,
    max_range: float = DEFAULT_MAX_RANGE,
    stats: CarmenStats | None = None,
    types: tuple[str, ...] = ("FLASER", "RLASER", "ROBOTLASER1", "ODOM"),
) -> Iterator[LaserScan | OdometryPose]:
    """Yield LaserScan (FLASER, RLASER, ROBOTLASER1) and OdometryPose (ODOM) in log order.

    Malformed lines raise CarmenFormatError naming ``file:line``; with ``lenient`` they are
    counted in ``stats.skipped`` and skipped.  Gzipped logs are detected by their magic bytes.
    """
    for _, msg in read_tagged(path, lenient=lenient, max_range=max_range, stats=stats,
                              types=types):
        yield msg


def read_tagged(
    path: str | Path,
    *,
    lenient: bool = False,
    max_range: float = DEFAULT_MAX_RANGE,
    stats: CarmenStats | None = None,
    types: tuple[str, ...] = ("FLASER", "RLASER", "ROBOTLASER1", "ODOM"),
) -> Iterator[tuple[str, LaserScan | OdometryPose]]:
    """:func:`read_carmen`'s messages, each with its line's kind (``"FLASER"``, ...)."""
    path = Path(path)
    st = stats if stats is not None else CarmenStats()
    seq = {"laser": 0, "rear": 0, "odom": 0}
    with _open(path) as fh:
        for lineno, line in enumerate(fh, start=1):
            st.lines += 1
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                st.ignored += 1
                continue
            kind = tok[0]
            if kind not in types:
                st.ignored += 1
                continue
            try:
                if kind in ("FLASER", "RLASER"):
                    frame = "laser" if kind == "FLASER" else "rear_laser"
                    key = "laser" if kind == "FLASER" else "rear"
                    msg = _parse_flaser(tok, seq[key], max_range, frame)
                    seq[key] += 1
                    st.scans += 1
                elif kind == "ROBOTLASER1":
                    msg = _parse_robotlaser(tok, seq["laser"])
                    seq["laser"] += 1
                    st.scans += 1
                else:
                    msg = _parse_odom(tok, seq["odom"])
                    seq["odom"] += 1
                    st.odometry += 1
            except (ValueError, IndexError) as exc:
                where = f"{path}:{lineno}: malformed {kind} line ({exc})"
                if not lenient:
                    raise CarmenFormatError(where) from None
                st.skipped += 1
                if st.first_error is None:
                    st.first_error = where
                continue
            st.by_type[kind] = st.by_type.get(kind, 0) + 1
            yield kind, msg


def read_scans(path: str | Path, *, lenient: bool = False,
               stats: CarmenStats | None = None, saturation: bool = True) -> list[LaserScan]:
    """All front-laser scans of a log (FLASER or ROBOTLASER1), in order.  With
    ``saturation``, a no-return value written as a reading (:func:`saturation_range`)
    becomes NaN, and ``stats`` records it."""
    return read_scans_and_wheels(path, lenient=lenient, stats=stats, saturation=saturation,
                                 wheels=False)[0]


def read_scans_and_wheels(path: str | Path, *, lenient: bool = False,
                          stats: CarmenStats | None = None, saturation: bool = True,
                          wheels: bool = True) -> tuple[list[LaserScan], WheelReadings | None]:
    """:func:`read_scans`, and with ``wheels`` the log's ODOM readings at each of those
    scans (:class:`WheelReadings`; None when the log has no ODOM line), from one reading of
    the file."""
    st = stats if stats is not None else CarmenStats()
    types = ("FLASER", "ROBOTLASER1", "ODOM") if wheels else ("FLASER", "ROBOTLASER1")
    tagged = list(read_tagged(path, lenient=lenient, stats=st, types=types))
    lines = sum(k != "ODOM" for k, _ in tagged)
    if st.both_scan_kinds:
        index = RepeatIndex(m for k, m in tagged if k == "ROBOTLASER1")
        tagged = [(k, m) for k, m in tagged if not index.repeats(k, m)]
    scans = [m for k, m in tagged if k != "ODOM"]
    st.duplicates = lines - len(scans)
    if saturation:
        limit = saturation_range(scans)
        if limit is not None:
            st.saturated_range = limit
            st.saturated_beams = sum(drop_saturated(s, limit) for s in scans)
    return scans, (wheel_readings(tagged) if wheels and st.odometry else None)


@dataclass
class WheelReadings:
    """A log's wheel odometry (its ODOM lines) at each front-laser scan, to replay the
    robot's own odometry rather than a noise model's.

    ``at[k]``: the odometry pose when scan k was taken; ``start[k]``: the pose the readings
    after scan k count from, so the wheels' motion from scan k-1 to scan k is ``start[k-1]``
    to ``at[k]``.  In a log of raw odometry the readings run on (``start`` is ``at``; ``at``
    is interpolated by time between the readings around the scan).  GMapping writes its
    corrected logs otherwise (``rebased``): after each scan an ODOM line at the scan's
    corrected pose, then the wheels' increments from there, the last one stamped with the
    next scan's time (the Intel and MIT CSAIL corrected logs are such).  NaN rows: no
    reading before the scan, so its step is unknown."""

    at: np.ndarray      # (n, 3)
    start: np.ndarray   # (n, 3)
    rebased: bool
    readings: int       # ODOM lines
    # share of the scans after the first whose ``at`` is a reading of the scan's own time
    # (stamped within 1 ms, or interpolated): where it is low, the log's readings came
    # between the scans and each step misses the motion after its last reading
    at_scan_time: float = 1.0


REBASE_TOL = 1e-3  # m and rad: an ODOM line that repeats the scan's pose (logs round to 1e-6)


def wheel_readings(tagged: list[tuple[str, LaserScan | OdometryPose]]) -> WheelReadings:
    """:class:`WheelReadings` from a log's front-laser scans and ODOM readings in log order
    (``(kind, message)`` as :func:`read_tagged` yields them).  The log counts as ``rebased``
    when the first reading after at least 90 % of its scans (those followed by one before the
    next scan) sits at the scan's own odometry pose."""
    scan_at = [i for i, (k, _) in enumerate(tagged) if k != "ODOM"]
    odo_at = np.array([i for i, (k, _) in enumerate(tagged) if k == "ODOM"], int)
    odo = np.array([(m.x, m.y, m.theta) for k, m in tagged if k == "ODOM"],
                   float).reshape(-1, 3)
    t_odo = np.array([m.stamp_ns for k, m in tagged if k == "ODOM"], np.int64)
    n = len(scan_at)
    # per scan: the last reading before its line and the first after it (-1 / len: none)
    before = np.searchsorted(odo_at, scan_at) - 1
    after = before + 1
    nxt = np.append(scan_at[1:], len(tagged))
    follows = (after < len(odo_at)) & (odo_at[np.minimum(after, len(odo_at) - 1)] < nxt)
    own = np.array([m.pose_odom if m.pose_odom is not None else
                    (m.pose_ref if m.pose_ref is not None else (np.nan,) * 3)
                    for k, m in tagged if k != "ODOM"], float).reshape(-1, 3)
    first = odo[np.minimum(after, len(odo) - 1)] if len(odo) else np.full((n, 3), np.nan)
    d = np.abs(first - own)
    d[:, 2] = np.abs(_wrap(d[:, 2]))
    at_pose = follows & (d.max(axis=1) <= REBASE_TOL)
    rebased = bool(follows.sum() and at_pose.sum() >= 0.9 * follows.sum())
    at = np.full((n, 3), np.nan)
    has = before >= 0
    if rebased:  # a reading older than the scan before counts from another rebase
        prev = np.append(-1, scan_at[:-1])
        has &= odo_at[np.maximum(before, 0)] > prev
    at[has] = odo[before[has]]
    t_scan = np.array([tagged[i][1].stamp_ns for i in scan_at], np.int64)
    # (a log whose stamps are too coarse to tell its scans apart says nothing of time)
    timely = (has & (np.abs(t_odo[np.maximum(before, 0)] - t_scan) <= 1_000_000)
              & np.append(True, np.diff(t_scan) != 0))
    if rebased:
        start = np.where((follows & at_pose)[:, None], first, at)
        return WheelReadings(at, start, True, len(odo), _share(timely[1:]))
    # raw odometry: between the readings around the scan by time, where their stamps allow
    both = has & (after < len(odo))
    k = np.flatnonzero(both)
    t0, t1 = t_odo[before[k]], t_odo[after[k]]
    ok = (t1 > t0) & (t0 <= t_scan[k]) & (t_scan[k] <= t1)
    k, t0, t1 = k[ok], t0[ok], t1[ok]
    w = ((t_scan[k] - t0) / (t1 - t0))[:, None]
    p0, p1 = odo[before[k]], odo[after[k]]
    step = p1 - p0
    step[:, 2] = _wrap(step[:, 2])
    at[k] = p0 + w * step
    timely[k] = True
    return WheelReadings(at, at.copy(), False, len(odo), _share(timely[1:]))


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _share(flags: np.ndarray) -> float:
    return round(float(flags.mean()), 4) if len(flags) else 1.0


class RepeatIndex:
    """A log's ROBOTLASER1 scans by time, to tell the FLASER lines that repeat them: some
    loggers write each scan twice, and mapped twice each scan would be matched against
    itself.  A repeat has the same beam count, a stamp within ``tol_ns``, its finite ranges
    within ``tol_m`` (the two lines may round differently) and its no-returns in the same
    beams; a FLASER scan of another laser, or of another time, is none."""

    def __init__(self, robot_scans: Iterable[LaserScan], tol_ns: int = 1_000_000,
                 tol_m: float = 0.011):
        self.tol_ns, self.tol_m = tol_ns, tol_m
        self._by: dict[int, list[tuple[int, np.ndarray]]] = {}
        for s in robot_scans:  # float32 copies: a long log's ranges, kept only for this
            self._by.setdefault(s.stamp_ns // tol_ns, []).append(
                (s.stamp_ns, np.asarray(s.ranges, np.float32)))

    def repeats(self, kind: str, scan: LaserScan) -> bool:
        """Whether ``scan``, read from a ``kind`` line, is a FLASER copy of a ROBOTLASER1 one."""
        if kind != "FLASER":
            return False
        k = scan.stamp_ns // self.tol_ns
        r = np.asarray(scan.ranges, np.float32)
        for t, other in (*self._by.get(k - 1, ()), *self._by.get(k, ()),
                         *self._by.get(k + 1, ())):
            if (abs(t - scan.stamp_ns) <= self.tol_ns and len(other) == len(r)
                    and np.array_equal(np.isnan(other), np.isnan(r))
                    and np.nanmax(np.abs(other - r), initial=0.0) <= self.tol_m):
                return True
        return False


SATURATION_TOL = 0.0051  # readings this close below the top count as it (cm-rounded logs)


def saturation_range(scans: Iterable[LaserScan], min_share: float = 0.002,
                     min_count: int = 20, min_scans: int = 10) -> float | None:
    """The reading a log's sensor gives for "no return", when the logger kept it as a range:
    the largest reading, if at least ``min_share`` of all beams (and ``min_count``) sit at it
    in a log of ``min_scans`` or more.  One pass over ``scans`` (a list or a stream).

    A SICK LMS in its 8 m mode reports 8.18 m, and some loggers keep such values (or clip to
    their own maximum) where others write 81.83 or 0.  Taken as points, they draw an arc
    around the robot that travels with it: split-and-merge cuts it into metre-long chords,
    walls that match every scan wherever it is.  Real surfaces do not repeat the log's
    maximum to the centimetre: on the Intel log it occurs once in 163 800 beams.
    None when no reading repeats like that."""
    top, at_top, beams, finite, n = -math.inf, 0, 0, 0, 0
    for s in scans:
        r = s.ranges[np.isfinite(s.ranges)]
        n, beams, finite = n + 1, beams + len(s.ranges), finite + len(r)
        if not len(r):
            continue
        m = float(r.max())
        if m > top + SATURATION_TOL:  # a new top: what sat at the old one was readings
            top, at_top = m, 0
        top = max(top, m)
        at_top += int(np.count_nonzero(r >= top - SATURATION_TOL))
    if (n < min_scans  # a handful of scans (a test, a snippet) shows no pattern
            or at_top < max(min_count, min_share * beams)
            or finite - at_top < min_count):  # and real readings besides
        return None
    return top


def drop_saturated(scan: LaserScan, limit: float) -> int:
    """Readings of ``scan`` at the saturation value ``limit`` to NaN (in place); how many."""
    hit = scan.ranges >= limit - SATURATION_TOL
    scan.ranges[hit] = np.nan
    scan.range_max = min(scan.range_max, limit)
    return int(hit.sum())


# Written for "no return": the 80 m mode's saturation value, which readers treat as such.
NO_RETURN = 81.91


def flaser_line(scan: LaserScan) -> str:
    """One old-format FLASER line (with its newline) for ``scan``: ranges in metres (NaN as
    :data:`NO_RETURN`), the reference and odometry poses (``pose_ref`` / ``pose_odom``, each
    standing in for the other when only one is set) and the stamp as both timestamps.
    ValueError when the scan does not span 180° from -90° as FLASER implies, or has no pose."""
    n = len(scan.ranges)
    a0, inc = beam_geometry(n)
    if abs(scan.angle_min - a0) > 1e-6 or abs(scan.angle_increment - inc) > 1e-9:
        raise ValueError(f"FLASER implies {n} beams from -90 deg every {math.degrees(inc):g} "
                         f"deg; this scan starts at {math.degrees(scan.angle_min):g} deg "
                         f"every {math.degrees(scan.angle_increment):g} deg")
    ref = scan.pose_ref if scan.pose_ref is not None else scan.pose_odom
    odo = scan.pose_odom if scan.pose_odom is not None else scan.pose_ref
    if ref is None:
        raise ValueError("FLASER needs a pose: the scan has neither pose_ref nor pose_odom")
    r = np.where(np.isfinite(scan.ranges), scan.ranges, NO_RETURN)
    t = f"{scan.stamp_ns * 1e-9:.6f}"
    poses = " ".join(f"{v:.6f}" for v in (*ref, *odo))
    return f"FLASER {n} {' '.join(f'{v:.3f}' for v in r)} {poses} {t} cgamap {t}\n"


def robotlaser_line(scan: LaserScan, robot_pose=None, max_range: float = NO_RETURN) -> str:
    """One ROBOTLASER1 line (with its newline) for ``scan``: its own beam geometry, NaN
    ranges as ``max_range`` (the line's maximum, so they read back as no return), no
    remissions, ``pose_ref`` as the laser pose and ``robot_pose`` (default ``pose_odom``,
    else the laser pose) as the robot's.  ValueError when the scan has no pose."""
    laser = scan.pose_ref if scan.pose_ref is not None else scan.pose_odom
    if laser is None:
        raise ValueError("ROBOTLASER1 needs a pose: the scan has neither pose_ref nor pose_odom")
    robot = robot_pose if robot_pose is not None else (
        scan.pose_odom if scan.pose_odom is not None else laser)
    n = len(scan.ranges)
    r = np.where(np.isfinite(scan.ranges), scan.ranges, max_range)
    t = f"{scan.stamp_ns * 1e-9:.6f}"
    head = (f"ROBOTLASER1 0 {scan.angle_min:.6f} {scan.angle_increment * max(n - 1, 1):.6f} "
            f"{scan.angle_increment:.9f} {max_range:.2f} 0.01 0 {n}")
    poses = " ".join(f"{v:.6f}" for v in (*laser, *robot))
    return (f"{head} {' '.join(f'{v:.3f}' for v in r)} 0 {poses} 0 0 0 0 0 {t} cgamap {t}\n")


def write_carmen(path: str | Path, scans, kind: str = "FLASER", robot_poses=None) -> int:
    """Write ``scans`` as an old-format CARMEN log (one ``kind`` line each: FLASER or
    ROBOTLASER1, the latter with ``robot_poses`` (n, 3) as the robot's when given), after a
    format comment, to be read back by :func:`read_carmen`; returns the lines written."""
    if kind == "FLASER":
        body = [flaser_line(s) for s in scans]
    elif kind == "ROBOTLASER1":
        robots = [None] * len(scans) if robot_poses is None else list(robot_poses)
        body = [robotlaser_line(s, r) for s, r in zip(scans, robots, strict=True)]
    else:
        raise ValueError(f"write_carmen: kind must be FLASER or ROBOTLASER1, got {kind!r}")
    lines = [f"# message formats defined: {kind}\n", *body]
    Path(path).write_text("".join(lines), encoding="ascii")
    return len(lines) - 1
