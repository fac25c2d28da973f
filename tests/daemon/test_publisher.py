"""The daemon's publisher: a version is coded only when a transport can take it, against the base acked by then."""

from __future__ import annotations

import asyncio
import csv
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.codec import encode, read_header
from mapd.commands.status_text import render_status
from mapd.daemon import publisher
from mapd.daemon.server import Daemon
from mapd.daemon.versions import incarnation_at, make, split
from mapd.envelope import Envelope
from mapd.identity import read_identity
from transports.base import Arrived, Failed, OnAir, Received, TransportContext, TransportEvent
from transports.virtual import VirtualOptions, VirtualTransport


def num(version: int) -> int:
    """The number within the robot's incarnation (the daemon's versions start a new one)."""
    return split(version)[1]


def coded(d: Daemon) -> list[dict[str, Any]]:
    with open(d.cfg.state.dir / "updates.csv", newline="") as fh:
        return list(csv.DictReader(fh))


async def settle() -> None:
    for _ in range(50):  # let the publisher task and its worker thread run
        await asyncio.sleep(0.01)


@asynccontextmanager
async def one_peer(
    d: Daemon, channel: str, dk: SimpleNamespace, heard: list[TransportEvent]
) -> AsyncIterator[tuple[VirtualTransport, VirtualTransport]]:
    """Run daemon ``d`` on the virtual ``channel`` with one peer, robot1 (its events go to ``heard``),
    until both see each other; yields the daemon's link and the peer."""
    peer = VirtualTransport(
        VirtualOptions(channel=channel),
        TransportContext(robot="robot1", fleet="default", max_message_bytes=1 << 20, emit=heard.append),
    )
    task = asyncio.create_task(d.run())
    try:
        await dk.wait_for(lambda: bool(d.transports) and d.transports[0].peers() == [], what="daemon up")
        await peer.start()
        await dk.wait_for(lambda: d.transports[0].peers() == ["robot1"], what="peer seen")
        link = d.transports[0]
        assert isinstance(link, VirtualTransport)
        yield link, peer
    finally:
        d.request_stop()
        await task
        await peer.close()


def test_busy_link_codes_only_the_newest_version_against_the_base_acked_by_then(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    async def main() -> None:
        channel = dk.channel()
        d, source = dk.virtual_daemon(tmp_path, "robot0", channel)
        heard: list[TransportEvent] = []
        async with one_peer(d, channel, dk, heard) as (link, peer):
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: len(link.offers) == 1, what="v1 offered")
            assert [num(e.version) for e in link.offers] == [1] and link.offers[0].is_keyframe
            for v in (2, 3, 4):  # the link is still busy with v1: nothing is coded or offered
                await source.queue.put(dk.growing_map(v))
                await settle()
            assert len(link.offers) == 1
            assert [num(int(r["version"])) for r in coded(d)] == [1]
            assert len([e for e in heard if isinstance(e, Received)]) == 1  # the peer got v1 as bytes
            # the peer acks v1: the newest version goes out, as a delta against v1
            v1 = link.offers[0].version
            peer.ack("robot0", v1)
            await dk.wait_for(lambda: len(link.offers) == 2, what="v4 offered")
            assert [num(e.version) for e in link.offers] == [1, 4]
            head = read_header(link.offers[1].payload)
            assert head.delta and head.base_version == v1
            assert [(num(int(r["version"])), r["kind"]) for r in coded(d)] == [(1, "keyframe"), (4, "delta")]
            # acked again, and nothing newer: nothing more is coded
            v4 = link.offers[1].version
            peer.ack("robot0", v4)
            await settle()
            assert len(link.offers) == 2
            assert d.store.acked() == {"robot1": v4}

    asyncio.run(main())


def test_a_paced_link_keeps_its_offer_until_it_says_the_map_is_on_the_air(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    # P1 on a paced link (uwb): a map half sent is never replaced by a newer one, whatever the
    # timeout says; the link's OnAir event reaches the publisher through the daemon's inbox.
    async def main() -> None:
        channel = dk.channel()
        d, source = dk.virtual_daemon(tmp_path, "robot0", channel)
        assert d.publisher.paced == set()  # the virtual link does not pace: plain timeouts
        d.publisher.paced.add("virtual")
        d.publisher.inflight_timeout_s = 0.2
        monkeypatch.setattr(publisher, "PACED_HOLD", 1e6)  # only OnAir can free the link here
        async with one_peer(d, channel, dk, []) as (link, _):
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: len(link.offers) == 1, what="v1 offered")
            await source.queue.put(dk.growing_map(2))
            await asyncio.sleep(0.6)  # three timeouts: the peer never acks, yet v1 is not on the air
            assert len(link.offers) == 1
            # mapd status says so
            offer = d.snapshot()["offers"]["virtual"]
            assert offer["version"] == link.offers[0].version and offer["waiting"] == ["robot1"]
            assert offer["on_air"] is False and offer["age_s"] >= 0.5
            line = next(x for x in render_status(d.snapshot()).splitlines() if x.startswith("offer"))
            assert "virtual:" in line and "still going out; waiting for robot1" in line
            link.ctx.emit(OnAir("virtual", "robot0", link.offers[0].version))
            await dk.wait_for(lambda: len(link.offers) == 2, what="v2 offered once v1 is on the air")
            assert num(link.offers[1].version) == 2
            assert d.snapshot()["offers"]["virtual"]["on_air"] is False  # v2's turn now

    asyncio.run(main())


