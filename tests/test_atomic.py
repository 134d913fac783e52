"""One atomic write for every file the stack saves: a crash mid-write leaves the old file whole
and no temp file; keep_previous keeps the old one under a backup name."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest
from cgamap.calib.pairs import PairSet, load_pairs, save_pairs
from cgamap.daemon.store import CheckpointStore
from cgamap.mapping import fileio
from cgamap.mapping.fileio import backup_path, write_bytes_atomic, write_text_atomic
from cgamap.mapping.places import PlaceDatabase
from cgamap.mapping.planemap import PlaneMap
from hypothesis import given, settings
from hypothesis import strategies as st


class Crash(Exception):
    pass


def leftovers(directory) -> list[str]:
    return [p for p in os.listdir(directory) if p.endswith(".tmp")]


def crash_on(monkeypatch, name: str, after: int = 0) -> None:
    """Make ``os.<name>`` raise on its call number ``after`` (0: the first) only."""
    real, calls = getattr(os, name), []

    def boom(*args, **kwargs):
        calls.append(args)
        if len(calls) == after + 1:
            raise Crash(name)
        return real(*args, **kwargs)

    monkeypatch.setattr(os, name, boom)


def test_write_replaces_content_and_fsyncs_the_directory(tmp_path, monkeypatch):
    synced = []
    real = fileio.fsync_dir
    monkeypatch.setattr(fileio, "fsync_dir", lambda d: (synced.append(str(d)), real(d)))
    p = tmp_path / "a.json"
    assert write_text_atomic(p, "one") is None
    assert write_text_atomic(p, "twö") is None
    assert p.read_text(encoding="utf-8") == "twö"
    assert synced == [str(tmp_path)] * 2
    assert leftovers(tmp_path) == [] and not backup_path(p).exists()


@pytest.mark.parametrize("where", [("fsync", 0), ("replace", 0)])
def test_crash_mid_write_keeps_the_old_file_and_no_temp(tmp_path, monkeypatch, where):
    p = tmp_path / "map.json"
    p.write_text("old")
    crash_on(monkeypatch, *where)
    with pytest.raises(Crash):
        write_text_atomic(p, "new " * 10_000)
    monkeypatch.undo()
    assert p.read_text() == "old"
    assert sorted(os.listdir(tmp_path)) == ["map.json"]


def test_crash_between_backup_and_rename_puts_the_old_file_back(tmp_path, monkeypatch):
    p = tmp_path / "calib.yaml"
    p.write_text("old")
    crash_on(monkeypatch, "replace", after=1)  # the backup rename passes, the second fails
    with pytest.raises(Crash):
        write_text_atomic(p, "new", keep_previous=True)
    monkeypatch.undo()
    assert p.read_text() == "old"
    assert sorted(os.listdir(tmp_path)) == ["calib.yaml"]


def test_keep_previous(tmp_path):
    p = tmp_path / "pairs.json"
    assert write_text_atomic(p, "1", keep_previous=True) is None  # nothing to keep yet
    assert write_text_atomic(p, "2", keep_previous=True) == tmp_path / "pairs.json.bak"
    assert (tmp_path / "pairs.json.bak").read_text() == "1"
    assert write_text_atomic(p, "3", keep_previous="pairs.old") == tmp_path / "pairs.old"
    assert (tmp_path / "pairs.old").read_text() == "2" and p.read_text() == "3"
    assert write_text_atomic(p, "4") is None  # default: the previous one is not kept
    assert (tmp_path / "pairs.old").read_text() == "2"
    with pytest.raises(ValueError, match="keep_previous"):
        write_text_atomic(p, "5", keep_previous="sub/x")
    assert p.read_text() == "4" and leftovers(tmp_path) == []


def test_mode_follows_umask_and_target_dir_is_refused(tmp_path):
    old = os.umask(0o027)
    try:
        write_bytes_atomic(tmp_path / "a", b"x")
        write_bytes_atomic(tmp_path / "b", b"x", mode=0o600)
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a").stat().st_mode) == 0o640
    assert stat.S_IMODE((tmp_path / "b").stat().st_mode) == 0o600
    (tmp_path / "d").mkdir()
    with pytest.raises(IsADirectoryError):
        write_text_atomic(tmp_path / "d", "x")
    assert leftovers(tmp_path) == []


def test_relative_path_in_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    write_text_atomic("rel.txt", "x", keep_previous=True)
    write_text_atomic("rel.txt", "y", keep_previous=True)
    assert (tmp_path / "rel.txt").read_text() == "y"
    assert (tmp_path / "rel.txt.bak").read_text() == "x"


@settings(max_examples=30, deadline=None)
@given(st.binary(max_size=5000))
def test_bytes_round_trip(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("rt") / "f.bin"
    write_bytes_atomic(p, data)
    assert p.read_bytes() == data


# -- the writers that use it ---------------------------------------------------------------


def test_planemap_and_places_saves_are_atomic(tmp_path, monkeypatch):
    pm = PlaneMap()
    pm.add_virtual_walls(np.array([[[0.0, 0.0], [4.0, 0.0]]]))
    db = PlaceDatabase()
    for path, save in ((tmp_path / "planes.json", pm.save_json),
                       (tmp_path / "places.json", db.save)):
        save(path)
        before = path.read_text()
        json.loads(before)
        crash_on(monkeypatch, "fsync")
        with pytest.raises(Crash):
            save(path)
        monkeypatch.undo()
        assert path.read_text() == before
    assert leftovers(tmp_path) == []
    assert len(PlaneMap.from_dict(json.loads((tmp_path / "planes.json").read_text())).planes) == 1


def test_pairs_file_keeps_previous(tmp_path):
    eye = np.tile(np.eye(4), (3, 1, 1))
    p = tmp_path / "pairs.json"
    save_pairs(p, PairSet(eye, eye, meta={"run": 1}))
    save_pairs(p, PairSet(eye, eye, meta={"run": 2}))
    assert load_pairs(p).meta["run"] == 2
    assert load_pairs(backup_path(p)).meta["run"] == 1


def test_checkpoint_crash_mid_save_keeps_current_and_prev(tmp_path, monkeypatch):
    store = CheckpointStore(tmp_path)
    store.save({"i": 1})
    store.save({"i": 2})
    crash_on(monkeypatch, "replace", after=1)  # current -> .prev passes, tmp -> current fails
    with pytest.raises(Crash):
        store.save({"i": 3})
    monkeypatch.undo()
    assert leftovers(tmp_path) == []
    assert CheckpointStore(tmp_path).load()["i"] == 2
    assert stat.S_IMODE(store.current.stat().st_mode) & 0o007 == 0  # 0640: not world-readable
