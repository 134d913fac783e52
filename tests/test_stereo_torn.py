"""A stereo recording that survives a crash mid-write: the index's torn last line is dropped
and counted, a damaged line elsewhere is an error naming it, each line is written whole
(one write, fsync) after the frame's files, and missing files are one clear line."""

from __future__ import annotations

import json
import logging
import os
import shutil

import numpy as np
import pytest
from cgamap.daemon import cli
from cgamap.drivers import stereo_replay
from cgamap.drivers.sim.stereo_render import SyntheticGrabber
from cgamap.drivers.stereo_replay import (
    RecordingIndexError,
    ReplayGrabber,
    SequenceWriter,
    read_index,
)

pytest.importorskip("cv2")

N = 3
TORN = b'{"seq": 3, "stamp_ns": 4000, "left": "left/0000'   # a line cut short


@pytest.fixture(scope="module")
def frames():
    g = SyntheticGrabber("corridor", size=(160, 100), fx=110.0, fps=2.0, t0=1.0,
                         sgbm={"num_disparities": 16})
    return list(g.frames(count=N + 1))


@pytest.fixture(scope="module")
def master(tmp_path_factory, frames):
    out = tmp_path_factory.mktemp("rec")
    w = SequenceWriter(out, stride=4)
    for f in frames[:N]:
        w.write(f)
    return out


@pytest.fixture
def rec(tmp_path, master):
    """A fresh copy of the three-frame recording (tests damage it)."""
    out = tmp_path / "rec"
    shutil.copytree(master, out)
    return out


def index(rec) -> bytes:
    return (rec / "frames.jsonl").read_bytes()


def set_index(rec, data: bytes) -> None:
    (rec / "frames.jsonl").write_bytes(data)


def replay_all(folder, **kw) -> tuple[ReplayGrabber, list]:
    g = ReplayGrabber(folder, use_recorded=True, **kw)
    with g:
        got = list(g.frames())
    return g, got


def _cli(monkeypatch, argv):
    monkeypatch.setattr(cli, "COMMAND_MODULES", ["cgamap.daemon.cmd_stereo"])
    return cli.main([str(a) for a in argv])


def one_line(err: str, *needles: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


# -- reading -------------------------------------------------------------------------------

def test_torn_last_line_is_dropped_counted_and_warned_once(rec, caplog):
    set_index(rec, index(rec) + TORN)
    with caplog.at_level(logging.WARNING, logger="cgamap.drivers.stereo_replay"):
        g, got = replay_all(rec)
    assert g.torn_tail == 1 and len(g) == N
    assert [f.seq for f in got] == list(range(N))
    warns = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warns) == 1 and "torn" in warns[0].getMessage()
    assert "line 4" not in warns[0].getMessage() and "(4)" in warns[0].getMessage()


def test_whole_recording_has_no_torn_tail(rec, caplog):
    with caplog.at_level(logging.WARNING):
        g, got = replay_all(rec)
    assert g.torn_tail == 0 and len(got) == N and not caplog.records


def test_last_line_missing_only_its_newline_is_a_frame(rec):
    set_index(rec, index(rec).rstrip(b"\n"))
    g, got = replay_all(rec)
    assert g.torn_tail == 0 and len(got) == N


@pytest.mark.parametrize("tail", [b"\0" * 37, b'{"seq"', b"\xff\xfe{", b"{" * 5])
def test_any_unterminated_non_json_tail_is_torn(rec, tail):
    set_index(rec, index(rec) + tail)
    records, torn = read_index(rec / "frames.jsonl")
    assert torn == 1 and len(records) == N


def test_only_a_torn_line_is_no_frames(rec):
    set_index(rec, TORN)
    with pytest.raises(ValueError, match="no image pairs"):
        ReplayGrabber(rec).open()


