"""Shared fixtures. Real data is read in place from ../shared/data (override with MAPD_DATA)."""

from __future__ import annotations

import gzip
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.data import data_dir as _data_dir
from mapd.data import shared_maps as _shared_maps
from mapd.grid import OCCUPIED, OccupancyGrid, Pose2D
from mapd.mapping.lidar import Lidar
from mapd.mapping.synthetic import room_grid as make_room_grid

NO_DATA = "shared data folder not found: set MAPD_DATA or place ../shared/data beside the checkout"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared data folder; tests that use it skip with a clear reason when it is absent."""
    d = _data_dir()
    if d is None:
        pytest.skip(NO_DATA)
    return d


@pytest.fixture(scope="session")
def shared_maps(data_dir: Path) -> list[Path]:
    maps = _shared_maps(data_dir)
    if not maps:
        pytest.skip(f"no map_server YAML under {data_dir}/maps")
    return maps


@pytest.fixture(scope="session")
def intel_log(data_dir: Path) -> Path:
    p = data_dir / "logs" / "intel-corrected.log.gz"
    if not p.exists():
        pytest.skip(f"{p} not found")
    return p


# make_room_grid (mapd.mapping.synthetic.room_grid) keeps its name here: the lossless corpus's
# make_corpus.py imports it from this file.
@pytest.fixture
def room_grid() -> OccupancyGrid:
    return make_room_grid()


# Small CARMEN logs drawn from a known world (mapping and source tests).


def make_box_world(size_m: float = 8.0, resolution: float = 0.05) -> OccupancyGrid:
    """A square room with 0.15 m walls and a pillar, in a frame whose origin is the room's corner."""
    n = round(size_m / resolution)
    d = np.zeros((n, n), dtype=np.int8)
    t = 3
    d[:t, :] = d[-t:, :] = d[:, :t] = d[:, -t:] = OCCUPIED
    c = n // 2
    d[c - 8 : c + 8, c + 20 : c + 36] = OCCUPIED
    return OccupancyGrid(d, resolution, Pose2D(0.0, 0.0, 0.0), frame_id="world")


def flaser_line(ranges: np.ndarray, pose: Pose2D, stamp: float) -> str:
    rs = " ".join(f"{r:.3f}" for r in ranges)
    p = f"{pose.x:.6f} {pose.y:.6f} {pose.yaw:.6f}"
    return f"FLASER {len(ranges)} {rs} {p} {p} {stamp:.6f} testhost {stamp:.6f}\n"


def write_box_log(
    path: Path, scans: int = 30, *, extra: list[str] | None = None, dt: float = 0.1
) -> list[Pose2D]:
    """A CARMEN log of a robot driving a circle in :func:`box_world`; returns the laser poses."""
    world = make_box_world()
    # CARMEN FLASER: 180 beams over 180 degrees starting at -90 degrees.
    lidar = Lidar(world.data >= 65, world.resolution, world.origin, beams=180, fov_deg=180.0, max_range=30.0)
    lidar.angles = -math.pi / 2 + math.pi / 180 * np.arange(180)
    poses = []
    lines = ["# synthetic CARMEN log\n", "PARAM robot_front_laser_max 81.9 nohost 0\n"]
    for i in range(scans):
        a = 2 * math.pi * i / scans
        pose = Pose2D(4.0 + 1.5 * math.cos(a), 4.0 + 1.5 * math.sin(a), a + math.pi / 2)
        poses.append(pose)
        ranges = lidar.scan(pose)
        ranges[~np.isfinite(ranges)] = 81.83
        lines.append(flaser_line(ranges, pose, 100.0 + dt * i))
        lines.append(f"ODOM 0 0 0 0 0 0 {100.0 + dt * i:.6f} testhost {100.0 + dt * i:.6f}\n")
    if extra:
        # Bad lines go in the middle, so the replay must carry on past them.
        mid = len(lines) // 2
        lines[mid:mid] = extra
    text = "".join(lines).encode()
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(text))
    else:
        path.write_bytes(text)
    return poses


@pytest.fixture
def box_log(tmp_path: Path) -> Callable[..., tuple[Path, list[Pose2D]]]:
    def make(name: str = "box.log.gz", **kw: object) -> tuple[Path, list[Pose2D]]:
        p = tmp_path / name
        poses = write_box_log(p, **kw)  # type: ignore[arg-type]
        return p, poses

    return make


@pytest.fixture
def box_world() -> OccupancyGrid:
    return make_box_world()


# Fleets of real daemons (mapd.demo.fleet.Fleet): waiting on their status, reading what they hold.


