"""Recordings: device messages to and from MCAP (JSON messages with Foxglove schema names, so
Foxglove opens them), and CARMEN logs read through the CARMEN driver.

Each message keeps what Foxglove needs at top level (``timestamp``, ``frame_id``, ``pose``, ...)
and what replay needs to rebuild the message exactly under ``cgamap`` (seq, stamps, angles).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from cgamap.drivers.messages import LaserScan, OdometryPose, PanTiltState, WheelTicks

log = logging.getLogger(__name__)

TOPICS = {  # message type -> (topic, schema name)
    LaserScan: ("/scan", "foxglove.LaserScan"),
    OdometryPose: ("/odom", "foxglove.PoseInFrame"),
    WheelTicks: ("/wheel_ticks", "cgamap.WheelTicks"),
    PanTiltState: ("/pantilt", "foxglove.FrameTransform"),
}
POSE_TOPIC = ("/pose", "foxglove.PoseInFrame")


def _schema(name: str) -> bytes:
    """A minimal JSON schema: Foxglove needs the name; the fields document the layout."""
    return json.dumps({"title": name, "type": "object"}).encode()


def _stamp(ns: int) -> dict:
    return {"sec": int(ns // 1_000_000_000), "nsec": int(ns % 1_000_000_000)}


def _quat_z(theta: float) -> dict:
    return {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2), "w": math.cos(theta / 2)}


def _num(x: float):
    return None if not math.isfinite(x) else round(float(x), 5)


def to_record(msg: Any) -> dict:
    """The JSON body of one device message."""
    if isinstance(msg, LaserScan):
        n = len(msg.ranges)
        return {
            "timestamp": _stamp(msg.stamp_ns), "frame_id": msg.frame,
            "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": _quat_z(0.0)},
            "start_angle": msg.angle_min,
            "end_angle": msg.angle_min + msg.angle_increment * max(n - 1, 0),
            "ranges": [_num(r) for r in msg.ranges],
            "intensities": [] if msg.intensities is None else
            [float(v) for v in msg.intensities],
            "cgamap": {"seq": msg.seq, "stamp_ns": msg.stamp_ns, "device_stamp": msg.device_stamp,
                       "angle_increment": msg.angle_increment, "range_min": msg.range_min,
                       "range_max": _num(msg.range_max), "scan_time": msg.scan_time,
                       "pose_ref": msg.pose_ref, "pose_odom": msg.pose_odom},
        }
    if isinstance(msg, OdometryPose):
        return {"timestamp": _stamp(msg.stamp_ns), "frame_id": "odom",
                "pose": {"position": {"x": msg.x, "y": msg.y, "z": 0.0},
                         "orientation": _quat_z(msg.theta)},
                "cgamap": {"seq": msg.seq, "stamp_ns": msg.stamp_ns, "theta": msg.theta,
                           "tv": msg.tv, "rv": msg.rv}}
    if isinstance(msg, WheelTicks):
        return {"timestamp": _stamp(msg.stamp_ns), "cgamap": msg.to_json()}
    if isinstance(msg, PanTiltState):
        # as a transform base -> head: yaw = pan (the tilt is left out of the quaternion)
        return {"timestamp": _stamp(msg.stamp_ns), "parent_frame_id": "base",
                "child_frame_id": "head", "translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                "rotation": _quat_z(msg.pan),
                "cgamap": {"seq": msg.seq, "stamp_ns": msg.stamp_ns, "pan": msg.pan,
                           "tilt": msg.tilt, "moving": msg.moving}}
    raise TypeError(f"cannot record {type(msg).__name__}")


def from_record(topic: str, body: dict) -> Any | None:
    """Rebuild a device message from its recorded JSON (None for topics replay skips)."""
    c = body.get("cgamap", {})
    if topic == "/scan":
        ranges = np.array([np.nan if r is None else r for r in body["ranges"]], dtype=float)
        inten = np.asarray(body["intensities"], float) if body.get("intensities") else None
        rmax = c.get("range_max")
        return LaserScan(seq=c["seq"], stamp_ns=c["stamp_ns"], angle_min=body["start_angle"],
                         angle_increment=c["angle_increment"], ranges=ranges,
                         range_min=c.get("range_min", 0.0),
                         range_max=float("inf") if rmax is None else rmax,
                         scan_time=c.get("scan_time", 0.0), intensities=inten,
                         device_stamp=c.get("device_stamp"), frame=body.get("frame_id", "laser"),
                         pose_ref=tuple(c["pose_ref"]) if c.get("pose_ref") else None,
                         pose_odom=tuple(c["pose_odom"]) if c.get("pose_odom") else None)
    if topic == "/odom":
        p = body["pose"]["position"]
        return OdometryPose(stamp_ns=c["stamp_ns"], x=p["x"], y=p["y"], theta=c["theta"],
                            tv=c.get("tv", 0.0), rv=c.get("rv", 0.0), seq=c.get("seq", 0))
    if topic == "/wheel_ticks":
        return WheelTicks(seq=c["seq"], stamp_ns=c["stamp_ns"], left=c["left"], right=c["right"],
                          left_speed=c.get("left_speed"), right_speed=c.get("right_speed"),
                          status=c.get("status"), estop=c.get("estop", False),
                          errors=dict(c.get("errors") or {}),
                          stamp_uncertainty_ns=int(c.get("stamp_uncertainty_ns", 0)))
    if topic == "/pantilt":
        return PanTiltState(seq=c["seq"], stamp_ns=c["stamp_ns"], pan=c["pan"], tilt=c["tilt"],
                            moving=c.get("moving", False))
    return None


class McapRecorder:
    """Writes device messages (and optionally poses) to an MCAP file."""

    def __init__(self, stream: BinaryIO):
        from mcap.writer import Writer

        self.w = Writer(stream)
        self.w.start(profile="", library="cgamap")
        self.channels: dict[str, int] = {}
        self.count = 0

    def _channel(self, topic: str, schema: str) -> int:
        if topic not in self.channels:
            sid = self.w.register_schema(name=schema, encoding="jsonschema", data=_schema(schema))
            self.channels[topic] = self.w.register_channel(topic=topic, message_encoding="json",
                                                           schema_id=sid)
        return self.channels[topic]

    def write_json(self, topic: str, schema: str, body: dict, stamp_ns: int) -> None:
        data = json.dumps(body, separators=(",", ":")).encode()
        self.w.add_message(self._channel(topic, schema), log_time=int(stamp_ns),
                           publish_time=int(stamp_ns), data=data)
        self.count += 1

    def write(self, msg: Any) -> bool:
        spec = TOPICS.get(type(msg))
        if spec is None:
            return False
        self.write_json(spec[0], spec[1], to_record(msg), msg.stamp_ns)
        return True

    def write_pose(self, stamp_ns: int, x: float, y: float, theta: float) -> None:
        body = {"timestamp": _stamp(stamp_ns), "frame_id": "map",
                "pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": _quat_z(theta)}}
        self.write_json(*POSE_TOPIC, body, stamp_ns)

    def finish(self) -> None:
        self.w.finish()


def read_mcap(path: str | Path) -> Iterator[Any]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        for _s, channel, message in make_reader(f).iter_messages(log_time_order=True):
            msg = from_record(channel.topic, json.loads(message.data))
            if msg is not None:
                yield msg


def is_mcap(path: str | Path) -> bool:
    with open(path, "rb") as f:
        return f.read(8) == b"\x89MCAP0\r\n"


def read_messages(path: str | Path) -> Iterator[Any]:
    """Device messages of a recording: MCAP or CARMEN (plain or gzipped)."""
    if is_mcap(path):
        yield from read_mcap(path)
        return
    from cgamap.drivers.carmen import (
        CarmenStats,
        RepeatIndex,
        drop_saturated,
        read_tagged,
        saturation_range,
    )

    # a no-return value the log keeps as a reading (an LMS's 8 m mode): found in a first
    # pass over the scans, dropped as ``map build`` drops it
    st = CarmenStats()
    limit = saturation_range(m for _, m in read_tagged(path, lenient=True, stats=st,
                                                       types=("FLASER", "ROBOTLASER1")))
    if limit is not None:
        log.info("replay: readings of %g m (the log's longest, repeated) taken as no return",
                 limit)
    # each scan written twice (FLASER and ROBOTLASER1): replayed once, as ``map build`` reads it
    index = (RepeatIndex(m for _, m in read_tagged(path, lenient=True, types=("ROBOTLASER1",)))
             if st.both_scan_kinds else None)
    dropped = 0
    for kind, msg in read_tagged(path, lenient=True):
        if index is not None and index.repeats(kind, msg):
            dropped += 1
            continue
        if limit is not None and isinstance(msg, LaserScan) and msg.frame == "laser":
            drop_saturated(msg, limit)
        yield msg
    if dropped:
        log.info("replay: %d FLASER scans repeated ROBOTLASER1 scans: replayed once", dropped)
