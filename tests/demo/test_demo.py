"""``mapd demo``, the main job, end to end as a user runs it (shortened): outputs exist and make sense."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

needs_socat = pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")


@pytest.mark.slow
@needs_socat
def test_demo_runs_two_robots_over_uwb_and_writes_its_report(tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "mapd", "demo", "--duration", "25", "--out", str(out), "--drop", "0.05"],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    # live progress lines, then the summary table
    progress = [ln for ln in proc.stdout.splitlines() if ln.startswith("t=")]
    assert len(progress) >= 5 and "robot0 v" in progress[-1] and "link" in progress[-1]
    assert "global map" in proc.stdout
    for name in ("global_map.png", "bandwidth.png", "quality.png"):
        with Image.open(out / name) as im:
            assert im.width > 100 and im.height > 100
    assert (out / "global.yaml").exists() and (out / "global.pgm").exists()
    with open(out / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    robots = {r["robot"] for r in rows}
    assert robots == {"robot0", "robot1"}
    for robot in robots:
        mine = [r for r in rows if r["robot"] == robot]
        assert len(mine) >= 3 and mine[0]["kind"] == "keyframe"
        assert any(r["kind"] == "delta" for r in mine)  # deltas after the first keyframe
        assert all(float(r["ratio"]) > 1 for r in mine)
    summary = json.loads((out / "summary.json").read_text())["robots"]
    for r in summary:
        # what the radio carried: something, and never more than the paced 12.5 kb/s on average
        assert 0 < r["link_bps"] <= 12500
        assert r["loop_ms"] >= 0  # its event loop's worst lateness, measured (NaN: not reported)
    relay = json.loads((out / "run" / "uwb" / "relay-stats.json").read_text())
    assert relay["rate_bps"] == 12500 and relay["dropped"] > 0  # the faults reached the radio


def test_global_map_picture_names_each_robots_tint() -> None:
    import numpy as np

    from mapd.demo.report import COLOURS, with_legend

    img = np.full((50, 300, 3), 205, dtype=np.uint8)
    out = with_legend(img, ["robot0", "robot1", "robot2"])
    assert out.shape[1] == 300 and out.shape[0] > 50
    assert np.array_equal(out[:50], img)  # the map itself is untouched
    strip = out[50:].reshape(-1, 3).astype(int)
    for i in range(3):
        tint = (0.55 * 250.0 + 0.45 * COLOURS[i]).astype(int)
        assert (np.abs(strip - tint).max(axis=1) <= 1).sum() > 50  # a swatch of that robot's colour
    dark = (strip.max(axis=1) < 80).sum()
    assert dark > 30  # and text beside the swatches


def test_global_map_picture_marks_each_robot_where_it_is() -> None:
    import numpy as np

    from mapd.demo.report import COLOURS, mark_robots
    from mapd.grid import OccupancyGrid, Pose2D

    g = OccupancyGrid(np.zeros((100, 200), np.int8), 0.1, origin=Pose2D(-5.0, 2.0, 0.0))
    img = np.full((100, 200, 3), 250, dtype=np.uint8)
    # robot1 at x = 5 m, y = 6 m: column (5 - -5) / 0.1 = 100, row 99 - (6 - 2) / 0.1 = 59
    out = mark_robots(img, g, {"robot1": [5.0, 6.0, 0.0]}, ["robot0", "robot1"])
    assert np.array_equal(out[59, 98], COLOURS[1].astype(np.uint8))  # robot1's colour at its place
    assert (out[59, 100:110].max(axis=1) < 60).any()  # the heading line points along +x (yaw 0)
    assert np.array_equal(out[10, 10], img[10, 10])  # the rest untouched
    changed = np.argwhere((out != img).any(axis=2))
    assert changed[:, 0].min() >= 50 and changed[:, 0].max() <= 68  # one marker, around row 59


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--transport", "zenoh", "--out-of-range", "0-1"], "add --transport uwb"),
        (["--transport", "uwb", "--robots", "3", "--out-of-range", "0-3"], "numbered 0..2"),
        (["--transport", "uwb", "--out-of-range", "1-1"], "two different robot indices"),
    ],
)
def test_demo_refuses_a_bad_out_of_range_pair_in_one_line(
    tmp_path: Path, extra: list[str], says: str
) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "mapd", "demo", "--out", str(tmp_path), *extra],
        capture_output=True,
        text=True,
        timeout=60,
    )
    # one clear line, last (argparse's own errors print the usage above it)
    assert r.returncode != 0 and says in r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr


def test_demo_readies_the_codec_once_before_any_robot_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A first demo on a fresh machine spent its window compiling numba kernels in every robot, and
    # one stopped mid-compile outlasted its stop timeout ("robot0 did not stop within 10 s").
    import mapd.codec.api
    from mapd.cli import build_parser
    from mapd.demo import fleet

    calls: list[str] = []

    class Started(Exception):
        pass

    def prepare(self: object) -> None:
        calls.append("prepare")
        raise Started

    monkeypatch.setattr(mapd.codec.api, "warm_up", lambda name: calls.append(f"warm_up {name}") or 0.0)
    monkeypatch.setattr(fleet.Fleet, "prepare", prepare)
    args = build_parser().parse_args(["demo", "--out", str(tmp_path), "--codec", "pooled"])
    with pytest.raises(Started):
        fleet.run_demo(args)
    assert calls == ["warm_up pooled", "prepare"]


def _processes_naming(text: str) -> list[str]:
    """Command lines of the running processes that hold ``text`` (from /proc, as ps shows them)."""
    out = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            args = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # gone meanwhile
            continue
        if text in args:
            out.append(args)
    return out


@needs_socat
@pytest.mark.parametrize("log", ["absent.log", "."])
def test_a_demo_whose_setup_fails_leaves_no_radio_relay_or_socat_behind(tmp_path: Path, log: str) -> None:
    # Before, the relay (started first) and its two socat ptys outlived the one error line, for
    # ever, one set per mistyped --log.
    out = tmp_path / "demo"
    r = subprocess.run(
        [sys.executable, "-m", "mapd", "demo", "--transport", "uwb", "--log", str(tmp_path / log),
         "--duration", "3", "--out", str(out)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode != 0 and r.stderr.strip().splitlines()[-1].startswith("mapd: error: "), r.stderr
    assert "Traceback" not in r.stderr
    assert (out / "run" / "uwb").is_dir(), "the relay was not started: the test shows nothing"
    assert _processes_naming(str(out)) == []


def test_a_robot_killed_by_a_signal_is_said_so_not_as_an_exit_code(tmp_path: Path) -> None:
    # "robot1 exited with code -9: ... the wall clock is not synchronized": a signal read as an
    # exit code, and the log's last line read as the cause.
    import signal

    from mapd.demo.fleet import Fleet
    from mapd.errors import DaemonError

    fleet = Fleet.__new__(Fleet)
    fleet.run_dir = tmp_path
    (tmp_path / "robot1").mkdir()
    (tmp_path / "robot1" / "daemon.log").write_text("WARNING the wall clock is not synchronized\n")
    proc = subprocess.Popen(["sleep", "30"])
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    fleet.procs = {"robot1": proc}
    with pytest.raises(
        DaemonError, match=r"^robot1 was killed by signal 9 \(SIGKILL\); stopping the other robots$"
    ):
        fleet.check_alive()
    # a real-time signal has no name: said by its number, not a ValueError traceback
    rt = subprocess.Popen(["sleep", "30"])
    rt.send_signal(signal.SIGRTMIN + 1)
    rt.wait(10)
    fleet.procs = {"robot1": rt}
    with pytest.raises(
        DaemonError, match=rf"^robot1 was killed by signal {int(signal.SIGRTMIN) + 1}; stopping"
    ):
        fleet.check_alive()
