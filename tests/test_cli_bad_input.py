"""Bad input to every command: one clear line naming what is wrong, a non-zero exit, no
traceback, nothing lost, no hang.  Most cases run ``cgamap.daemon.cli.main`` in-process (the
checks happen before any device is opened); a few run the real entry points as subprocesses.
"""

from __future__ import annotations

import gzip
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cgamap.daemon.cli import main

REPO = Path(__file__).resolve().parents[1]


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line(code: int, err: str, *needles: str, expect: int | None = None) -> None:
    """The contract: non-zero exit, one line on stderr naming the problem, no traceback."""
    assert code != 0, err
    if expect is not None:
        assert code == expect, (code, err)
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], (n, lines[0])


def run_proc(args: list[str], timeout: float = 20.0, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout, **kw)


# -- sim-device -------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, needle", [
    (["sim-device", "lms2xx", "--world", "nope"], "--world"),
    (["sim-device", "lms2xx", "--fault-rate", "2"], "--fault-rate"),
    (["sim-device", "hokuyo", "--fault-rate", "nan"], "--fault-rate"),
    (["sim-device", "cola", "--port", "99999"], "--port"),
    (["sim-device", "modbus-base", "--port", "-5"], "--port"),
    (["sim-device", "lms2xx", "--rtu"], "--rtu"),
    (["sim-device", "cola", "--model", "UTM-30LX"], "--model"),
])
def test_sim_device_refuses_bad_flags(argv, needle, capsys):
    code, _, err = run_cli(argv, capsys)
    one_line(code, err, needle, expect=2)


def test_sim_device_port_in_use_is_one_line(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        code, _, err = run_cli(["sim-device", "cola", "--port", port], capsys)
    one_line(code, err, f"--port {port}", expect=1)


# -- scan -------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, needle", [
    (["--device", "", "--model", "lms2xx"], "--device"),
    (["--device", "tcp://127.0.0.1:99999", "--model", "cola"], "tcp://127.0.0.1:99999"),
    (["--device", "x", "--model", "hokuyo", "--timeout", "inf"], "--timeout"),
])
def test_scan_refuses_bad_input(argv, needle, capsys):
    code, _, err = run_cli(["scan", *argv], capsys)
    one_line(code, err, needle, expect=2)


# -- odom and pantilt -------------------------------------------------------------------------

@pytest.mark.parametrize("extra, needle", [
    (["--rate", "nan"], "--rate"),
    (["--rate", "inf"], "--rate"),
    (["--timeout", "-1"], "--timeout"),
    (["--wheel-radius", "0"], "--wheel-radius"),
    (["--track", "-0.3"], "--track"),
    (["--ticks-per-rev", "0"], "--ticks-per-rev"),
    (["--unit", "-5"], "--unit"),
    (["--drive", "nan,1"], "--drive"),
    (["--drive", "1e9,1"], "--drive"),
    (["--count", "-1"], "--count"),
])
def test_odom_refuses_bad_flags(extra, needle, capsys):
    code, _, err = run_cli(["odom", "--device", "tcp://127.0.0.1:1", *extra], capsys)
    one_line(code, err, needle, expect=2)


@pytest.mark.parametrize("url", ["127.0.0.1:1?unit=abc", "/dev/ttyNOPE?baudrate=abc",
                                 "127.0.0.1:1?unit=999"])
def test_odom_malformed_url_is_one_line(url, capsys):
    code, _, err = run_cli(["odom", "--device", url, "--count", "1"], capsys)
    one_line(code, err, url, expect=2)


def test_odom_missing_serial_port_says_so(tmp_path, capsys):
    code, _, err = run_cli(["odom", "--device", tmp_path / "ttyNOPE", "--count", "1"], capsys)
    one_line(code, err, "ttyNOPE", "no such device", expect=1)


