"""Atomic file writes: a reader (or the next start after a crash) sees the old file or the new
one, never half of one.

The data goes to a temp file in the target's directory (a rename is only atomic within one
file system), is flushed and fsynced, renamed over the target with ``os.replace``, and the
directory is fsynced so the rename itself survives a power cut.  Optionally the previous file
is first renamed to a backup name.  ``mapping`` is the lowest layer that writes files, so
``calib`` and ``daemon`` import this module from here.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

BACKUP_SUFFIX = ".bak"


def backup_path(path: str | os.PathLike, keep_previous: bool | str = True) -> Path:
    """Where ``keep_previous`` puts the previous file: ``<name>.bak`` for True, else the given
    file name in the same directory."""
    path = Path(path)
    if keep_previous is True:
        return path.with_name(path.name + BACKUP_SUFFIX)
    name = str(keep_previous)
    if not name or Path(name).name != name:
        raise ValueError(f"keep_previous: expected a file name without a directory, got {name!r}")
    return path.with_name(name)


def temp_pattern(path: str | os.PathLike) -> str:
    """Glob (relative to the directory) matching the temp files a killed write leaves."""
    return f".{Path(path).name}.*.tmp"


def fsync_dir(directory: str | os.PathLike) -> None:
    """Make renames in ``directory`` durable."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _open_temp(path: Path, mode: int) -> tuple[int, Path]:
    # O_EXCL with our own unique name instead of mkstemp: the kernel applies the umask to
    # ``mode`` (mkstemp makes 0600, and reading the umask means changing it, racing threads)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
        try:
            return os.open(tmp, flags, mode), tmp
        except FileExistsError:
            continue
    raise FileExistsError(17, "no free temp file name", str(path))


def write_bytes_atomic(path: str | os.PathLike, data: bytes, keep_previous: bool | str = False,
                       mode: int = 0o666) -> Path | None:
    """Replace ``path`` by ``data`` atomically (temp file, fsync, ``os.replace``, directory
    fsync).  ``keep_previous``: True keeps an existing file as ``<name>.bak``, a string keeps
    it under that file name in the same directory.  ``mode`` is masked by the umask as with
    ``open``.  Returns the backup's path when a previous file was kept, else None.  On any
    error the target is untouched and no temp file is left behind."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(21, "Is a directory", str(path))
    backup = backup_path(path, keep_previous) if keep_previous else None
    fd, tmp = _open_temp(path, mode)
    moved = False
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if backup is not None and path.is_file():
            os.replace(path, backup)
            moved = True
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        if moved and not path.exists():  # put the previous file back where it was
            os.replace(backup, path)
        raise
    fsync_dir(path.parent)
    return backup if moved else None


def write_text_atomic(path: str | os.PathLike, text: str, keep_previous: bool | str = False,
                      mode: int = 0o666, encoding: str = "utf-8") -> Path | None:
    """``write_bytes_atomic`` for text (UTF-8 by default)."""
    return write_bytes_atomic(path, text.encode(encoding), keep_previous, mode)
