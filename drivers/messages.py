"""Typed, timestamped messages that drivers yield (shared by devices, twins and log replay).

Timestamps: ``stamp_ns`` is ``time.monotonic_ns()`` when the driver had the last byte of the
message (for log replay: the log's own time in ns); ``device_stamp`` is the device's own
counter or clock where the protocol has one (SCIP timestamp, SICK scan counter), else None.
Where the device has a clock (Hokuyo SCIP), ``stamp_ns`` is the arrival time the message would
have had on an idle host, mapped from ``device_stamp`` by :class:`.device_clock.DeviceClock`:
a scan read late by a busy host keeps the instant it was taken (the odometry at that instant
is what places it).  A SICK LMS2xx scan's ``stamp_ns`` is when its (last) mirror sweep ended:
the arrival of its telegram's first byte, on a real serial line no later than the last byte's
arrival minus the wire time of the rest at the session baud; with real-time indices on,
``device_stamp`` is the sweep count (the one-byte index unwrapped, 75 Hz) and the stamp goes
through a :class:`.device_clock.DeviceClock` on it.  Where the device samples on request
(a Modbus base's encoder counters), ``stamp_ns`` is the midpoint of the request and its reply.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ErrorCounters:
    """Counters a driver keeps; every dropped or repaired input increments one of them."""

    checksum: int = 0      # frames/lines with a bad CRC or checksum (dropped)
    framing: int = 0       # garbage bytes skipped while resynchronising, truncated frames
    timeout: int = 0       # replies or frames that did not arrive in time
    device: int = 0        # error statuses reported by the device itself
    disconnects: int = 0   # transport lost (port vanished, socket closed)
    dropped: int = 0       # complete messages discarded (e.g. a partial scan set abandoned)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class LaserScan:
    """One full scan of a 2D laser range finder.

    ``ranges`` in metres, float64, one per beam at ``angle_min + i * angle_increment`` in the
    laser frame (x forward, y left, counter-clockwise positive).  A beam with no return (out of
    range, dazzled, blocked) is NaN; ranges are never clipped to ``range_max``.
    """

    seq: int
    stamp_ns: int
    angle_min: float
    angle_increment: float
    ranges: np.ndarray
    range_min: float = 0.0
    range_max: float = float("inf")
    scan_time: float = 0.0
    intensities: np.ndarray | None = None
    device_stamp: int | None = None
    frame: str = "laser"
    # Poses carried by logs (CARMEN FLASER: reference pose and odometry pose) or by a twin
    # (ground truth): (x, y, theta) in the world/odometry frame, else None.  pose_ref is the
    # laser's; a CARMEN pose_odom is the robot's (the same for a laser at its centre)
    pose_ref: tuple[float, float, float] | None = None
    pose_odom: tuple[float, float, float] | None = None
    errors: dict[str, int] = field(default_factory=dict)

    @property
    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges))

    def to_json(self) -> dict:
        def num(x):
            return None if not np.isfinite(x) else round(float(x), 4)

        out = {
            "seq": self.seq,
            "stamp_ns": self.stamp_ns,
            "device_stamp": self.device_stamp,
            "angle_min": self.angle_min,
            "angle_increment": self.angle_increment,
            "range_min": self.range_min,
            "range_max": num(self.range_max),
            "scan_time": self.scan_time,
            "ranges": [num(r) for r in self.ranges],
        }
        if self.intensities is not None:
            out["intensities"] = [float(v) for v in self.intensities]
        if self.errors:
            out["errors"] = self.errors
        return out


@dataclass
class OdometryPose:
    """An odometry pose as a log records it (CARMEN ODOM): x, y, theta in the odometry frame,
    with translational and rotational velocity where known."""

    stamp_ns: int
    x: float
    y: float
    theta: float
    tv: float = 0.0
    rv: float = 0.0
    seq: int = 0


@dataclass
class WheelTicks:
    """Raw wheel encoder counts of a differential base (unwrapped, signed), as read from the
    motor controller; turning them into a pose is mapping's work."""

    seq: int
    stamp_ns: int
    left: int
    right: int
    left_speed: float | None = None   # rad/s where the controller reports it
    right_speed: float | None = None
    status: int | None = None
    estop: bool = False
    errors: dict[str, int] = field(default_factory=dict)
    # The controller sampled its counters within +- this of stamp_ns (half the request/reply
    # round trip of the tick registers; stamp_ns is that round trip's midpoint); 0: unknown.
    stamp_uncertainty_ns: int = 0

    def to_json(self) -> dict:
        return {"seq": self.seq, "stamp_ns": self.stamp_ns,
                "stamp_uncertainty_ns": self.stamp_uncertainty_ns, "left": self.left,
                "right": self.right, "left_speed": self.left_speed,
                "right_speed": self.right_speed, "status": self.status, "estop": self.estop,
                "errors": self.errors}


@dataclass
class PanTiltState:
    """Present pan and tilt joint angles (radians) of the head."""

    seq: int
    stamp_ns: int
    pan: float
    tilt: float
    moving: bool = False
    hardware_error: int = 0
    errors: dict[str, int] = field(default_factory=dict)
