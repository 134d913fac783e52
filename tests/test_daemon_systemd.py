"""The systemd unit: `systemd-analyze verify` and the offline security score, where
systemd-analyze exists (Debian's systemd package); skipped with the reason where not."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "cgamapd.service"
RULES = REPO / "systemd" / "99-cgamap-serial.rules"
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze not installed "
                                   "(apt-get install systemd)")


def unit_copy(tmp_path: Path) -> Path:
    """The unit with ExecStart pointing at an existing file (verify checks it exists)."""
    exe = shutil.which("true") or "/bin/true"
    path = tmp_path / "cgamapd.service"
    path.write_text(UNIT.read_text().replace("/usr/local/bin/cgamapd", exe))
    return path


def unit_settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            k, v = line.split("=", 1)
            out.setdefault(k.strip(), []).append(v.strip())
    return out


def test_unit_has_the_required_settings():
    s = unit_settings()
    assert s["Type"] == ["notify"] and s["WatchdogSec"]
    assert s["SupplementaryGroups"] == ["dialout plugdev"]
    for key in ("StateDirectory", "RuntimeDirectory", "ConfigurationDirectory"):
        assert s[key] == ["cgamap"]
    assert s["ProtectSystem"] == ["strict"] and s["DevicePolicy"] == ["closed"]
    assert {"char-ttyUSB rw", "char-ttyACM rw", "char-usb_device rw"} <= set(s["DeviceAllow"])
    assert "PrivateDevices" not in s  # it would hide the serial and USB nodes
    assert s["RestartPreventExitStatus"] == ["78"]
    # the mapper's compiled kernels: cached where the service may write (the package is
    # read-only under ProtectSystem=strict), and JIT code needs writable-executable pages
    assert s["CacheDirectory"] == ["cgamap"]
    assert "NUMBA_CACHE_DIR=/var/cache/cgamap/numba" in s["Environment"]
    assert "MemoryDenyWriteExecute" not in s


def test_udev_rule_sets_ftdi_latency():
    text = RULES.read_text()
    assert re.search(r'DRIVER=="ftdi_sio".*ATTR\{latency_timer\}="1"', text)


@needs_analyze
def test_systemd_analyze_verify(tmp_path):
    out = subprocess.run([ANALYZE, "verify", str(unit_copy(tmp_path))], capture_output=True,
                         text=True, timeout=60)
    problems = [ln for ln in (out.stdout + out.stderr).splitlines() if "cgamapd" in ln]
    assert out.returncode == 0 and not problems, out.stdout + out.stderr


@needs_analyze
def test_systemd_analyze_verify_catches_a_typo(tmp_path):
    path = unit_copy(tmp_path)
    path.write_text(path.read_text().replace("ProtectSystem=", "ProtectSytem="))
    out = subprocess.run([ANALYZE, "verify", str(path)], capture_output=True, text=True,
                         timeout=60)
    assert "ProtectSytem" in out.stdout + out.stderr


@needs_analyze
def test_systemd_analyze_security_offline(tmp_path):
    out = subprocess.run([ANALYZE, "security", "--offline=yes", "--threshold=30",
                          str(unit_copy(tmp_path))], capture_output=True, text=True, timeout=60)
    if "Unknown option" in out.stderr or "unrecognized option" in out.stderr:
        pytest.skip(f"this systemd-analyze has no offline security: {out.stderr.strip()}")
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", out.stdout)
    assert m, out.stdout + out.stderr
    print("exposure:", m.group(1))
    assert float(m.group(1)) <= 3.0 and out.returncode == 0
