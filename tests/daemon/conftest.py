"""Daemon tests in one process: a source the test feeds, configs, and the virtual transport."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mapd import config as configmod
from mapd.daemon.server import Daemon
from mapd.grid import OccupancyGrid
from mapd.identity import Identity, read_identity
from mapd.sources.base import MapSource, SourceContext

_channels = itertools.count()
#: The robots of a test fleet: each gets its own key; every config lists them all.
FLEET = ("robot0", "robot1", "robot2")


class QueueSource(MapSource):
    """A map source whose maps the test puts in, one at a time."""

    name = "queue"

    def __init__(self, robot: str) -> None:
        super().__init__(None, SourceContext(robot=robot))
        self.queue: asyncio.Queue[OccupancyGrid] = asyncio.Queue()

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        while True:
            yield await self.queue.get()


def fleet_keys(tmp_path: Path, robots: tuple[str, ...] = FLEET) -> str:
    """Make each robot's key under ``tmp_path/keys`` (once) and return the ``[fleet]`` tables."""
    keys = tmp_path / "keys"
    keys.mkdir(exist_ok=True)
    lines = ["[fleet]", "[fleet.roster]"]
    for robot in robots:
        path = keys / f"{robot}.key"
        if not path.exists():
            Identity.generate(robot).write(path)
        lines.append(f'{robot} = "{read_identity(path, robot).public_text}"')
    return "\n".join(lines) + "\n"


def write_config(
    tmp_path: Path, robot: str, *, codec: str = "lossless", extra: str = "", **tables: str
) -> Path:
    """A signed config for ``robot`` with its state under ``tmp_path/robot``; ``tables``: name -> TOML body."""
    root = tmp_path / robot
    root.mkdir(parents=True, exist_ok=True)
    body = (
        f'[robot]\nname = "{robot}"\nkey_file = "{tmp_path / "keys" / f"{robot}.key"}"\n'
        f'[source]\nuse = "sim"\n[codec]\nuse = "{codec}"\nkeyframe_every = 50\n'
        f'[state]\ndir = "{root / "state"}"\nruntime_dir = "{root / "run"}"\n{extra}'
    )
    body += fleet_keys(tmp_path)
    for name, table in tables.items():
        body += f"[{name}]\n{table}\n"
    path = root / "config.toml"
    path.write_text(body)
    return path


def virtual_daemon(tmp_path: Path, robot: str, channel: str) -> tuple[Daemon, QueueSource]:
    """A daemon on the ``virtual`` transport's ``channel``, fed by a :class:`QueueSource`."""
    cfg = configmod.load(
        write_config(
            tmp_path,
            robot,
            extra='[transports]\nuse = ["virtual"]\n',
            **{"transports.virtual": f'channel = "{channel}"'},
        )
    )
    source = QueueSource(robot)
    return Daemon(cfg, source=source), source


def growing_map(version: int) -> OccupancyGrid:
    """A cluttered room whose explored part grows a little with each version (so deltas pay)."""
    rng = np.random.default_rng(0)
    room = np.where(rng.random((200, 200)) < 0.04, 100, 0).astype(np.int8)
    data = np.full((200, 200), -1, np.int8)
    data[:, : 100 + 5 * version] = room[:, : 100 + 5 * version]
    return OccupancyGrid(data, 0.05, robot="robot0", version=version)


async def wait_for(cond: Callable[[], bool], timeout: float = 10.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"{what} not met within {timeout} s")
        await asyncio.sleep(0.01)


def run_until(*daemons: Daemon, until: Callable[[], bool], timeout: float = 20.0) -> None:
    """Run ``daemons`` together until ``until()`` holds (AssertionError after ``timeout``), then
    stop them all and wait for them."""

    async def main() -> None:
        tasks = [asyncio.create_task(d.run()) for d in daemons]
        try:
            await wait_for(until, timeout)
        finally:
            for d in daemons:
                d.request_stop()
            await asyncio.gather(*tasks)

    asyncio.run(main())


@contextlib.contextmanager
def mapd_run(
    config: Path, log: Path, *, cwd: Path | None = None, env: dict[str, str] | None = None
) -> Iterator[subprocess.Popen[bytes]]:
    """``mapd run --config config`` as a process, its output in ``log``; killed on the way out if
    the test did not stop it."""
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mapd", "run", "--config", str(config)],
            cwd=cwd,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


class AckingLink:
    """What the daemon's receiving half asks of a map's transport, keeping the acks it is given."""

    def __init__(self, name: str = "virtual") -> None:
        self.name = name
        self.acks: list[tuple[str, int]] = []

    def ack(self, robot: str, version: int) -> None:
        self.acks.append((robot, version))

    def relayed(self, env: object) -> None:
        pass

    def held(self, env: object, data: bytes) -> None:
        pass

    # What a reload and the status ask of every link (one in the daemon's list of transports).
    def forget(self, robot: str) -> None:
        pass

    def peers(self) -> list[str]:
        return []

    def stats(self) -> dict[str, object]:
        return {}


@pytest.fixture
def dk() -> SimpleNamespace:
    """The helpers above, for test modules (importlib mode keeps conftest out of reach of imports)."""
    return SimpleNamespace(
        QueueSource=QueueSource,
        AckingLink=AckingLink,
        write_config=write_config,
        fleet_keys=fleet_keys,
        virtual_daemon=virtual_daemon,
        growing_map=growing_map,
        wait_for=wait_for,
        run_until=run_until,
        mapd_run=mapd_run,
        channel=lambda: f"test-{next(_channels)}",
    )
