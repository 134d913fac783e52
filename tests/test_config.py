"""Config schema: the shipped configs validate; each malformed config gives its one line, 78."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from cgamap.daemon import config

REPO = Path(__file__).resolve().parents[1]
BAD = sorted((REPO / "tests" / "data" / "bad_configs").glob("*.yaml"))


def expected(path: Path) -> str:
    first = path.read_text().splitlines()[0]
    assert first.startswith("# expect:"), path
    return first.split("expect:", 1)[1].strip()


def test_corpus_is_large_enough():
    assert len(BAD) >= 20


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_config_names_key_and_problem(path):
    with pytest.raises(config.ConfigError) as info:
        config.load(path)
    assert expected(path) in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name", ["robot.yaml", "sim.yaml"])
def test_shipped_configs_validate(name):
    cfg = config.load(REPO / "config" / name)
    assert {d["role"] for d in cfg["devices"].values()} == set(config.ROLES)


def test_defaults_filled_in():
    cfg = config.validate({})
    assert cfg["checkpoint"]["interval"] == 30.0
    assert cfg["server"]["tcp"] is False and cfg["server"]["tcp_host"] == "127.0.0.1"
    assert cfg["devices"] == {}


def test_hand_eye_file_is_loaded_relative_to_config(tmp_path):
    (tmp_path / "he.yaml").write_text(yaml.safe_dump(
        {"head_T_cam": [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}))
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"devices": {"head": {
        "role": "pantilt", "model": "dynamixel", "url": "serial:///dev/ttyUSB1",
        "hand_eye": "he.yaml"}}}))
    cfg = config.load(tmp_path / "c.yaml")
    assert cfg["devices"]["head"]["head_T_cam"][0][3] == 0.1


def test_systemd_directories_win(monkeypatch):
    cfg = config.validate({})
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/x")
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/x")
    state, sock = config.resolve_paths(cfg)
    assert state == Path("/var/lib/x") and sock == Path("/run/x/cgamapd.sock")


@pytest.mark.parametrize("path", BAD[:3] + BAD[-3:], ids=lambda p: p.stem)
def test_check_config_cli_exit_78(path):
    out = subprocess.run([sys.executable, "-m", "cgamap.daemon.main", "--check-config",
                          str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 78
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and expected(path) in lines[0], out.stderr


def test_check_config_cli_ok():
    out = subprocess.run([sys.executable, "-m", "cgamap.daemon.main", "--check-config",
                          str(REPO / "config" / "sim.yaml")], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
