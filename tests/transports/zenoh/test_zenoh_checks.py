"""Verification off the event loop, bounded per robot; unadmitted robots refused unread and unheard."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

import transports.zenoh.core as core_mod
from mapd.envelope import Envelope, unpack
from mapd.errors import EnvelopeError, SignatureError
from mapd.identity import Identity, Roster
from transports.base import KeyframeNeeded, Received
from transports.zenoh import keys, queries
from transports.zenoh.checks import OVERHEAD, CheckQueue
from transports.zenoh.core import ZenohCore

IDS = {n: Identity.generate(n) for n in ("a", "b")}
ROSTER = Roster({n: i.public_key for n, i in IDS.items()})


def run(coro) -> None:  # type: ignore[no-untyped-def]
    asyncio.run(asyncio.wait_for(coro, 30))


def signed_core(robot: str = "b") -> ZenohCore:
    return ZenohCore(
        robot=robot, fleet="testfleet", identity=IDS[robot], roster=ROSTER, max_message_bytes=1 << 20
    )


def wait_until(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, "condition not met"
        time.sleep(0.005)


# -- the core: check is pure, state changes apply its result -----------------------------------------


def test_check_touches_nothing_and_the_checked_result_is_applied(zk) -> None:
    c = signed_core()
    fresh = dataclasses.asdict(c.counters)
    good = zk.envelope("a", 1, signer=IDS["a"]).pack()
    forged = zk.envelope("a", 2, 1, signer=Identity.generate("a")).pack()
    got = c.check(good)
    assert isinstance(got, Envelope) and got.version == 1
    assert isinstance(c.check(forged), SignatureError)
    garbage = c.check(b"\xc1 not msgpack")
    assert isinstance(garbage, EnvelopeError) and not isinstance(garbage, SignatureError)
    assert dataclasses.asdict(c.counters) == fresh and c.last_version("a") == 0 and c.peers() == []
    # Applying the results does what on_update would have done with the bytes.
    step = c.on_update_checked("a", good, got, now=0)
    assert [unpack(e.data).version for e in step.events if isinstance(e, Received)] == [1]
    assert c.on_update_checked("a", forged, c.check(forged), now=0).events == []
    assert c.on_reply_checked("a", b"\xc1 not msgpack", garbage, now=0).events == []
    assert (c.counters.updates_rx, c.counters.bad_signature, c.counters.dropped) == (1, 1, 1)
    assert c.counters.bytes_rx == len(good) + len(forged) + len(b"\xc1 not msgpack")


def test_unadmitted_robots_are_refused_before_any_verification(zk, monkeypatch) -> None:
    def never(*a: Any, **k: Any) -> Any:
        raise AssertionError("unpack called for a robot the roster does not admit")

    c = signed_core()
    ghost = zk.envelope("ghost", 1, signer=Identity.generate("ghost")).pack()
    monkeypatch.setattr(core_mod, "unpack", never)
    assert c.on_update(keys.update_key("testfleet", "ghost"), ghost, now=0).events == []
    assert c.on_reply("ghost", ghost, now=0).events == []
    assert c.counters.unadmitted == 2 and c.counters.bad_signature == 0 and c.counters.bytes_rx == 0
    assert c.update_robot(keys.update_key("testfleet", "ghost")) == "ghost" and not c.admits("ghost")
    assert c.update_robot(keys.update_key("testfleet", "b")) is None  # our own key


def test_a_query_from_a_robot_off_the_roster_asks_for_no_keyframe() -> None:
    c = signed_core(robot="a")
    assert c.on_query("ghost").events == []
    params = signed_core(robot="b").query_parameters("a", wall_ns=1).split(";")
    n, sig = (p.split("=", 1)[1] for p in params[1:])
    assert c.on_query("b", n, sig).events == [KeyframeNeeded("zenoh", "b", "a")]
    assert c.counters.unadmitted == 1 and c.counters.queries_served == 2


# -- the check queue ---------------------------------------------------------------------------------


class Held:
    """A check function that blocks its first call until released, recording what it checked."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        self.checked: list[bytes] = []

    def __call__(self, data: bytes) -> int:
        if not self.entered.is_set():
            self.entered.set()
            assert self.release.wait(10)
        self.checked.append(data)
        return len(data)