@pytest.mark.parametrize("argv, needle", [
    (["--ids", "1,1", "status"], "--ids"),
    (["--ids=300,2", "status"], "--ids"),
    (["--pan-limits", "1,-1", "move", "0", "0"], "--pan-limits"),
    (["--tilt-limits", "nan,1", "move", "0", "0"], "--tilt-limits"),
    (["--velocity", "-1", "move", "0.1", "0"], "--velocity"),
    (["--velocity", "nan", "move", "0.1", "0"], "--velocity"),
    (["move", "0.1", "0", "--wait-timeout", "-1"], "--wait-timeout"),
    (["move", "nan", "0"], "finite"),
])
def test_pantilt_refuses_bad_flags(argv, needle, tmp_path, capsys):
    code, _, err = run_cli(["pantilt", "--device", tmp_path / "ttyNOPE", *argv], capsys)
    one_line(code, err, needle, expect=2)


@pytest.mark.parametrize("url", ["foo://x", "/dev/ttyNOPE?baudrate=abc", "socket://",
                                 "tcp://host:port"])
def test_pantilt_malformed_url_is_one_line(url, capsys):
    code, _, err = run_cli(["pantilt", "--device", url, "status"], capsys)
    one_line(code, err, url, expect=2)


# -- planes -----------------------------------------------------------------------------------

def _small_cloud(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    path = tmp_path / "floor.npy"
    np.save(path, pts)
    return path


def test_planes_cloud_file_problems(tmp_path, capsys):
    (tmp_path / "dir.pcd").mkdir()
    (tmp_path / "empty.npy").write_bytes(b"")
    np.save(tmp_path / "nan.npy", np.full((50, 3), np.nan))
    code, _, err = run_cli(["planes", "--cloud", tmp_path / "dir.pcd"], capsys)
    one_line(code, err, "dir.pcd", "is a directory", expect=2)
    code, _, err = run_cli(["planes", "--cloud", tmp_path / "empty.npy"], capsys)
    one_line(code, err, "--cloud", "empty.npy", expect=2)
    code, _, err = run_cli(["planes", "--cloud", tmp_path / "nan.npy"], capsys)
    one_line(code, err, "nan.npy", "finite points", expect=2)


@pytest.mark.parametrize("extra, needle", [
    (["--threshold", "inf"], "--threshold"),
    (["--range-noise", "nan"], "--range-noise"),
    (["--max-depth", "0"], "--max-depth"),
    (["--up", "nan", "0", "1", "--configurations"], "--up"),
    (["--hough-png", "view.txt"], "--hough-png"),
    (["--ply", "no/such/dir/planes.ply"], "--ply"),
])
def test_planes_refuses_bad_flags_before_detecting(extra, needle, tmp_path, capsys):
    code, out, err = run_cli(["planes", "--cloud", _small_cloud(tmp_path), *extra], capsys)
    one_line(code, err, needle, expect=2)
    assert out == ""  # refused before any detection output


def test_planes_exports_still_written(tmp_path, capsys):
    ply, png = tmp_path / "p.ply", tmp_path / "p.png"
    code, out, err = run_cli(["planes", "--cloud", _small_cloud(tmp_path), "--min-inliers",
                              "100", "--ply", ply, "--hough-png", png], capsys)
    assert code == 0, err
    assert ply.stat().st_size > 0 and png.stat().st_size > 0


def test_planes_stereo_input_problems(tmp_path, capsys):
    import cv2

    left, right, small = tmp_path / "l.png", tmp_path / "r.png", tmp_path / "s.png"
    cv2.imwrite(str(left), np.zeros((40, 60), np.uint8))
    cv2.imwrite(str(right), np.zeros((40, 60), np.uint8))
    cv2.imwrite(str(small), np.zeros((30, 60), np.uint8))
    bad_yaml = tmp_path / "calib.yaml"
    bad_yaml.write_text("fx: [\n")
    binary = tmp_path / "calib.bin"
    binary.write_bytes(bytes(range(128, 256)) * 8)
    code, _, err = run_cli(["planes", "--stereo", left, right, "--calib", bad_yaml], capsys)
    one_line(code, err, "--calib", "YAML", expect=2)
    code, _, err = run_cli(["planes", "--stereo", left, right, "--calib", binary], capsys)
    one_line(code, err, "--calib", "calib.bin", expect=2)
    code, _, err = run_cli(["planes", "--stereo", left, right, "--calib", tmp_path], capsys)
    one_line(code, err, "--calib", "is a directory", expect=2)
    code, _, err = run_cli(["planes", "--stereo", left, small, "--calib", bad_yaml], capsys)
    one_line(code, err, "--stereo", "differ in size", expect=2)


# -- stereo -----------------------------------------------------------------------------------

def test_stereo_never_writes_into_an_existing_recording(tmp_path, capsys):
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "frames.jsonl").write_text('{"seq": 0}\n')
    (rec / "calibration.yaml").write_text("fx: 1.0\n")
    code, _, err = run_cli(["stereo", "--model", "synthetic", "--out", rec], capsys)
    one_line(code, err, "--out", "already holds a recording", expect=2)
    code, _, err = run_cli(["stereo", "--model", "replay", "--device", rec, "--out", rec],
                           capsys)
    one_line(code, err, "--out", "replayed", expect=2)
    assert (rec / "frames.jsonl").read_text() == '{"seq": 0}\n'
    assert (rec / "calibration.yaml").read_text() == "fx: 1.0\n"


