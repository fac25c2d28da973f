"""Real daemons as processes: over zenoh and over socat through the fault relay, status, SIGTERM, kill -9."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from mapd.demo import Fleet

pytestmark = pytest.mark.slow


def fleet(tmp: Path, transport: str, duration: float = 30.0) -> Fleet:
    args = argparse.Namespace(
        robots=2, transport=transport, codec="lossless", log=None, seed=7, out=tmp, duration=duration
    )
    f = Fleet(args)
    f.prepare()
    return f


def wait_for(pred: Any, timeout: float, f: Fleet) -> dict[str, dict[str, Any]]:
    deadline = time.monotonic() + timeout
    snaps: dict[str, dict[str, Any]] = {}
    while time.monotonic() < deadline:
        f.check_alive()
        snaps = f.status()
        if pred(snaps):
            return snaps
        time.sleep(1.0)
    raise AssertionError(f"condition not met in {timeout} s: {json.dumps(snaps)[:2000]}")


def holds_each_other(snaps: dict[str, dict[str, Any]], min_version: int = 3) -> bool:
    return len(snaps) == 2 and all(
        any(p.get("version", 0) >= min_version for p in s.get("peers", {}).values()) for s in snaps.values()
    )


@pytest.mark.parametrize("transport", ["zenoh", "uwb"])
def test_two_daemons_exchange_and_fuse(tmp_path: Path, transport: str) -> None:
    f = fleet(tmp_path, transport)
    f.start()
    try:
        snaps = wait_for(holds_each_other, 90, f)
        # mapd status --json against a live daemon, as a user runs it
        sock = f.run_dir / "robot0" / "run" / "mapd.sock"
        out = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--json", "--socket", str(sock)],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert out.returncode == 0, out.stderr
        doc = json.loads(out.stdout)
        assert doc["robot"] == "robot0" and "robot1" in doc["peers"]
        assert doc["codec"]["deltas"] + doc["codec"]["keyframes"] >= 3
        wait_for(lambda s: all(x.get("fusion", {}).get("maps", 0) >= 2 for x in s.values()), 60, f)
        assert snaps
    finally:
        codes = f.stop(timeout=10)
    assert codes == {"robot0": 0, "robot1": 0}
    for name in f.names:
        assert (f.run_dir / name / "state" / "global" / "global.yaml").exists()


def test_sigterm_exits_cleanly_within_2s(tmp_path: Path) -> None:
    f = fleet(tmp_path, "zenoh")
    f.start()
    try:
        wait_for(lambda s: len(s) == 2 and all(x.get("peers") for x in s.values()), 60, f)
        p = f.procs["robot0"]
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        assert p.wait(10) == 0
        assert time.monotonic() - t0 < 2.0
        assert not (f.run_dir / "robot0" / "run" / "mapd.sock").exists()
    finally:
        f.stop()


def test_kill_9_and_restart_resumes(tmp_path: Path) -> None:
    f = fleet(tmp_path, "zenoh")
    f.start()
    try:
        wait_for(holds_each_other, 90, f)
        before = f.status()["robot0"]
        v_own = before["source"]["version"]
        os.kill(f.procs["robot0"].pid, signal.SIGKILL)
        f.procs["robot0"].wait(10)
        state = json.loads((f.run_dir / "robot0" / "state" / "state.json").read_text())
        assert state["own_version"] >= v_own - 1 and "robot1" in state["peers"]
        # restart the same daemon with the same state directory
        d = f.run_dir / "robot0"
        f.procs["robot0"] = subprocess.Popen(
            [sys.executable, "-m", "mapd", "run", "--config", str(d / "config.toml")],
            stdout=open(d / "daemon2.log", "wb"),  # noqa: SIM115 - lives as long as the process
            stderr=subprocess.STDOUT,
        )
        snaps = wait_for(
            lambda s: "robot0" in s and s["robot0"]["peers"].get("robot1", {}).get("version", 0) > 0, 60, f
        )
        after = snaps["robot0"]
        # it held the peer's map and the global map from before the crash, and its versions keep rising
        assert after["fusion"]["global"] is not None
        snaps = wait_for(
            lambda s: "robot0" in s and s["robot0"]["source"]["version"] > state["own_version"], 60, f
        )
        # the peer accepts the restarted robot's new versions (never a stale or repeated one)
        wait_for(
            lambda s: (
                s.get("robot1", {}).get("peers", {}).get("robot0", {}).get("version", 0)
                > state["own_version"]
            ),
            60,
            f,
        )
    finally:
        codes = f.stop()
    assert codes["robot1"] == 0


def test_bad_config_is_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[robot]\nname = "a"\n[source]\nuse = "sim"\n[transports]\nuse = ["uwb"]\n'
        '[transports.uwb]\nport = "/dev/does-not-exist"\n[transports.uwb.nodes]\na = 1\nb = 2\n'
        f'[state]\ndir = "{tmp_path / "s"}"\nruntime_dir = "{tmp_path / "r"}"\n'
    )
    out = subprocess.run(
        [sys.executable, "-m", "mapd", "run", "--config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0
    lines = [ln for ln in out.stderr.splitlines() if ln.startswith("mapd: error:")]
    assert len(lines) == 1 and "does-not-exist" in lines[0], out.stderr
    assert "Traceback" not in out.stderr