def test_small_samples_are_checked_whole_and_in_order_while_the_thread_is_busy() -> None:
    held = Held()
    done: list[tuple[bytes, int]] = []
    q: CheckQueue[int] = CheckQueue("test-check", held, budget=1 << 20, max_robots=2)
    try:
        assert q.submit("a", b"first", lambda d, r: done.append((d, r)))
        assert held.entered.wait(5)
        burst = [b"a%03d" % i for i in range(100)]
        for data in burst:
            assert q.submit("a", data, lambda d, r: done.append((d, r)))
        assert q.waiting("a") == 100 and q.superseded == 0
        # A third robot is refused while two have samples in the queue.
        assert q.submit("b", b"b", lambda d, r: done.append((d, r)))
        assert not q.submit("c", b"c", lambda d, r: done.append((d, r))) and q.rejected == 1
        held.release.set()
        wait_until(lambda: len(done) == 102)
        assert [d for d, _ in done] == [b"first", *burst, b"b"] and all(r == len(d) for d, r in done)
        assert q.waiting() == 0
    finally:
        held.release.set()
        q.stop()


def test_large_samples_collapse_to_the_newest_while_the_thread_is_busy() -> None:
    held = Held()
    done: list[bytes] = []
    budget = 4096
    big = budget // 2  # with OVERHEAD, two of these never fit the budget together
    q: CheckQueue[int] = CheckQueue("test-check", held, budget=budget, max_robots=4)
    try:
        q.submit("a", b"0" * big, lambda d, r: done.append(d))
        assert held.entered.wait(5)
        samples = [bytes([65 + i]) * big for i in range(20)]
        for data in samples:
            q.submit("a", data, lambda d, r: done.append(d))
            assert q.waiting("a") == 1  # latest wins: never more than one waits
        q.submit("b", b"x", lambda d, r: done.append(d))  # another robot's sample is not pushed out
        assert q.superseded == len(samples) - 1
        held.release.set()
        wait_until(lambda: len(done) == 3)
        assert done == [b"0" * big, samples[-1], b"x"]
        assert held.checked == done  # the superseded ones were never checked
    finally:
        held.release.set()
        q.stop()
    assert 2 * (big + OVERHEAD) > budget


def test_calls_run_after_what_was_submitted_before_them() -> None:
    held = Held()
    order: list[str] = []
    q: CheckQueue[int] = CheckQueue("test-check", held, budget=1 << 20, max_robots=1)
    try:
        q.submit("a", b"1", lambda d, r: order.append("sample 1"))
        assert held.entered.wait(5)
        q.submit("a", b"2", lambda d, r: order.append("sample 2"))
        assert q.after(lambda: order.append("after"))
        held.release.set()
        wait_until(lambda: len(order) == 3)
        assert order == ["sample 1", "sample 2", "after"]
    finally:
        held.release.set()
        q.stop()
    assert not q.submit("a", b"3", lambda d, r: None) and not q.after(lambda: None)


# -- real zenoh sessions -----------------------------------------------------------------------------


def test_verification_runs_off_the_loop_and_state_changes_on_it(zk, monkeypatch) -> None:
    """An 8 MiB update's Ed25519 check stalled the event loop ~15 ms; now it runs on the check thread."""
    unpacked_on: list[int] = []
    applied: list[tuple[str, int]] = []
    real_unpack = core_mod.unpack

    def recording_unpack(data: bytes, **kw: Any) -> Envelope:
        unpacked_on.append(threading.get_ident())
        return real_unpack(data, **kw)

    def recording(name: str, method: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(self: ZenohCore, *args: Any, **kw: Any) -> Any:
            applied.append((name, threading.get_ident()))
            return method(self, *args, **kw)

        return wrapper

    monkeypatch.setattr(core_mod, "unpack", recording_unpack)
    for name in ("on_update_checked", "on_reply_checked"):
        monkeypatch.setattr(ZenohCore, name, recording(name, getattr(ZenohCore, name)))

    async def main() -> None:
        loop_thread = threading.get_ident()
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep], signed=True)
            a.offer(zk.envelope("a", 1, signer=zk.ident("a")))  # heard by b only as its join query's reply
            b = await f.start("b", connect=[f.ep], signed=True)
            await b.wait(lambda: b.received("a") == [("a", 1, 0)])
            a.offer(zk.envelope("a", 2, 1, signer=zk.ident("a")))  # heard as an update
            await b.wait(lambda: len(b.received("a")) == 2)
            assert b.received("a") == [("a", 1, 0), ("a", 2, 1)]
            assert b.t.stats()["bad_signature"] == 0
        assert len(unpacked_on) >= 2 and loop_thread not in unpacked_on
        assert {name for name, _ in applied} == {"on_update_checked", "on_reply_checked"}
        assert all(ident == loop_thread for _, ident in applied)

    run(main())