def test_a_paced_link_that_says_its_deadline_for_a_map_keeps_the_offer_that_long(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A map longer on the air than PACED_HOLD timeouts (uwb: over about 150 kB at 12.5 kb/s): the
    # link says how long it may take (uwb: its deadline, which grows with the map's size), and a
    # newer version does not supersede it half sent before then.
    async def main() -> None:
        channel = dk.channel()
        d, source = dk.virtual_daemon(tmp_path, "robot0", channel)
        d.publisher.paced.add("virtual")
        d.publisher.inflight_timeout_s = 0.1  # held PACED_HOLD timeouts: 0.4 s
        monkeypatch.setattr(publisher, "INFLIGHT_PER_PEER_S", 0.0)
        async with one_peer(d, channel, dk, []) as (link, _):
            monkeypatch.setattr(link, "offer_deadline_s", lambda env: 2.0, raising=False)
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: len(link.offers) == 1, what="v1 offered")
            t0 = time.monotonic()
            await source.queue.put(dk.growing_map(2))
            await asyncio.sleep(1.2)  # three times the hold: v1 is still going out
            assert len(link.offers) == 1
            await dk.wait_for(lambda: len(link.offers) == 2, what="v2 offered once v1's deadline passed")
            assert num(link.offers[1].version) == 2 and time.monotonic() - t0 >= 1.8

    asyncio.run(main())


def test_a_robot_that_comes_into_reach_is_offered_the_newest_map(tmp_path: Path, dk: SimpleNamespace) -> None:
    # P6 through the daemon's inbox: robot2 joins after robot1 acked v1 and nothing new is made. The
    # link says Arrived (uwb does when no map on its way reaches the robot), so v1 goes out again,
    # whole, and robot2 gets it; robot1, back too but holding v1, changes nothing.
    async def main() -> None:
        channel = dk.channel()
        d, source = dk.virtual_daemon(tmp_path, "robot0", channel)
        async with one_peer(d, channel, dk, []) as (link, peer):
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: len(link.offers) == 1, what="v1 offered")
            peer.ack("robot0", link.offers[0].version)
            await settle()
            heard: list[TransportEvent] = []
            late = VirtualTransport(
                VirtualOptions(channel=channel),
                TransportContext(
                    robot="robot2", fleet="default", max_message_bytes=1 << 20, emit=heard.append
                ),
            )
            await late.start()
            try:
                await dk.wait_for(lambda: "robot2" in link.peers(), what="robot2 seen")
                await settle()
                assert len(link.offers) == 1  # virtual's late joiners query: PeerUp alone offers nothing
                link.ctx.emit(Arrived("virtual", "robot1"))
                await settle()
                assert len(link.offers) == 1  # robot1 holds the newest
                link.ctx.emit(Arrived("virtual", "robot2"))
                await dk.wait_for(lambda: len(link.offers) == 2, what="v1 offered again")
                again = link.offers[1]
                assert again.version == link.offers[0].version and again.is_keyframe
                await dk.wait_for(
                    lambda: any(isinstance(e, Received) and e.peer == "robot0" for e in heard),
                    what="robot2 got robot0's map",
                )
                snap = d.snapshot()
                assert snap["offers"]["virtual"]["waiting"] == ["robot2"]
                assert snap["codec"]["reoffers"] == 1  # mapd status says so
                line = next(x for x in render_status(snap).splitlines() if x.startswith("codec"))
                assert "1 offered again (robots come into range, or failed)" in line
            finally:
                await late.close()

    asyncio.run(main())


