"""Helpers for the zenoh transport tests: free ports, envelopes, and a robot harness.

Every session listens or connects on ``tcp/127.0.0.1:<free port>`` with multicast scouting off,
so tests never reach past loopback or see each other.
"""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.envelope import Envelope
from mapd.grid import Pose2D
from transports.base import Received, TransportContext, TransportEvent
from transports.zenoh.link import ZenohTransport

FLEET = "testfleet"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def envelope(
    robot: str, version: int, base: int = 0, payload: bytes = b"cells", key: bytes | None = None
) -> Envelope:
    env = Envelope(
        fleet=FLEET,
        robot=robot,
        version=version,
        base_version=base,
        codec="raw",
        width=4,
        height=3,
        resolution=0.05,
        origin=Pose2D(0.0, 0.0, 0.0),
        payload=payload,
        seq=version,
    )
    return env.signed(key) if key is not None else env


class Bot:
    """One robot's zenoh transport in this process, recording what it emits."""

    def __init__(
        self,
        robot: str,
        *,
        listen: list[str] | None = None,
        connect: list[str] | None = None,
        key: bytes | None = None,
        max_message_bytes: int = 4 << 20,
        **options: Any,
    ) -> None:
        self.events: list[TransportEvent] = []
        self.keyframe: Envelope | None = None
        opts = ZenohTransport.Options(
            multicast_scouting=False, listen=listen or [], connect=connect or [], **options
        )
        self.ctx = TransportContext(
            robot=robot,
            fleet=FLEET,
            key=key,
            max_message_bytes=max_message_bytes,
            emit=self.events.append,
            latest_keyframe=lambda: self.keyframe,
        )
        self.t = ZenohTransport(opts, self.ctx)

    async def start(self) -> Bot:
        await self.t.start()
        return self

    def offer(self, env: Envelope) -> None:
        if env.is_keyframe:
            self.keyframe = env  # what the daemon would keep for late joiners
        self.t.offer(env)

    def of(self, kind: type) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]

    def received(self, peer: str | None = None) -> list[tuple[str, int, int]]:
        """(peer, version, base) of every Received, unpacked for reading."""
        from mapd.envelope import unpack

        out = []
        for e in self.of(Received):
            env = unpack(e.data)
            if peer is None or e.peer == peer:
                out.append((e.peer, env.version, env.base_version))
        return out

    async def wait(self, cond: Callable[[], bool], timeout: float = 5.0) -> None:
        """Wait until ``cond()`` holds; fail the test (showing the events) after ``timeout``."""
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                raise AssertionError(
                    f"{self.ctx.robot}: condition not met in {timeout} s; events: {self.events}; {self.t.stats()}"
                )
            await asyncio.sleep(0.01)


async def meet(*bots: Bot, timeout: float = 5.0) -> None:
    """Wait until every bot sees every other one's token. A token is declared after the
    subscribers, so a robot that sees a peer's token also knows where to send it updates."""
    for bot in bots:
        others = sorted(o.ctx.robot for o in bots if o is not bot)
        await bot.wait(lambda bot=bot, others=others: all(r in bot.t.peers() for r in others), timeout)


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


@pytest.fixture
def zk() -> SimpleNamespace:
    """The helpers above, for test modules (importlib mode keeps conftest out of reach of imports)."""
    return SimpleNamespace(
        Bot=Bot, meet=meet, envelope=envelope, free_port=free_port, endpoint=endpoint, FLEET=FLEET
    )
