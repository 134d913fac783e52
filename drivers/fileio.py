"""Durable in-place writes for what the drivers layer records (stereo recordings).

A file is on the disk after a power cut only once its data is fsynced, and a newly made file
or folder only once the folder holding its name is fsynced too.  ``mapping.fileio`` has the
atomic (temp file + rename) writer the CLI hands down; drivers may not import ``mapping``
(layer rule), so the few primitives a driver needs by itself live here.
"""

from __future__ import annotations

import os
from pathlib import Path


def fsync_dir(directory: str | os.PathLike) -> None:
    """Make the names created, renamed or removed in ``directory`` durable."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def mkdir_synced(path: str | os.PathLike) -> None:
    """``mkdir -p`` whose new folders survive a power cut: each one made is fsynced into its
    parent.  A folder that already exists costs one ``stat``."""
    path = Path(path)
    missing: list[Path] = []
    while not path.is_dir():
        missing.append(path)
        if path.parent == path:
            break
        path = path.parent
    for folder in reversed(missing):
        try:
            folder.mkdir()
        except FileExistsError:  # made meanwhile by another writer, or a file in the way
            if not folder.is_dir():
                raise
        fsync_dir(folder.parent)


def write_bytes_synced(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` in place and fsync it (and, for a new file, its folder), so
    that once this returns the file is on the disk under its name.  Not atomic: a crash in
    the middle can leave a partial file, which a caller recording an index must not have named
    yet."""
    path = Path(path)
    created = not path.exists()
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    if created:
        fsync_dir(path.parent)


__all__ = ["fsync_dir", "mkdir_synced", "write_bytes_synced"]
