"""The daemon's event inbox: latest update per peer wins, control events are never crowded out."""

from __future__ import annotations

import asyncio

from mapd.daemon.events import EventQueue
from transports.base import Delivered, PeerUp, Received


def test_newest_update_per_peer_wins_and_control_goes_first() -> None:
    box = EventQueue(max_events=4, max_peers=2)
    for v in range(100):
        box.put(Received("zenoh", "a", bytes([v])))
    box.put(Received("zenoh", "b", b"b1"))
    box.put(Delivered("zenoh", "a", "me", 3))
    box.put(Received("uwb", "a", b"other link"))  # a third peer key: over max_peers, dropped
    assert len(box) == 3
    assert box.get_nowait() == Delivered("zenoh", "a", "me", 3)
    assert box.get_nowait() == Received("zenoh", "a", bytes([99]))
    assert box.get_nowait() == Received("zenoh", "b", b"b1")
    assert box.get_nowait() is None
    assert (box.counters.superseded, box.counters.dropped) == (99, 1)


def test_control_events_are_bounded() -> None:
    box = EventQueue(max_events=3)
    for i in range(5):
        box.put(PeerUp("zenoh", f"p{i}"))
    assert [box.get_nowait() for _ in range(4)] == [PeerUp("zenoh", f"p{i}") for i in range(3)] + [None]
    assert box.counters.dropped == 2


def test_get_waits_for_the_next_event() -> None:
    async def main() -> list[object]:
        box = EventQueue()
        got: list[object] = []

        async def reader() -> None:
            got.append(await box.get())
            got.append(await box.get())

        task = asyncio.create_task(reader())
        await asyncio.sleep(0.01)
        assert not got
        box.put(Received("zenoh", "a", b"1"))
        box.put(PeerUp("zenoh", "a"))
        await asyncio.wait_for(task, 1.0)
        return got

    assert asyncio.run(main()) == [PeerUp("zenoh", "a"), Received("zenoh", "a", b"1")]