@pytest.mark.parametrize("extra, needle", [
    (["--max-depth", "nan"], "--max-depth"),
    (["--max-depth", "-1"], "--max-depth"),
    (["--timeout", "0"], "--timeout"),
    (["--calib", "no-such-calib.yaml"], "--calib"),
    (["--num-disparities", "1600000"], "--num-disparities"),  # was minutes of allocation
    (["--block-size", "999"], "--block-size"),  # was a frame with 0 points
])
def test_stereo_refuses_bad_flags(extra, needle, tmp_path, capsys):
    out = tmp_path / "out"
    code, _, err = run_cli(["stereo", "--model", "synthetic", "--out", out, *extra], capsys)
    one_line(code, err, needle, expect=2)
    assert not out.exists()


def test_stereo_bad_out_and_replay_folder(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("keep\n")
    code, _, err = run_cli(["stereo", "--model", "synthetic", "--out", afile], capsys)
    one_line(code, err, "--out", "not a folder", expect=2)
    code, _, err = run_cli(["stereo", "--model", "synthetic", "--out", afile / "sub"], capsys)
    one_line(code, err, "--out", "cannot create", expect=2)
    assert afile.read_text() == "keep\n"
    code, _, err = run_cli(["stereo", "--model", "replay", "--device", tmp_path / "nope",
                            "--out", tmp_path / "o"], capsys)
    one_line(code, err, "--device", "no such folder", expect=2)


# -- calib ------------------------------------------------------------------------------------

def _pairs_file(tmp_path: Path, n: int = 6) -> Path:
    """Noise-free pose pairs about varied axes (a solvable file)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    X = np.eye(4)
    X[:3, :3] = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
    X[:3, 3] = [0.05, 0.02, 0.1]
    base_T_target = np.eye(4)
    base_T_target[:3, 3] = [1.0, 0.0, 0.5]
    pairs = []
    for _ in range(n):
        H = np.eye(4)
        H[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        H[:3, 3] = rng.normal(0, 0.1, 3)
        C = np.linalg.inv(H @ X) @ base_T_target
        pairs.append({"base_T_head": H.tolist(), "cam_T_target": C.tolist()})
    path = tmp_path / "pairs.json"
    path.write_text(json.dumps({"pairs": pairs}))
    return path


def test_hand_eye_out_never_overwrites_the_pairs(tmp_path, capsys):
    pairs = _pairs_file(tmp_path)
    before = pairs.read_text()
    code, _, err = run_cli(["calib", "hand-eye", "--pairs", pairs, "--out", pairs], capsys)
    one_line(code, err, "--out", "--pairs file", expect=2)
    assert pairs.read_text() == before


def test_hand_eye_rewrite_keeps_the_previous_calibration(tmp_path, capsys):
    pairs, out = _pairs_file(tmp_path), tmp_path / "calib.yaml"
    out.write_text("head_T_cam: old\n")
    code, _, err = run_cli(["calib", "hand-eye", "--pairs", pairs, "--out", out], capsys)
    assert code == 0, err
    assert "head_T_cam:" in out.read_text() and "old" not in out.read_text()
    assert (tmp_path / "calib.yaml.bak").read_text() == "head_T_cam: old\n"
    assert oct(out.stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_hand_eye_bad_pairs_files(tmp_path, capsys):
    binary = tmp_path / "bin.json"
    binary.write_bytes(bytes(range(128, 256)) * 4)
    huge = tmp_path / "huge.json"
    m = [[1e308] * 4] * 3 + [[0, 0, 0, 1]]
    huge.write_text(json.dumps({"pairs": [{"base_T_head": m, "cam_T_target": m}]}))
    bomb = tmp_path / "bomb.yaml"
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{k}: &a{k} [{', '.join([f'*a{k - 1}'] * 9)}]" for k in range(1, 8)]
    lines += ["pairs:", "- base_T_head: *a7", "  cam_T_target: *a7"]
    bomb.write_text("\n".join(lines) + "\n")
    for path, needle in ((binary, "not a text"), (huge, "rotation"), (bomb, "4x4")):
        code, _, err = run_cli(["calib", "hand-eye", "--pairs", path], capsys)
        one_line(code, err, path.name, needle, expect=2)


@pytest.mark.parametrize("extra, needle", [
    (["--cols", "0"], "--cols"),
    (["--square", "-1"], "--square"),
    (["--pan-range", "nan"], "--pan-range"),
    (["--max-reproj", "-1"], "--max-reproj"),
    (["--intrinsics", "no-such.yaml"], "--intrinsics"),
    (["--out", "no/such/dir/p.json"], "--out"),
    (["--truth", "no/such/dir/t.json"], "--truth"),
])
def test_collect_refuses_bad_flags_before_collecting(extra, needle, tmp_path, capsys,
                                                      monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(["calib", "collect", "--sim", "--sim-joints", "direct", *extra],
                             capsys)
    one_line(code, err, needle, expect=2)
    assert out == ""  # no pose was visited


def test_collect_keeps_the_previous_pairs_file(tmp_path, capsys):
    out = tmp_path / "pairs.json"
    out.write_text('{"pairs": "from yesterday"}\n')
    code, _, err = run_cli(["calib", "collect", "--sim", "--sim-joints", "direct", "--poses",
                            "3", "--out", out], capsys)
    assert code == 0, err
    assert (tmp_path / "pairs.json.bak").read_text() == '{"pairs": "from yesterday"}\n'
    assert "pairs.json.bak" in err
    assert len(json.loads(out.read_text())["pairs"]) == 3


# -- cgamapd: config and start-up ------------------------------------------------------------

def cgamapd(args: list, timeout: float = 20.0) -> subprocess.CompletedProcess:
    return run_proc([sys.executable, "-m", "cgamap.daemon.main", *map(str, args)], timeout)


def test_config_file_problems_exit_78(tmp_path):
    from cgamap.daemon import config

    cases = {
        "binary.yaml": (bytes(range(128, 256)), "not a text"),
        "dup.yaml": (b"log_level: info\nlog_level: debug\n", "duplicate key"),
        "mode.yaml": (b"server:\n  socket_mode: 99999\n", "server.socket_mode"),
        "backoff.yaml": (b"supervisor:\n  backoff_initial: 5\n  backoff_max: 1\n",
                         "supervisor.backoff_initial"),
        "empty_path.yaml": (b'paths:\n  state_dir: ""\n', "paths.state_dir"),
        "float_text.yaml": (b"checkpoint:\n  interval: 1e3\n", "1.0e-3"),
        "bare_path.yaml": (b"devices:\n  l:\n    role: laser\n    model: hokuyo\n"
                           b"    url: /dev/ttyACM0\n", "serial:///dev/ttyACM0"),
        "port0.yaml": (b"devices:\n  l:\n    role: laser\n    model: cola\n"
                       b"    url: tcp://10.0.0.2:0\n", "devices.l.url"),
        "baud0.yaml": (b"devices:\n  l:\n    role: laser\n    model: lms2xx\n"
                       b"    url: serial:///dev/ttyS0?baudrate=0\n", "baudrate"),
        "he_dir.yaml": (b"devices:\n  h:\n    role: pantilt\n    model: dynamixel\n"
                        b"    url: tcp://h:1\n    hand_eye: .\n", "is a directory"),
    }
    for name, (text, needle) in cases.items():
        (tmp_path / name).write_bytes(text)
        with pytest.raises(config.ConfigError) as info:
            config.load(tmp_path / name)
        assert needle in str(info.value) and "\n" not in str(info.value), (name, info.value)
    proc = cgamapd(["--check-config", tmp_path / "binary.yaml"])
    assert proc.returncode == 78 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1 and "binary.yaml" in proc.stderr
    proc = cgamapd(["--check-config", tmp_path])
    assert proc.returncode == 78 and proc.stderr.count("\n") == 1, proc.stderr


@pytest.fixture
def minimal_config(tmp_path) -> Path:
    cfg = tmp_path / "cgamapd.yaml"
    cfg.write_text(f"log_level: warning\npaths:\n  state_dir: {tmp_path / 'state'}\n"
                   f"  runtime_dir: {tmp_path / 'run'}\ndevices: {{}}\n")
    return cfg


def test_cgamapd_refuses_bad_replay_input_instead_of_retrying_forever(tmp_path,
                                                                      minimal_config):
    log = REPO.parent / "shared" / "data" / "laser" / "intel-corrected.log.gz"
    cut = tmp_path / "cut.log.gz"
    if log.is_file():
        cut.write_bytes(log.read_bytes()[:50_000])
    else:  # a gzip stream cut short is enough
        cut.write_bytes(gzip.compress(b"ODOM 0 0 0 0 0 0 0 host 0\n" * 5000)[:-20])
    garbage = tmp_path / "garbage.log"
    garbage.write_bytes(bytes(range(256)) * 20)
    empty = tmp_path / "empty.log"
    empty.write_bytes(b"")
    cases = [(tmp_path / "nope.log", "no such file"), (tmp_path, "is a directory"),
             (empty, "empty"), (cut, "damaged gzip"), (garbage, "no device messages")]
    for path, needle in cases:
        proc = cgamapd(["-c", minimal_config, "--replay", path, "--exit-after-replay"])
        assert proc.returncode == 66, (path, proc.stderr)
        assert proc.stderr.count("\n") == 1 and needle in proc.stderr, proc.stderr
    proc = cgamapd(["-c", minimal_config, "--replay", garbage, "--replay-rate", "-1"])
    assert proc.returncode == 64 and "--replay-rate" in proc.stderr


def test_cgamapd_never_replaces_a_file_at_the_socket_path(tmp_path, minimal_config):
    precious = tmp_path / "notes.txt"
    precious.write_text("keep me\n")
    proc = cgamapd(["-c", minimal_config, "--socket", precious])
    assert proc.returncode == 73 and "not a socket" in proc.stderr, proc.stderr
    assert precious.read_text() == "keep me\n"


def test_cgamapd_refuses_an_unusable_state_dir(tmp_path, minimal_config):
    afile = tmp_path / "afile"
    afile.write_text("x")
    for state in (afile, afile / "sub"):
        proc = cgamapd(["-c", minimal_config, "--state-dir", state])
        assert proc.returncode == 73 and "state directory" in proc.stderr, proc.stderr
        assert proc.stderr.count("\n") == 1
    assert afile.read_text() == "x"


# -- daemon client commands -------------------------------------------------------------------

@pytest.mark.parametrize("argv, needle", [
    (["watch", "--count", "-1"], "--count"),
    (["watch", "--interval", "nan"], "--interval"),
    (["map", "export", "--format", "png", "--resolution", "-1"], "--resolution"),
    (["map", "export", "--format", "pgm", "--resolution", "1e-9"], "--resolution"),
    (["map", "export", "--format", "png", "-o", "{tmp}/map.txt"], ".png"),
    (["map", "export", "--format", "json", "-o", "{tmp}"], "is a directory"),
    (["relocalize", "--radius", "2"], "--near"),
    (["relocalize", "--near", "1", "2", "30", "--map", "{tmp}/map.json"], "--near"),
    (["relocalize", "--near", "nan", "0", "0"], "--near"),
    (["relocalize", "--near", "0", "0", "0", "--radius", "-1"], "--radius"),
    (["relocalize", "--near", "0", "0", "0", "--turn", "500"], "--turn"),
    (["set-pose", "nan", "0", "0"], "x"),
    (["set-pose", "0", "1e308", "0"], "y"),
    (["record", "{tmp}", "--duration", "1"], "is a directory"),
    (["record", "{tmp}/r.mcap", "--duration", "-1"], "--duration"),
    (["demo", "--duration", "-1", "--out", "{tmp}/demo"], "--duration"),
    (["demo", "--world", "atlantis", "--out", "{tmp}/demo"], "--world"),
    (["demo", "--config", "{tmp}/nope.yaml", "--duration", "1", "--out", "{tmp}/demo"],
     "nope.yaml"),
])
def test_daemon_client_commands_refuse_bad_input(argv, needle, tmp_path, capsys):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    sock = ["--socket", str(tmp_path / "no.sock")] if argv[0] != "demo" else []
    code, _, err = run_cli(argv + sock, capsys)
    one_line(code, err, needle)
    assert code in (2, 78), err
    assert not (tmp_path / "demo").exists()


def test_record_never_overwrites_and_survives_a_quiet_daemon(tmp_path, capsys):
    """A fake daemon that sends a message, stays quiet for longer than the client's socket
    timeout, then sends another: both are recorded (a buffered reader broke after one
    timeout), and an existing recording is never overwritten."""
    import threading
    import time

    old = tmp_path / "old.mcap"
    old.write_bytes(b"earlier recording")
    code, _, err = run_cli(["record", old, "--socket", tmp_path / "no.sock"], capsys)
    one_line(code, err, "exists", expect=2)
    assert old.read_bytes() == b"earlier recording"

    path = tmp_path / "d.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(1)
    srv.settimeout(10)

    def serve() -> None:
        conn, _ = srv.accept()
        with conn:
            conn.recv(4096)
            msg = {"class": "raw", "topic": "/odom", "schema": "foxglove.PoseInFrame",
                   "body": {"x": 1}, "stamp_ns": 1}
            conn.sendall(json.dumps(msg).encode() + b"\n")
            time.sleep(1.6)
            conn.sendall(json.dumps({**msg, "stamp_ns": 2}).encode() + b"\n")
            time.sleep(1.0)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        # the fake daemon hangs up 2.6 s in: the duration only bounds a run that goes wrong
        # (2.5 s left 0.9 s for the client to connect, too little on a loaded machine)
        code, out, err = run_cli(["record", tmp_path / "new.mcap", "--socket", path,
                                  "--duration", "6"], capsys)
    finally:
        t.join(10)
        srv.close()
    assert code == 0, err
    assert "2 messages" in out


# -- a closed stdout (`| head`) ---------------------------------------------------------------

def _run_into_closed_pipe(argv: list, timeout: float = 30.0) -> subprocess.CompletedProcess:
    r, w = os.pipe()
    os.close(r)  # every write gets EPIPE
    try:
        return subprocess.run([sys.executable, "-m", "cgamap.daemon.cli", *map(str, argv)],
                              stdout=w, stderr=subprocess.PIPE, text=True, timeout=timeout)
    finally:
        os.close(w)


def test_closed_stdout_is_not_a_traceback(tmp_path):
    proc = _run_into_closed_pipe(["planes", "--cloud", _small_cloud(tmp_path),
                                  "--min-inliers", "100"])
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    twin = subprocess.Popen([sys.executable, "-m", "cgamap.daemon.cli", "sim-device",
                             "modbus-base"], stdout=subprocess.PIPE, text=True)
    try:
        addr = twin.stdout.readline().strip()
        proc = _run_into_closed_pipe(["odom", "--device", addr, "--json", "--drive", "1,1"])
        assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    finally:
        twin.terminate()
        twin.wait(10)


def test_record_failure_leaves_no_empty_recording(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(bytes(range(128, 256)))
    out = tmp_path / "r.mcap"
    code, _, err = run_cli(["record", out, "--config", bad, "--duration", "1"], capsys)
    one_line(code, err, "bad.yaml", expect=78)
    assert not out.exists()
    code, _, err = run_cli(["record", out, "--socket", tmp_path / "no.sock", "--duration",
                            "1"], capsys)
    one_line(code, err, "no.sock", expect=69)
    assert not out.exists()


def test_stereo_replay_of_a_damaged_recording(tmp_path, capsys):
    import cv2

    rec = tmp_path / "rec"
    for sub in ("left", "right"):
        (rec / sub).mkdir(parents=True)
        cv2.imwrite(str(rec / sub / "000000.png"), np.zeros((40, 60), np.uint8))
    (rec / "calibration.yaml").write_text("fx: [\n")
    code, _, err = run_cli(["stereo", "--model", "replay", "--device", rec, "--out",
                            tmp_path / "o1"], capsys)
    one_line(code, err, "--device", "calibration YAML", expect=1)
    (rec / "calibration.yaml").write_text("fx: 50.0\ncx: 30.0\ncy: 20.0\nbaseline: 0.1\n")
    (rec / "frames.jsonl").write_text("not json\n")
    code, _, err = run_cli(["stereo", "--model", "replay", "--device", rec, "--out",
                            tmp_path / "o2"], capsys)
    one_line(code, err, "--device", "frames.jsonl", expect=1)
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()  # no debris


@pytest.mark.parametrize("device, needle", [
    ({"role": "odometry", "model": "modbus-base", "url": "tcp://h:502",
      "params": {"wheel_radus": 0.07}}, "params.wheel_radus"),
    ({"role": "odometry", "model": "modbus-base", "url": "tcp://h:502",
      "params": {"wheel_radius": -1}}, "params.wheel_radius"),
    ({"role": "laser", "model": "lms2xx", "url": "serial:///dev/ttyS0",
      "params": {"resolution": 0.3}}, "params"),
    ({"role": "laser", "model": "hokuyo", "url": "serial:///dev/ttyS0",
      "params": {"nonsense": 1}}, "nonsense"),
    ({"role": "pantilt", "model": "dynamixel", "url": "serial:///dev/ttyS0",
      "params": {"protocl": 1.0}}, "params.protocl"),
])
def test_config_device_params_checked_against_the_driver(device, needle):
    """A typo or bad value in params was dropped silently or failed only when the daemon
    opened the device (retried forever)."""
    from cgamap.daemon import config

    with pytest.raises(config.ConfigError) as info:
        config.validate({"devices": {"d": device}})
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_second_cgamapd_on_the_same_state_dir_is_refused(tmp_path, minimal_config):
    first = subprocess.Popen([sys.executable, "-m", "cgamap.daemon.main", "-c",
                              str(minimal_config), "--socket", str(tmp_path / "a.sock")],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        lock = tmp_path / "state" / "cgamapd.lock"
        for _ in range(200):  # until the first one holds the lock (its pid is written)
            if lock.is_file() and lock.read_text().strip():
                break
            if first.poll() is not None:
                break
            time.sleep(0.05)
        assert first.poll() is None, first.stderr.read()
        proc = cgamapd(["-c", minimal_config, "--socket", tmp_path / "b.sock"])
        assert proc.returncode == 73 and "in use by another cgamapd" in proc.stderr
        assert proc.stderr.count("\n") == 1
    finally:
        first.terminate()
        first.wait(10)


def test_stereo_opencv_refusal_is_one_line(tmp_path, capsys):
    code, _, err = run_cli(["stereo", "--model", "synthetic", "--out", tmp_path / "o",
                            "--num-disparities", "1024"], capsys)  # wider than the image
    one_line(code, err, "--num-disparities", expect=1)


def _fake_daemon(path: Path, reply: bytes | None):
    """A Unix socket that answers every connection with ``reply`` (None: never answers)."""
    import threading

    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(8)
    conns: list = []

    def serve() -> None:
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            conns.append(conn)
            if reply is not None:
                conn.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    return srv, conns


@pytest.mark.parametrize("reply, needle", [
    (None, "no reply"),
    (b"\xff\xfe not json\n", "not cgamapd's JSON"),
    (b"[1, 2]\n", "not cgamapd's JSON"),
    (b'{"class": "status"}\n', "unexpected reply"),
])
def test_status_against_a_stuck_or_foreign_socket(reply, needle, tmp_path, capsys,
                                                  monkeypatch):
    from cgamap.daemon import cmd_daemon

    monkeypatch.setattr(cmd_daemon, "REPLY_TIMEOUT", 0.5)
    srv, conns = _fake_daemon(tmp_path / "d.sock", reply)
    try:
        code, _, err = run_cli(["status", "--socket", tmp_path / "d.sock"], capsys)
        one_line(code, err, needle, "d.sock")
        if reply is None:
            code, _, err = run_cli(["watch", "--socket", tmp_path / "d.sock", "--interval",
                                    "0.1"], capsys)
            one_line(code, err, "nothing from the daemon", expect=69)
    finally:
        srv.close()
        for c in conns:
            c.close()


def test_cgamapd_refuses_a_cut_mcap_recording(tmp_path, minimal_config):
    from cgamap.daemon.recording import McapRecorder

    full = tmp_path / "full.mcap"
    with open(full, "wb") as f:
        rec = McapRecorder(f)
        for k in range(20):
            rec.write_json("/odom", "foxglove.PoseInFrame", {"k": k}, k + 1)
        rec.finish()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:-100])
    proc = cgamapd(["-c", minimal_config, "--replay", cut, "--exit-after-replay"])
    assert proc.returncode == 66 and "incomplete" in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1


def test_odom_drive_stops_the_base_on_sigterm(capsys):
    import signal

    twin = subprocess.Popen([sys.executable, "-m", "cgamap.daemon.cli", "sim-device",
                             "modbus-base"], stdout=subprocess.PIPE, text=True)
    try:
        addr = twin.stdout.readline().strip()
        odom = subprocess.Popen([sys.executable, "-m", "cgamap.daemon.cli", "odom", "--device",
                                 addr, "--drive", "2,2", "--json"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            for _ in range(30):  # until it is surely driving
                if json.loads(odom.stdout.readline())["v"] > 0:
                    break
            odom.send_signal(signal.SIGTERM)
            _, err = odom.communicate(timeout=10)
        finally:
            odom.kill()
        assert "Traceback" not in err, err
        time.sleep(0.2)
        code, out, err = run_cli(["odom", "--device", addr, "--count", "5", "--json"], capsys)
        assert code == 0, err
        assert json.loads(out.splitlines()[-1])["v"] == 0.0  # the wheels were stopped
    finally:
        twin.terminate()
        twin.wait(10)
