"""deploy/: the systemd unit verifies, asks for what the daemon needs, and matches what install.sh sets up."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def unit() -> configparser.RawConfigParser:
    # systemd units repeat keys (DeviceAllow): keep the last, which is enough for these checks
    cp = configparser.RawConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # type: ignore[assignment,method-assign]
    cp.read(DEPLOY / "mapd.service")
    return cp


def test_unit_asks_for_notify_watchdog_directories_and_hardening() -> None:
    s = unit()["Service"]
    assert s["Type"] == "notify" and int(s["WatchdogSec"]) > 0 and s["Restart"] == "on-failure"
    for key in ("StateDirectory", "RuntimeDirectory", "ConfigurationDirectory", "CacheDirectory"):
        assert s[key] == "mapd", key
    assert s["ProtectSystem"] == "strict" and s["NoNewPrivileges"] == "yes" and s["PrivateTmp"] == "yes"
    assert "dialout" in s["SupplementaryGroups"] and s["DevicePolicy"] == "closed"
    # uwb TDMA counts slots on the wall clock: start once it is synchronized, where that is waited for
    assert "time-sync.target" in unit()["Unit"]["After"].split()
    env = dict(kv.split("=", 1) for kv in s["Environment"].split())
    # numba may only write below CacheDirectory under ProtectSystem=strict, and install.sh warms it
    assert env["NUMBA_CACHE_DIR"].startswith("/var/cache/mapd/")
    install = (DEPLOY / "install.sh").read_text()
    assert f"NUMBA_CACHE_DIR={env['NUMBA_CACHE_DIR']}" in install and "mapd warmup" in install


def test_install_script_parses() -> None:
    out = subprocess.run(["bash", "-n", str(DEPLOY / "install.sh")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    # verify checks that ExecStart exists: point it at this checkout's mapd instead of /opt/mapd
    mapd = Path(sys.executable).parent / "mapd"
    text = (DEPLOY / "mapd.service").read_text().replace("/opt/mapd/venv/bin/mapd", str(mapd))
    (tmp_path / "mapd.service").write_text(text)
    out = subprocess.run(
        ["systemd-analyze", "verify", str(tmp_path / "mapd.service")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0 and not out.stderr.strip(), out.stderr


def test_warmup_command_compiles_the_lossless_kernels(tmp_path: Path) -> None:
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PATH": "/usr/bin:/bin"}
    out = subprocess.run(
        [sys.executable, "-m", "mapd", "warmup", "--codec", "lossless", "raw"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0].startswith("lossless: ready in")
    assert any((tmp_path / "numba").rglob("*.nbi")), "numba wrote no cache index under NUMBA_CACHE_DIR"
