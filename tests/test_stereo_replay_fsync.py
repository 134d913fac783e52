"""The stereo recorder's default writer puts every file of a frame on the disk (data fsynced,
new names fsynced into their folders) before the ``frames.jsonl`` line that names it, and what
it writes reads back: the index is accepted whole and replays bit for bit.  Plus the drivers
layer's own ``fileio`` primitives."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from cgamap.drivers import fileio
from cgamap.drivers.sim.stereo_render import SyntheticGrabber
from cgamap.drivers.stereo_replay import (
    FILE_FIELDS,
    INDEX_NAME,
    ReplayGrabber,
    SequenceWriter,
    read_index,
)

pytest.importorskip("cv2")
if not os.path.isdir("/proc/self/fd"):
    pytest.skip("needs /proc/self/fd to name the fsynced files", allow_module_level=True)

N = 3


@pytest.fixture(scope="module")
def frames():
    g = SyntheticGrabber("corridor", size=(120, 80), fx=90.0, fps=2.0, t0=1.0,
                         sgbm={"num_disparities": 16})
    return list(g.frames(count=N))


@pytest.fixture
def fsynced(monkeypatch) -> list[Path]:
    """The paths fsynced from now on, in order (files and folders alike)."""
    seen: list[Path] = []
    real = os.fsync

    def fsync(fd):
        seen.append(Path(os.readlink(f"/proc/self/fd/{fd}")))
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return seen


def test_default_writer_fsyncs_each_file_and_name_before_its_line(tmp_path, frames, fsynced):
    out = (tmp_path / "new" / "rec").resolve()
    w = SequenceWriter(out, stride=4)
    recs = [w.write(f) for f in frames]
    index = out / INDEX_NAME
    line_at = [i for i, p in enumerate(fsynced) if p == index]
    assert len(line_at) == N                             # one fsync per appended line
    assert fsynced[:line_at[0]].count(tmp_path.resolve()) >= 1   # "new/" made durably
    for rec, at in zip(recs, line_at, strict=True):
        before = fsynced[:at]
        named = [out / rec[k] for k in FILE_FIELDS if k in rec]
        assert len(named) >= 3                           # left, right, points at least
        for path in named:
            assert path in before, f"{path} not fsynced before its line"
            # a new file's name is in its folder for good: the folder fsynced after the file
            first = before.index(path)
            assert path.parent in before[first + 1:], f"{path.parent} not fsynced"
        # the folders themselves (left/, right/, ...) were fsynced into the recording folder
        assert out in before


def test_default_writer_recording_reads_back_whole(tmp_path, frames):
    w = SequenceWriter(tmp_path / "rec", stride=4)
    recs = [w.write(f) for f in frames]
    records, torn = read_index(tmp_path / "rec" / INDEX_NAME)
    assert records == recs and torn == 0
    g = ReplayGrabber(tmp_path / "rec", use_recorded=True)
    with g:
        got = list(g.frames())
    assert g.torn_tail == 0 and [f.seq for f in got] == [f.seq for f in frames]
    for a, b in zip(got, frames, strict=True):
        assert a.stamp_ns == b.stamp_ns
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        want = np.where(b.disparity > 0, b.disparity, np.nan)    # 0 is stored as "none"
        assert np.allclose(a.disparity, want, atol=1 / 256, equal_nan=True)


# -- drivers.fileio ------------------------------------------------------------------------------

def test_write_bytes_synced_replaces_content_and_syncs_a_new_name(tmp_path, fsynced):
    target = (tmp_path / "f.bin").resolve()
    fileio.write_bytes_synced(target, b"first, longer")
    assert target.read_bytes() == b"first, longer"
    assert fsynced == [target, target.parent]            # data, then the new name
    fsynced.clear()
    fileio.write_bytes_synced(target, b"second")
    assert target.read_bytes() == b"second"
    assert fsynced == [target]                           # same name: nothing new in the folder


def test_mkdir_synced_makes_parents_durably_and_refuses_a_file(tmp_path, fsynced):
    base = tmp_path.resolve()
    fileio.mkdir_synced(base / "a" / "b" / "c")
    assert (base / "a" / "b" / "c").is_dir()
    assert fsynced == [base, base / "a", base / "a" / "b"]
    fsynced.clear()
    fileio.mkdir_synced(base / "a" / "b")                # exists: no work
    assert fsynced == []
    (base / "file").write_bytes(b"x")
    with pytest.raises(FileExistsError):
        fileio.mkdir_synced(base / "file")
    with pytest.raises(OSError):
        fileio.mkdir_synced(base / "file" / "sub")


def test_fsync_dir_refuses_a_file(tmp_path):
    (tmp_path / "f").write_bytes(b"")
    fileio.fsync_dir(tmp_path)
    with pytest.raises(NotADirectoryError):
        fileio.fsync_dir(tmp_path / "f")