@pytest.mark.parametrize("bad, problem", [
    (b'{"seq": 1, "left": "le', "Unterminated string"),
    (b"not json", "Expecting value"),
    (b"[1, 2]", "not an object"),
    (b'{"seq": 1}', '"left"'),
    (b'{"seq": 1, "left": 7}', '"left"'),
    (b'{"seq": 1, "left": "left/000001.png", "right": null}', '"right"'),
    (b'{"seq": 1, "left": "\xff"}', "UTF-8"),
    (b'{"seq": "1", "left": "left/000001.png"}', '"seq"'),
    (b'{"stamp_ns": 1.5, "left": "left/000001.png"}', '"stamp_ns"'),
    (b'{"left": "left/000001.png", "pose": [1, 2]}', '"pose"'),
    (b'{"left": "left/000001.png", "pan": 0.1}', '"pan" and "tilt"'),
    (b'{"left": "left/000001.png", "pan": 0.1, "tilt": "up"}', '"pan" and "tilt"'),
])
def test_damaged_middle_line_is_an_error_naming_the_line(rec, bad, problem):
    lines = index(rec).splitlines(keepends=True)
    lines[1] = bad + b"\n"
    set_index(rec, b"".join(lines) + TORN)        # a torn tail does not excuse the middle
    with pytest.raises(RecordingIndexError, match=r"line 2: ") as err:
        ReplayGrabber(rec).open()
    assert err.value.lineno == 2 and problem in err.value.problem
    assert "frames.jsonl" in str(err.value)


def test_damaged_last_line_with_its_newline_is_not_torn(rec):
    set_index(rec, index(rec) + TORN + b"\n")     # written whole: damage, not a cut write
    with pytest.raises(RecordingIndexError) as err:
        ReplayGrabber(rec).open()
    assert err.value.lineno == N + 1


def test_blank_lines_are_skipped_and_counted_in_line_numbers(rec):
    lines = index(rec).splitlines(keepends=True)
    set_index(rec, lines[0] + b"\n  \n" + b"oops\n" + b"".join(lines[1:]))
    with pytest.raises(RecordingIndexError, match="line 4"):
        ReplayGrabber(rec).open()


# -- missing files -------------------------------------------------------------------------

@pytest.mark.parametrize("sub, kw", [("left", {}), ("right", {}),
                                     ("disparity", {"use_recorded": True})])
def test_missing_file_of_a_frame_names_the_frame_and_the_file(rec, sub, kw):
    (rec / sub / "000001.png").unlink()
    g = ReplayGrabber(rec, **kw)
    g.open()
    g.grab()
    with pytest.raises(ValueError, match=rf"frame 1: {sub} file {sub}/000001.png is missing"):
        g.grab()


