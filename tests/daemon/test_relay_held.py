"""What the receiving half hands a relaying link (``Transport.held``): every map it accepts, and a
whole map of the version it already holds, which came as a delta.

A uwb relay asks a robot for a whole map on a neighbour's behalf when the delta it holds is on a
base that neighbour lacks; the robot answers with a keyframe of the version the relay holds. The
receiving half dropped it as a duplicate before the link saw it, so the relay asked again every
retry, in vain, and the neighbour never got the robot's last map (``mapd bench swarm``, the
building at 100 kb/s: 10 robots still lacked it 300 s after it was made). The relay core's side is
in ``tests/transports/uwb/test_uwb_relay_forwarding.py``.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from mapd.codec.api import encode
from mapd.daemon.versions import incarnation_at, make
from mapd.envelope import Envelope, unpack
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import read_identity
from transports.base import Received


def _map(tmp_path: Path, n: int, base: int) -> tuple[Received, int]:
    """robot1's version ``n`` (on ``base``, 0: whole), signed with its key, as a link hands it in."""
    ident = read_identity(tmp_path / "keys" / "robot1.key", "robot1")
    grid = OccupancyGrid(np.zeros((20, 30), np.int8), 0.05)
    inc = incarnation_at(time.time() - 60)
    env = Envelope(
        fleet="default", robot="robot1", version=make(inc, n), base_version=make(inc, base) if base else 0,
        codec="raw", width=30, height=20, resolution=0.05, origin=Pose2D(0, 0, 0),
        payload=encode(grid, "raw"),
    ).signed(ident)  # fmt: skip
    return Received("virtual", "robot2", env.pack()), env.version


def test_a_whole_map_of_the_version_held_goes_to_the_relaying_link(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    class HeldLink(dk.AckingLink):  # type: ignore[name-defined,misc]
        """A link that keeps what the daemon hands it to relay: (robot, version, base)."""

        def __init__(self) -> None:
            super().__init__()
            self.held_maps: list[tuple[str, int, int]] = []

        def held(self, env: Envelope, data: bytes) -> None:
            assert unpack(data) == env  # the bytes as received, still signed by their robot
            self.held_maps.append((env.robot, env.version, env.base_version))

    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    d.store.open()
    link = HeldLink()
    d.transports.append(link)
    whole, v4 = _map(tmp_path, 4, 0)
    delta, _ = _map(tmp_path, 4, 3)
    older, v3 = _map(tmp_path, 3, 0)

    async def main() -> None:
        await d.inbound.handle(whole)
        assert link.held_maps == [("robot1", v4, 0)]  # accepted: held, as before
        await d.inbound.handle(whole)  # again: the whole map asked for on a neighbour's behalf
        assert link.held_maps == [("robot1", v4, 0)] * 2
        await d.inbound.handle(delta)  # a delta of the version held serves nobody more
        await d.inbound.handle(older)  # nor does an older version
        assert link.held_maps == [("robot1", v4, 0)] * 2, v3

    asyncio.run(main())
