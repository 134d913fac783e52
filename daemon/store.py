"""The map store: checkpoints of the maps and the pose, written so that a crash never leaves an
unreadable map.

A checkpoint is one JSON document with a SHA-256 of its payload.  Saving writes a temp file in
the same directory, fsyncs it, moves the current checkpoint to ``.prev``, renames the temp file
into place and fsyncs the directory.  Whatever moment the process dies at, the directory holds
a complete current checkpoint, or a complete previous one (loading falls back to it with a
warning).  numpy arrays inside the payload are encoded as tagged lists.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from cgamap.mapping.fileio import temp_pattern, write_bytes_atomic

log = logging.getLogger(__name__)

FORMAT = "cgamap-checkpoint"
VERSION = 1
CURRENT = "checkpoint.json"
PREVIOUS = "checkpoint.prev.json"


class CheckpointError(Exception):
    """A checkpoint file exists but cannot be used (truncated, corrupt, wrong format)."""


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return {"__nd__": str(obj.dtype), "shape": list(obj.shape), "data": obj.ravel().tolist()}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {str(k): _encode(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_encode(v) for v in obj]
    return obj


def _decode(obj: Any) -> Any:
    if isinstance(obj, dict):
        if "__nd__" in obj:
            return np.asarray(obj["data"], dtype=obj["__nd__"]).reshape(obj["shape"])
        return {k: _decode(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_decode(v) for v in obj]
    return obj


def encode_checkpoint(payload: dict) -> bytes:
    body = json.dumps(_encode(payload), separators=(",", ":"), allow_nan=True)
    digest = hashlib.sha256(body.encode()).hexdigest()
    head = json.dumps({"format": FORMAT, "version": VERSION, "saved_at": time.time(),
                       "sha256": digest})
    # header line, then payload line: the digest covers the payload bytes exactly
    return (head + "\n" + body + "\n").encode()


def decode_checkpoint(data: bytes) -> dict:
    try:
        head_line, body, *_ = data.decode().split("\n")
        head = json.loads(head_line)
    except (UnicodeDecodeError, ValueError) as exc:
        raise CheckpointError(f"unreadable header: {exc}") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise CheckpointError("not a cgamap checkpoint")
    if head.get("version") != VERSION:
        raise CheckpointError(f"unsupported version {head.get('version')!r}")
    if hashlib.sha256(body.encode()).hexdigest() != head.get("sha256"):
        raise CheckpointError("checksum mismatch (truncated or corrupt)")
    payload = _decode(json.loads(body))
    payload["_saved_at"] = head.get("saved_at")
    return payload


class CheckpointStore:
    """Checkpoints in ``state_dir``: ``checkpoint.json`` and the one before, ``.prev``."""

    def __init__(self, state_dir: str | os.PathLike):
        self.dir = Path(state_dir)
        self.saves = 0
        self.last_save_s: float | None = None  # duration of the last save
        self.last_saved_at: float | None = None
        self._current_bad = False  # set by load() when checkpoint.json was unusable

    @property
    def current(self) -> Path:
        return self.dir / CURRENT

    @property
    def previous(self) -> Path:
        return self.dir / PREVIOUS

    def save(self, payload: dict) -> Path:
        """Write ``payload`` atomically; the previous checkpoint becomes ``.prev``."""
        t0 = time.monotonic()
        self.dir.mkdir(parents=True, exist_ok=True)
        data = encode_checkpoint(payload)
        # a corrupt current one must not push a good .prev out
        write_bytes_atomic(self.current, data, mode=0o640,
                           keep_previous=False if self._current_bad else PREVIOUS)
        self._current_bad = False
        self.saves += 1
        self.last_save_s = time.monotonic() - t0
        self.last_saved_at = time.time()
        return self.current

    def load(self) -> dict | None:
        """The newest readable checkpoint, else None.  A corrupt current one falls back to the
        previous with a warning; leftover temp files of a killed save are removed."""
        for stale in self.dir.glob(temp_pattern(self.current)):
            try:
                stale.unlink()
            except OSError:
                pass
        for path in (self.current, self.previous):
            if not path.exists():
                continue
            try:
                payload = decode_checkpoint(path.read_bytes())
            except (CheckpointError, OSError, ValueError) as exc:
                log.warning("checkpoint %s unusable (%s); trying the previous one", path, exc)
                self._current_bad = path == self.current
                continue
            payload["_file"] = str(path)
            if path == self.previous:
                log.warning("loaded the previous checkpoint %s", path)
            return payload
        return None
