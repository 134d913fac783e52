"""``cgamap calib collect`` / ``cgamap calib hand-eye`` end to end on the simulated rig."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from cgamap.calib.collect import pose_set
from cgamap.calib.se3 import pose_errors
from cgamap.calib.sim import default_rig
from cgamap.daemon.cli import main


def _run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def sim_pairs(tmp_path_factory):
    d = tmp_path_factory.mktemp("calib")
    pairs = d / "pairs.json"
    code = main(["calib", "collect", "--sim", "--seed", "3", "--out", str(pairs),
                 "--truth", str(d / "truth.json"), "--json"])
    assert code == 0
    return pairs, json.loads((d / "truth.json").read_text())


def test_collect_then_hand_eye_recovers_the_hidden_mount(sim_pairs, tmp_path, capsys):
    pairs, truth = sim_pairs
    doc = json.loads(pairs.read_text())
    assert len(doc["pairs"]) == 20 and "pan" in doc["pairs"][0]
    out_file = tmp_path / "calib.yaml"
    code, out, err = _run(["calib", "hand-eye", "--pairs", str(pairs), "--out", str(out_file)],
                          capsys)
    assert code == 0, err
    assert "translation" in out and "quaternion" in out and "RPY" in out
    assert out.count("\n") > 20  # per-pair residual lines
    cal = yaml.safe_load(out_file.read_text())
    X = np.array(cal["head_T_cam"])
    true_X = np.array(truth["head_T_cam"])
    # The truth is also what default_rig(seed) hides: the test does not trust the file alone.
    np.testing.assert_allclose(true_X, default_rig(3).head_T_cam, atol=1e-12)
    rot, trans = pose_errors(X, true_X)
    assert rot < 0.5 and trans < 0.005
    # Fields the daemon and the camera chain need.
    assert cal["method"] == "motor"
    np.testing.assert_allclose(cal["t_eye"], X[:3, 3])
    np.testing.assert_allclose(cal["R_eye"], X[:3, :3])
    assert len(cal["q_eye"]) == 4 and len(cal["residuals"]["rot_deg"]) == 20
    assert len(cal["uncertainty"]["rot_deg_1sigma"]) == 3
    from cgamap.calib.handeye import _BASIS
    from cgamap.cga import Multivector, motor_to_matrix

    M = Multivector(np.array(list(cal["motor"].values())) @ _BASIS.v)
    np.testing.assert_allclose(motor_to_matrix(M), X, atol=1e-9)  # the motor is the mount
    assert "motor M = T R" in out
    assert all(s < 0.5 for s in cal["uncertainty"]["rot_deg_1sigma"])


def test_written_file_loads_into_the_daemon_config(sim_pairs, tmp_path, capsys):
    pytest.importorskip("cgamap.daemon.config")
    from cgamap.daemon.config import load_hand_eye

    pairs, _ = sim_pairs
    out_file = tmp_path / "hand_eye.yaml"
    assert _run(["calib", "hand-eye", "--pairs", str(pairs), "--out", str(out_file)],
                capsys)[0] == 0
    m = load_hand_eye(out_file, "devices.head.hand_eye")
    np.testing.assert_allclose(m, yaml.safe_load(out_file.read_text())["head_T_cam"])


@pytest.mark.parametrize("method", ["motor", "tsai", "park", "daniilidis"])
def test_json_output(sim_pairs, capsys, method):
    pairs, truth = sim_pairs
    code, out, _ = _run(["calib", "hand-eye", "--pairs", str(pairs), "--method", method,
                         "--json"], capsys)
    assert code == 0
    doc = json.loads(out)  # exactly one JSON object
    assert doc["method"] == method
    rot, trans = pose_errors(np.array(doc["head_T_cam"]), np.array(truth["head_T_cam"]))
    assert rot < 1.0 and trans < 0.02


def test_yaml_pairs_file_and_axes(sim_pairs, tmp_path, capsys):
    pairs, _ = sim_pairs
    y = tmp_path / "pairs.yaml"
    y.write_text(yaml.safe_dump(json.loads(pairs.read_text())))
    code, out, err = _run(["calib", "hand-eye", "--pairs", str(y), "--axes", "--json"], capsys)
    assert code == 0, err
    axes = json.loads(out)["axes"]
    # The simulated head has orthogonal, intersecting axes through its axis point.
    assert abs(axes["non_orthogonality_deg"]) < 0.5
    assert axes["offset_m"] < 0.005
    np.testing.assert_allclose(axes["axis_point"], default_rig(3).axis_point, atol=0.01)


def _bad_files(tmp_path, good):
    item = good["pairs"][0]
    not_rot = json.loads(json.dumps(item))
    not_rot["cam_T_target"][0][0] = 3.0
    short = json.loads(json.dumps(item))
    short["base_T_head"] = short["base_T_head"][:3]
    missing = {k: v for k, v in item.items() if k != "cam_T_target"}
    cases = {
        "broken.json": ('{"pairs": [', "invalid JSON at line 1"),
        "nolist.json": ('{"poses": []}', "'pairs' list"),
        "empty.yaml": ("pairs: []\n", "non-empty"),
        "missing.json": (json.dumps({"pairs": [item, missing]}),
                         "pairs[1]: missing 'cam_T_target'"),
        "shape.json": (json.dumps({"pairs": [item, item, short]}),
                       "pairs[2].base_T_head: expected a 4x4"),
        "rot.json": (json.dumps({"pairs": [not_rot]}), "pairs[0].cam_T_target: upper-left 3x3"),
        "tabs.yaml": ("pairs:\n\t- 1\n", "invalid YAML"),
        "text.json": (json.dumps({"pairs": [dict(item, pan="left")]}), "pairs[0].pan"),
    }
    for name, (text, expect) in cases.items():
        (tmp_path / name).write_text(text)
        yield tmp_path / name, expect


def test_malformed_pairs_files_give_one_clear_line(sim_pairs, tmp_path, capsys):
    pairs, _ = sim_pairs
    good = json.loads(pairs.read_text())
    for path, expect in _bad_files(tmp_path, good):
        code, out, err = _run(["calib", "hand-eye", "--pairs", str(path)], capsys)
        assert code == 2, path.name
        assert err.count("\n") == 1 and "Traceback" not in err, err
        assert expect in err and path.name in err, (path.name, err)
    code, _, err = _run(["calib", "hand-eye", "--pairs", str(tmp_path / "nope.json")], capsys)
    assert code == 2 and "nope.json: cannot read" in err


def test_malformed_file_through_the_real_entry_point(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"pairs": [{"base_T_head": 1, "cam_T_target": 2}]}')
    exe = Path(sys.executable).with_name("cgamap")
    if not exe.exists():
        pytest.skip("cgamap entry point not installed beside this interpreter")
    proc = subprocess.run([str(exe), "calib", "hand-eye", "--pairs", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr
    assert "pairs[0].base_T_head" in proc.stderr


def test_degenerate_pairs_are_refused_by_the_cli(tmp_path, capsys):
    rig = default_rig(0)
    pans = np.radians(np.linspace(-10, 10, 6))
    from cgamap.calib.sim import pan_tilt_head_pose

    items = [{"base_T_head": pan_tilt_head_pose(p, 0.05, rig.axis_point).tolist(),
              "cam_T_target": rig.cam_T_target(p, 0.05).tolist(), "pan": float(p), "tilt": 0.05}
             for p in pans]
    f = tmp_path / "pan_only.json"
    f.write_text(json.dumps({"pairs": items}))
    code, _, err = _run(["calib", "hand-eye", "--pairs", str(f)], capsys)
    assert code == 2 and err.count("\n") == 1
    assert "tilt joint never moves" in err and "second, non-parallel axis" in err


def test_collect_skips_blurred_frames(tmp_path, capsys):
    out = tmp_path / "p.yaml"
    code, stdout, _ = _run(["calib", "collect", "--sim", "--sim-joints", "direct", "--poses", "8",
                            "--sim-blur", "2", "5",
                            "--out", str(out)], capsys)
    assert code == 0
    doc = yaml.safe_load(out.read_text())
    assert len(doc["pairs"]) == 6
    skipped = {s["pose"]: s["reason"] for s in doc["skipped"]}
    assert set(skipped) == {2, 5}
    assert all("blurred" in r or "not found" in r for r in skipped.values())
    assert "skipped" in stdout


def test_collect_charuco_sim(tmp_path, capsys):
    cv2 = pytest.importorskip("cv2")
    if not hasattr(cv2, "aruco"):
        pytest.skip("no cv2.aruco")
    out = tmp_path / "p.json"
    code, _, _ = _run(["calib", "collect", "--sim", "--sim-joints", "direct", "--target", "charuco",
                       "--poses", "10",
                       "--out", str(out), "--json"], capsys)
    assert code == 0
    assert len(json.loads(out.read_text())["pairs"]) >= 8
    code, stdout, _ = _run(["calib", "hand-eye", "--pairs", str(out), "--json"], capsys)
    rot, trans = pose_errors(np.array(json.loads(stdout)["head_T_cam"]),
                             default_rig(0).head_T_cam)
    assert code == 0 and rot < 0.5 and trans < 0.005


def test_collect_argument_errors(capsys):
    code, _, err = _run(["calib", "collect"], capsys)
    assert code == 2 and "--sim" in err
    code, _, err = _run(["calib", "collect", "--sim", "--poses", "2"], capsys)
    assert code == 2 and "at least 3" in err


def test_pose_set_excites_both_joints():
    q = pose_set(20, math.radians(12), math.radians(8))
    assert q.shape == (20, 2)
    assert np.ptp(q[:, 0]) > math.radians(20) and np.ptp(q[:, 1]) > math.radians(14)
    assert abs(np.corrcoef(q[:, 0], q[:, 1])[0, 1]) < 0.5


def test_sim_joints_run_through_the_dynamixel_twin():
    from cgamap.calib.collect import DXL_TICK, HeadJoints

    joints = HeadJoints(None, 0.0, twin=True)
    try:
        assert joints.twin is not None and joints.twin.path
        pan, tilt = joints.move(0.1, -0.05)
        assert abs(pan - 0.1) <= 2 * DXL_TICK and abs(tilt + 0.05) <= 2 * DXL_TICK
        # The twin's servo really is there (the byte path was used, not a shortcut).
        assert abs(joints.twin.angle(1) - pan) <= 2 * DXL_TICK
    finally:
        joints.close()
    assert joints.twin is None


def test_hardware_path_fails_with_one_clear_line(tmp_path, capsys):
    code, _, err = _run(["calib", "collect", "--pantilt", str(tmp_path / "ttyNOPE"),
                         "--camera", "synthetic://corridor", "--out", str(tmp_path / "p.json")],
                        capsys)
    assert code == 2 and err.count("\n") == 1 and "--pantilt" in err
    code, _, err = _run(["calib", "collect", "--pantilt", "x", "--camera", "nourl"], capsys)
    assert code == 2 and "MODEL://DEVICE" in err


def test_hardware_path_plumbing_on_the_twins(tmp_path, capsys):
    """--pantilt/--camera open the real driver (on the Dynamixel twin's pty) and the camera
    grabber (synthetic backend, which shows no target): every pose is visited and skipped."""
    from cgamap.drivers.sim.dynamixel import DynamixelBusTwin

    twin = DynamixelBusTwin()
    path = twin.start()
    out = tmp_path / "p.json"
    out.write_text('{"previous": "run"}\n')      # a useful earlier file must survive
    try:
        code, stdout, err = _run(["calib", "collect", "--pantilt", path, "--camera",
                                  "synthetic://corridor", "--poses", "3", "--settle", "0",
                                  "--out", str(out)], capsys)
    finally:
        twin.stop()
    assert code == 1 and "only 0 usable poses of 3" in err and "3 x target not found" in err
    assert len(err.strip().splitlines()) == 1 and "not written" in err
    assert out.read_text() == '{"previous": "run"}\n'


def test_uncertainty_matches_the_spread_on_the_rendered_pipeline():
    from cgamap.calib.collect import DirectJoints, SimSource, collect
    from cgamap.calib.handeye import solve

    err, pred = [], []
    for seed in range(8):
        rig = default_rig(seed)
        pairs = collect(SimSource(rig, seed, DirectJoints()), rig.board,
                        pose_set(20, math.radians(12), math.radians(8)), rig.axis_point,
                        1.0, 100.0).pairs
        r = solve(pairs.base_T_head, pairs.cam_T_target)
        err.append(pose_errors(r.head_T_cam, rig.head_T_cam))
        pred.append((np.linalg.norm(r.std_rot_deg), np.linalg.norm(r.std_trans_m)))
    ratio = np.sqrt(np.mean(np.square(err), 0)) / np.sqrt(np.mean(np.square(pred), 0))
    assert np.all((0.4 < ratio) & (ratio < 2.5)), ratio