def test_updates_arriving_faster_than_they_verify_keep_only_the_newest_waiting(zk, monkeypatch) -> None:
    held = threading.Event()
    release = threading.Event()
    real_unpack = core_mod.unpack

    def slow_unpack(data: bytes, **kw: Any) -> Envelope:
        # Hold b's check thread on its first sample, as a long verification would.
        if threading.current_thread().name == "mapd-zenoh-check-b" and not held.is_set():
            held.set()
            assert release.wait(15)
        return real_unpack(data, **kw)

    monkeypatch.setattr(core_mod, "unpack", slow_unpack)
    blob = bytes(5 << 20)  # over half of max_message_bytes: two never wait together
    n = 8

    async def main() -> None:
        try:
            async with zk.pair("a", "b", max_message_bytes=8 << 20) as (a, b):
                # b's join query of a must have ended (unanswered): a reply of v1 would be one more sample.
                await b.wait(lambda: b.t.core._robots["a"].query_until is None)
                for v in range(1, n + 1):
                    a.offer(zk.envelope("a", v, payload=blob))
                    # one put at a time, so that every version reaches b (the outbox would merge them)
                    await a.wait(lambda v=v: a.t.stats()["updates_tx"] == v, timeout=10)
                    if v == 1:
                        await b.wait(held.is_set)
                    else:  # v waits, pushing out v-1 (which waited since it came)
                        await b.wait(
                            lambda v=v: b.t.stats()["superseded"] == v - 2 and b.t._checks.waiting("a") == 1,
                            timeout=10,
                        )
                # The loop is free meanwhile (this test runs on it); v1 is held, v2..v7 were pushed out.
                assert b.received() == [] and b.t.stats()["superseded"] == n - 2
                release.set()
                await b.wait(lambda: len(b.received()) == 2)
                await asyncio.sleep(0.1)
                assert b.received() == [("a", 1, 0), ("a", n, 0)]
                st = b.t.stats()
                assert st["updates_rx"] == 2 and st["superseded"] == n - 2 and b.t._checks.waiting() == 0
        finally:
            release.set()

    run(main())


def test_samples_of_robots_off_the_roster_are_refused_unread(zk, monkeypatch) -> None:
    lengths: list[int] = []
    real_unpack = core_mod.unpack

    def recording_unpack(data: bytes, **kw: Any) -> Envelope:
        lengths.append(len(data))
        return real_unpack(data, **kw)

    monkeypatch.setattr(core_mod, "unpack", recording_unpack)
    ghost = 100_003

    async def main() -> None:
        async with zk.pair("b", "a", signed=True) as (b, _a):
            with zk.raw_session(b.listen[0], watch="b") as raw:
                await b.wait(lambda: bool(raw.seen))
                raw.put(keys.update_key(zk.FLEET, "ghost"), bytes(ghost))  # not on the roster
                raw.put(keys.update_key(zk.FLEET, "a"), zk.envelope("a", 9).pack())  # unsigned: checked
                await b.wait(lambda: b.t.stats()["unadmitted"] == 1 and b.t.stats()["bad_signature"] == 1)
                assert ghost not in lengths and b.t.stats()["bytes_rx"] < ghost

    run(main())


