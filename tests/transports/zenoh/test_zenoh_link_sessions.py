"""Two and three real zenoh sessions in this process, on loopback TCP with multicast scouting off."""

from __future__ import annotations

import asyncio
import logging
import threading
import time

import pytest

from mapd.codec.api import decode, encode
from mapd.envelope import Envelope, unpack
from mapd.identity import Identity
from transports.base import Delivered, KeyframeNeeded, PeerDown, Received
from transports.zenoh import keys


def run(coro) -> None:  # type: ignore[no-untyped-def]
    asyncio.run(asyncio.wait_for(coro, 30))


def test_an_update_arrives_and_decodes(zk, room_grid) -> None:
    async def main() -> None:
        async with zk.pair("a", "b") as (a, b):
            payload = encode(room_grid, "raw")
            env = Envelope(
                fleet=zk.FLEET,
                robot="a",
                version=1,
                base_version=0,
                codec="raw",
                width=room_grid.width,
                height=room_grid.height,
                resolution=room_grid.resolution,
                origin=room_grid.origin,
                payload=payload,
            )
            a.offer(env)
            # a counts the update on its outbox thread once put() returns, which b may beat
            await b.wait(lambda: bool(b.received("a")) and a.t.stats()["updates_tx"] == 1)
            got = unpack(b.of(Received)[0].data)
            assert got == env
            assert decode(got.payload).digest() == room_grid.digest()
            st_a, st_b = a.t.stats(), b.t.stats()
            # (and once more if it answered b's join query with it: a reply, on its wire too)
            assert st_a["updates_tx"] == 1 and st_a["reply_bytes_tx"] in (0, len(env.pack()))
            assert st_a["bytes_tx"] == len(env.pack()) + st_a["reply_bytes_tx"]
            # b may also hear v1 again as the reply to its join query: counted as stale, not passed on.
            assert st_b["updates_rx"] == 1 and len(b.of(Received)) == 1
            assert st_b["bytes_rx"] == len(env.pack()) * (1 + st_b["stale"])
            assert st_b["peers"] == 1 and b.t.peers() == ["a"]
            # The daemon acks after decoding: the sender hears it as Delivered.
            b.t.ack("a", 1)
            await a.wait(lambda: a.of(Delivered))
            assert a.of(Delivered) == [Delivered("zenoh", "b", "a", 1)]
            # The ack is on b's wire: bytes_tx, which mapd bench fleet reports, once lacked acks.
            await b.wait(lambda: b.t.stats()["acks_tx"] == 1)
            st_b = b.t.stats()
            assert st_b["bytes_tx"] == st_b["ack_bytes_tx"] > 0

    run(main())


def test_late_joiner_gets_the_keyframe_then_deltas(zk) -> None:
    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep])
            offered = [
                zk.envelope("a", 1),
                zk.envelope("a", 2, 1),
                zk.envelope("a", 3),
                zk.envelope("a", 4, 3),
            ]
            for env in offered:  # nobody hears the first two
                a.offer(env)
            b = await f.start("b", connect=[f.ep])
            # b asks for a's latest keyframe (v3) as soon as it sees a.
            await b.wait(lambda: b.received("a"))
            assert b.received("a") == [("a", 3, 0)]
            await a.wait(lambda: a.of(KeyframeNeeded))
            assert a.of(KeyframeNeeded)[0] == KeyframeNeeded("zenoh", "b", "a")
            # The next delta on the keyframe it now holds applies in order.
            a.offer(zk.envelope("a", 5, 3))
            await b.wait(lambda: len(b.received("a")) == 2)
            assert b.received("a") == [("a", 3, 0), ("a", 5, 3)]
            assert b.t.stats()["keyframe_queries"] == 1 and b.t.stats()["gaps"] == 0
            # The keyframe a answered with is on its wire too (bytes_tx once lacked replies).
            st_a = a.t.stats()
            keyframe = len(offered[2].pack())
            assert st_a["replies_tx"] == 1 and st_a["reply_bytes_tx"] == keyframe
            # (an offer not yet put is replaced by the next, so count the updates put: all are the
            # same size, and each is counted with its bytes under one lock)
            assert {len(e.pack()) for e in offered} == {keyframe}
            updates = st_a["updates_tx"] * keyframe
            assert st_a["bytes_tx"] == updates + keyframe + st_a["ack_bytes_tx"] + st_a["pose_bytes_tx"]

    run(main())


