"""The last in-place writers go through mapping.fileio: the stereo recorder's per-frame files
and calibration (injected by ``cgamap stereo``), the plane map's Hough picture.  A write that
fails midway leaves no partial file under a final name, no temp file, and earlier files whole."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest
from cgamap.daemon.cli import main
from cgamap.drivers.sim.stereo_render import SyntheticGrabber
from cgamap.drivers.stereo_calib import (
    calibration_text,
    load_calibration,
    rectified_calibration,
    save_calibration,
)
from cgamap.drivers.stereo_replay import ReplayGrabber, SequenceWriter
from cgamap.mapping.fileio import write_bytes_atomic
from cgamap.mapping.planemap import MapPlane, PlaneMap

SIZE = (160, 100)


class Crash(OSError):
    pass


def crash_replace_on(monkeypatch, call: int) -> list:
    """``os.replace`` raises on its call number ``call`` (0: the first) and after."""
    real, calls = os.replace, []

    def replace(src, dst):
        calls.append(dst)
        if len(calls) > call:
            raise Crash(28, "No space left on device", str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    return calls


def snapshot(folder) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def temps(folder) -> list[str]:
    return [p.name for p in folder.rglob("*.tmp")]


@pytest.fixture(scope="module")
def frames():
    g = SyntheticGrabber("corridor", size=SIZE, fx=110.0, fps=2.0, t0=1.0,
                         sgbm={"num_disparities": 16})
    return list(g.frames(count=2))


def test_calibration_text_is_what_save_calibration_writes(tmp_path):
    c = rectified_calibration(300.0, 160.0, 100.0, 0.12, size=(320, 200), doffs=1.5)
    save_calibration(c, tmp_path / "a.yaml")
    assert (tmp_path / "a.yaml").read_text() == calibration_text(c)
    back = load_calibration(tmp_path / "a.yaml")
    assert (back.fx, back.baseline, back.doffs, back.size) == (300.0, 0.12, 1.5, (320, 200))


def test_recorder_frame_cut_midway_leaves_earlier_frames_and_no_partial_file(
        tmp_path, monkeypatch, frames):
    w = SequenceWriter(tmp_path, write_file=write_bytes_atomic)
    w.write(frames[0])
    before = snapshot(tmp_path)
    n_files = len(w.encode(frames[1])[1])
    calls = crash_replace_on(monkeypatch, 2)     # the second frame's third file fails
    with pytest.raises(Crash):
        w.write(frames[1])
    monkeypatch.undo()
    assert len(calls) == 3 < n_files
    after = snapshot(tmp_path)
    assert {k: after[k] for k in before} == before   # frame 0 and the index untouched
    assert temps(tmp_path) == []
    # what frame 1 left are whole files (each decodes) that no index line names
    rec1, files1 = w.encode(frames[1])
    new = set(after) - set(before)
    assert new == set(list(files1)[:2])
    assert all(after[k] == files1[k] for k in new)
    assert [p.name for p in (tmp_path / "disparity").iterdir()] == ["000000.png"]
    replay = ReplayGrabber(tmp_path)
    replay.open()
    assert len(replay) == 1 and replay.grab().seq == frames[0].seq


def test_recorder_keeps_an_existing_calibration_when_its_write_fails(
        tmp_path, monkeypatch, frames):
    (tmp_path / "calibration.yaml").write_text("fx: 1\ncx: 0\ncy: 0\nbaseline: 1\n")
    crash_replace_on(monkeypatch, 0)
    with pytest.raises(Crash):
        SequenceWriter(tmp_path, write_file=write_bytes_atomic).write(frames[0])
    monkeypatch.undo()
    assert snapshot(tmp_path) == {"calibration.yaml": b"fx: 1\ncx: 0\ncy: 0\nbaseline: 1\n"}


def test_recorder_encodes_the_whole_frame_before_writing_anything(tmp_path, frames):
    bad = dataclasses.replace(frames[0], right=np.zeros((4, 4, 7), np.uint8))  # 7 channels
    with pytest.raises(ValueError, match="cannot encode"):
        SequenceWriter(tmp_path).write(bad)   # the default in-place writer, too
    assert snapshot(tmp_path) == {}


def test_cgamap_stereo_writes_frames_atomically(tmp_path, monkeypatch, capsys):
    out = tmp_path / "rec"
    argv = ["stereo", "--model", "synthetic", "--device", "corridor", "--count", "2",
            "--num-disparities", "16", "--stride", "8", "--out", str(out)]
    calls = crash_replace_on(monkeypatch, 7)   # calibration + 5 files of frame 0, then 1 more
    code = main(argv)
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert code != 0 and "No space left" in err and "Traceback" not in err, err
    assert len(calls) == 8      # every file went through os.replace: the atomic writer
    assert temps(out) == []
    recs = [json.loads(x) for x in (out / "frames.jsonl").read_text().splitlines()]
    assert [r["seq"] for r in recs] == [0]
    for rel in (recs[0][k] for k in ("left", "right", "disparity", "depth", "points")):
        assert (out / rel).stat().st_size > 0


def _plane_map() -> PlaneMap:
    pm = PlaneMap()
    square = np.array([[0, 0, 0.5], [1, 0, 0.5], [1, 1, 0.5], [0, 1, 0.5]], float)
    pm.planes.append(MapPlane(np.array([0.0, 0.0, 1.0]), 0.5, square, inliers=100))
    return pm


def test_hough_png_write_failure_keeps_the_previous_picture(tmp_path, monkeypatch):
    path = tmp_path / "hough.png"
    pm = _plane_map()
    pm.save_hough_png(path)
    before = snapshot(tmp_path)
    assert before["hough.png"].startswith(b"\x89PNG")
    pm.planes[0].rho = 2.0
    crash_replace_on(monkeypatch, 0)
    with pytest.raises(Crash):
        pm.save_hough_png(path, size=(640, 360))
    monkeypatch.undo()
    assert snapshot(tmp_path) == before
    pm.save_hough_png(path, size=(640, 360))
    assert snapshot(tmp_path) != before and temps(tmp_path) == []

