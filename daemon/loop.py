"""The mapping loop: time-aligned fusion of the device messages into the 2D and 3D maps.

Single-threaded by design (the service calls it from its main loop): odometry poses are kept
in a short history and interpolated to each scan's timestamp (DESIGN eqs. 10-11: the scan's
odometry guess, corrected by matching); the pan-tilt state nearest each stereo frame sets its
camera chain; the 3D pipeline runs per frame at its own rate.  When the match quality stays
below ``lost_quality`` for ``lost_after`` scans, relocalisation in the Hough domain is tried:
first within ``lost_radius`` of the pose the robot had (a slip or a push seldom moves it
far, and a look-alike place elsewhere is then no rival), then over the whole map.
Everything here is plain data in, plain data out; the mapping maths lives in ``mapping``.
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import fields
from typing import Any

import numpy as np
from cgamap.drivers.messages import LaserScan, OdometryPose, PanTiltState, WheelTicks
from cgamap.mapping import planemap
from cgamap.mapping.odometry import WheelGeometry, compose_pose2d, ticks_to_increment, wrap_angle
from cgamap.mapping.posegraph import relative

from .config import mapper_params, params3d

log = logging.getLogger(__name__)


class PoseHistory:
    """A bounded history of timestamped planar poses, interpolated at any stamp."""

    def __init__(self, maxlen: int = 4096):
        self.items: collections.deque = collections.deque(maxlen=maxlen)

    def add(self, stamp_ns: int, pose) -> None:
        if self.items and stamp_ns < self.items[-1][0]:
            return  # out of order: the history stays monotonic
        self.items.append((int(stamp_ns), np.asarray(pose, dtype=float)))

    def __len__(self) -> int:
        return len(self.items)

    @property
    def latest(self) -> tuple[int, np.ndarray] | None:
        return self.items[-1] if self.items else None

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """Pose at ``stamp_ns``: linear in x, y and (wrap-aware) theta between neighbours;
        the end value outside the covered span."""
        if not self.items:
            return None
        i = bisect.bisect_left(self.items, stamp_ns, key=lambda item: item[0])
        if i == 0:
            return self.items[0][1].copy()
        if i >= len(self.items):
            return self.items[-1][1].copy()
        (t0, p0), (t1, p1) = self.items[i - 1], self.items[i]
        f = (stamp_ns - t0) / max(t1 - t0, 1)
        d = p1 - p0
        d[2] = wrap_angle(d[2])
        out = p0 + f * d
        out[2] = wrap_angle(out[2])
        return out


class WheelOdometry:
    """Integrates wheel ticks into an odometry pose with ``mapping.odometry``."""

    def __init__(self, params: dict):
        known = {f.name for f in fields(WheelGeometry)}
        alias = {"track": "track_width"}
        kw = {alias.get(k, k): v for k, v in params.items() if alias.get(k, k) in known}
        self.geom = WheelGeometry(**kw)
        self.pose = np.zeros(3)
        self.last: tuple[int, int] | None = None

    def update(self, t: WheelTicks) -> np.ndarray:
        if self.last is not None:
            inc = ticks_to_increment(t.left - self.last[0], t.right - self.last[1], self.geom)
            self.pose = compose_pose2d(self.pose, inc)
        self.last = (t.left, t.right)
        return self.pose.copy()


# -- the 2D mapper adapter ------------------------------------------------------------------

# relocalisation: another place scoring within this of the best makes the answer ambiguous
# (the fraction of scan points on map walls); a lost robot does not jump to such a pose
RELOC_AMBIGUITY = 0.05
RELOC_RIVALS = 4  # rivals reported with an answer
# a lost robot's first try: within this turn of its pose, and a pose found there must fit
# this share of the scan.  Measured (``bench_relocalize_hint`` and the Intel seed-0 map, 150
# scans): with the hint about 1 m / 10 deg off, right answers score 0.89 or more (5th
# percentile); with it 10 m off (a robot carried away), 26 of 150 Intel scans still fit
# something near it, 3 of them at 0.8 or more
LOST_TURN = np.deg2rad(30.0)
LOST_SCORE = 0.8


class MapReplaced(RuntimeError):
    """A finishing pass computed for a mapper that was replaced meanwhile (checkpoint load)."""


class Mapper2D:
    """``mapping.slam2d.Mapper`` behind a small interface: step, segments, state, set_pose.

    The mapper reports laser poses; this adapter hands base poses to the daemon.  Setting the
    pose re-anchors the mapper: its next scan starts a new chain at the given pose."""

    def __init__(self, mount: tuple[float, float, float] | None, params: dict):
        from cgamap.mapping.finishing import NeighbourParams
        from cgamap.mapping.slam2d import Mapper, MapperParams

        # a daemon runs for months: the pose graph keeps its newest nodes (params2d.max_nodes);
        # it never finishes: the finishing pass runs on demand (``optimize``), so the mapper's
        # own pass stays off while it keeps each kept node's segments for it (they are
        # compacted away with their nodes)
        base = MapperParams(mount=mount, neighbours=NeighbourParams(enabled=False),
                            max_nodes=20_000)
        P = mapper_params(params, base=base)
        self._make = lambda pose: Mapper(P, initial_pose=pose)
        self.m = self._make((0.0, 0.0, 0.0))
        self.m.keep_scans = True
        self.node_stamps: collections.deque = collections.deque()  # scan stamp per graph node
        self._pose = np.zeros(3)
        self._field = None       # the map's distance field for relocalisation, and the
        self._field_key = None   # (map, scans, segments) it was built for

    @property
    def pose(self) -> np.ndarray:
        return self._pose.copy()

    @property
    def slips(self) -> int:
        """Scans the mapper found again after the odometry had put them out of reach."""
        return self.m.slips

    @property
    def cleared(self) -> int:
        """Map segments the mapper dropped because later scans saw through them."""
        return self.m.cleared

    @property
    def moved(self) -> int:
        """Scan segments the mapper left out: where a scan a moment earlier saw through."""
        return self.m.moved

    def step(self, scan: LaserScan, odom) -> tuple[np.ndarray, float | None, int]:
        added = self.m.count + self.m.dropped
        try:
            res = self.m.step(scan.ranges, scan.angle_min, scan.angle_increment, odom)
        finally:  # a step that failed after adding its node still numbers it
            self.node_stamps.extend([scan.stamp_ns] * (self.m.count + self.m.dropped - added))
            while len(self.node_stamps) > self.m.count:  # compacted nodes
                self.node_stamps.popleft()
        q = None if res.correction is None else float(res.correction.matched_fraction)
        self._pose = self.m.base_pose(res.pose)
        return self._pose.copy(), q, int(res.segments)

    def segments(self) -> np.ndarray:
        lm = self.m.map
        if not len(lm):
            return np.zeros((0, 4))
        return np.concatenate([lm.a, lm.b], axis=1)

    def set_pose(self, pose) -> None:
        self._pose = np.asarray(pose, dtype=float)
        self.m.initial = self._pose.copy()
        self.m.last_odom = None

    def state(self) -> dict:
        lm = self.m.map
        return {"map": {f.name: getattr(lm, f.name) for f in fields(lm)}, "pose": self._pose}

    def load_state(self, st: dict) -> None:
        from cgamap.mapping.linemap import LineMap

        names = {f.name for f in fields(LineMap)}
        self._pose = np.asarray(st["pose"], dtype=float)
        self.m = self._make(tuple(self._pose))
        self.m.keep_scans = True
        self.node_stamps.clear()
        self.m.map = LineMap(**{k: v for k, v in st["map"].items() if k in names})

    def optimize_job(self) -> Any:
        """The finishing pass on a snapshot of the kept nodes
        (``Mapper.live_finishing_job``)."""
        return self.m.live_finishing_job()

    def apply_optimize(self, job: Any) -> dict:
        """Adopt a computed job; a mapper replaced meanwhile (checkpoint load) ignores it."""
        if job.source is not self.m:
            raise MapReplaced("the map was replaced while optimising; nothing applied")
        out = self.m.apply_finish(job)
        if self.m.count and self.m.last_odom is not None:  # not re-anchored since its scan
            self._pose = self.m.base_pose(self.m.pose)  # the last node's, or tracked from it
        return out

    def node_poses(self) -> dict[int, np.ndarray]:
        """Base pose of each kept graph node by its scan's stamp."""
        if not self.m.count:
            return {}
        base = self.m.base_pose(self.m.poses)
        return dict(zip(self.node_stamps, base, strict=True))

    def relocalize(self, scan: LaserScan, near: tuple | None = None
                   ) -> tuple[np.ndarray, float, list] | None:
        """Global pose of ``scan`` in the map by Hough-domain relocalisation, its score and
        its rivals (look-alike places scoring within ``RELOC_AMBIGUITY``, as (base pose,
        score)), or None.  ``near``: (base pose, metres, radians), a hint (someone says
        roughly where the robot is): only poses that close to it are considered."""
        from cgamap.mapping.relocalize import DistanceField, RelocParams, relocalize, rivals
        from cgamap.mapping.segments import extract_segments

        seg = extract_segments(scan.ranges, scan.angle_min, scan.angle_increment,
                               self.m.params.segments)
        if len(seg) < 1 or len(self.m.map) < 2:  # one line: the correlative sweep places it
            return None
        # the map's distance field (~25 ms on a building) is kept while the map is unchanged:
        # a lost robot retries on every scan
        key = (id(self.m.map), self.m.count, len(self.m.map))
        if self._field_key != key:
            self._field = DistanceField(self.m.map, RelocParams().field_resolution)
            self._field_key = key
        prior = None if near is None else (self.m.laser_pose(near[0]), near[1], near[2])
        res = relocalize(self.m.map, seg, self._field, near=prior)
        if not res.found or res.pose is None:
            return None
        alts = rivals(res.hypotheses, res.hypotheses[0], RELOC_AMBIGUITY, 0.5)
        return (self.m.base_pose(res.pose), float(res.score),
                [(self.m.base_pose(h.pose), float(h.score)) for h in alts[:RELOC_RIVALS]])


