"""``mapd replay`` as a real process: snapshots as map_server files, poses, clear errors."""

from __future__ import annotations

import builtins
import errno
import io
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from mapd.cli import main
from mapd.grid import Pose2D
from mapd.grid.load import load_map
from mapd.mapping.replay import replay_log

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


class _FullDisk:
    """A file opened for writing on a full disk: the open succeeds (and truncates), writes fail."""

    def __init__(self, fh: Any) -> None:
        self._fh = fh

    def write(self, data: Any) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __enter__(self) -> _FullDisk:
        return self

    def __exit__(self, *exc: object) -> None:
        self._fh.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._fh, name)


def test_a_full_disk_leaves_no_partial_poses_file(
    box_log: BoxLog, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    log, _poses = box_log(scans=12)
    out = tmp_path / "out"
    out.mkdir()  # an empty folder that exists already is a fine output
    real_open = builtins.open

    def full_disk_open(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        fh = real_open(file, mode, *args, **kwargs)
        # poses.yaml itself or a temp file beside it: the disk fills as it is written
        if not isinstance(file, int) and "poses.yaml" in os.fspath(file) and set(mode) & set("wax"):
            return _FullDisk(fh)
        return fh

    monkeypatch.setattr(builtins, "open", full_disk_open)
    monkeypatch.setattr(io, "open", full_disk_open)  # what Path.write_text opens with
    rc = main(["replay", str(log), "-o", str(out), "--every", "100"])
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert rc == 1
    assert [ln for ln in err.splitlines() if ln.startswith("mapd: error: ")] == [
        f"mapd: error: {out}/poses.yaml: cannot write: No space left on device"
    ]
    # Neither a truncated poses.yaml nor a temp file beside it.
    assert sorted(p.name for p in out.iterdir()) == ["robot0"]


@pytest.mark.parametrize("value", ["100", "inf", "1e300", "1e-300", "0", "-0.05", "nan"])
def test_a_resolution_the_mapper_cannot_take_is_one_usage_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    # Refused while parsing, before the log is even opened (it does not exist here).
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_:
        main(["replay", str(tmp_path / "absent.log"), "-o", str(out), "--resolution", value])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.splitlines()[-1].startswith("mapd replay: error: argument --resolution: ")
    assert len(err.splitlines()[-1]) < 120
    assert not out.exists()


def _errors(err: str) -> list[str]:
    assert "Traceback" not in err
    return [ln for ln in err.splitlines() if ln.startswith("mapd: error: ")]


@pytest.mark.parametrize(
    ("name", "data", "says"),
    [
        ("map.yaml", b"image: map.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "not a CARMEN log"),
        ("empty.log", b"", "the log is empty"),
        ("g.log.gz", b"garbage", "named .gz but not gzip-compressed"),
        ("bad.log", b"FLASER 3 1 2\nFLASER x\n", "no usable scan in its 2 scan lines"),
    ],
)
def test_a_replay_that_read_no_scan_is_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, data: bytes, says: str
) -> None:
    log = tmp_path / name
    log.write_bytes(data)
    out = tmp_path / "out"
    rc = main(["replay", str(log), "-o", str(out)])
    errors = _errors(capsys.readouterr().err)
    assert rc == 1
    assert len(errors) == 1 and errors[0].startswith(f"mapd: error: {log}: ") and says in errors[0], errors
    assert not (out / "poses.yaml").exists()  # no empty poses.yaml that looks like a finished run


def test_an_output_folder_holding_an_earlier_replay_is_refused(
    box_log: BoxLog, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log, _poses = box_log(scans=30)
    out = tmp_path / "out"
    assert main(["replay", str(log), "-o", str(out), "--every", "2", "--robots", "2"]) == 0
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    assert "robot1/map_0009.yaml" in before
    capsys.readouterr()
    # Fewer snapshots and robots: in place, the first run's map_0002..0009 and robot1/ would have stayed.
    rc = main(["replay", str(log), "-o", str(out), "--every", "50"])
    errors = _errors(capsys.readouterr().err)
    assert rc == 1
    assert errors == [
        f"mapd: error: {out}: already holds a replay (poses.yaml, robot0, robot1); "
        "give another -o folder, or remove this one first"
    ]
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before  # refused before any work
    # A robot's folder alone (a run stopped before its poses.yaml) is an earlier replay too.
    only = tmp_path / "only"
    (only / "robot3").mkdir(parents=True)
    assert main(["replay", str(log), "-o", str(only)]) == 1
    assert "already holds a replay (robot3)" in capsys.readouterr().err
