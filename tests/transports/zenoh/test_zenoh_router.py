"""Robots as zenoh clients of one router (deploy/zenoh/router.json5 in a process of its own), daemons and all."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd.data import REPO_ROOT

pytestmark = pytest.mark.slow


def test_three_daemons_through_one_router(tmp_path: Path, fk: SimpleNamespace) -> None:
    f = fk.router_fleet(tmp_path)
    assert f.router is not None and f.router.poll() is None
    cfg = (f.run_dir / "robot0" / "config.toml").read_text()
    assert 'mode = "client"' in cfg and "listen" not in cfg.split("[transports.zenoh]")[1].split("[")[0]
    f.start()
    try:
        pairs = [(a, b) for a in f.names for b in f.names if a != b]
        snaps = fk.wait_for(lambda s: all(fk.held(s, a, b) >= 2 for a, b in pairs), 120, f)
        for me in f.names:  # every robot waits for the other two (both showed signed messages)
            assert sorted(snaps[me]["links"]["zenoh"]["peers"]) == sorted(n for n in f.names if n != me)
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0, "robot2": 0}
    assert f.router.poll() is not None  # stopped with the fleet


def test_router_with_a_bad_config_says_so_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    out = subprocess.run(
        [sys.executable, "-m", "transports.zenoh.router", "--config", str(bad)],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert (
        out.returncode == 1
        and out.stderr.startswith("router: cannot start:")
        and "Traceback" not in out.stderr
    )
    assert (REPO_ROOT / "deploy" / "zenoh" / "router.json5").exists()
