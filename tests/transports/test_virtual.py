"""The in-process ``virtual`` transport: what one member offers, acks or asks reaches the others as events."""

from __future__ import annotations

import asyncio
import threading

import pytest

from mapd import plugins
from mapd.envelope import Envelope, unpack
from mapd.errors import TransportError
from mapd.grid import Pose2D
from transports.base import (
    Delivered,
    KeyframeNeeded,
    PeerDown,
    PeerUp,
    Received,
    TransportContext,
    TransportEvent,
)
from transports.virtual import VirtualOptions, VirtualTransport


def env(robot: str, version: int) -> Envelope:
    return Envelope(
        fleet="f", robot=robot, version=version, base_version=0, codec="raw", width=2, height=2,
        resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"\x00" * 4,
    )  # fmt: skip


class Member:
    def __init__(self, robot: str, channel: str) -> None:
        self.events: list[TransportEvent] = []
        self.keyframe_threads: list[str] = []

        def latest() -> Envelope:
            self.keyframe_threads.append(threading.current_thread().name)
            return env(robot, 9)

        ctx = TransportContext(
            robot=robot, fleet="f", max_message_bytes=1 << 16, emit=self.events.append,
            latest_keyframe=latest,
        )  # fmt: skip
        self.t = VirtualTransport(VirtualOptions(channel=channel), ctx)

    def of(self, kind: type) -> list[TransportEvent]:
        return [e for e in self.events if isinstance(e, kind)]


def test_registered_as_a_transport_plugin() -> None:
    assert plugins.load("transport", "virtual") is VirtualTransport


def test_members_see_each_other_and_exchange_maps_acks_and_keyframe_requests() -> None:
    async def main() -> None:
        a, b, c = Member("a", "t1"), Member("b", "t1"), Member("c", "other")
        for m in (a, b, c):
            await m.t.start()
        await asyncio.sleep(0)
        assert a.t.peers() == ["b"] and b.t.peers() == ["a"] and c.t.peers() == []
        assert a.of(PeerUp) == [PeerUp("virtual", "b")] and b.of(PeerUp) == [PeerUp("virtual", "a")]
        a.t.offer(env("a", 1))
        assert b.of(Received) == []  # delivered after the caller returns, as a real link would
        await asyncio.sleep(0)
        (got,) = b.of(Received)
        assert isinstance(got, Received) and got.peer == "a" and unpack(got.data).version == 1
        assert c.of(Received) == []  # another channel hears nothing
        b.t.ack("a", 1)
        await b.t.request_keyframe("a")
        await asyncio.sleep(0)
        assert a.of(Delivered) == [Delivered("virtual", "b", "a", 1)]
        assert a.of(KeyframeNeeded) == [KeyframeNeeded("virtual", "b", "a")]
        kf = await b.t.query_keyframe("a")
        assert kf is not None and kf.version == 9
        assert a.keyframe_threads and a.keyframe_threads[0] != threading.current_thread().name
        assert a.t.stats()["offers"] == 1 and b.t.stats()["acks_out"] == 1
        await b.t.close()
        await asyncio.sleep(0)
        assert a.of(PeerDown) == [PeerDown("virtual", "b")] and a.t.peers() == []
        for m in (a, c):
            await m.t.close()

    asyncio.run(main())


def test_one_robot_joins_a_channel_once() -> None:
    async def main() -> None:
        a, again = Member("a", "t2"), Member("a", "t2")
        await a.t.start()
        with pytest.raises(TransportError, match="already on channel"):
            await again.t.start()
        await a.t.close()

    asyncio.run(main())
