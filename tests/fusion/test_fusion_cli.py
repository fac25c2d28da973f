"""`mapd merge` as a real process: JSON, files, poses, and one-line errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map
from mapd.grid.save import save_map


def _mapd(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapd", *args], cwd=cwd, capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def two_maps(tmp_path_factory: pytest.TempPathFactory, building: OccupancyGrid) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("maps")
    a = building.replace(
        data=np.ascontiguousarray(building.data[0:220, 0:170]), origin=Pose2D(-1.0, 2.0, 0.0)
    )
    b = building.replace(
        data=np.ascontiguousarray(building.data[60:300, 110:260]), origin=Pose2D(0.0, 0.0, 0.0)
    )
    (d / "one").mkdir()
    (d / "two").mkdir()
    return save_map(a, d / "one" / "map.yaml"), save_map(b, d / "two" / "map.yaml")


def test_merge_prints_transforms_in_the_first_maps_frame(tmp_path: Path, two_maps: tuple[Path, Path]) -> None:
    a, b = two_maps
    out, png = tmp_path / "merged.yaml", tmp_path / "merged.png"
    r = _mapd("merge", str(a), str(b), "-o", str(out), "--png", str(png), "--json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    (t,) = doc["transforms"]
    assert {"x", "y", "yaw", "confidence", "agreement", "accepted"} <= set(t)
    assert t["robot"] == "1"  # both files are called map.yaml: robots are named by position
    # b's cell (0, 0) corner sits at a's cell (60, 110), i.e. a's origin + (5.5, 3.0) m
    assert (
        t["accepted"]
        and math.isclose(t["x"], -1.0 + 5.5, abs_tol=0.1)
        and math.isclose(t["y"], 2.0 + 3.0, abs_tol=0.1)
    )
    assert abs(t["yaw"]) < math.radians(1.0) and t["confidence"] >= 0.5 and t["agreement"] >= 0.8
    merged = load_map(out)
    assert merged.cells >= 240 * 260 and png.stat().st_size > 0


def test_known_pose_and_text_output(tmp_path: Path, two_maps: tuple[Path, Path]) -> None:
    a, b = two_maps
    out = tmp_path / "m.yaml"
    r = _mapd(
        "merge", str(a), str(b), "-o", str(out), "--pose", "0=0,0,0", "--pose", "1=4.5,5,0", cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    assert "x     4.500" in r.stdout and "(pose)" in r.stdout


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--pose", "1=1,2"], "three numbers"),
        (["--pose", "7=1,2,3"], "no input named '7'"),
        (["--min-confidence", "2"], "must lie in [0, 1]"),
    ],
)
def test_bad_options_give_one_line(
    tmp_path: Path, two_maps: tuple[Path, Path], args: list[str], words: str
) -> None:
    a, b = two_maps
    r = _mapd("merge", str(a), str(b), "-o", str(tmp_path / "x.yaml"), *args, cwd=tmp_path)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mapd: error:") and words in lines[0]


def test_missing_map_gives_one_line(tmp_path: Path, two_maps: tuple[Path, Path]) -> None:
    r = _mapd(
        "merge", str(two_maps[0]), str(tmp_path / "nope.yaml"), "-o", str(tmp_path / "x.yaml"), cwd=tmp_path
    )
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [f"mapd: error: {tmp_path / 'nope.yaml'}: no such map file"]


def test_merge_shows_its_progress_on_a_terminal_and_nothing_in_a_pipe(
    tmp_path: Path, two_maps: tuple[Path, Path]
) -> None:
    """Each map is tried against every map placed before it: eight maps took 50 s without a word."""
    import fcntl
    import os
    import pty
    import struct
    import termios

    a, b = two_maps
    master, slave = pty.openpty()
    # a terminal of 80 columns (a new pty has none, and a bar 0 columns wide is empty)
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mapd", "merge", str(a), str(b), "-o", str(tmp_path / "t.yaml")],
            cwd=tmp_path, stdin=slave, stdout=subprocess.DEVNULL, stderr=slave,
        )  # fmt: skip
        os.close(slave)
        seen = b""
        while True:
            try:
                chunk = os.read(master, 1 << 16)
            except OSError:  # the terminal closed with the process
                break
            if not chunk:
                break
            seen += chunk
        assert proc.wait(timeout=120) == 0
    finally:
        os.close(master)
    assert b"placing maps" in seen and b"1: placed" in seen, seen[-500:]
    r = _mapd("merge", str(a), str(b), "-o", str(tmp_path / "p.yaml"), cwd=tmp_path)
    assert r.returncode == 0 and r.stderr == "", r.stderr


def test_a_first_map_left_out_is_reported_with_the_frame_the_output_is_in(
    tmp_path: Path, two_maps: tuple[Path, Path]
) -> None:
    """Only the second map posed, the first matching nothing: the report said the output was in
    the first map's frame, called the merged map "accepted: false", and never named the map left out."""
    room = np.full((40, 60), -1, np.int8)
    room[5:35, 5:55] = 0
    room[5, 5:55] = 100  # a bare rectangle: many placements fit it equally, so none is accepted
    first = save_map(OccupancyGrid(room, 0.05, (-1.0, -1.0, 0.0)), tmp_path / "room.yaml")
    second = save_map(load_map(two_maps[1]), tmp_path / "hall.yaml")
    out = tmp_path / "m.yaml"
    args = ("merge", str(first), str(second), "-o", str(out), "--pose", "hall=0.5,0,0")
    r = _mapd(*args, "--json", cwd=tmp_path)
    assert r.returncode == 3, r.stderr  # written, but a map is left out: a status of its own
    doc = json.loads(r.stdout)
    assert "--pose" in doc["frame"] and "room" not in doc["frame"], doc["frame"]
    rows = {m["robot"]: m for m in doc["maps"]}
    assert set(rows) == {"room", "hall"} and doc["left_out"] == ["room"]
    assert not rows["room"]["accepted"] and rows["room"]["reason"] and rows["room"]["x"] is None
    hall = rows["hall"]
    assert hall["accepted"] and (hall["x"], hall["y"], hall["yaw"]) == (0.5, 0.0, 0.0)
    assert doc["transforms"] == doc["maps"][1:]
    assert (doc["global"]["maps_merged"], doc["global"]["maps_left_out"]) == (1, 1)
    assert load_map(out).cells > 0  # the output was written all the same
    assert "room" in r.stderr and "left out" in r.stderr
    text = _mapd(*args, cwd=tmp_path)
    assert text.returncode == 3
    assert "frame of the --pose options (hall)" in text.stdout and "room" in text.stdout
    assert "x     0.500" in text.stdout  # the merged map is listed as merged, with its transform


