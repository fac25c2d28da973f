"""The daemon's event inbox: latest update per peer wins, control events are never crowded out."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from types import SimpleNamespace

from mapd.daemon.events import MAX_RELAYED, EventQueue
from mapd.daemon.versions import incarnation_at, make
from mapd.envelope import unpack
from mapd.identity import Identity, read_identity
from tests.daemon.test_hostile_peer import envelope
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


def _map(robot: str, version: int, identity: Identity | None = None) -> bytes:
    """A small packed map envelope of ``robot`` (signed when ``identity`` is given)."""
    env = envelope(version, fleet="default", robot=robot)
    return (env.signed(identity) if identity is not None else env).pack()


def test_maps_of_other_robots_a_peer_relays_never_replace_its_own() -> None:
    # Audit F3: the inbox kept one waiting map per (transport, link sender), and a UWB relayer's
    # link carries its own maps and other robots' (relayed): robot0's map relayed by robot1
    # silently dropped robot1's own waiting map, which the radio had already acknowledged.
    box = EventQueue()
    own, relayed, other = _map("robot1", 7), _map("robot0", 12), _map("robot3", 4)
    box.put(Received("uwb", "robot1", own))  # the daemon is busy; robot1's own map waits
    box.put(Received("uwb", "robot1", relayed))  # then robot1 forwards robot0's map
    box.put(Received("uwb", "robot1", other))  # and robot3's
    newer = _map("robot1", 8)
    box.put(Received("uwb", "robot1", newer))  # latest wins still holds per robot: v8 replaces v7
    got = []
    while (e := box.get_nowait()) is not None:
        got.append(e)
    assert [unpack(e.data).robot for e in got] == ["robot0", "robot3", "robot1"]
    assert all(e.peer == "robot1" for e in got)  # the link sender is still who handed it over
    assert got[-1].data == newer
    assert (box.counters.superseded, box.counters.dropped) == (1, 0)


def test_robots_a_peer_invents_cannot_grow_the_inbox_or_crowd_out_real_maps() -> None:
    box = EventQueue(max_events=4, max_peers=64)
    box.put(Received("uwb", "robot1", _map("robot1", 1)))
    for i in range(200):  # a key holder forging link frames names robots by the hundred
        box.put(Received("uwb", "robot1", _map(f"ghost{i}", 1)))
    box.put(Received("uwb", "robot2", _map("robot2", 1)))  # another peer's own map still gets in
    assert len(box) == 2 + MAX_RELAYED
    assert box.counters.dropped == 200 - MAX_RELAYED
    robots = []
    while (e := box.get_nowait()) is not None:
        robots.append(unpack(e.data).robot)
    assert robots[0] == "robot1" and robots[-1] == "robot2"
    # taken, the slots are free again for the next relays
    box.put(Received("uwb", "robot1", _map("robot0", 2)))
    assert len(box) == 1


def test_bytes_that_are_no_envelope_wait_in_their_senders_slot() -> None:
    box = EventQueue()
    head = _map("robot0", 3)[:20]  # cut short before its robot
    for data in (b"\xc1 not msgpack", b"\x81\xa1r\x05", head, b"\xdf\xff\xff\xff\xff", _map("robot1", 2)):
        box.put(Received("uwb", "robot1", data))
    assert len(box) == 1 and box.counters.superseded == 4


def test_a_relayed_map_and_the_relayers_own_map_both_reach_the_daemon(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    async def main() -> None:
        d, _ = dk.virtual_daemon(tmp_path, "robot2", dk.channel())
        keys = tmp_path / "keys"
        version = make(incarnation_at(time.time()), 1)
        r0, r1 = read_identity(keys / "robot0.key", "robot0"), read_identity(keys / "robot1.key", "robot1")
        # Both wait in the inbox before the daemon takes any (it was busy): robot1's own map, then
        # robot0's, relayed over robot1's radio.
        d.events.put(Received("uwb", "robot1", _map("robot1", version, r1)))
        d.events.put(Received("uwb", "robot1", _map("robot0", version, r0)))
        task = asyncio.create_task(d.run())
        try:
            await dk.wait_for(lambda: {"robot0", "robot1"} <= set(d.receiver.maps), 10, "both maps held")
        finally:
            d.request_stop()
            await task
        assert d.events.counters.superseded == 0

    asyncio.run(main())