# -- the 3D plane map ---------------------------------------------------------------------


class PlaneMap:
    """``mapping.planemap.PlaneMap`` (planes merged across frames, as CGA entities) behind
    the loop's small interface; checkpoints hold it under ``"planemap"``."""

    def __init__(self):
        self.m = planemap.PlaneMap()

    @property
    def planes(self) -> list:
        return self.m.planes

    def integrate(self, detected: list) -> int:
        return len(self.m.add_planes(detected))

    def as_list(self) -> list[dict]:
        out = []
        for mp in self.m.planes:
            d = mp.to_dict()
            d.pop("extent", None)
            d.pop("cga", None)
            out.append(d)
        return out

    def state(self) -> dict:
        return {"planemap": self.m.to_dict()}

    def load_state(self, st) -> None:
        if isinstance(st, dict) and "planemap" in st:
            self.m = planemap.PlaneMap.from_dict(st["planemap"])
        elif isinstance(st, dict) and "simple" in st:
            self.m = planemap.PlaneMap.from_dict(planemap_from_simple(st["simple"]))


def planemap_from_simple(simple: list[dict]) -> dict:
    """Migrate a checkpoint of the stand-in map older builds used without OpenCV (``"simple"``:
    normal, rho, area, corners, observations per plane) into the ``PlaneMap.to_dict`` layout;
    its corner quad becomes the extent."""
    planes = []
    for i, q in enumerate(simple):
        corners = np.asarray(q["corners"], float).reshape(-1, 3)
        planes.append({"id": i, "normal": np.asarray(q["normal"], float), "rho": float(q["rho"]),
                       "extent": corners, "corners": corners,
                       "observations": int(q.get("observations", 1))})
    return {"planes": planes}


