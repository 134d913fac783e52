"""The query socket: JSON lines on a Unix socket (mode 0660), in the manner of gpsd.

A request is one line: a JSON object ``{"cmd": "status"}`` (or just the word ``status``).
Commands: ``status``, ``map``, ``trajectory``, ``watch`` (then a stream of event lines until
the client hangs up; ``{"cmd": "watch", "raw": true}`` adds every device message, which is
what ``cgamap record`` writes), ``relocalize``, ``checkpoint``, ``set-pose`` (``x``, ``y``,
``theta``), ``optimize`` (the finishing pass; replies when done), ``version``.  Every reply
is one JSON object with ``"class"``; errors are ``{"class": "error", "error": "..."}``.  TCP
is off unless configured (127.0.0.1 by default).
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import socketserver
import stat
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

MAX_LINE = 65536


class Handler(socketserver.StreamRequestHandler):
    timeout = 600.0  # an idle client gives its slot back after 10 min (watch never idles)

    def handle(self) -> None:
        server: Any = self.server
        if not server.slots.acquire(blocking=False):
            self._send({"class": "error", "error": "too many clients"})
            return
        try:
            while not server.stopping.is_set():
                line = self.rfile.readline(MAX_LINE)
                if not line:
                    return
                line = line.strip()
                if not line:
                    continue
                try:
                    req = json.loads(line) if line.startswith(b"{") else {"cmd": line.decode()}
                    if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
                        raise ValueError("expected {\"cmd\": ...}")
                except (ValueError, UnicodeDecodeError) as exc:
                    self._send({"class": "error", "error": f"bad request: {exc}"})
                    continue
                if req["cmd"] == "watch":
                    server.app.watch(req, self._send, server.stopping)
                    return
                self._send(server.app.command(req))
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            return
        finally:
            server.slots.release()

    def _send(self, obj: dict) -> bool:
        try:
            self.wfile.write(json.dumps(obj, separators=(",", ":")).encode() + b"\n")
            self.wfile.flush()
            return True
        except (BrokenPipeError, ConnectionResetError, OSError):
            return False


class _Unix(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    daemon_threads = True
    block_on_close = False


class _Tcp(socketserver.ThreadingMixIn, socketserver.TCPServer):
    daemon_threads = True
    block_on_close = False
    allow_reuse_address = True


class QueryServer:
    """Serves ``app`` (an object with ``command(req) -> dict`` and ``watch(req, send, stop)``)
    on a Unix socket and, if asked, a TCP port."""

    def __init__(self, app: Any, socket_path: str | os.PathLike, mode: int = 0o660,
                 tcp: tuple[str, int] | None = None, max_clients: int = 16):
        self.app = app
        self.path = Path(socket_path)
        self.mode = mode
        self.tcp = tcp
        self.max_clients = max_clients
        self.stopping = threading.Event()
        self.servers: list[socketserver.BaseServer] = []
        self.threads: list[threading.Thread] = []
        self.tcp_address: tuple[str, int] | None = None

    def _prepare_path(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):   # a file, directory or symlink: not ours to delete
            raise RuntimeError(f"{self.path}: exists and is not a socket; refusing to replace it")
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.settimeout(0.5)
            try:
                probe.connect(str(self.path))
            except OSError:
                self.path.unlink()  # stale socket of a previous run
            else:
                raise RuntimeError(f"{self.path}: another daemon is answering there")

    def start(self) -> None:
        self._prepare_path()
        old = os.umask(0o117)  # no window in which the socket is wider than 0660
        try:
            unix = _Unix(str(self.path), Handler)
        finally:
            os.umask(old)
        os.chmod(self.path, self.mode)
        self.servers.append(unix)
        if self.tcp is not None:
            tcp = _Tcp(self.tcp, Handler)
            self.tcp_address = tcp.server_address[:2]
            self.servers.append(tcp)
        slots = threading.BoundedSemaphore(self.max_clients)
        for srv in self.servers:
            srv.app, srv.stopping, srv.slots = self.app, self.stopping, slots  # type: ignore
            t = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.1},
                                 name="query-server", daemon=True)
            t.start()
            self.threads.append(t)

    def stop(self) -> None:
        self.stopping.set()
        for srv in self.servers:
            srv.shutdown()
            srv.server_close()
        try:
            self.path.unlink()
        except OSError:
            pass


# -- client side ------------------------------------------------------------------------------


class DaemonUnavailable(Exception):
    pass


POSE_LIMIT_M = 1e6  # |x|, |y| bound for a pose given: beyond it the map's extent cannot be drawn
HINT_RADIUS_M = 2.0            # a relocalisation hint's defaults: metres ...
HINT_TURN = math.radians(30.0)  # ... and radians


def hint_problem(pose, radius: float, turn: float) -> str | None:
    """What is wrong with a relocalisation hint (``pose`` x, y, theta in radians, ``radius``
    metres, ``turn`` radians), as "field: problem", or None: the CLI checks before it asks,
    the daemon for any client."""
    if not all(math.isfinite(v) for v in pose):
        return "near: x, y, theta must be finite"
    if max(abs(pose[0]), abs(pose[1])) > POSE_LIMIT_M:
        return f"near: x, y must be within +-{POSE_LIMIT_M:g} m"
    if not (math.isfinite(radius) and 0 < radius <= 1000):
        return f"radius: must be in (0, 1000] m, got {radius}"
    if not (math.isfinite(turn) and 0 < turn <= math.pi):
        return f"turn: must be in (0, 180] degrees, got {math.degrees(turn):g}"
    return None


def connect(path: str | os.PathLike, timeout: float = 5.0) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    try:
        s.connect(str(path))
    except OSError as exc:
        s.close()
        raise DaemonUnavailable(f"{path}: cannot connect to cgamapd ({exc.strerror or exc})") \
            from None
    return s


def request(path: str | os.PathLike, cmd: str, timeout: float = 10.0, **kw) -> dict:
    """Send one command and return its reply."""
    with connect(path, timeout) as s:
        s.sendall(json.dumps({"cmd": cmd, **kw}).encode() + b"\n")
        f = s.makefile("rb")
        line = f.readline()
    if not line:
        raise DaemonUnavailable(f"{path}: cgamapd closed the connection")
    return json.loads(line)


def stream(path: str | os.PathLike, timeout: float = 10.0, **kw):
    """Yield the event objects of a ``watch`` until the daemon or the caller stops."""
    with connect(path, timeout) as s:
        s.sendall(json.dumps({"cmd": "watch", **kw}).encode() + b"\n")
        f = s.makefile("rb")
        for line in f:
            yield json.loads(line)


def handler_table(app: Any) -> dict[str, Callable[[dict], dict]]:
    return {name.replace("cmd_", "").replace("_", "-"): getattr(app, name)
            for name in dir(app) if name.startswith("cmd_")}
