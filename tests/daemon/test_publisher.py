"""The daemon's publisher: a version is coded only when a transport can take it, against the base acked by then."""

from __future__ import annotations

import asyncio
import csv
from pathlib import Path
from typing import Any

import numpy as np

from mapd import config as configmod
from mapd.codec import read_header
from mapd.daemon.server import Daemon
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid
from transports.base import Delivered, Transport


class SlowLink(Transport):
    """A transport that holds what it was offered until the test says the peer acked it."""

    name = "slow"

    def __init__(self) -> None:
        self.offers: list[Envelope] = []

    async def start(self) -> None:
        pass

    async def close(self) -> None:
        pass

    def offer(self, envelope: Envelope) -> None:
        self.offers.append(envelope)

    def peers(self) -> list[str]:
        return ["robot1"]


def growing_map(version: int) -> OccupancyGrid:
    """A cluttered room whose explored part grows a little with each version (so deltas pay)."""
    rng = np.random.default_rng(0)
    room = np.where(rng.random((200, 200)) < 0.04, 100, 0).astype(np.int8)
    data = np.full((200, 200), -1, np.int8)
    data[:, : 100 + 5 * version] = room[:, : 100 + 5 * version]
    return OccupancyGrid(data, 0.05, robot="robot0", version=version)


def daemon(tmp_path: Path) -> Daemon:
    cfg_file = tmp_path / "c.toml"
    cfg_file.write_text(
        '[robot]\nname = "robot0"\n[source]\nuse = "sim"\n[codec]\nuse = "lossless"\nkeyframe_every = 50\n'
        f'[state]\ndir = "{tmp_path / "state"}"\nruntime_dir = "{tmp_path / "run"}"\n'
    )
    d = Daemon(configmod.load(cfg_file))
    d.store.open()
    return d


def coded(d: Daemon) -> list[dict[str, Any]]:
    with open(d.cfg.state.dir / "updates.csv", newline="") as fh:
        return list(csv.DictReader(fh))


async def settle() -> None:
    for _ in range(50):  # let the publisher task and its worker thread run
        await asyncio.sleep(0.01)


def test_busy_link_codes_only_the_newest_version_against_the_base_acked_by_then(tmp_path: Path) -> None:
    async def main() -> None:
        d = daemon(tmp_path)
        link = SlowLink()
        d.transports.append(link)
        task = asyncio.create_task(d._publisher())
        try:
            d._pending = growing_map(1)
            d._publish.set()
            await settle()
            assert [e.version for e in link.offers] == [1] and link.offers[0].is_keyframe
            for v in (2, 3, 4):  # the link is still busy with v1: nothing is coded or offered
                d._pending = growing_map(v)
                d._publish.set()
                await settle()
            assert len(link.offers) == 1
            assert [int(r["version"]) for r in coded(d)] == [1]
            # the peer acks v1: the newest version goes out, as a delta against v1
            await d._handle(Delivered("slow", "robot1", "robot0", 1))
            await settle()
            assert [e.version for e in link.offers] == [1, 4]
            head = read_header(link.offers[1].payload)
            assert head.delta and head.base_version == 1
            assert [(int(r["version"]), r["kind"]) for r in coded(d)] == [(1, "keyframe"), (4, "delta")]
            # acked again, and nothing newer: nothing more is coded
            await d._handle(Delivered("slow", "robot1", "robot0", 4))
            await settle()
            assert len(link.offers) == 2
        finally:
            task.cancel()

    asyncio.run(main())