def test_a_gap_leads_to_recovery_within_one_update(zk) -> None:
    async def main() -> None:
        async with zk.pair("b", "a") as (b, a):
            a.offer(zk.envelope("a", 1))
            await b.wait(lambda: b.received("a"))
            queries = b.t.stats()["keyframe_queries"]
            # Version 2 (a keyframe) is lost on the way: a's daemon holds it, b never saw it.
            a.keyframe = zk.envelope("a", 2)
            a.offer(zk.envelope("a", 3, 2))
            # b must not pass on the delta (its base is unknown), and fetches keyframe 2 at once.
            await b.wait(lambda: len(b.received("a")) == 2)
            assert b.received("a") == [("a", 1, 0), ("a", 2, 0)]
            st = b.t.stats()
            assert st["gaps"] == 1 and st["keyframe_queries"] == queries + 1
            a.offer(zk.envelope("a", 4, 2))
            await b.wait(lambda: len(b.received("a")) == 3)
            assert b.received("a")[-1] == ("a", 4, 2)

    run(main())


def test_request_keyframe_on_demand(zk) -> None:
    async def main() -> None:
        async with zk.pair("a", "b") as (a, b):
            a.offer(zk.envelope("a", 1))
            await b.wait(lambda: len(b.received("a")) == 1)
            a.offer(zk.envelope("a", 2, 1))
            await b.wait(lambda: len(b.received("a")) == 2)
            # The daemon failed to decode v2: it asks again and gets the keyframe, even though v1 is older.
            await b.t.request_keyframe("a")
            await b.wait(lambda: len(b.received("a")) == 3)
            assert b.received("a")[-1] == ("a", 1, 0)

    run(main())


def test_three_sessions_presence_appears_and_disappears(zk) -> None:
    async def main() -> None:
        pa, pb, pc = (zk.endpoint(zk.free_port()) for _ in range(3))
        async with zk.fleet() as f:
            a = await f.start("a", listen=[pa])
            b = await f.start("b", listen=[pb], connect=[pa])
            c = await f.start("c", listen=[pc], connect=[pa, pb])
            for bot, others in ((a, ["b", "c"]), (b, ["a", "c"]), (c, ["a", "b"])):
                await bot.wait(lambda bot=bot, others=others: bot.t.peers() == others)
            a.offer(zk.envelope("a", 1))
            await b.wait(lambda: b.received("a"))
            await c.wait(lambda: c.received("a"))
            start = time.monotonic()
            await c.t.close()
            await a.wait(lambda: PeerDown("zenoh", "c") in a.events)
            await b.wait(lambda: PeerDown("zenoh", "c") in b.events)
            assert time.monotonic() - start < 2.0  # undeclared on close, not left to a lease timeout
            assert a.t.peers() == ["b"] and b.t.peers() == ["a"]
            assert a.t.stats()["peers"] == 1

    run(main())


def test_bad_signatures_are_dropped_and_counted(zk) -> None:
    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep], signed=True)
            b = await f.start("b", connect=[f.ep], signed=True)
            # m is on the roster, but this process signs with a key that is not m's
            impostor = Identity.generate("m")
            rogue = await f.start("m", connect=[f.ep], identity=impostor)
            with zk.raw_session(f.ep, watch="b") as raw:
                await zk.meet(a, b, rogue)
                # raw learns b's token after b's subscriber (gossip connects it to b directly).
                await b.wait(lambda: bool(raw.seen))
                rogue.offer(zk.envelope("m", 1, signer=impostor))
                raw.put(keys.update_key(zk.FLEET, "a"), zk.envelope("a", 7).pack())  # unsigned, as if from a
                raw.put(keys.update_key(zk.FLEET, "a"), b"\xc1 not msgpack")
                raw.put(keys.ack_key(zk.FLEET, "b", "a"), (1).to_bytes(8, "big") + bytes(64))  # forged ack
                # m's update may be heard twice (published, and as the reply to b's join query of m).
                await b.wait(lambda: b.t.stats()["bad_signature"] >= 2 and b.t.stats()["dropped"] == 1)
                await a.wait(lambda: a.t.stats()["bad_signature"] >= 1)
                # A properly signed update still arrives, and nothing forged was ever emitted.
                a.offer(zk.envelope("a", 2, signer=zk.ident("a")))
                await b.wait(lambda: b.received())
                assert b.received() == [("a", 2, 0)]
                assert not a.of(Delivered)
                b.t.ack("a", 2)
                await a.wait(lambda: a.of(Delivered))
                assert a.of(Delivered) == [Delivered("zenoh", "b", "a", 2)]

    run(main())


