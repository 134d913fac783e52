"""Stereo sources and sinks: recording/replay, OpenCV capture, the CLI, the depthai backend."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from cgamap.daemon import cli
from cgamap.drivers.sim.stereo_render import SyntheticGrabber
from cgamap.drivers.stereo import frame_points, open_grabber
from cgamap.drivers.stereo_calib import load_calibration, save_calibration
from cgamap.drivers.stereo_opencv import parse_device
from cgamap.drivers.stereo_replay import (
    ReplayGrabber,
    SequenceWriter,
    decode_disparity,
    encode_disparity,
)

cv2 = pytest.importorskip("cv2")

SIZE = (320, 200)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Three synthetic corridor frames written as a recording."""
    out = tmp_path_factory.mktemp("rec")
    g = SyntheticGrabber("corridor", size=SIZE, fx=225.0, fps=2.0, t0=1.0, tilt=0.1,
                         sgbm={"num_disparities": 32})
    frames = list(g.frames(count=3))
    w = SequenceWriter(out)
    for f in frames:
        w.write(f)
    return out, frames


def test_disparity_png_codec():
    d = np.array([[0.0, 1.5, np.nan], [63.25, 200.0, 0.00390625]], np.float32)
    back = decode_disparity(encode_disparity(d))
    assert np.isnan(back[0, 0]) and np.isnan(back[0, 2])  # 0 and NaN both mean none
    assert np.allclose(back[np.isfinite(back)], [1.5, 63.25, 200.0, 0.00390625])


def test_recording_layout(recorded):
    out, frames = recorded
    recs = [json.loads(x) for x in (out / "frames.jsonl").read_text().splitlines()]
    assert [r["seq"] for r in recs] == [0, 1, 2]
    for sub in ("left", "right", "disparity", "depth", "points"):
        assert len(list((out / sub).iterdir())) == 3
    c = load_calibration(out / "calibration.yaml")
    assert c.fx == pytest.approx(225.0) and c.baseline == pytest.approx(0.075)
    pts = np.load(out / recs[0]["points"])
    assert pts.shape == (recs[0]["n_points"], 3) and pts.dtype == np.float32
    assert recs[1]["pose"] != recs[0]["pose"] and "tilt" in recs[0]


def test_replay_reproduces_frames(recorded):
    out, frames = recorded
    with ReplayGrabber(out, sgbm={"num_disparities": 32}) as g:
        replayed = list(g.frames())
    assert len(replayed) == 3
    for a, b in zip(frames, replayed, strict=True):
        assert a.stamp_ns == b.stamp_ns and a.seq == b.seq
        assert np.array_equal(a.left, b.left)
        assert np.allclose(a.disparity, b.disparity, equal_nan=True)  # same SGBM path
        assert b.ground_truth is not None and b.pantilt.tilt == pytest.approx(0.1)
        assert tuple(b.pose_ref) == pytest.approx(a.pose_ref)
    # Using the recorded disparity instead gives the same points (to the PNG's 1/256 px).
    with ReplayGrabber(out, use_recorded=True) as g:
        f = g.grab()
    p1, p2 = frame_points(frames[0]), frame_points(f)
    assert len(p1) == len(p2) and np.allclose(p1, p2, atol=0.05)


def test_replay_plain_folder_and_loop(tmp_path, recorded):
    out, frames = recorded
    for sub in ("left", "right"):
        (tmp_path / sub).mkdir()
        for p in sorted((out / sub).iterdir()):
            (tmp_path / sub / p.name).write_bytes(p.read_bytes())
    (tmp_path / "calibration.yaml").write_bytes((out / "calibration.yaml").read_bytes())
    g = open_grabber("replay", str(tmp_path), {"loop": True, "sgbm": {"num_disparities": 32}})
    with g:
        seqs = [f.seq for f in g.frames(count=5)]
    assert seqs == [0, 1, 2, 0, 1]


def test_replay_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such folder"):
        ReplayGrabber(tmp_path / "nope").open()
    with pytest.raises(FileNotFoundError, match="calibration"):
        ReplayGrabber(tmp_path).open()


def test_parse_opencv_device():
    assert parse_device("0,1") == ("pair", [0, 1])
    assert parse_device("sbs:2") == ("sbs", [2])
    assert parse_device("4") == ("sbs", [4])
    assert parse_device("a.avi, b.avi") == ("pair", ["a.avi", "b.avi"])
    with pytest.raises(ValueError):
        parse_device("0,1,2")