def test_a_map_whose_offer_failed_goes_again_to_a_peer_still_in_reach(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    # P7 through the daemon's inbox: the link gives up on v1 for robot1 (uwb: its deadline passed
    # on a one-way link) while robot1 stays in reach; the map no longer changes, yet v1 goes again,
    # a timeout after the failed offer went out, and once robot1 acks it nothing more is sent.
    async def main() -> None:
        channel = dk.channel()
        d, source = dk.virtual_daemon(tmp_path, "robot0", channel)
        d.publisher.inflight_timeout_s = 0.3
        async with one_peer(d, channel, dk, []) as (link, peer):
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: len(link.offers) == 1, what="v1 offered")
            v1 = link.offers[0].version
            link.ctx.emit(Failed("virtual", "robot1", "robot0", v1, "deadline"))
            await dk.wait_for(lambda: len(link.offers) == 2, what="v1 offered again")
            assert link.offers[1].version == v1 and link.offers[1].is_keyframe
            assert d.publisher.counters.failed == {"virtual": 1}
            assert d.snapshot()["offers"]["virtual"]["waiting"] == ["robot1"]
            assert ", 1 failed on virtual" in render_status(d.snapshot())  # mapd status says so
            peer.ack("robot0", v1)
            await asyncio.sleep(0.8)  # more than two timeouts
            assert len(link.offers) == 2

    asyncio.run(main())


def test_a_peer_that_starts_again_without_its_state_gets_the_next_map_whole(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    # robot1 acked v1, then lost its disk and started again, quicker than its link could tell (zenoh
    # within its lease). Its maps now come from a new incarnation: it holds none of robot0's maps,
    # so robot0's next version goes whole, not as a delta against a v1 that robot1 no longer has.
    def robot1_map(version: int) -> Envelope:
        grid = dk.growing_map(1).replace(robot="robot1", version=version)
        env = Envelope(
            fleet="default", robot="robot1", version=version, base_version=0, codec="raw",
            width=grid.width, height=grid.height, resolution=grid.resolution,
            origin=grid.origin, seq=split(version)[1], payload=encode(grid, "raw"),
        )  # fmt: skip
        return env.signed(read_identity(tmp_path / "keys" / "robot1.key", "robot1"))

    async def main() -> None:
        channel = dk.channel()
        d, source = dk.virtual_daemon(tmp_path, "robot0", channel)
        async with one_peer(d, channel, dk, []) as (link, peer):

            def held() -> int:
                return int(d.snapshot()["peers"].get("robot1", {}).get("version") or 0)

            before = incarnation_at(time.time()) - 3600
            peer.offer(robot1_map(make(before, 5)))
            await dk.wait_for(lambda: held() == make(before, 5), what="robot1's map taken")
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: len(link.offers) == 1, what="v1 offered")
            peer.ack("robot0", link.offers[0].version)
            await source.queue.put(dk.growing_map(2))
            await dk.wait_for(lambda: len(link.offers) == 2, what="v2 offered")
            assert not link.offers[1].is_keyframe  # a delta against v1, which robot1 acked
            peer.ack("robot0", link.offers[1].version)
            await settle()
            assert d.store.acked() == {"robot1": link.offers[1].version}
            again = make(incarnation_at(time.time()), 1)  # robot1 with a new disk
            peer.offer(robot1_map(again))
            await dk.wait_for(lambda: held() == again, what="robot1's new incarnation taken")
            assert d.store.acked() == {}  # what it acked before is no base any more
            await source.queue.put(dk.growing_map(3))
            await dk.wait_for(lambda: len(link.offers) == 3, what="v3 offered")
            assert link.offers[2].is_keyframe
            assert [r["kind"] for r in coded(d)] == ["keyframe", "delta", "keyframe"]

    asyncio.run(main())


def test_a_version_that_cannot_be_saved_is_not_sent_and_the_robot_runs_on(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """A full disk while saving an own version: that version is not sent unsaved (after a restart
    its number could come again), the daemon does not stop, and the next version goes out."""
    from mapd.errors import StateError

    async def main() -> None:
        channel = dk.channel()
        d, source = dk.virtual_daemon(tmp_path, "robot0", channel)
        d.publisher.inflight_timeout_s = 0.1
        save = d.store.save_own
        full = {"disk": False}

        def save_own(grid: Any) -> None:
            if full["disk"]:
                raise StateError(f"{d.cfg.state.dir}: cannot save own map: No space left on device")
            save(grid)

        d.store.save_own = save_own  # type: ignore[method-assign]
        async with one_peer(d, channel, dk, []) as (link, _):
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: len(link.offers) == 1, what="v1 offered")
            full["disk"] = True
            for v in (2, 3):
                await source.queue.put(dk.growing_map(v))
                await settle()
            assert len(link.offers) == 1  # neither v2 nor v3 went out unsaved
            full["disk"] = False
            await source.queue.put(dk.growing_map(4))
            await dk.wait_for(lambda: len(link.offers) == 2, what="v4 offered once saved")
            assert num(link.offers[1].version) == 4
        errors = [r for r in caplog.records if "No space left" in r.getMessage()]
        assert len(errors) == 1  # one line for the run of failures, not one a version

    asyncio.run(main())


