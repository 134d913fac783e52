"""The daemon's YAML configuration: schema, validation, defaults.

Validation is a small explicit walk over a schema of ``Spec`` nodes.  Every problem is reported
as one line naming the key path (``devices.laser.url: ...``) and the daemon exits with 78
(EX_CONFIG, sysexits.h), the code systemd shows as "configuration error".
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml
from cgamap.drivers.transport import DeviceUrlError, parse_device_url
from cgamap.drivers.yaml_errors import yaml_error_text

EX_CONFIG = 78

ROLES = ("laser", "odometry", "pantilt", "camera")
# Driver models per role; the daemon's device factory maps each to a driver class.
MODELS = {
    "laser": ("lms2xx", "hokuyo", "cola", "carmen"),
    "odometry": ("modbus-base", "carmen"),
    "pantilt": ("dynamixel",),
    "camera": ("oak", "sim-stereo", "depthai", "opencv", "synthetic", "replay"),
}
URL_SCHEMES = ("serial", "tcp", "sim", "file", "usb")
LOG_LEVELS = ("debug", "info", "warning", "error")


class ConfigError(Exception):
    """One configuration problem: ``path`` is the dotted key path, ``problem`` what is wrong."""

    code = EX_CONFIG

    def __init__(self, path: str, problem: str):
        super().__init__(f"{path or '<top>'}: {problem}")
        self.path = path
        self.problem = problem


@dataclass
class Spec:
    """One schema node.  ``kind``: str, int, float, bool, list, record (fixed keys), map (free
    keys, each value ``values``), any.  ``check`` returns an error text or None."""

    kind: str
    required: bool = False
    default: Any = None
    choices: tuple | None = None
    fields: dict[str, Spec] = field(default_factory=dict)
    values: Spec | None = None
    items: Spec | None = None
    length: int | None = None
    check: Callable[[Any], str | None] | None = None


def _positive(v) -> str | None:
    return None if v > 0 else f"must be > 0, got {v}"


def _non_negative(v) -> str | None:
    return None if v >= 0 else f"must be >= 0, got {v}"


def _port(v) -> str | None:
    return None if 0 <= v <= 65535 else f"must be a TCP port 0..65535, got {v}"


def _file_mode(v) -> str | None:
    if 0 <= v <= 0o777:
        return None
    return (f"must be a file mode 0..0o777, got {v} (write it in octal with a leading 0, "
            "e.g. 0660)")


def _non_empty(v) -> str | None:
    return None if v.strip() else "must not be empty"


def with_overrides(default, values: dict, where: str = "", what: str = "2D mapper parameter"):
    """``default`` (a dataclass instance) with the fields ``values`` names replaced, nested
    dataclasses from nested mappings (``{"map": {"clear": {"enabled": False}}}``), each
    value of its default's type (lists for tuples).  ValueError naming the dotted field for
    an unknown name or a wrong type: a typo is an error, not ignored."""
    from dataclasses import MISSING, is_dataclass, replace

    known = {}
    for f in fields(default):
        if f.init and (f.default is not MISSING or f.default_factory is not MISSING):
            known[f.name] = getattr(default, f.name)
    changes = {}
    for key, value in values.items():
        name = f"{where}{key}"
        if key not in known:
            raise ValueError(f"unknown {what} {name!r} (one of "
                             f"{', '.join(where + k for k in sorted(known))})")
        want = known[key]
        if is_dataclass(want):
            if not isinstance(value, dict):
                raise ValueError(f"{name}: expected a mapping of its fields, got {value!r}"[:160])
            changes[key] = with_overrides(want, value, f"{name}.", what)
            continue
        if isinstance(want, bool):
            ok = isinstance(value, bool)
        elif isinstance(want, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif isinstance(want, float):
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        elif isinstance(want, str):
            ok = isinstance(value, str)
        elif isinstance(want, tuple):  # tuples of numbers
            ok = isinstance(value, list) and len(value) == len(want) and all(
                isinstance(x, int | float) and not isinstance(x, bool) for x in value)
            value = tuple(value) if ok else value
        else:
            ok = False
        if not ok:
            raise ValueError(f"{name}: expected {_type_name(want)} like {want!r}, "
                             f"got {value!r}"[:160])
        changes[key] = value
    return replace(default, **changes)


def mapper_params(values: dict, where: str = "", base=None,
                  mount_note: str = "set by the laser device's mount, not here"):
    """``mapping.slam2d.MapperParams`` (``base``, default the defaults) with the ``params2d``
    overrides ``values`` (:func:`with_overrides`, dotted names after ``where``).  The laser
    mount is never one of them (``mount_note`` says where it comes from).  ValueError naming
    the field at fault."""
    from cgamap.mapping.slam2d import MapperParams

    if "mount" in values:
        raise ValueError(f"{where}mount: {mount_note}")
    return with_overrides(MapperParams() if base is None else base, values, where)


def _check_params2d(v: dict) -> str | None:
    try:
        mapper_params(v)
    except ValueError as exc:
        return str(exc)
    return None


@dataclass(frozen=True)
class Frames3D:
    """How the daemon turns a camera frame into planes: the ``mapping.params3d`` keys of
    its own; the others are :class:`~cgamap.mapping.planes.PlaneParams` fields (one flat
    mapping, as configs have written it)."""

    max_depth: float = 8.0    # points farther than this from the camera are dropped (m)
    stride: int = 4           # every stride-th pixel in each direction
    method: str = "ransac"    # plane detector: ransac or hough


PLANE_METHODS = ("ransac", "hough")


def params3d(values: dict):
    """``mapping.params3d`` as (:class:`Frames3D`, ``PlaneParams``).  ValueError naming the
    key for an unknown name, a wrong type or a value out of range."""
    from cgamap.mapping.planes import PlaneParams

    own = {f.name for f in fields(Frames3D)}
    known = {f.name for f in fields(PlaneParams)} | own
    unknown = sorted(k for k in values if k not in known)
    if unknown:
        raise ValueError(f"unknown 3D mapping parameter {unknown[0]!r} (one of "
                         f"{', '.join(sorted(known))})")
    frames = with_overrides(Frames3D(), {k: v for k, v in values.items() if k in own},
                            what="3D mapping parameter")
    planes = with_overrides(PlaneParams(), {k: v for k, v in values.items() if k not in own},
                            what="3D mapping parameter")
    if frames.method not in PLANE_METHODS:
        raise ValueError(f"method: expected one of {', '.join(PLANE_METHODS)}, "
                         f"got {frames.method!r}")
    for name, low in (("max_depth", 0.0), ("threshold", 0.0)):
        v = getattr(frames if name in own else planes, name)
        if not v > low:
            raise ValueError(f"{name}: must be > {low:g}, got {v}")
    for name, low in (("stride", 1), ("min_inliers", 3), ("max_planes", 1)):
        v = getattr(frames if name in own else planes, name)
        if v < low:
            raise ValueError(f"{name}: must be >= {low}, got {v}")
    return frames, planes


def _check_params3d(v: dict) -> str | None:
    try:
        params3d(v)
    except ValueError as exc:
        return str(exc)
    return None


def check_url(url: str) -> str | None:
    """A device URL: ``serial:///dev/ttyUSB0?baudrate=38400``, ``tcp://host:port``,
    ``sim://name``, ``file:///path/log.gz``, ``usb://`` (first device of the model).

    ``parse_device_url`` (the drivers' one parser) takes it apart and rejects what no driver
    could open (no host:port, no device path, a bad baud rate); the config adds its own rules:
    the scheme is written out, it is one the daemon runs, ``file://`` names a file, ``unit``/
    ``id`` are whole numbers, and ``spy+`` tracing is for the byte-stream schemes."""
    if url.startswith("/"):  # the drivers read a bare path as serial; a config spells it out
        return f"a bare device path {url!r}: write serial://{url}"
    if "://" not in url and url.strip():
        return (f"no scheme in {url!r}: write one of {', '.join(URL_SCHEMES)} "
                "(e.g. serial:///dev/ttyUSB0, tcp://host:port)")
    try:
        u = parse_device_url(url)
    except DeviceUrlError as exc:
        return str(exc)
    if u.scheme not in URL_SCHEMES:
        return f"unknown scheme {u.scheme!r} in {url!r} (one of {', '.join(URL_SCHEMES)})"
    # the parser keeps a file:// URL whole as a handler URL: its path follows the "://"
    if u.scheme in ("serial", "file") and not u.path.split("://", 1)[-1].strip("/"):
        return f"no device path in {url!r}"
    if u.spy and u.scheme not in ("serial", "tcp"):
        return f"spy+ (trace) is for serial:// and tcp:// devices, not {u.scheme}:// in {url!r}"
    for key in ("unit", "id"):
        value = u.options.get(key)
        if value is not None and not value.isdigit():
            return f"query {key}={value!r} must be an integer"
    return None


def _pose_spec() -> Spec:
    f = Spec("float", default=0.0)
    return Spec("record", fields={k: f for k in ("x", "y", "z", "roll", "pitch", "yaw")})


def _vec3_spec(default=(0.0, 0.0, 0.0)) -> Spec:
    return Spec("list", default=list(default), items=Spec("float"), length=3)


DEVICE = Spec("record", fields={
    "role": Spec("str", required=True, choices=ROLES),
    "model": Spec("str", required=True),
    "url": Spec("str", required=True, check=check_url),
    "enabled": Spec("bool", default=True),
    "queue": Spec("int", default=16, check=_positive),
    "timeout": Spec("float", default=1.0, check=_positive),
    # laser: the mount motor M_BL; camera: unused
    "mount": _pose_spec(),
    # pan-tilt: axis point P in the base frame, eye offset (P to left camera) in the head
    # frame, or a hand-eye calibration file (``calib hand-eye`` YAML with head_T_cam)
    "axis_point": _vec3_spec(),
    "eye_offset": _vec3_spec(),
    "hand_eye": Spec("str"),
    "rate": Spec("float", default=10.0, check=_positive),
    "params": Spec("map", default={}, values=Spec("any")),
})

SCHEMA = Spec("record", fields={
    "log_level": Spec("str", default="info", choices=LOG_LEVELS),
    "paths": Spec("record", default={}, fields={
        "state_dir": Spec("str", default="/var/lib/cgamap", check=_non_empty),
        "runtime_dir": Spec("str", default="/run/cgamap", check=_non_empty),
        "socket": Spec("str", default="cgamapd.sock", check=_non_empty),
    }),
    "server": Spec("record", default={}, fields={
        "tcp": Spec("bool", default=False),
        "tcp_host": Spec("str", default="127.0.0.1"),
        "tcp_port": Spec("int", default=2950, check=_port),
        "socket_mode": Spec("int", default=0o660, check=_file_mode),
        "max_clients": Spec("int", default=16, check=_positive),
    }),
    "checkpoint": Spec("record", default={}, fields={
        "interval": Spec("float", default=30.0, check=_positive),
    }),
    "supervisor": Spec("record", default={}, fields={
        "backoff_initial": Spec("float", default=0.2, check=_positive),
        "backoff_max": Spec("float", default=1.0, check=_positive),
        # READY=1 when all devices stream, or after this many seconds with those that do
        "ready_timeout": Spec("float", default=10.0, check=_non_negative),
    }),
    "devices": Spec("map", default={}, values=DEVICE),
    "mapping": Spec("record", default={}, fields={
        "map2d": Spec("bool", default=True),
        "map3d": Spec("bool", default=True),
        "rate3d": Spec("float", default=1.0, check=_positive),
        "odometry": Spec("map", default={}, values=Spec("any")),
        "params2d": Spec("map", default={}, values=Spec("any"), check=_check_params2d),
        "params3d": Spec("map", default={}, values=Spec("any"), check=_check_params3d),
        "lost_quality": Spec("float", default=0.2, check=_non_negative),
        "lost_after": Spec("int", default=8, check=_positive),
        # a lost robot first relocalises within this many metres of its pose (0: the whole
        # map at once)
        "lost_radius": Spec("float", default=3.0, check=_non_negative),
        "max_interp_gap": Spec("float", default=0.5, check=_positive),
        # scans are mapped when the robot moved this much (m, rad) since the last mapped one,
        # and at most scan_max_rate per second: a standing robot does not grow the pose graph
        "min_travel": Spec("float", default=0.05, check=_non_negative),
        "min_turn": Spec("float", default=0.05, check=_non_negative),
        "scan_max_rate": Spec("float", default=10.0, check=_positive),
        # the finishing pass (as `map build` ends with) every this many seconds; 0: only on
        # request ({"cmd": "optimize"})
        "optimize_every_s": Spec("float", default=0.0, check=_non_negative),
    }),
    # sim-only: what the demo drives; ignored by the daemon itself
    "sim": Spec("map", default={}, values=Spec("any")),
})

_TYPES: dict[str, tuple[type, ...]] = {
    "str": (str,), "int": (int,), "float": (int, float), "bool": (bool,),
    "list": (list,), "record": (dict,), "map": (dict,),
}


def _type_name(v: Any) -> str:
    return {dict: "mapping", list: "list", str: "string", bool: "boolean", int: "integer",
            float: "number", type(None): "null"}.get(type(v), type(v).__name__)


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _validate(spec: Spec, value: Any, path: str) -> Any:
    if spec.kind == "any":
        return value
    ok = _TYPES[spec.kind]
    if not isinstance(value, ok) or (spec.kind in ("int", "float") and isinstance(value, bool)):
        want = {"record": "mapping", "map": "mapping", "float": "number", "int": "integer",
                "str": "string", "bool": "boolean (true/false)"}.get(spec.kind, spec.kind)
        hint = ""
        if spec.kind == "float" and isinstance(value, str) and _looks_numeric(value):
            hint = " (YAML reads 1e-3 as text: write 1.0e-3)"
        raise ConfigError(path, f"expected {want}, got {_type_name(value)} {value!r}"[:160]
                          + hint)
    if spec.kind == "float":
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(path, f"must be a finite number, got {value}")
    if spec.choices is not None and value not in spec.choices:
        raise ConfigError(path, f"{value!r} is not one of {', '.join(map(str, spec.choices))}")
    if spec.kind == "list":
        if spec.length is not None and len(value) != spec.length:
            raise ConfigError(path, f"expected {spec.length} items, got {len(value)}")
        value = [_validate(spec.items, v, f"{path}[{i}]") for i, v in enumerate(value)]
    elif spec.kind == "record":
        value = _validate_record(spec, value, path)
    elif spec.kind == "map":
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ConfigError(path, f"key {k!r} must be a string")
            out[k] = _validate(spec.values, v, f"{path}.{k}" if path else k)
        value = out
    if spec.check is not None:
        problem = spec.check(value)
        if problem:
            raise ConfigError(path, problem)
    return value


def _validate_record(spec: Spec, value: dict, path: str) -> dict:
    for k in value:
        if k not in spec.fields:
            where = f"{path}.{k}" if path else str(k)
            raise ConfigError(where, f"unknown key (expected one of {', '.join(spec.fields)})")
    out = {}
    for k, sub in spec.fields.items():
        where = f"{path}.{k}" if path else k
        if k in value and value[k] is not None:
            out[k] = _validate(sub, value[k], where)
        elif k in value and sub.kind != "any" and not sub.required:
            raise ConfigError(where, "is empty (remove the key or give a value)")
        elif sub.required:
            raise ConfigError(where, "missing required key")
        elif sub.kind == "record":
            out[k] = _validate(sub, dict(sub.default or {}), where)
        else:
            out[k] = _copy(sub.default)
    return out


def _copy(v):
    return list(v) if isinstance(v, list) else dict(v) if isinstance(v, dict) else v


def _check_devices(cfg: dict, base: Path) -> None:
    """Cross-field checks: the model fits the role, calibration files exist and parse."""
    for name, dev in cfg["devices"].items():
        path = f"devices.{name}"
        if dev["model"] not in MODELS[dev["role"]]:
            raise ConfigError(f"{path}.model", f"{dev['model']!r} is not a {dev['role']} model "
                              f"(one of {', '.join(MODELS[dev['role']])})")
        if dev["model"] == "carmen" and parse_device_url(dev["url"]).scheme != "file":
            raise ConfigError(f"{path}.url", "a carmen log needs a file:// URL")
        _check_params(f"{path}.params", dev)
        if dev["hand_eye"]:
            he = Path(dev["hand_eye"])
            he = he if he.is_absolute() else base / he
            dev["hand_eye"] = str(he)
            dev["head_T_cam"] = load_hand_eye(he, f"{path}.hand_eye")
    sup = cfg["supervisor"]
    if sup["backoff_initial"] > sup["backoff_max"]:
        raise ConfigError("supervisor.backoff_initial", f"{sup['backoff_initial']} is above "
                          f"backoff_max {sup['backoff_max']}")
    roles = [d["role"] for d in cfg["devices"].values() if d["enabled"]]
    for role in ("laser", "odometry", "pantilt", "camera"):
        if roles.count(role) > 1:
            raise ConfigError("devices", f"more than one enabled {role} device")


def _check_params(key: str, dev: dict) -> None:
    """A device's free ``params`` against its driver: the drivers drop unknown keys or fail
    only when the daemon opens the device (and the supervisor retries that forever), so a
    typo (``wheel_radus``) or a bad value is reported here, before the daemon starts."""
    params, model = dev["params"], dev["model"]
    try:
        if dev["role"] == "laser" and model in ("lms2xx", "hokuyo", "cola"):
            from cgamap.daemon.devices import LASER_CLASSES, _import

            cls = _import(*LASER_CLASSES[model])
            cls(dev["url"], dev["timeout"], reconnect=False, **params)
        elif model == "modbus-base":
            from cgamap.drivers.modbus_base import ModbusBaseConfig

            known = {f.name for f in fields(ModbusBaseConfig)} | {"rate", "track", "timeout"}
            _known_keys(key, params, known)
            cfg = ModbusBaseConfig.from_dict(dev)
            for name in ("wheel_radius", "track_width", "ticks_per_rev"):
                value = getattr(cfg, name)
                if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                    raise ConfigError(f"{key}.{name}", f"must be a number > 0, got {value!r}")
        elif model == "dynamixel":
            from cgamap.drivers.pantilt import PanTiltConfig

            _known_keys(key, params, {f.name for f in fields(PanTiltConfig)} - {"url"})
            PanTiltConfig.from_dict({**params, "url": dev["url"]})
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(key, f"rejected by the {model} driver: {exc}"[:200]) from None


def _known_keys(key: str, params: dict, known: set[str]) -> None:
    for k in params:
        if k not in known:
            raise ConfigError(f"{key}.{k}", f"unknown key (expected one of "
                              f"{', '.join(sorted(known))})"[:300])


def load_hand_eye(path: Path, key: str) -> list[list[float]]:
    """``head_T_cam`` (4x4, rows) from a ``calib hand-eye`` YAML file."""
    if path.is_dir():
        raise ConfigError(key, f"calibration file {str(path)!r} is a directory")
    if not path.is_file():
        raise ConfigError(key, f"calibration file {str(path)!r} not found")
    try:
        data = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)
    except UnicodeDecodeError:
        raise ConfigError(key, f"{str(path)!r} is not a text (YAML) file") from None
    except yaml.YAMLError as exc:
        raise ConfigError(key, f"cannot read {str(path)!r}: {yaml_error_text(exc)}") from None
    except OSError as exc:
        raise ConfigError(key, f"cannot read {str(path)!r}: {exc.strerror or exc}") from None
    m = data.get("head_T_cam") if isinstance(data, dict) else None
    if isinstance(m, dict):  # some writers nest the matrix as {rows: .., data: ..}
        m = m.get("data") or m.get("matrix")
    try:
        import numpy as np

        arr = np.asarray(m, dtype=float).reshape(4, 4)
        if not np.all(np.isfinite(arr)) or not np.allclose(arr[3], [0, 0, 0, 1]):
            raise ValueError
    except (TypeError, ValueError):
        raise ConfigError(key, f"{str(path)!r} has no valid 4x4 head_T_cam") from None
    return arr.tolist()


def validate(raw: Any, base: Path | None = None) -> dict:
    """Validated config with defaults filled in; raises ConfigError on the first problem."""
    if raw is None:
        raw = {}
    cfg = _validate(SCHEMA, raw, "")
    _check_devices(cfg, base or Path.cwd())
    return cfg


class YamlFileError(ValueError):
    """A YAML file that cannot be read: ``key`` the entry at fault ("" for the whole file),
    the message says what is wrong (with the line where YAML knows it)."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


def read_yaml(path: str | os.PathLike, what: str = "config file") -> Any:
    """The document of a YAML file (``what`` it should be, for the messages); a key given
    twice in one mapping is refused.  YamlFileError for every kind of problem."""
    p = Path(path)
    if p.is_dir():
        raise YamlFileError("", f"cannot read {str(p)!r}: is a directory, not a {what}")
    try:
        text = p.read_text()
    except OSError as exc:
        raise YamlFileError("", f"cannot read {str(p)!r}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise YamlFileError("", f"cannot read {str(p)!r}: not a text (YAML) file (undecodable "
                            f"byte at offset {exc.start})") from None
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except DuplicateKeyError as exc:
        raise YamlFileError(exc.key_path, f"duplicate key at line {exc.line} (the first one "
                            "would be ignored)") from None
    except yaml.YAMLError as exc:
        raise YamlFileError("", yaml_error_text(exc)) from None


def load(path: str | os.PathLike) -> dict:
    """Read and validate a YAML config file (ConfigError for every kind of problem)."""
    p = Path(path)
    try:
        raw = read_yaml(p)
    except YamlFileError as exc:
        raise ConfigError(exc.key, str(exc)) from None
    if raw is not None and not isinstance(raw, dict):
        raise ConfigError("", f"top level must be a mapping, got {_type_name(raw)}")
    cfg = validate(raw, p.resolve().parent)
    cfg["_file"] = str(p.resolve())
    return cfg


class DuplicateKeyError(yaml.YAMLError):
    def __init__(self, key_path: str, line: int):
        super().__init__(f"{key_path}: duplicate key at line {line}")
        self.key_path, self.line = key_path, line


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last one
    silently: a second ``devices:`` block would drop the first)."""

    def construct_mapping(self, node, deep=False):
        seen: set = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                dup = key in seen
            except TypeError:  # an unhashable key: SafeLoader reports it below
                dup = False
            if dup:
                raise DuplicateKeyError(str(key), key_node.start_mark.line + 1)
            try:
                seen.add(key)
            except TypeError:
                pass
        return super().construct_mapping(node, deep=deep)


def resolve_paths(cfg: dict) -> tuple[Path, Path]:
    """(state dir, socket path): systemd's $STATE_DIRECTORY / $RUNTIME_DIRECTORY win."""
    state = Path(os.environ.get("STATE_DIRECTORY", "").split(":")[0] or cfg["paths"]["state_dir"])
    run = Path(os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
               or cfg["paths"]["runtime_dir"])
    sock = Path(cfg["paths"]["socket"])
    return state, sock if sock.is_absolute() else run / sock
