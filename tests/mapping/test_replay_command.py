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


def test_each_kind_of_bad_line_is_said_once_however_many_robots_read_it(
    box_log: BoxLog, tmp_path: Path
) -> None:
    import gzip

    log, _poses = box_log(scans=40)
    lines = gzip.decompress(log.read_bytes()).decode().splitlines(keepends=True)
    # Near the start, so every robot's pass (and the lookup of its first pose) reads them.
    lines[1:1] = ["BOGUS 1 2 3\n", "BOGUS 4 5 6\n", "FLASER 3 1.0 2.0\n"]
    bad = tmp_path / "bad.log"
    bad.write_text("".join(lines))
    r = _mapd("replay", str(bad), "-o", str(tmp_path / "out"), "--every", "6", "--robots", "3")
    assert r.returncode == 0, r.stderr
    said = [ln for ln in r.stderr.splitlines() if "skipped; further lines like it" in ln]
    assert len(said) == 2, said  # the unknown type once (not per line or robot), the short scan once
    assert sum("unknown message type" in ln for ln in said) == 1
    assert sum(f"{bad}: line 4:" in ln for ln in said) == 1
