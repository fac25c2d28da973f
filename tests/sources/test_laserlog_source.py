"""The laserlog source and replay_log: on a synthetic log of a known room and on the real intel log."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from mapd import plugins
from mapd.codec.metrics import occupied_f1
from mapd.config import MapdConfig
from mapd.errors import SourceError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map
from mapd.mapping.replay import first_pose, replay_log, resample
from mapd.sources.base import SourceContext
from mapd.sources.laserlog import LaserLogOptions, LaserLogSource

BoxLog = Callable[..., tuple[Path, list[Pose2D]]]


def _collect(src: LaserLogSource) -> list[OccupancyGrid]:
    async def go() -> list[OccupancyGrid]:
        return [g async for g in src.maps()]

    return asyncio.run(go())


def test_registered_under_mapd_sources() -> None:
    assert plugins.load("source", "laserlog") is LaserLogSource


def test_replay_log_versions_growth_and_known_walls(box_log: BoxLog, box_world: OccupancyGrid) -> None:
    from mapd.grid import OCCUPIED

    path, poses = box_log(scans=30)
    snaps = list(replay_log(path, every=7))
    assert [g.version for _, g in snaps] == [1, 2, 3, 4, 5]  # 30 scans: 4 full groups and a last one
    assert [t for t, _ in snaps] == sorted(t for t, _ in snaps)
    assert snaps[-1][0] == pytest.approx(100.0 + 0.1 * 29)
    # The map frame is the first laser pose; put the map back in the world frame and compare walls.
    world = box_world
    final = resample(snaps[-1][1], poses[0], world)
    wall = world.data == OCCUPIED
    seen = final.data != -1
    assert occupied_f1(world.data * seen, final.data, tolerance=1) > 0.9
    assert (final.data[seen & wall] == 100).mean() > 0.5
    assert (final.data[seen & ~wall] == 0).mean() > 0.95


def test_source_emits_every_n_scans_and_counts_bad_lines(box_log: BoxLog, tmp_path: Path) -> None:
    bad = ["FLASER 3 1 2\n", "WHAT 1 2\n", "FLASER 2 nan 1 0 0 0 0 0 0 1 h 1\n"]
    path, _ = box_log(scans=20, extra=bad)
    src = LaserLogSource(LaserLogOptions(log=path, every=5, realtime=0), SourceContext(robot="r7"))
    maps = _collect(src)
    assert [g.version for g in maps] == [1, 2, 3, 4]
    assert all(g.robot == "r7" for g in maps)
    st = src.stats()
    assert st["scans"] == 20 and st["skipped_lines"] == 3 and st["versions"] == 4
    assert str(path) in str(st["last_error"])


def test_every_seconds_of_log_time(box_log: BoxLog) -> None:
    path, _ = box_log(scans=20, dt=0.5)  # 9.5 s of log time
    src = LaserLogSource(
        LaserLogOptions(log=path, every=None, every_s=3.0, realtime=0), SourceContext(robot="r")
    )
    stamps = [g.stamp for g in _collect(src)]
    assert stamps == [103.0, 106.0, 109.0, 109.5]


def test_realtime_factor_paces_the_replay(box_log: BoxLog) -> None:
    path, _ = box_log(scans=6, dt=0.1)  # 0.5 s of log time
    src = LaserLogSource(LaserLogOptions(log=path, every=1, realtime=2.0), SourceContext(robot="r"))
    t0 = time.perf_counter()
    maps = _collect(src)
    took = time.perf_counter() - t0
    assert len(maps) == 6
    assert took >= 0.24  # 0.5 s of log at twice real time


def test_two_robots_get_overlapping_slices_and_start_poses(box_log: BoxLog) -> None:
    path, poses = box_log(scans=40)
    a = LaserLogSource(
        LaserLogOptions(log=path, robots=2, index=0, every=100, realtime=0), SourceContext(robot="a")
    )
    b = LaserLogSource(
        LaserLogOptions(log=path, robots=2, index=1, every=100, realtime=0), SourceContext(robot="b")
    )
    assert a.start_pose() == pytest.approx(poses[0], abs=1e-5)
    assert b.start_pose() == pytest.approx(poses[16], abs=1e-5)  # slices 0..23 and 16..39 of 40
    ma, mb = _collect(a), _collect(b)
    assert a.stats()["scans"] == 24 and b.stats()["scans"] == 24
    assert ma[-1].stamp == pytest.approx(100.0 + 0.1 * 23) and mb[-1].stamp == pytest.approx(100.0 + 0.1 * 39)


def test_missing_log_is_one_source_error(tmp_path: Path) -> None:
    src = LaserLogSource(LaserLogOptions(log=tmp_path / "none.log", realtime=0), SourceContext(robot="r"))
    with pytest.raises(SourceError, match="no such log file"):
        _collect(src)


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("hello world\n", r"text\.log: not a CARMEN log \(no FLASER or ROBOTLASER1 line\)$"),
        (
            "FLASER 3 1.0 x\nFLASER 2 nan\n",
            r"text\.log: no valid scan \(2 scan lines in the log, none usable there\)$",
        ),
    ],
)
def test_a_log_without_a_scan_is_one_error_at_check_and_at_start(
    tmp_path: Path, text: str, says: str
) -> None:
    # Before, check-config said ok and the source logged a warning, then "finished": the daemon ran
    # with no map of its own, and `mapd demo --log` on a config file exited 0 with an empty report.
    (tmp_path / "text.log").write_text(text)
    opts = LaserLogOptions(log=tmp_path / "text.log", realtime=0)
    with pytest.raises(ValueError, match="^log: .*" + says):
        opts.check_with_config(MapdConfig.model_validate({"robot": {"name": "r"}}))
    with pytest.raises(SourceError, match=says):
        _collect(LaserLogSource(opts, SourceContext(robot="r")))


def test_options_are_validated() -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        LaserLogOptions(robots=2, index=2)
    with pytest.raises(ValidationError):
        LaserLogOptions(every=None, every_s=None)
    with pytest.raises(ValidationError):
        LaserLogOptions(realtme=1.0)  # type: ignore[call-arg]


def test_intel_final_map_agrees_with_the_reference(intel_log: Path, data_dir: Path) -> None:
    ref = load_map(data_dir / "maps" / "radish_derived" / "intel" / "intel.yaml")
    src = LaserLogSource(LaserLogOptions(log=intel_log, every=300, realtime=0), SourceContext(robot="intel"))
    maps = _collect(src)
    assert src.stats()["scans"] == 910 and src.stats()["skipped_lines"] == 0
    pose = src.start_pose()
    assert pose is not None and pose == first_pose(intel_log)
    # The map is in the robot's frame (its first pose); align it with the reference's world frame.
    aligned = resample(maps[-1], pose, ref)
    f1 = occupied_f1(ref.data, aligned.data, tolerance=1)
    assert f1 >= 0.85, f"occupied F1 {f1:.3f} against radish_derived/intel"
    # Without the alignment it does not agree: the robot's frame really is not the world frame.
    unaligned = resample(maps[-1], Pose2D(), ref)
    assert occupied_f1(ref.data, unaligned.data, tolerance=1) < 0.5


def test_reading_and_ray_casting_run_off_the_event_loop(
    box_log: BoxLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Parsing the log, ray-casting each scan and copying snapshots are CPU work: never on the
    loop's thread, where they would delay every timer and link of the daemon."""
    import threading

    from mapd.mapping import carmen
    from mapd.mapping.mapper import Mapper

    threads: dict[str, set[int]] = {"parse": set(), "integrate": set(), "snapshot": set()}
    parse, integrate, snapshot = carmen.parse_flaser, Mapper.integrate, Mapper.snapshot

    def spy(name: str, fn: Callable[..., object]) -> Callable[..., object]:
        def wrapped(*a: object, **k: object) -> object:
            threads[name].add(threading.get_ident())
            return fn(*a, **k)

        return wrapped

    monkeypatch.setattr(carmen, "parse_flaser", spy("parse", parse))
    monkeypatch.setattr(Mapper, "integrate", spy("integrate", integrate))
    monkeypatch.setattr(Mapper, "snapshot", spy("snapshot", snapshot))
    path, _ = box_log(scans=12)
    src = LaserLogSource(LaserLogOptions(log=path, every=4, realtime=0), SourceContext(robot="r1"))

    async def go() -> tuple[int, list[OccupancyGrid]]:
        return threading.get_ident(), [g async for g in src.maps()]

    loop_thread, maps = asyncio.run(go())
    assert len(maps) == 3
    for name, seen in threads.items():
        assert seen and loop_thread not in seen, name