def test_unreadable_image_and_array_are_named(rec):
    (rec / "left" / "000000.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="frame 0: left file left/000000.png is not a readable"):
        ReplayGrabber(rec, use_recorded=True).grab()
    rec2 = rec.parent / "rec2"
    shutil.copytree(rec, rec2)
    shutil.copy(rec / "left" / "000001.png", rec2 / "left" / "000000.png")
    recs, _ = read_index(rec2 / "frames.jsonl")
    for r in recs:   # depth must stand in for the matching: no right image, no disparity
        r.pop("right"), r.pop("disparity")
    set_index(rec2, "".join(json.dumps(r) + "\n" for r in recs).encode())
    (rec2 / "depth" / "000000.npy").write_bytes(b"\x93NUMPY torn")
    with pytest.raises(ValueError, match="frame 0: depth file depth/000000.npy is not a read"):
        ReplayGrabber(rec2).grab()
    (rec2 / "depth" / "000000.npy").unlink()
    with pytest.raises(ValueError, match="frame 0: depth file depth/000000.npy is missing"):
        ReplayGrabber(rec2).grab()


def test_missing_ground_truth_depth_is_still_optional(rec):
    (rec / "depth" / "000001.npy").unlink()   # right image present: depth is ground truth only
    g = ReplayGrabber(rec, sgbm={"num_disparities": 16})
    with g:
        got = list(g.frames())
    assert len(got) == N and got[1].ground_truth is None and got[0].ground_truth is not None


# -- writing -------------------------------------------------------------------------------

def test_each_line_is_one_write_then_fsync_after_the_frames_files(tmp_path, frames,
                                                                  monkeypatch):
    events: list[tuple] = []
    real_write, real_fsync = os.write, os.fsync

    def write(fd, data):
        events.append(("write", bytes(data)))
        return real_write(fd, data)

    def fsync(fd):
        events.append(("fsync",))
        return real_fsync(fd)

    def write_file(path, data):
        events.append(("file", path.relative_to(tmp_path).as_posix()))
        path.write_bytes(data)

    monkeypatch.setattr(stereo_replay.os, "write", write)
    monkeypatch.setattr(stereo_replay.os, "fsync", fsync)
    w = SequenceWriter(tmp_path, write_file=write_file, stride=4)
    recs = [w.write(f) for f in frames[:2]]
    monkeypatch.undo()
    writes = [e for e in events if e[0] == "write"]
    assert [json.loads(e[1]) for e in writes] == recs
    assert all(e[1].endswith(b"\n") and e[1].count(b"\n") == 1 for e in writes)
    for r in recs:
        at = events.index(("write", (json.dumps(r) + "\n").encode()))
        files = {e[1] for e in events[:at] if e[0] == "file"}
        named = {r[k] for k in stereo_replay.FILE_FIELDS if k in r}
        assert named <= files                                 # files first, then the line
        assert events[at + 1] == ("fsync",)                   # and the line is on the disk
    assert index(tmp_path) == b"".join(e[1] for e in writes)


def test_short_write_leaves_no_partial_line(tmp_path, frames, monkeypatch):
    w = SequenceWriter(tmp_path, stride=4)
    w.write(frames[0])
    before = index(tmp_path)
    real_write = os.write
    monkeypatch.setattr(stereo_replay.os, "write", lambda fd, data: real_write(fd, data[:9]))
    with pytest.raises(OSError, match="No space left"):
        w.write(frames[1])
    monkeypatch.undo()
    assert index(tmp_path) == before and w.count == 1
    w.write(frames[1])                       # the disk freed up: the next line is whole
    assert [r["seq"] for r in read_index(tmp_path / "frames.jsonl")[0]] == [0, 1]


def test_writer_on_existing_folder_truncates_a_torn_tail(rec, frames, caplog):
    whole = index(rec)
    set_index(rec, whole + TORN)
    with caplog.at_level(logging.WARNING, logger="cgamap.drivers.stereo_replay"):
        w = SequenceWriter(rec, stride=4)
    assert w.torn_tail == 1 and index(rec) == whole
    assert len(caplog.records) == 1
    w.write(frames[N])
    records, torn = read_index(rec / "frames.jsonl")
    assert torn == 0 and [r["seq"] for r in records] == list(range(N + 1))


def test_writer_on_existing_folder_completes_a_whole_last_line(rec, frames):
    set_index(rec, index(rec).rstrip(b"\n"))
    w = SequenceWriter(rec, stride=4)
    assert w.torn_tail == 0
    w.write(frames[N])
    records, torn = read_index(rec / "frames.jsonl")
    assert torn == 0 and [r["seq"] for r in records] == list(range(N + 1))


def test_writer_on_a_folder_of_only_a_torn_line(rec):
    set_index(rec, TORN)
    assert SequenceWriter(rec).torn_tail == 1 and index(rec) == b""


# -- the CLI -------------------------------------------------------------------------------

def test_cli_replays_a_recording_with_a_torn_tail(rec, tmp_path, monkeypatch, capsys, caplog):
    set_index(rec, index(rec) + TORN)
    out = tmp_path / "again"
    caplog.set_level(logging.WARNING, logger="cgamap.drivers.stereo_replay")
    rc = _cli(monkeypatch, ["stereo", "--model", "replay", "--device", rec, "--out", out,
                            "--count", "10", "--num-disparities", "16", "--stride", "4"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert len(cap.out.strip().splitlines()) == N
    # the one warning (on stderr outside pytest, whose handler takes the log here)
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert "torn" in caplog.records[0].getMessage()
    assert [r["seq"] for r in read_index(out / "frames.jsonl")[0]] == list(range(N))


def test_cli_damaged_middle_line_is_one_line(rec, tmp_path, monkeypatch, capsys):
    lines = index(rec).splitlines(keepends=True)
    lines[1] = lines[1][:20] + b"\n"
    set_index(rec, b"".join(lines))
    rc = _cli(monkeypatch, ["stereo", "--model", "replay", "--device", rec, "--out",
                            tmp_path / "o"])
    err = capsys.readouterr().err
    assert rc == 1
    one_line(err, f"--device {rec}", "frames.jsonl is damaged (line 2:")
    assert not (tmp_path / "o").exists()


def test_cli_missing_image_is_one_line(rec, tmp_path, monkeypatch, capsys):
    (rec / "right" / "000001.png").unlink()
    rc = _cli(monkeypatch, ["stereo", "--model", "replay", "--device", rec, "--out",
                            tmp_path / "o", "--count", "5", "--num-disparities", "16"])
    cap = capsys.readouterr()
    assert rc == 1 and len(cap.out.strip().splitlines()) == 1   # frame 0 went through
    one_line(cap.err, "frame 1", "right/000001.png", "missing")


def test_whole_frames_of_the_recorder_replay_bit_for_bit(rec, frames):
    _, got = replay_all(rec)
    for a, b in zip(frames[:N], got, strict=True):
        assert np.array_equal(a.left, b.left) and a.stamp_ns == b.stamp_ns