@pytest.mark.parametrize("x, y", [(-10.0, -10.0), (-10.025, 3.0137)])
def test_a_map_merged_with_itself_comes_back_as_it_was(
    tmp_path: Path, building: OccupancyGrid, x: float, y: float
) -> None:
    """The one-shot merge padded its output out to the daemon's 64-cell blocks: a map merged with
    itself came back larger, with an unknown border and its origin moved. Blocks keep a live global
    map's size steady across merges; a one-shot merge has no later merge to keep steady. And a map
    whose origin is off its frame's lattice (-10.025 at 5 cm) came back resampled, walls moved by
    half a cell."""
    assert building.resolution == 0.05
    g = building.replace(origin=Pose2D(x, y, 0.0))  # off the blocks; on or off its 5 cm lattice
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a, b = save_map(g, tmp_path / "a" / "map.yaml"), save_map(g, tmp_path / "b" / "map.yaml")
    r = _mapd("merge", str(a), str(b), "-o", str(tmp_path / "m.yaml"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = load_map(tmp_path / "m.yaml")
    assert (out.width, out.height) == (g.width, g.height)
    assert math.isclose(out.origin.x, x, abs_tol=1e-9) and math.isclose(out.origin.y, y, abs_tol=1e-9)
    assert np.array_equal(out.data, g.data)