# -- the loop -------------------------------------------------------------------------------


def configured_mount(devices: dict) -> tuple[float, float, float] | None:
    """The laser device's mount (x, y, yaw) in the base frame, None without a laser."""
    laser = next((d for d in devices.values() if d["role"] == "laser"), None)
    if laser is None:
        return None
    mt = laser["mount"]
    return (mt["x"], mt["y"], mt["yaw"])


class MappingLoop:
    """Fuses device messages; ``status()``, ``map_json()``, ``state()`` for the service."""

    def __init__(self, cfg: dict, mapper2d: Any | None = None, devices: dict | None = None,
                 laser_mount: tuple[float, float, float] | None = None,
                 lossless: bool = False):
        """``laser_mount`` (x, y, yaw), when given, replaces the laser device's configured
        mount (a replayed log states its own).  ``lossless``: a scan that finds the queue
        of waiting scans full maps the oldest first instead of dropping it (a replay as fast
        as the mapper goes: a log of scans alone arrives hundreds at a time)."""
        m = cfg["mapping"]
        self.cfg = cfg
        self.lossless = lossless
        self.lost_quality = m["lost_quality"]
        self.lost_after = m["lost_after"]
        self.lost_radius = m["lost_radius"]
        self.period3d_ns = int(1e9 / m["rate3d"])
        self.min_travel, self.min_turn = m["min_travel"], m["min_turn"]
        self.scan_period_ns = int(1e9 / m["scan_max_rate"])
        devices = devices if devices is not None else cfg["devices"]
        self.roles = {name: d["role"] for name, d in devices.items()}
        mount = configured_mount(devices)
        if laser_mount is not None:
            mount = tuple(float(v) for v in laser_mount)
        if mount is not None and not any(mount):
            mount = None
        self.laser_mount = mount
        self.mapper = mapper2d
        if self.mapper is None and m["map2d"]:
            try:
                self.mapper = Mapper2D(mount, m["params2d"])
            except ImportError as exc:
                log.warning("2D mapper unavailable (%s): no 2D map", exc)
        odom_dev = next((d for d in devices.values() if d["role"] == "odometry"), None)
        self.wheels = None
        if odom_dev is not None and odom_dev["model"] == "modbus-base":
            self.wheels = WheelOdometry({**odom_dev["params"], **m["odometry"]})
        head = next((d for d in devices.values() if d["role"] == "pantilt"), None)
        self.camera_mount = None
        if head is not None:
            H = head.get("head_T_cam")
            if H:  # a hand-eye calibration: the camera's offset and its rotation
                self.camera_mount = {"t_axis": tuple(head["axis_point"]),
                                     "t_eye": tuple(r[3] for r in H[:3]),
                                     "R_eye": tuple(tuple(r[:3]) for r in H[:3])}
            else:
                self.camera_mount = {"t_axis": tuple(head["axis_point"]),
                                     "t_eye": tuple(head["eye_offset"])}
        self.map3d_enabled = bool(m["map3d"])
        # checked when the config was loaded; built once, not per frame
        self.frames3d, self.plane_params = params3d(m["params3d"])
        self.planes = PlaneMap()
        self.odom = PoseHistory()
        self.pantilt: collections.deque = collections.deque(maxlen=256)
        self.pending: collections.deque = collections.deque(maxlen=64)
        self.scan_poses = PoseHistory(8192)       # corrected pose per processed scan
        self.trajectory: collections.deque = collections.deque(maxlen=100_000)
        self.last_scan_odom: np.ndarray | None = None
        self.pose = np.zeros(3)
        self.pose_stamp_ns = 0
        self.quality: float | None = None
        self.low_quality_run = 0
        self.lost = False
        self.counts = collections.Counter()
        self.last_3d_ns: int | None = None
        self.rates: dict[str, collections.deque] = collections.defaultdict(
            lambda: collections.deque(maxlen=50))
        self.events: collections.deque = collections.deque(maxlen=256)
        self.event_seq = 0
        self.map_version = 0
        self.timing = {"scan_ms": 0.0, "frame_ms": 0.0}
        self._last_scan: LaserScan | None = None
        self._map_segments = 0
        self.odometry_expected = odom_dev is not None
        self.scan_odometry = False
        # scans older than the first odometry sample wait for it (skipped), for no longer
        # than the devices get to start: see _before_odometry
        self.odometry_wait_ns = int(1e9 * cfg.get("supervisor", {}).get("ready_timeout", 10.0))
        self._first_scan_ns: int | None = None
        self._first_odom_ns: int | None = None
        self._optimize_job: Any = None  # the finishing pass being computed, if any
        self._optimize_t0 = 0.0
        self.last_optimize: dict | None = None

    # -- inputs ---------------------------------------------------------------------------
    def handle(self, name: str, msg: Any) -> None:
        if isinstance(msg, OdometryPose):
            if not self.scan_odometry:
                self.on_odometry(msg.stamp_ns, (msg.x, msg.y, msg.theta))
        elif isinstance(msg, WheelTicks):
            if self.wheels is None:
                self.wheels = WheelOdometry(self.cfg["mapping"]["odometry"])
            self.on_odometry(msg.stamp_ns, self.wheels.update(msg))
        elif isinstance(msg, LaserScan):
            self.counts["scans_in"] += 1
            if msg.pose_odom is not None:
                # a log's scan carries the odometry of its own instant (CARMEN FLASER): better
                # than interpolating, and the log's separate ODOM lines are then ignored
                self.scan_odometry = True
                self.on_odometry(msg.stamp_ns, msg.pose_odom)
            if len(self.pending) == self.pending.maxlen:
                if self.lossless:     # in log order: the oldest's odometry is in
                    self._guarded("scan", self.on_scan, self.pending.popleft())
                else:
                    self.counts["scans_dropped"] += 1  # the oldest waiting scan goes
            self.pending.append(msg)
        elif isinstance(msg, PanTiltState):
            self.pantilt.append(msg)
        elif hasattr(msg, "calib") and hasattr(msg, "stamp_ns"):
            self._guarded("frame", self.on_frame, msg)
        self.rates[name].append(time.monotonic())

    def _guarded(self, what: str, fn, msg: Any) -> None:
        """A failing mapping step loses that one message, never the daemon: counted, and
        logged with its traceback the first time (then every 100th time)."""
        try:
            fn(msg)
        except Exception:  # noqa: BLE001 - the maps so far stay served
            key = f"errors_{what}"
            self.counts[key] += 1
            if self.counts[key] % 100 == 1:
                log.exception("%s pipeline failed (%d so far)", what, self.counts[key])

    def on_odometry(self, stamp_ns: int, pose) -> None:
        self.counts["odometry"] += 1
        if self._first_odom_ns is None:
            self._first_odom_ns = int(stamp_ns)
        self.odom.add(stamp_ns, pose)

    def process(self, final: bool = False, odometry_live: bool = True) -> int:
        """Run the scans whose odometry is in (or that cannot wait longer); returns how many.

        A scan waits until odometry newer than it has arrived, so its guess is interpolated,
        not extrapolated; it stops waiting when a later scan is queued behind it, when no
        odometry source is live, or at the end of a replay."""
        done = 0
        while self.pending:
            scan = self.pending[0]
            latest = self.odom.latest
            ready = (final or not odometry_live or len(self.pending) > 1
                     or (latest is not None and latest[0] >= scan.stamp_ns))
            if not ready:
                break
            self.pending.popleft()
            self._guarded("scan", self.on_scan, scan)
            done += 1
        return done

    def odom_guess(self, stamp_ns: int) -> np.ndarray:
        p = self.odom.at(stamp_ns)
        return np.zeros(3) if p is None else p

    def on_scan(self, scan: LaserScan) -> None:
        t0 = time.perf_counter()
        self._last_scan = scan
        if self._before_odometry(scan):
            self.counts["scans_before_odometry"] += 1
            return
        if self.pose_stamp_ns and scan.stamp_ns < self.pose_stamp_ns:
            # a clock that went back (or a log whose stamps do): never mapped out of order,
            # counted apart from the rate limit's skips, said at the 1st, 2nd, 4th, ... time
            self.counts["scans_skipped"] += 1
            self.counts["scans_out_of_order"] += 1
            n = self.counts["scans_out_of_order"]
            if n & (n - 1) == 0:
                log.warning("scan stamped %.3f s before the last mapped one: skipped (%d so far)",
                            (self.pose_stamp_ns - scan.stamp_ns) / 1e9, n)
            return
        odom = self.odom_guess(scan.stamp_ns)
        if self._skip(scan, odom):
            self.counts["scans_skipped"] += 1
            return
        if self.mapper is None:
            # no 2D mapper: the pose follows odometry alone
            if self.last_scan_odom is not None:
                self.pose = compose_pose2d(self.pose, relative(self.last_scan_odom, odom))
            q, nseg = None, 0
        else:
            slips, cleared = self.mapper.slips, self.mapper.cleared
            moved = self.mapper.moved
            self.pose, q, nseg = self.mapper.step(scan, odom)
            if self.mapper.slips > slips:
                # the odometry put this scan beyond the correction's reach (wheel slip, a
                # push): found again from the walls (mapping.slip)
                self.counts["slips_recovered"] += 1
            if self.mapper.cleared > cleared:
                # map segments later scans saw through (mapping.free_space)
                self.counts["segments_cleared"] += self.mapper.cleared - cleared
            if self.mapper.moved > moved:
                # people and carts on the move, not mapped (mapping.moving)
                self.counts["segments_moving"] += self.mapper.moved - moved
        self.last_scan_odom = odom
        self.pose_stamp_ns = scan.stamp_ns
        self.scan_poses.add(scan.stamp_ns, self.pose)
        self.counts["scans"] += 1
        self.quality = q
        dev = -1 if scan.device_stamp is None else scan.device_stamp
        self.trajectory.append((scan.stamp_ns, dev, *map(float, self.pose),
                                -1.0 if q is None else q))
        self._track_quality(q, scan)
        self.map_version += 1
        self.timing["scan_ms"] = 0.9 * self.timing["scan_ms"] + 100 * (time.perf_counter() - t0)
        self._event("pose", {"pose": self.pose_list(), "quality": q, "segments": nseg})
        n_map = len(self.segments())
        if n_map != self._map_segments:
            self._map_segments = n_map
            self._event("map", {"segments": n_map, "version": self.map_version})

    def _before_odometry(self, scan: LaserScan) -> bool:
        """Whether ``scan`` predates the odometry: a scan older than the first odometry sample
        has no guess (the history would give it that later sample's pose), so the motion until
        then would be missing from the map's first steps, their walls left behind as ghosts --
        the laser streams before the base answers when the daemon starts, the more so on a
        busy machine.  While odometry is expected such scans are not mapped, but only for
        ``supervisor.ready_timeout`` of scans with no odometry at all: a base that never
        answers must not stop the map."""
        if not self.odometry_expected or self.scan_odometry:
            return False
        if self._first_scan_ns is None:
            self._first_scan_ns = scan.stamp_ns
        if self._first_odom_ns is None:
            return scan.stamp_ns - self._first_scan_ns < self.odometry_wait_ns
        return scan.stamp_ns < self._first_odom_ns

    def _skip(self, scan: LaserScan, odom: np.ndarray) -> bool:
        """Skip a scan taken too soon after the last mapped one, or with no motion since."""
        if self.last_scan_odom is None or not self.pose_stamp_ns:
            return False
        if scan.stamp_ns - self.pose_stamp_ns < self.scan_period_ns:
            return True
        if not len(self.odom):
            return False  # no odometry: motion unknown, map at the rate limit
        d = relative(self.last_scan_odom, odom)
        moved = np.hypot(d[0], d[1]) >= self.min_travel or abs(d[2]) >= self.min_turn
        return not moved and scan.stamp_ns - self.pose_stamp_ns < 20 * self.scan_period_ns

    def _track_quality(self, q: float | None, scan: LaserScan) -> None:
        if q is None:
            return
        if q < self.lost_quality:
            self.low_quality_run += 1
        else:
            self.low_quality_run = 0
            self.lost = False
        if self.low_quality_run >= self.lost_after:
            self.lost = True
            self.low_quality_run = 0
            self.counts["lost"] += 1
            log.warning("match quality below %.2f for %d scans: relocalising",
                        self.lost_quality, self.lost_after)
            if self.lost_radius > 0:
                near = (self.current_pose(), self.lost_radius, LOST_TURN)
                if self.relocalize(scan, jump_if_ambiguous=False, near=near,
                                   min_score=LOST_SCORE)["ok"]:
                    self.counts["relocalized_near"] += 1
                    return
            self.relocalize(scan, jump_if_ambiguous=False)

    def relocalize(self, scan: LaserScan | None = None, jump_if_ambiguous: bool = True,
                   near: tuple | None = None, min_score: float = 0.0) -> dict:
        """Relocalise on ``scan`` (default: the last processed one).  The answer names the
        look-alike places (``alternatives``: x, y, theta, score) and says ``ambiguous`` when
        there are any; with ``jump_if_ambiguous`` false (a lost robot's own attempt) such an
        answer leaves the pose alone: the robot moves on and tries again.  ``near``: (base
        pose, metres, radians), a hint: only poses within that distance and turn of it;
        ``min_score``: a pose fitting less of the scan is no answer."""
        self.counts["relocalize_tries"] += 1
        if self.mapper is None or not hasattr(self.mapper, "relocalize"):
            return {"ok": False, "error": "no 2D mapper"}
        scan = scan or self._last_scan
        if scan is None:
            return {"ok": False, "error": "no scan yet"}
        res = self.mapper.relocalize(scan, near=near)
        if res is None:
            return {"ok": False, "error": "relocalisation found no pose"
                    + ("" if near is None else " near the hint")}
        pose, score, rivals = res
        if score < min_score:
            return {"ok": False, "error": f"relocalisation fits {score:.2f} of the scan, "
                    f"under {min_score:.2f}", "score": score}
        alts = [[*map(float, p), round(sc, 4)] for p, sc in rivals]
        if alts and not jump_if_ambiguous:
            self.counts["relocalize_ambiguous"] += 1
            return {"ok": False, "error": "relocalisation is ambiguous (look-alike places)",
                    "ambiguous": True, "pose": [*map(float, pose)], "score": score,
                    "alternatives": alts}
        self.set_pose(pose, reason="relocalize")
        self.counts["relocalized"] += 1
        return {"ok": True, "pose": self.pose_list(), "score": score, "ambiguous": bool(alts),
                "alternatives": alts}

    # -- the finishing pass on demand ------------------------------------------------------
    # Computed on a snapshot, applied between scans: the pass over 20 000 nodes takes seconds
    # to minutes, and the scans must keep flowing meanwhile.  A time budget in the map thread
    # would cut the pass short (half a pass leaves the graph with some neighbour edges and
    # not others); a snapshot needs only copies of the graph's lists and the kept scans'
    # segments (no copy of arrays), the computation touches nothing the map thread changes,
    # and the apply step (index shift for compacted nodes, poses, map rebuild) is bounded by
    # the graph and map sizes.  Scans mapped meanwhile follow the newest snapshot node.
    def optimize_begin(self) -> Any:
        """Snapshot for the finishing pass (call under the loop's lock); ValueError when
        one is already running or there is no mapper that keeps its scans."""
        if self._optimize_job is not None:
            raise ValueError("already running; wait for its reply")
        if self.mapper is None or not hasattr(self.mapper, "optimize_job"):
            raise ValueError("no 2D mapper")
        job = self.mapper.optimize_job()
        self._optimize_job, self._optimize_t0 = job, time.perf_counter()
        return job

    def optimize_end(self, job: Any) -> dict:
        """Apply a computed job (call under the loop's lock): the map follows the new poses
        (the next checkpoint saves it); returns the reply's figures."""
        if job is not self._optimize_job:
            raise ValueError("not the running optimisation")
        try:
            got = self.mapper.apply_optimize(job)
        finally:
            self._optimize_job = None
        if got["edges"]:
            self.pose = self.mapper.pose
            self.map_version += 1
            if hasattr(self.mapper, "node_poses"):
                self._retrace(self.mapper.node_poses())
        out = {"edges": int(got["edges"]), "nodes": int(got["nodes"]),
               "snapshot_nodes": int(job.nodes), "pairs": int(job.pairs),
               "sweep_edges": int(job.sweep_edges),
               "max_shift_m": round(float(got["max_shift_m"]), 4),
               "ms": round(1000 * (time.perf_counter() - self._optimize_t0), 1)}
        if getattr(job, "calibration", None):
            from cgamap.mapping.finishing import calibration_figures
            out["odometry_calibration"] = calibration_figures(job.calibration)
        self.counts["optimized"] += 1
        self.last_optimize = out
        self._event("optimize", dict(out))
        return out

    def _retrace(self, at: dict[int, np.ndarray]) -> None:
        """The kept nodes' new poses into the trajectory and the scan pose history (the
        newest rows, by scan stamp): ``trajectory`` and 3D frames see the optimised poses.
        A scan the mapper only tracked (no node of its own) moves with the node before it."""
        if not at:
            return
        oldest = min(at)

        def redo(dq: collections.deque, pose_of, make) -> None:
            tail = []
            while dq and dq[-1][0] >= oldest:
                tail.append(dq.pop())
            was = now = None  # the last node's pose before and after
            for row in reversed(tail):
                p = at.get(row[0])
                if p is not None:
                    was, now = pose_of(row), np.asarray(p, float)
                elif was is not None:
                    p = compose_pose2d(now, relative(was, pose_of(row)))
                dq.append(row if p is None else make(row, p))

        redo(self.trajectory, lambda r: np.array(r[2:5], float),
             lambda r, p: (r[0], r[1], *map(float, p), r[5]))
        redo(self.scan_poses.items, lambda r: np.asarray(r[1], float),
             lambda r, p: (r[0], np.asarray(p, float)))

    def optimize_abort(self, job: Any) -> None:
        """Forget a job that failed or was abandoned (call under the loop's lock)."""
        if job is self._optimize_job:
            self._optimize_job = None

    @property
    def optimizing(self) -> bool:
        return self._optimize_job is not None

    def optimize(self, lock: contextlib.AbstractContextManager | None = None,
                 stop: Callable[[], bool] | None = None,
                 stopping: str = "stop requested; nothing applied") -> dict:
        """The whole pass, for every caller: snapshot and apply under ``lock``, the
        computation outside it, so a map thread sharing the lock (the daemon's) keeps
        mapping meanwhile; no lock for a single-threaded caller (tests).  ``stop()`` true
        abandons the computation and applies nothing (ValueError ``stopping``).  ValueError
        also for a pass already running, no mapper, and a map replaced meanwhile; any
        exception of the computation forgets the job and propagates."""
        lock = contextlib.nullcontext() if lock is None else lock
        with lock:
            job = self.optimize_begin()
        try:
            job.run(stop=stop)
        except BaseException:
            with lock:
                self.optimize_abort(job)
            raise
        with lock:
            if stop is not None and stop():
                self.optimize_abort(job)
                raise ValueError(stopping)
            try:
                return self.optimize_end(job)
            except MapReplaced as exc:  # a checkpoint was loaded while the job ran
                raise ValueError(str(exc)) from None

    def set_pose(self, pose, reason: str = "set-pose") -> None:
        self.pose = np.asarray(pose, dtype=float)
        if self.mapper is not None:
            self.mapper.set_pose(self.pose)
        latest = self.odom.latest
        self.last_scan_odom = None if latest is None else latest[1].copy()
        # no odometry yet: no stamp to compare the next scan with (this clock's time is not
        # the scans' -- a replayed log's stamps are its own)
        self.pose_stamp_ns = 0 if latest is None else latest[0]
        self.lost = False
        self._event("pose", {"pose": self.pose_list(), "reason": reason})

    def on_frame(self, frame: Any) -> None:
        self.counts["frames_in"] += 1
        if not self.map3d_enabled:
            return
        if self.last_3d_ns is not None and frame.stamp_ns - self.last_3d_ns < self.period3d_ns:
            return
        self.last_3d_ns = frame.stamp_ns
        t0 = time.perf_counter()
        try:
            from cgamap.drivers.stereo import frame_points_global, nearest_pantilt
            from cgamap.drivers.stereo_points import CameraMount
            from cgamap.mapping.planes import detect_planes
        except ImportError as exc:
            log.warning("3D pipeline unavailable: %s", exc)
            self.map3d_enabled = False
            return
        if self.pantilt:
            frame.pantilt = nearest_pantilt(frame.stamp_ns, list(self.pantilt), 200_000_000)
        pose = self.pose_at(frame.stamp_ns)
        mount = CameraMount.from_dict(self.camera_mount) if self.camera_mount else None
        pts = frame_points_global(frame, mount, tuple(pose),
                                  max_depth=self.frames3d.max_depth,
                                  stride=self.frames3d.stride)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) < 200:
            return
        planes = detect_planes(pts, self.frames3d.method, self.plane_params)
        n = self.planes.integrate(planes)
        self.counts["frames"] += 1
        self.map_version += 1
        self.timing["frame_ms"] = 0.8 * self.timing["frame_ms"] + 200 * (time.perf_counter() - t0)
        self._event("planes", {"detected": len(planes), "merged": n,
                               "total": len(self.planes.planes)})

    def pose_at(self, stamp_ns: int) -> np.ndarray:
        """Best pose at ``stamp_ns``: the scan pose before it plus odometry since."""
        items = self.scan_poses.items
        if not items:
            return self.pose.copy()
        base_stamp, base_pose = items[-1]
        if stamp_ns < base_stamp:
            p = self.scan_poses.at(stamp_ns)
            return p if p is not None else self.pose.copy()
        o0, o1 = self.odom.at(base_stamp), self.odom.at(stamp_ns)
        if o0 is None or o1 is None:
            return base_pose.copy()
        return compose_pose2d(base_pose, relative(o0, o1))

    def current_pose(self) -> np.ndarray:
        """The pose now: last corrected scan pose plus the odometry since that scan."""
        latest = self.odom.latest
        if latest is None or self.last_scan_odom is None:
            return self.pose.copy()
        return compose_pose2d(self.pose, relative(self.last_scan_odom, latest[1]))

    def pose_list(self) -> list[float]:
        return [round(float(v), 5) for v in self.current_pose()]

    # -- outputs --------------------------------------------------------------------------
    def _event(self, kind: str, body: dict) -> None:
        self.event_seq += 1
        self.events.append({"class": kind, "seq": self.event_seq, **body})

    def rate(self, name: str) -> float:
        d = self.rates.get(name)
        if not d or len(d) < 2 or time.monotonic() - d[-1] > 5.0:
            return 0.0
        return (len(d) - 1) / max(d[-1] - d[0], 1e-6)

    def segments(self) -> np.ndarray:
        return self.mapper.segments() if self.mapper is not None else np.zeros((0, 4))

    def status(self) -> dict:
        return {"pose": self.pose_list(), "quality": self.quality, "lost": self.lost,
                "map": {"segments": len(self.segments()), "planes": len(self.planes.planes),
                        "version": self.map_version},
                "counts": dict(self.counts), "pending_scans": len(self.pending),
                "timing_ms": {k: round(v, 2) for k, v in self.timing.items()},
                "optimize": {"running": self.optimizing, "last": self.last_optimize},
                "laser_mount": None if self.laser_mount is None else [
                    round(float(v), 5) for v in self.laser_mount]}

    def map_json(self) -> dict:
        seg = self.segments()
        return {"frame": "map", "pose": self.pose_list(),
                "segments": np.round(seg, 4).tolist(), "planes": self.planes.as_list(),
                "configurations": self.configurations(), "version": self.map_version}

    def configurations(self) -> list[dict]:
        """Corridors, stairways, doorways, workplaces among the map's planes (PRL figures),
        indices into ``planes``; empty when the module or the planes are not there."""
        if not self.planes.planes:
            return []
        try:
            from cgamap.mapping.configurations import find_configurations

            found = find_configurations(self.planes.planes)
        except Exception:  # noqa: BLE001 - an optional summary must not break `map`
            log.exception("configurations failed")
            return []
        return [{"kind": c.kind, "planes": [int(i) for i in c.planes], "params": c.params}
                for c in found]

    def state(self) -> dict:
        return {"pose": self.current_pose(),
                "map2d": None if self.mapper is None else self.mapper.state(),
                "map3d": self.planes.state(), "counts": dict(self.counts),
                "trajectory": np.asarray(list(self.trajectory)[-5000:], dtype=float)
                if self.trajectory else np.zeros((0, 6))}

    def load_state(self, st: dict) -> None:
        if st.get("map2d") is not None and self.mapper is not None:
            self.mapper.load_state(st["map2d"])
        self.planes.load_state(st.get("map3d") or {})
        self.pose = np.asarray(st.get("pose", (0, 0, 0)), dtype=float)
        if self.mapper is not None:
            self.mapper.set_pose(self.pose)
        self.last_scan_odom = None