def test_latest_wins_under_a_burst(zk) -> None:
    async def main() -> None:
        async with zk.pair("a", "b") as (a, b):
            blob = bytes(512 * 1024)
            n = 60
            for v in range(1, n + 1):  # offered faster than they can be sent
                a.offer(zk.envelope("a", v, payload=blob))
            # a counts each update on its outbox thread once put() returns, which b may beat
            await b.wait(
                lambda: (
                    bool(b.received())
                    and b.received()[-1][1] == n
                    and a.t.stats()["updates_tx"] + a.t.stats()["replaced"] == n
                )
            )
            got = [v for _, v, _ in b.received()]
            assert got == sorted(set(got))  # in order, never a stale one after a newer one
            st = a.t.stats()
            assert st["replaced"] > 0 and st["updates_tx"] + st["replaced"] == n
            assert len(got) == st["updates_tx"]

    run(main())


def test_close_is_prompt_idempotent_and_final(zk) -> None:
    async def main() -> None:
        async with zk.pair("a", "b") as (a, b):
            start = time.monotonic()
            await a.t.close()
            await a.t.close()
            assert time.monotonic() - start < 1.0
            a.offer(zk.envelope("a", 1))  # after close: ignored, not an error
            await b.wait(lambda: b.of(PeerDown))
            await asyncio.sleep(0.1)
            assert not b.of(Received) and a.t.stats()["updates_tx"] == 0
            await b.t.close()
            # zenoh's callback threads have ended too: one still ending at exit would abort the process.
            assert not [t.name for t in threading.enumerate() if "pyo3-closure" in t.name]

    run(main())


def test_oversized_messages_never_reach_mapd(zk) -> None:
    async def main() -> None:
        limit = 256 * 1024
        async with zk.pair("b", "a", max_message_bytes=limit) as (b, a):
            with zk.raw_session(b.listen[0], watch="b") as raw:
                await b.wait(lambda: bool(raw.seen))
                # zenoh itself refuses a message past the cap, so it is never even allocated for mapd.
                raw.put(keys.update_key(zk.FLEET, "x"), bytes(4 * limit))
                raw.put(keys.update_key(zk.FLEET, "x"), bytes(limit // 2))  # under the cap: mapd sees it
                await b.wait(lambda: b.t.stats()["dropped"] >= 1)
                await asyncio.sleep(0.1)
                assert b.t.stats()["bytes_rx"] == limit // 2 and b.t.stats()["dropped"] == 1
                # And we never send one: the offer is refused and counted.
                a.offer(zk.envelope("a", 1, payload=bytes(limit)))
                a.offer(zk.envelope("a", 2, payload=b"small"))
                await b.wait(lambda: b.received("a"))
                assert b.received("a") == [("a", 2, 0)] and a.t.stats()["oversize"] == 1

    run(main())


def test_own_maps_over_the_limit_are_said_once_until_one_fits(zk, caplog: pytest.LogCaptureFixture) -> None:
    # Each of this robot's maps over its limit was a warning of its own: one a map period, all day.
    caplog.set_level(logging.WARNING, logger="transports.zenoh")

    def said() -> list[str]:
        return [r.getMessage() for r in caplog.records if "over limits.max_message_bytes" in r.getMessage()]

    async def main() -> None:
        limit = 64 * 1024
        async with zk.pair("b", "a", max_message_bytes=limit) as (_, a):
            for v in (1, 2, 3):
                a.offer(zk.envelope("a", v, payload=bytes(limit)))
            assert a.t.stats()["oversize"] == 3 and len(said()) == 1, said()
            a.offer(zk.envelope("a", 4, payload=b"small"))  # one fits: the next one over is news
            a.offer(zk.envelope("a", 5, payload=bytes(limit)))
            assert a.t.stats()["oversize"] == 4 and len(said()) == 2, said()
            assert "raise it on every robot" in said()[0]

    run(main())