def test_a_keyframe_query_off_the_roster_forged_or_replayed_is_answered_but_not_heeded(zk) -> None:
    async def main() -> None:
        async with zk.pair("a", "b", signed=True) as (a, b):
            kf = zk.envelope("a", 3, signer=zk.ident("a"))
            a.offer(kf)
            with zk.raw_session(a.listen[0], watch="a") as raw:
                await a.wait(lambda: bool(raw.seen))
                latest = keys.latest_key(zk.FLEET, "a")

                def ask(params: str) -> list[bytes]:
                    got = raw.session.get(f"{latest}?{params}", timeout=3)
                    return [r.ok.payload.to_bytes() for r in got if r.ok]

                assert await asyncio.to_thread(ask, "from=ghost") == [kf.pack()]
                await a.wait(lambda: a.t.stats()["unadmitted"] == 1)
                assert KeyframeNeeded("zenoh", "ghost", "a") not in a.events
                # A robot on the roster named by someone without its key: answered, not heeded.
                assert await asyncio.to_thread(ask, "from=b;n=5") == [kf.pack()]
                await a.wait(lambda: a.t.stats()["bad_signature"] == 1)
                # b's own signed query, recorded and played back: heeded once (the nonce is above
                # those of b's daemon so far, which are wall-clock nanoseconds too).
                signed = queries.parameters(
                    zk.ident("b"), fleet=zk.FLEET, asker="b", robot="a", nonce=time.time_ns()
                )
                for _ in range(2):
                    assert await asyncio.to_thread(ask, signed) == [kf.pack()]
                await a.wait(lambda: a.t.stats()["replayed"] == 1)
                assert a.t.stats()["bad_signature"] == 1  # so the first of the two was heeded
                # b's daemon asking is heeded.
                heard = a.events.count(KeyframeNeeded("zenoh", "b", "a"))
                await b.t.request_keyframe("a")
                await a.wait(lambda: a.events.count(KeyframeNeeded("zenoh", "b", "a")) > heard)
                assert [a.t.stats()[k] for k in ("unadmitted", "bad_signature", "replayed")] == [1, 1, 1]

    run(main())


def test_a_flood_of_keyframe_queries_is_rationed_and_maps_still_go_out(zk) -> None:
    from transports.zenoh.answers import MAX_REPLIES_PENDING, REPLY_BURST, REPLY_RATE_HZ

    async def main() -> None:
        async with zk.pair("a", "b", signed=True) as (a, b):
            a.offer(zk.envelope("a", 3, signer=zk.ident("a")))
            await b.wait(lambda: ("a", 3, 0) in b.received())
            with zk.raw_session(a.listen[0], watch="a") as raw:
                await a.wait(lambda: bool(raw.seen))
                latest = keys.latest_key(zk.FLEET, "a")
                before = a.t.stats()  # b's own query when it saw a took an answer already
                heard = a.events.count(KeyframeNeeded("zenoh", "b", "a"))
                # b's own signed query comes last, when the ration is spent: answered or not, it
                # still makes a publish its next map whole.
                signed = queries.parameters(
                    zk.ident("b"), fleet=zk.FLEET, asker="b", robot="a", nonce=time.time_ns()
                )
                t0 = time.monotonic()
                asked = await asyncio.to_thread(
                    lambda: (
                        [raw.session.get(latest, timeout=5) for _ in range(299)]
                        + [raw.session.get(f"{latest}?{signed}", timeout=5)]
                    )
                )
                a.offer(zk.envelope("a", 4, signer=zk.ident("a")))  # while the flood is answered
                # Generous waits: a loaded CI machine serves 300 queries slower than a quiet one.
                await b.wait(lambda: ("a", 4, 0) in b.received(), timeout=20)
                await a.wait(
                    lambda: a.t.stats()["queries_served"] >= before["queries_served"] + 300, timeout=20
                )
                elapsed = time.monotonic() - t0
                answered = await asyncio.to_thread(lambda: sum(1 for h in asked for r in h if r.ok))
                st = a.t.stats()
                assert answered == 300 - (st["queries_shed"] - before["queries_shed"])
                # The first ones find the answer slots free (but one, if b's own query still held
                # it); then no more than the budget is answered.
                assert MAX_REPLIES_PENDING - 1 <= answered <= REPLY_BURST + REPLY_RATE_HZ * elapsed + 1
                assert st["errors"] == 0
                assert a.events.count(KeyframeNeeded("zenoh", "b", "a")) == heard + 1

    run(main())


@pytest.fixture(autouse=True)
def _no_stray_threads() -> Any:
    yield
    # The check threads end when their transport closes (after a check in progress, if any).
    wait_until(lambda: not [t for t in threading.enumerate() if t.name.startswith("mapd-zenoh-check-")])