def test_peer_maps_that_cannot_be_saved_are_used_and_said_once(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """A full disk on the receiving robot: every peer map still reaches fusion, and the run of
    failed saves is one error line (a fleet's maps come several a second), then one line when
    saving works again."""
    import logging

    from mapd import config as configmod
    from mapd.errors import StateError

    caplog.set_level(logging.INFO, logger="mapd.daemon")
    channel = dk.channel()
    daemons = []
    for robot in ("robot0", "robot1"):
        path = dk.write_config(
            tmp_path, robot, extra='[transports]\nuse = ["virtual"]\n',
            **{"transports.virtual": f'channel = "{channel}"'},
        )  # fmt: skip
        daemons.append(Daemon(configmod.load(path), source=dk.QueueSource(robot)))
    d0, d1 = daemons
    source = d0.source
    assert isinstance(source, dk.QueueSource)
    save, full = d1.store.save_peer, {"disk": True}

    def save_peer(grid: Any, *rest: Any) -> None:
        if full["disk"]:
            raise StateError(f"{d1.cfg.state.dir}: cannot save map of {grid.robot}: No space left on device")
        save(grid, *rest)

    d1.store.save_peer = save_peer  # type: ignore[method-assign]

    async def main() -> None:
        tasks = [asyncio.create_task(d.run()) for d in daemons]
        try:
            await dk.wait_for(lambda: d0.transports and d0.transports[0].peers() == ["robot1"], what="peers")
            for v in (1, 2, 3, 4):
                if v == 4:
                    full["disk"] = False
                await source.queue.put(dk.growing_map(v))
                await dk.wait_for(
                    lambda v=v: num(getattr(d1.receiver.maps.get("robot0"), "version", 0)) == v, what=f"v{v}"
                )
            # The line comes once the save's worker returned: the saved file alone comes before it.
            await dk.wait_for(
                lambda: any(r.getMessage() == "state saved again" for r in caplog.records), what="v4 saved"
            )
        finally:
            for d in daemons:
                d.request_stop()
            await asyncio.gather(*tasks)

    asyncio.run(main())
    errors = [r for r in caplog.records if "No space left" in r.getMessage()]
    assert len(errors) == 1 and errors[0].levelname == "ERROR"
    assert any(r.getMessage() == "state saved again" for r in caplog.records)
    assert num(d1.store.peer_map("robot0").version) == 4  # type: ignore[union-attr]


def test_a_lossy_codec_with_deltas_names_the_base_its_receiver_decoded(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    # The pooled codec is lossy: robot1 holds robot0's v1 as it decoded it, not as robot0 made it.
    # v2 must go as a delta against that, and decode there; the sender's own PSNR check decodes too.
    from mapd import config as configmod
    from mapd.codec.api import get_codec

    channel = dk.channel()
    daemons = []
    for robot in ("robot0", "robot1"):
        path = dk.write_config(
            tmp_path, robot, codec="pooled", extra='[transports]\nuse = ["virtual"]\n',
            **{"transports.virtual": f'channel = "{channel}"'},
        )  # fmt: skip
        cfg = configmod.load(path)
        cfg.codec.measure_quality = True
        daemons.append((Daemon(cfg, source=dk.QueueSource(robot)), robot))
    (d0, _), (d1, _) = daemons
    source = d0.source
    assert isinstance(source, dk.QueueSource)

    async def main() -> None:
        tasks = [asyncio.create_task(d.run()) for d, _ in daemons]
        try:
            await dk.wait_for(lambda: d0.transports and d0.transports[0].peers() == ["robot1"], what="peers")
            for v in (1, 2):
                await source.queue.put(dk.growing_map(v))
                await dk.wait_for(
                    lambda v=v: num(getattr(d1.receiver.maps.get("robot0"), "version", 0)) == v, what=f"v{v}"
                )
        finally:
            for d, _ in daemons:
                d.request_stop()
            await asyncio.gather(*tasks)

    asyncio.run(main())
    rows = coded(d0)
    assert [r["kind"] for r in rows] == ["keyframe", "delta"]
    assert all(float(r["psnr"]) > 0 for r in rows)  # measured against what the receiver decodes
    want = get_codec("pooled").held(dk.growing_map(2))
    assert (d1.receiver.maps["robot0"].data == want.data).all()
    assert d1.receiver.counters.decode_errors == 0