def wait_for_fleet(pred: Any, timeout: float, fleet: Any) -> dict[str, dict[str, Any]]:
    """Poll every daemon's status until ``pred(snapshots)`` holds; fail with the last ones after ``timeout``."""
    deadline = time.monotonic() + timeout
    snaps: dict[str, dict[str, Any]] = {}
    while time.monotonic() < deadline:
        fleet.check_alive()
        snaps = fleet.status()
        if pred(snaps):
            return snaps
        time.sleep(1.0)
    raise AssertionError(f"condition not met in {timeout} s: {json.dumps(snaps)[:3000]}")


def demo_fleet(
    out: Path,
    robots: int = 3,
    *,
    transport: str = "zenoh",
    duration: float = 60.0,
    router: bool = False,
    edit: dict[str, Callable[[dict[str, Any]], None]] | None = None,
    out_of_range: list[str] | None = None,
) -> Any:
    """A prepared demo fleet (:class:`mapd.demo.fleet.Fleet`) of ``robots`` daemons on
    ``transport``, lossless maps of the sim building (with ``router``: zenoh clients of one router
    process, which runs); the daemons not started yet. ``edit``: robot -> a change to its config
    (the parsed TOML, written back), for fleets whose configs disagree. ``out_of_range``: pairs
    ``"0-2"`` of robots the emulated uwb radio keeps apart (as ``mapd demo --out-of-range``)."""
    import argparse
    import tomllib

    from mapd.demo.fleet import Fleet, write_config

    fleet = Fleet(
        argparse.Namespace(
            robots=robots, transport=transport, codec="lossless", log=None, seed=7, out=out,
            duration=duration, router=router, out_of_range=out_of_range or [],
        )
    )  # fmt: skip
    fleet.prepare()
    for robot, change in (edit or {}).items():
        path = fleet.run_dir / robot / "config.toml"
        cfg = tomllib.loads(path.read_text())
        change(cfg)
        write_config(path, cfg)
    return fleet


def kill9(fleet: Any, name: str) -> None:
    """``kill -9`` daemon ``name`` of a started ``fleet`` (a crash: nothing saved at exit)."""
    import os
    import signal

    os.kill(fleet.procs[name].pid, signal.SIGKILL)
    fleet.procs[name].wait(10)


def restart(fleet: Any, name: str, log: str = "daemon2.log") -> None:
    """Start daemon ``name`` of ``fleet`` again, on its config and state directory, logging to
    ``log`` in its folder."""
    import subprocess
    import sys

    d = fleet.run_dir / name
    fleet.procs[name] = subprocess.Popen(
        [sys.executable, "-m", "mapd", "run", "--config", str(d / "config.toml")],
        stdout=open(d / log, "wb"),  # noqa: SIM115 - lives as long as the process
        stderr=subprocess.STDOUT,
    )


def router_fleet(out: Path, robots: int = 3) -> Any:
    """:func:`demo_fleet` of zenoh clients of one router process."""
    return demo_fleet(out, robots, router=True)


def status_text(sock: Path) -> str:
    """What ``mapd status --socket SOCK`` prints, as a user runs it."""
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-m", "mapd", "status", "--socket", str(sock)],
        capture_output=True,
        text=True,
        timeout=30,
    ).stdout


def held_version(snaps: dict[str, dict[str, Any]], who: str, of: str) -> int:
    """The version of ``of``'s map that ``who`` holds (0: none), incarnation and all."""
    return int(snaps.get(who, {}).get("peers", {}).get(of, {}).get("version", 0))


def held_number(snaps: dict[str, dict[str, Any]], who: str, of: str) -> int:
    """Which map of ``of``'s current incarnation ``who`` holds: how many it has made (see versions.py)."""
    from mapd.daemon.versions import split

    return split(held_version(snaps, who, of))[1]


def wait_zenoh_link(session: Any, timeout: float = 20.0) -> None:
    """Wait until a zenoh ``session`` is linked to another; the subscriptions declared so far travel
    with the link, and reach the other side a moment after it (a fixed sleep assumed both)."""
    deadline = time.monotonic() + timeout
    while not (list(session.info.peers_zid()) or list(session.info.routers_zid())):
        if time.monotonic() > deadline:
            raise AssertionError(f"no zenoh link within {timeout} s")
        time.sleep(0.05)
    time.sleep(0.5)


@pytest.fixture
def zenoh_linked() -> Callable[..., None]:
    """:func:`wait_zenoh_link`, for test modules."""
    return wait_zenoh_link


@pytest.fixture
def fk() -> SimpleNamespace:
    """The fleet helpers above, for test modules (importlib mode keeps conftest out of reach of imports)."""
    return SimpleNamespace(
        wait_for=wait_for_fleet,
        held=held_number,
        version=held_version,
        router_fleet=router_fleet,
        demo_fleet=demo_fleet,
        status_text=status_text,
        kill9=kill9,
        restart=restart,
    )