def _write_video(path, frames):
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 5, (w, h), isColor=False)
    assert vw.isOpened()
    for f in frames:
        vw.write(f)
    vw.release()


def test_opencv_backend_side_by_side_and_pair(tmp_path, recorded):
    _, frames = recorded
    save_calibration(frames[0].calib, tmp_path / "calib.yaml")
    _write_video(tmp_path / "sbs.avi", [np.hstack([f.left, f.right]) for f in frames])
    _write_video(tmp_path / "l.avi", [f.left for f in frames])
    _write_video(tmp_path / "r.avi", [f.right for f in frames])
    cfg = {"calibration": str(tmp_path / "calib.yaml"), "sgbm": {"num_disparities": 32}}
    for url in (f"sbs:{tmp_path / 'sbs.avi'}", f"{tmp_path / 'l.avi'},{tmp_path / 'r.avi'}"):
        with open_grabber("opencv", url, cfg) as g:
            got = list(g.frames(count=10))  # stops at the end of the video
        assert len(got) == 3
        assert np.allclose(got[1].disparity, frames[1].disparity, equal_nan=True)
    with pytest.raises(ValueError, match="calibration file is required"):
        open_grabber("opencv", "0,1", {})
    with pytest.raises(RuntimeError, match="cannot open"):
        with open_grabber("opencv", f"sbs:{tmp_path / 'missing.avi'}", cfg):
            pass


# ---------------------------------------------------------------- CLI

def _cli(monkeypatch, argv):
    monkeypatch.setattr(cli, "COMMAND_MODULES", ["cgamap.daemon.cmd_stereo"])
    return cli.main(argv)