def test_a_flood_of_acks_waits_for_the_loop_in_a_bounded_backlog(zk) -> None:
    # Anyone on the bus can put acks faster than the loop checks their signatures: each waited on the
    # loop's queue, unbounded (273,000 after 47 s, every timer 16 s late).
    from transports.zenoh.acks import pack_ack
    from transports.zenoh.link import MAX_LOOP_BACKLOG

    forged = pack_ack(1, identity=Identity.generate("a"), fleet=zk.FLEET, peer="a", robot="b")
    flood = 5 * MAX_LOOP_BACKLOG

    async def main() -> None:
        async with zk.pair("b", "a", signed=True) as (b, _a):
            with zk.raw_session(b.listen[0], watch="b") as raw:
                await b.wait(lambda: bool(raw.seen))
                loop = asyncio.get_running_loop()
                ready = loop._ready  # type: ignore[attr-defined]  # the callbacks waiting to run
                peak, done = [0], threading.Event()

                def sample() -> None:
                    while not done.is_set():
                        peak[0] = max(peak[0], len(ready))
                        time.sleep(0.002)

                sampler = threading.Thread(target=sample, daemon=True)
                sampler.start()
                key = keys.ack_key(zk.FLEET, "a", "b")
                dropped = b.t.stats()["dropped"]
                # The loop is busy (blocked here) while the flood arrives.
                for _ in range(flood):
                    raw.put(key, forged)
                time.sleep(1.0)
                await b.wait(lambda: b.t.stats()["dropped"] + b.t.stats()["bad_signature"] >= dropped + flood)
                done.set()
                sampler.join(5)
                assert peak[0] <= MAX_LOOP_BACKLOG + 64, peak[0]
                assert b.t.stats()["dropped"] - dropped >= flood - MAX_LOOP_BACKLOG - 64

    run(main())


def test_poses_of_robots_off_the_roster_are_refused_unread(zk) -> None:
    # Each made-up name took a slot of the daemon's event queue (256 peers), which real maps need.
    from mapd.grid import Pose2D
    from mapd.poses import PoseMessage
    from transports.base import PoseReceived

    async def main() -> None:
        async with zk.pair("b", "a", signed=True) as (b, _a):
            with zk.raw_session(b.listen[0], watch="b") as raw:
                await b.wait(lambda: bool(raw.seen))
                for i in range(300):
                    name = f"ghost{i}"
                    msg = PoseMessage(zk.FLEET, name, time.time(), Pose2D(1.0, 2.0, 0.5))
                    raw.put(keys.pose_key(zk.FLEET, name), msg.signed(Identity.generate(name)).pack())
                await b.wait(lambda: b.t.stats()["unadmitted"] >= 300)
                assert not [e for e in b.events if isinstance(e, PoseReceived) and e.peer.startswith("ghost")]

    run(main())


def test_tokens_of_robots_off_the_roster_wait_for_nothing(zk) -> None:
    # Anyone on the bus can declare liveliness tokens: each change queued a loop callback, unbounded.
    from transports.base import PeerUp

    async def main() -> None:
        async with zk.pair("b", "a", signed=True) as (b, _a):
            with zk.raw_session(b.listen[0], watch="b") as raw:
                await b.wait(lambda: bool(raw.seen))
                tokens = [
                    raw.session.liveliness().declare_token(keys.presence_key(zk.FLEET, f"ghost{i}"))
                    for i in range(300)
                ]
                await b.wait(lambda: b.t.stats()["unadmitted"] >= 300)
                for token in tokens:
                    token.undeclare()
                await b.wait(lambda: b.t.stats()["unadmitted"] >= 600)
                assert not [e for e in b.events if isinstance(e, PeerUp) and e.peer.startswith("ghost")]
                assert not b.t._presence and PeerUp("zenoh", "a") in b.events  # the real one still

    run(main())


def test_token_changes_wait_coalesced_keeping_a_restart() -> None:
    # Latest wins per token, but a vanish then appear (a restart) stays two changes for the core.
    import zenoh

    from transports.base import PeerUp, TransportContext
    from transports.zenoh.link import ZenohTransport
    from transports.zenoh.session import ZenohOptions

    events: list[Any] = []
    ctx = TransportContext(robot="b", fleet="testfleet", max_message_bytes=1 << 20, emit=events.append)
    t = ZenohTransport(ZenohOptions(multicast_scouting=False), ctx)
    loop = asyncio.new_event_loop()
    t._loop = loop
    key = keys.presence_key("testfleet", "a")
    put, gone = zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE
    try:
        for kind in (put, gone, put, gone, put):  # five changes before the loop gets to them
            t._cb_presence(dataclasses.make_dataclass("S", ["key_expr", "kind"])(key, kind))
        assert t._presence == {key: [False, True]}
        loop.run_until_complete(asyncio.sleep(0))
        assert t._presence == {} and events == [PeerUp("zenoh", "a")]
    finally:
        loop.close()
