"""``mapd replay`` as a real process: snapshots as map_server files, poses, clear errors."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from mapd.grid import Pose2D, load_map
from mapd.mapping.mapper import replay_log

BoxLog = Callable[..., tuple[Path, list[Pose2D]]]


def _mapd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapd", *args], capture_output=True, text=True, timeout=120, check=False
    )


def test_replay_writes_each_robots_growing_snapshots(box_log: BoxLog, tmp_path: Path) -> None:
    log, poses = box_log(scans=40)
    out = tmp_path / "out"
    r = _mapd("replay", str(log), "-o", str(out), "--every", "6", "--robots", "2", "--resolution", "0.1")
    assert r.returncode == 0, r.stderr
    for i, first in ((0, 0), (1, 16)):
        files = sorted((out / f"robot{i}").glob("map_*.yaml"))
        # 24 scans each, a snapshot every 6.
        assert [f.name for f in files] == [f"map_{k:04d}.yaml" for k in range(1, 5)]
        grids = [load_map(f) for f in files]
        assert all(g.resolution == 0.1 for g in grids)
        known = [g.cells - g.counts()["unknown"] for g in grids]
        assert known == sorted(known) and known[-1] > known[0]
        # The last file is exactly what replay_log makes for that robot.
        *_, (_t, final) = replay_log(log, every=6, resolution=0.1, robots=2, index=i)
        assert grids[-1].same_map(final)
        assert f"robot{i}: scans {first}.." in r.stderr
    meta = yaml.safe_load((out / "poses.yaml").read_text())
    assert meta["robot1"] == pytest.approx(list(poses[16]), abs=1e-5)


def test_replay_errors_are_one_line(tmp_path: Path) -> None:
    r = _mapd("replay", str(tmp_path / "missing.log"), "-o", str(tmp_path / "o"))
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [f"mapd: error: {tmp_path / 'missing.log'}: no such log file"]
    r = _mapd("replay", str(tmp_path / "missing.log"), "-o", str(tmp_path / "o"), "--every", "0")
    assert r.returncode == 2 and "--every must be at least 1" in r.stderr