def test_cli_stereo_synthetic(tmp_path, monkeypatch, capsys):
    out = tmp_path / "grab"
    rc = _cli(monkeypatch, ["stereo", "--model", "synthetic", "--device", "corridor",
                            "--out", str(out), "--count", "2", "--stride", "2"])
    assert rc == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and "points" in lines[0]
    assert (out / "calibration.yaml").exists()
    assert len(list((out / "points").glob("*.npy"))) == 2
    disp = cv2.imread(str(out / "disparity" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert disp.dtype == np.uint16 and disp.shape == (400, 640)
    # Global-frame points: the corridor's walls bound them (|y| <= 1.8 m with the niches).
    rc = _cli(monkeypatch, ["stereo", "--model", "synthetic", "--out", str(tmp_path / "g"),
                            "--global-frame", "--max-depth", "8"])
    assert rc == 0
    capsys.readouterr()
    pts = np.load(tmp_path / "g" / "points" / "000000.npy")
    rec = json.loads((tmp_path / "g" / "frames.jsonl").read_text().splitlines()[0])
    assert rec["points_frame"] == "global"
    assert np.percentile(np.abs(pts[:, 1]), 99) < 1.9 and abs(np.percentile(pts[:, 2], 1)) < 0.1
    # ... and the recording replays through the CLI too.
    rc = _cli(monkeypatch, ["stereo", "--model", "replay", "--device", str(out),
                            "--out", str(tmp_path / "again"), "--count", "5"])
    assert rc == 0
    assert len(capsys.readouterr().out.strip().splitlines()) == 2


@pytest.mark.parametrize("argv,msg", [
    (["--model", "synthetic", "--device", "atlantis"], "unknown world"),
    (["--model", "opencv", "--device", "0,1"], "calibration file is required"),
    (["--model", "replay", "--device", "/nonexistent/rec"], "no such folder"),
    (["--model", "synthetic", "--num-disparities", "50"], "multiple of 16"),
    (["--model", "synthetic", "--count", "0"], "at least 1"),
])
def test_cli_stereo_bad_input(tmp_path, monkeypatch, capsys, argv, msg):
    rc = _cli(monkeypatch, ["stereo", "--out", str(tmp_path / "o")] + argv)
    err = capsys.readouterr().err
    assert rc != 0 and msg in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


# ---------------------------------------------------------------- depthai

def _run_py(code: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """Run depthai code in a child process: discovery or a wedged USB stack cannot hang us."""
    env = dict(os.environ, DEPTHAI_SEARCH_TIMEOUT="2000")
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=timeout, env=env)


@pytest.fixture(scope="module")
def oak_devices():
    pytest.importorskip("depthai")
    try:
        r = _run_py("""
            import json
            from cgamap.drivers.stereo_depthai import list_devices
            print(json.dumps(list_devices(5.0)))
        """)
    except subprocess.TimeoutExpired:
        pytest.skip("depthai device discovery did not finish within 60 s")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_depthai_import_is_lazy():
    # Making (not opening) a grabber must not import depthai or touch a device.
    r = _run_py("""
        import sys
        from cgamap.drivers.stereo import open_grabber
        g = open_grabber("depthai", "", {"size": (640, 400)})
        print("depthai" in sys.modules)
    """)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"


def test_depthai_calibration_from_handler():
    dai = pytest.importorskip("depthai")
    from cgamap.drivers.stereo_depthai import calibration_from_handler

    h = dai.CalibrationHandler()
    K = [[450.0, 0, 320.0], [0, 451.0, 200.0], [0, 0, 1]]
    for cam in (dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C):
        h.setCameraIntrinsics(cam, K, 640, 400)
    eye = np.eye(3).tolist()
    h.setCameraExtrinsics(dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C, eye,
                          [-7.5, 0, 0], [-7.5, 0, 0])
    c = calibration_from_handler(h, (1280, 800))
    assert c.fx == pytest.approx(900.0) and c.fy == pytest.approx(902.0)
    assert c.baseline == pytest.approx(0.075) and c.size == (1280, 800)
    assert c.R_rect is None  # no rectification stored: none applied
    R1 = cv2.Rodrigues(np.array([0.0, 0.02, 0.01]))[0]
    h.setStereoLeft(dai.CameraBoardSocket.CAM_B, R1.tolist())
    h.setStereoRight(dai.CameraBoardSocket.CAM_C, eye)
    assert np.allclose(calibration_from_handler(h, (640, 400)).R_rect, R1, atol=1e-6)


def test_depthai_frame_conversion_shared_path():
    from datetime import timedelta

    from cgamap.drivers.stereo_calib import rectified_calibration
    from cgamap.drivers.stereo_depthai import frame_from_messages

    class Msg:  # the ImgFrame methods the backend uses
        def __init__(self, img, seq):
            self.img, self.seq = img, seq

        def getFrame(self):
            return self.img

        def getCvFrame(self):
            return self.img

        def getTimestamp(self):
            return timedelta(seconds=12, microseconds=345)

        def getSequenceNum(self):
            return self.seq

    depth_mm = np.full((40, 60), 2000, np.uint16)
    depth_mm[0, 0] = 0
    c = rectified_calibration(50.0, 30.0, 20.0, 0.075)
    f = frame_from_messages(Msg(depth_mm, 7), Msg(np.zeros((40, 60), np.uint8), 7), c, 0)
    assert f.stamp_ns == 12_000_345_000 and f.device_stamp == 7
    pts = frame_points(f)
    assert len(pts) == 40 * 60 - 1 and np.allclose(pts[:, 2], 2.0)


def test_depthai_no_device_is_a_clear_error(oak_devices):
    if oak_devices:
        pytest.skip("an OAK device is attached")
    r = _run_py("""
        from cgamap.drivers.stereo_depthai import DepthaiGrabber, DeviceNotFound
        try:
            DepthaiGrabber(discovery_timeout=2.0).open()
        except DeviceNotFound as exc:
            print("ERR", exc)
    """)
    assert "ERR depthai: no OAK device found" in r.stdout, r.stdout + r.stderr


def test_depthai_device_frame(oak_devices):
    if not oak_devices:
        pytest.skip("no OAK device attached (depthai discovery found none within 5 s)")
    r = _run_py("""
        import numpy as np
        from cgamap.drivers.stereo import frame_points, open_grabber
        with open_grabber("depthai", "", {"size": (640, 400)}) as g:
            f = g.grab(timeout=10.0)
        print(f.depth.shape, f.calib.baseline, len(frame_points(f)))
    """, timeout=120)
    assert r.returncode == 0, r.stderr
    shape, baseline, n = r.stdout.strip().splitlines()[-1].rsplit(" ", 2)
    assert shape.startswith("(400, 640") and 0.02 < float(baseline) < 0.5 and int(n) > 1000
