"""The relay core's decisions (transports/uwb/forwarding.py): forward when a neighbour lacks a map
and does not hear its origin, not when it hears it, suppression, backoff and the rate bound."""

from __future__ import annotations

import asyncio

import pytest

from transports.uwb.forwarding import (
    RELAY_AIRTIMES,
    RELAY_FLOOR_S,
    ForwardingCore,
    Summary,
    SummaryError,
    pack_summary,
    unpack_summary,
)

A, B, C, D = 1, 2, 3, 4
KF = b"signed keyframe of A v3"


def _core(me: int = B) -> ForwardingCore:
    core = ForwardingCore(me, relay_period_s=10.0, retry_s=30.0)
    core.on_held(A, 3, 0, KF)
    return core


def test_summary_round_trip_and_malformed() -> None:
    # a daemon's versions carry its incarnation in the high bits: all 64 of them must survive
    from mapd.daemon.versions import split

    daemon_version = 395725895672791049
    assert split(daemon_version)[0] > 0 and daemon_version >= 2**32
    s = Summary({1: 7, 9: 2**32 - 1, 4: daemon_version}, frozenset({2, 3}))
    assert unpack_summary(pack_summary(s)) == s
    with pytest.raises(SummaryError, match="truncated"):
        unpack_summary(pack_summary(s)[:-1])
    with pytest.raises(SummaryError, match="trailing"):
        unpack_summary(pack_summary(s) + b"x")


def test_forwards_to_a_neighbour_that_lacks_and_does_not_hear_the_origin() -> None:
    core = _core()
    core.on_summary(C, Summary({A: 1}, frozenset({B})), 0.0)
    r = core.next_forward(0.0)
    assert r is not None and (r.origin, r.version, r.data, r.dests) == (A, 3, KF, (C,))


def test_no_forward_when_the_neighbour_hears_the_origin_or_holds_the_version() -> None:
    core = _core()
    core.on_summary(C, Summary({}, frozenset({A, B})), 0.0)  # A's own publisher serves C
    core.on_summary(D, Summary({A: 3}, frozenset({B})), 0.0)  # D has it already
    core.on_summary(A, Summary({}, frozenset({B})), 0.0)  # never back to the origin
    assert core.next_forward(0.0) is None


def test_overheard_forward_suppresses_and_expires() -> None:
    core = _core()
    core.on_summary(C, Summary({}, frozenset({B, D})), 0.0)
    core.on_overheard(A, 3, 0.0)
    assert core.next_forward(1.0) is None
    core.on_summary(C, Summary({}, frozenset({B, D})), 30.0)  # still lacks it after retry_s
    assert core.next_forward(30.0) is not None


def test_lower_link_id_serves_first_the_other_backs_off() -> None:
    core = _core(me=D)  # B (lower id) also holds A v3 and C hears B: D waits a relay period
    core.on_summary(B, Summary({A: 3}, frozenset({C, D})), 0.0)
    core.on_summary(C, Summary({}, frozenset({B, D})), 0.0)
    assert core.next_forward(0.0) is None and core.next_deadline() == 10.0
    assert core.next_forward(10.0) is not None  # B did not serve C in its turn: D does


def test_rate_bound_one_in_flight_and_one_per_period() -> None:
    core = _core()
    core.on_held(D, 5, 0, b"kf D")
    core.on_summary(C, Summary({}, frozenset({B})), 0.0)
    first = core.next_forward(0.0)
    assert first is not None and core.next_forward(0.0) is None  # one in flight
    core.relay_done()
    assert core.next_forward(5.0) is None and core.next_deadline() == 10.0  # one per relay_period_s
    second = core.next_forward(10.0)
    assert second is not None and second.origin != first.origin
    core.relay_done()
    assert core.next_forward(25.0) is None  # both forwarded: nothing until retry_s or a new version


def test_a_relay_gives_up_after_a_few_airtimes_at_the_robots_share_not_the_links_deadline() -> None:
    # A neighbour that walked off mid-relay (still heard through the walls now and then, so never
    # down) held up every later relay of this robot for the link's whole deadline.
    core = ForwardingCore(B, relay_period_s=1.0, share_bps=800.0, max_relay_s=120.0)
    core.on_held(A, 3, 0, KF)
    core.on_summary(C, Summary({}, frozenset({B})), 0.0)
    r = core.next_forward(0.0)
    assert r is not None and r.deadline_s == pytest.approx(
        RELAY_FLOOR_S + RELAY_AIRTIMES * 8 * len(KF) / 800.0
    )
    assert r.deadline_s < 120.0
    assert core.relay_deadline_s(5_000) == 120.0  # never past the link's own deadline
    # ... which grows with a map too long on the air for it (arq R6): a relay of such a map could
    # never complete at 120 s.
    assert core.relay_deadline_s(100_000) == pytest.approx(2 * 8 * 100_000 / 800.0)
    assert ForwardingCore(B, share_bps=1e5).relay_deadline_s(1000) == pytest.approx(5.32)  # 5 s + 4 x 80 ms
    assert ForwardingCore(B).relay_deadline_s(1000) is None  # no share known: the link's deadline
    assert ForwardingCore(B, max_relay_s=90.0).relay_deadline_s(1000) == 90.0


def test_a_revoked_robots_maps_are_no_longer_relayed() -> None:
    core = _core()
    core.on_held(A, 4, 3, b"delta of A v4 on v3")
    core.on_held(D, 5, 0, b"kf D")
    core.forget(A)
    core.on_summary(C, Summary({D: 5}, frozenset({B})), 0.0)  # C lacks A's maps, holds D's
    assert core.next_forward(0.0) is None and core.holds() == {D: 5}
    assert core._held_bytes == len(b"kf D") * 2  # D's keyframe, as newest keyframe and in its chain


def test_prefers_the_map_missing_at_most_neighbours_and_only_keeps_the_newest() -> None:
    core = _core()
    core.on_held(A, 2, 0, b"older")  # not newer: ignored
    core.on_held(D, 5, 0, b"kf D")
    core.on_summary(C, Summary({}, frozenset({B})), 0.0)
    core.on_summary(5, Summary({D: 5}, frozenset({B})), 0.0)
    core.on_summary(6, Summary({D: 5}, frozenset({B})), 0.0)
    r = core.next_forward(0.0)
    assert r is not None and r.origin == A and r.data == KF and r.dests == (C, 5, 6)
    assert core.holds() == {A: 3, D: 5}


def test_stale_summaries_are_forgotten() -> None:
    core = _core()
    core.on_summary(C, Summary({}, frozenset({B})), 0.0)
    assert core.next_forward(100.0) is None  # C's summary is older than summary_timeout_s


def test_a_delta_goes_only_to_neighbours_holding_its_base_the_keyframe_to_the_others() -> None:
    core = _core()  # keyframe A v3
    core.on_held(A, 4, 3, b"delta A v4 on v3")
    core.on_summary(C, Summary({A: 3}, frozenset({B})), 0.0)
    core.on_summary(D, Summary({A: 1}, frozenset({B})), 0.0)
    r = core.next_forward(0.0)
    assert r is not None and (r.version, r.data, r.dests) == (4, b"delta A v4 on v3", (C,))
    core.relay_done()
    r = core.next_forward(10.0)
    assert r is not None and (r.version, r.data, r.dests) == (3, KF, (D,))


def test_a_neighbour_behind_catches_up_along_the_chain_of_deltas() -> None:
    """The origin's deltas each go on the one before (its only neighbour acked it): a far robot
    holding v3 gets v4, then, its summary saying v4, v5, one relay each, never a dead end."""
    core = _core()  # keyframe A v3
    for v in (4, 5, 6):
        core.on_held(A, v, v - 1, f"delta A v{v}".encode())
    core.on_summary(C, Summary({A: 3}, frozenset({B})), 0.0)
    r = core.next_forward(0.0)
    assert r is not None and (r.version, r.data) == (4, b"delta A v4")
    core.relay_done()
    core.on_summary(C, Summary({A: 4}, frozenset({B})), 1.0)
    r = core.next_forward(10.0)
    assert r is not None and (r.version, r.data) == (5, b"delta A v5")
    assert core.holds() == {A: 6}


def test_a_neighbour_beyond_the_chain_makes_the_relay_ask_the_origin_for_a_keyframe() -> None:
    """C holds A's v5; B holds A's keyframe v3 and deltas v12..v19 only (v6..v11 went by): nothing B
    holds fits C, so B, which hears A, asks A for a whole map, once per retry_s, and forwards it."""
    core = _core()  # keyframe A v3
    for v in range(12, 20):
        core.on_held(A, v, v - 1, f"delta A v{v}".encode())
    core.on_summary(C, Summary({A: 5}, frozenset({B})), 0.0)
    assert core.next_forward(0.0) is None  # neither the keyframe (older) nor a delta fits
    assert core.keyframes_wanted(0.0, hears=set()) == []  # B does not hear A: nobody to ask
    assert core.keyframes_wanted(0.0, hears={A, C}) == [A]
    assert core.keyframes_wanted(10.0, hears={A, C}) == []  # asked within retry_s
    core.on_summary(C, Summary({A: 5}, frozenset({B})), 31.0)
    assert core.keyframes_wanted(31.0, hears={A, C}) == [A] and core.keyframes_asked == 2
    core.on_held(A, 20, 0, b"keyframe A v20")  # A answered with a whole map
    assert core.keyframes_wanted(70.0, hears={A, C}) == []  # now it fits C
    core.on_summary(C, Summary({A: 5}, frozenset({B})), 70.0)
    r = core.next_forward(70.0)
    assert r is not None and (r.version, r.data, r.dests) == (20, b"keyframe A v20", (C,))


def test_a_whole_map_of_the_version_held_as_a_delta_serves_a_neighbour_the_delta_cannot() -> None:
    """B holds A's v19 as a delta on v16 (the base every robot A sent it to had acked); C holds
    v18. B asks A for a whole map, and A's answer is a keyframe of v19, the version B holds: B
    forwards that one. Taken for the delta it already held, B asked again each retry_s, in vain,
    and C never got A's last map (``mapd bench swarm``, the building at 100 kb/s: 10 robots never
    did in the 300 s after the last map)."""
    core = _core()  # keyframe A v3
    core.on_held(A, 16, 0, b"keyframe A v16")
    core.on_held(A, 19, 16, b"delta A v19 on v16")
    core.on_summary(C, Summary({A: 18}, frozenset({B})), 0.0)
    assert core.next_forward(0.0) is None  # the delta needs v16, C holds v18
    assert core.keyframes_wanted(0.0, hears={A, C}) == [A]
    core.on_held(A, 19, 0, b"keyframe A v19")  # A's answer: the version B holds, whole
    assert core.keyframes_wanted(40.0, hears={A, C}) == []  # nothing more to ask for
    core.on_summary(C, Summary({A: 18}, frozenset({B})), 40.0)
    r = core.next_forward(40.0)
    assert r is not None and (r.version, r.data, r.dests) == (19, b"keyframe A v19", (C,))
    # and a neighbour holding the delta's base still gets the delta, the cheaper of the two
    other = _core()
    other.on_held(A, 16, 0, b"keyframe A v16")
    other.on_held(A, 19, 16, b"delta A v19 on v16")
    other.on_held(A, 19, 0, b"keyframe A v19")
    other.on_summary(D, Summary({A: 16}, frozenset({B})), 0.0)
    r = other.next_forward(0.0)
    assert r is not None and (r.version, r.data, r.dests) == (19, b"delta A v19 on v16", (D,))


def test_the_chain_is_bounded_in_length_and_bytes() -> None:
    from transports.uwb import forwarding

    core = _core()
    for v in range(4, 4 + 3 * forwarding.CHAIN):
        core.on_held(A, v, v - 1, bytes(100))
    assert len(core._chain[A]) == forwarding.CHAIN
    big = ForwardingCore(B)
    for o in (10, 11, 12):
        for v in range(1, 5):
            big.on_held(o, v, v - 1, bytes(forwarding.MAX_HELD_BYTES // 8))
    assert big._held_bytes <= forwarding.MAX_HELD_BYTES
    assert big.holds() == {10: 4, 11: 4, 12: 4}  # the newest of each origin is always kept


# --- a relayed envelope at the far robot's receiver -----------------------------------------------


def test_a_relayed_map_arrives_intact_still_signed_by_its_origin_and_tampering_is_refused() -> None:
    """robotA and robotC are out of range; robotB holds A's signed keyframe and forwards it as
    received. C's receiver accepts it from link peer robotB (the signature names A); flipped bits,
    or a map of "robotA" signed with another key, are refused."""
    from mapd.daemon.intake import Decode, Drop, open_envelope
    from mapd.daemon.receiver import Receiver
    from mapd.daemon.versions import EPOCH, incarnation_at, make
    from mapd.envelope import Envelope
    from mapd.errors import SignatureError
    from mapd.grid import Pose2D
    from mapd.identity import Identity, Roster

    now = EPOCH + 1_000_000.0
    a, b = Identity.generate("robotA"), Identity.generate("robotB")
    roster = Roster({"robotA": a.public_key, "robotB": b.public_key})
    version = make(incarnation_at(now - 60), 1)

    def envelope(signer: Identity) -> bytes:
        e = Envelope(
            fleet="f", robot="robotA", version=version, base_version=0, codec="raw", width=2, height=1,
            resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"\x00\x64",
        )  # fmt: skip
        return e.signed(signer).pack()

    relay = ForwardingCore(B)
    relay.on_held(A, version, 0, envelope(a))
    relay.on_summary(C, Summary({}, frozenset({B})), 0.0)
    r = relay.next_forward(0.0)
    assert r is not None and r.dests == (C,)
    env = open_envelope(r.data, max_bytes=1 << 20, roster=roster)
    assert env.robot == "robotA" and env.payload == b"\x00\x64"
    assert Receiver("robotC", "f", roster=roster).plan(env, "robotB", now) == Decode(None)

    tampered = bytearray(r.data)
    tampered[tampered.index(b"\x00\x64")] ^= 0xFF  # a relay changing a cell
    with pytest.raises(SignatureError):
        open_envelope(bytes(tampered), max_bytes=1 << 20, roster=roster)
    with pytest.raises(SignatureError):  # a third radio's map of "robotA" under its own key
        open_envelope(envelope(Identity.generate("robotA")), max_bytes=1 << 20, roster=roster)
    unsigned = Receiver("robotC", "f", roster=Roster({}, allow_unsigned=True))
    plain = Envelope(
        fleet="f", robot="robotA", version=version, base_version=0, codec="raw", width=2, height=1,
        resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"\x00\x64",
    )  # fmt: skip
    assert isinstance(unsigned.plan(plain, "robotB", now), Drop)  # unsigned fleets: the link is all


# --- the UwbTransport adapter (transport.py + relaying.py) -----------------------------------------


def test_uwb_transport_sends_summaries_and_relays_a_held_map_on_its_origin_stream() -> None:
    """Robot b (link id 2) hears a (1) and c (3); c's summary says it lacks a's map and does not hear
    a: the map the daemon accepted goes to c unaltered, on a's map stream. Unsigned fleets: no relay."""
    from types import SimpleNamespace
    from typing import Any

    from mapd.envelope import Envelope
    from mapd.grid import Pose2D
    from mapd.identity import Identity, Roster
    from transports.base import TransportContext
    from transports.uwb import arq
    from transports.uwb.forwarding import SUMMARY_STREAM
    from transports.uwb.link import POSE_STREAM
    from transports.uwb.transport import UwbOptions, UwbTransport

    ida = Identity.generate("a")
    roster = Roster({"a": ida.public_key})
    opts = UwbOptions(nodes={"a": 1, "b": 2, "c": 3}, summary_period_s=0.05, relay_period_s=0.01)
    sent: list[tuple[bytes, list[int], int]] = []
    deadlines: dict[int, float | None] = {}

    def send(data: bytes, dests: list[int], *, stream: int, **kw: Any) -> int:
        sent.append((data, dests, stream))
        deadlines[stream] = kw.get("deadline_s")
        return len(sent)

    async def scenario(
        opts: UwbOptions, *, already_relayed: bool, wait_s: float, revoked: bool = False
    ) -> tuple[UwbTransport, bytes]:
        """b holds a's v7 and c says it lacks it; ``already_relayed``: the daemon saw another robot
        forward v7 first (Transport.relayed)."""
        t = UwbTransport(opts, TransportContext("b", "f", 1 << 20, lambda e: None, roster=roster))
        t._link = SimpleNamespace(core=SimpleNamespace(peers_up=lambda: [1, 3]), send=send, stats=dict)  # type: ignore[assignment]
        assert t._relay is not None
        t._relay.start(send, lambda: [1, 3], t._dests)
        env = Envelope(
            fleet="f", robot="a", version=7, base_version=0, codec="raw", width=1, height=1,
            resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"\x00",
        ).signed(ida)  # fmt: skip
        if already_relayed:
            t.relayed(env)
        t.held(env, env.pack())
        if revoked:
            t.forget("a")  # the daemon revoked a (Transport.forget): its map is not passed on
        t._on_event(arq.MessageReceived(3, SUMMARY_STREAM, 9, pack_summary(Summary({}, frozenset({2})))))
        await asyncio.sleep(wait_s)
        await t._relay.close()
        return t, env.pack()

    t, data = asyncio.run(scenario(opts, already_relayed=False, wait_s=0.2))
    assert (data, [3], t._stream("a")) in sent  # the envelope's bytes, unaltered
    # Given up after four airtimes at b's equal turn (12.5 kb/s over three robots) past the floor.
    share = opts.link_rate_bps / 3
    assert deadlines[t._stream("a")] == pytest.approx(RELAY_FLOOR_S + RELAY_AIRTIMES * 8 * len(data) / share)
    summaries = [unpack_summary(d) for d, _, s in sent if s == SUMMARY_STREAM]
    assert summaries and summaries[-1].holds == {1: 7} and summaries[-1].hears == {1, 3}
    assert t.stats()["relays_tx"] == 1 and t.stats()["relays_failed"] == 0
    # c never took it by the relay's deadline: counted, and the next relay may start
    relay_msg = next(i + 1 for i, (_, _, stream) in enumerate(sent) if stream == t._stream("a"))
    t._on_event(arq.MessageClosed(relay_msg, "failed"))
    assert t.stats()["relays_failed"] == 1 and t._relay._relay_msg is None
    assert all(s < SUMMARY_STREAM for s in t._streams.values()) and SUMMARY_STREAM < POSE_STREAM

    # The same, but another robot forwarded v7 first: b does not repeat it (for two summary
    # periods: 1 s ones here, so the suppression outlasts the wait).
    sent.clear()
    slow = UwbOptions(nodes={"a": 1, "b": 2, "c": 3}, summary_period_s=1.0, relay_period_s=0.01)
    t, _ = asyncio.run(scenario(slow, already_relayed=True, wait_s=0.3))
    assert sent and all(s == SUMMARY_STREAM for _, _, s in sent)  # summaries only, no relay
    assert t.stats()["relays_tx"] == 0 and t.stats()["relays_overheard"] == 1
    sent.clear()
    t, _ = asyncio.run(scenario(opts, already_relayed=False, wait_s=0.2, revoked=True))
    assert sent and all(s == SUMMARY_STREAM for _, _, s in sent) and t.stats()["relays_tx"] == 0
    unsigned = TransportContext("b", "f", 1 << 20, lambda e: None, roster=Roster({}, allow_unsigned=True))
    assert UwbTransport(opts, unsigned)._relay is None


def test_a_relay_task_that_dies_says_why_to_its_watcher() -> None:
    from mapd.errors import TransportError
    from transports.uwb.relaying import RelayDriver

    def send(data: bytes, dests: list[int], **kw: object) -> int:
        raise RuntimeError("a bug in the send path")

    async def main() -> str:
        relay = RelayDriver(B, summary_period_s=0.05, relay_period_s=0.01, stream_of=lambda o: o)
        relay.held(A, 3, 0, KF)
        relay.start(send, lambda: [A, C], lambda: [A, C])  # the first summary goes out: it raises
        try:
            with pytest.raises(TransportError) as err:
                await asyncio.wait_for(relay.stopped(), 5)
            return str(err.value)
        finally:
            await relay.close()

    assert asyncio.run(main()) == "uwb: relay stopped: RuntimeError: a bug in the send path"


def test_maps_restored_from_the_state_directory_are_in_the_summary_and_never_forwarded() -> None:
    """A daemon that restarted holds its peers' maps from its state directory, with no envelope to
    forward. Before, its summary listed none of them, so each neighbour forwarded it a keyframe of
    every robot it held already (a robot's turns for minutes on a 12.5 kb/s channel)."""
    c = ForwardingCore(C, relay_period_s=10.0, retry_s=30.0)  # the restarted robot
    c.on_restored(A, 3)
    c.on_restored(A, 2)  # an older one changes nothing
    c.on_restored(C, 9)  # its own maps are not listed (they go out through its publisher)
    assert c.holds() == {A: 3}
    c.on_summary(D, Summary({}, frozenset({C})), 0.0)
    assert c.next_forward(0.0) is None  # nothing to forward: restored maps have no bytes here
    c.on_held(A, 4, 3, b"delta A v4 on v3")  # a newer one taken since: the newest is listed
    assert c.holds() == {A: 4}
    c.on_restored(A, 5)  # (restored and held in either order: the newest wins)
    assert c.holds() == {A: 5}

    # A neighbour that holds A's v3 keyframe reads C's summary: C needs nothing of it.
    b = _core()
    b.on_summary(C, pack_and_back(Summary({A: 3}, frozenset({B}))), 0.0)
    assert b.next_forward(0.0) is None
    # ... where C's summary without the restored map made B forward the keyframe C held already.
    b2 = _core()
    b2.on_summary(C, pack_and_back(Summary({}, frozenset({B}))), 0.0)
    r = b2.next_forward(0.0)
    assert r is not None and (r.origin, r.version, r.dests) == (A, 3, (C,))

    c.forget(A)  # revoked: neither its chain nor its restored version is listed
    assert c.holds() == {}


def pack_and_back(s: Summary) -> Summary:
    """``s`` as a neighbour hears it: packed for the air and parsed back."""
    return unpack_summary(pack_summary(s))


def test_between_two_robots_whose_maps_keep_changing_the_relay_takes_turns() -> None:
    """B hears A and C, which do not hear each other, and both make a new map every period. With
    the lowest link id first, B relayed only A's maps to C while C's waited for ever (in mapd demo
    --out-of-range 0-2, A held C's 6th map of 39)."""
    core = ForwardingCore(B, relay_period_s=1.0, retry_s=30.0)
    origins = []
    for k in range(6):
        now = 2.0 * k
        for origin in (A, C):
            core.on_held(origin, 10 + k, 0, f"kf {origin} v{10 + k}".encode())
        core.on_summary(A, Summary({}, frozenset({B})), now)  # lacks C's, does not hear C
        core.on_summary(C, Summary({}, frozenset({B})), now)  # lacks A's, does not hear A
        r = core.next_forward(now)
        assert r is not None
        origins.append(r.origin)
        assert r.dests == ((C,) if r.origin == A else (A,))
        core.relay_done()
    assert origins == [A, C, A, C, A, C]
    # the most neighbours served still goes first, though its origin went last (C, just now)
    for origin in (A, C):
        core.on_held(origin, 20, 0, f"kf {origin} v20".encode())
    core.on_summary(A, Summary({}, frozenset({B})), 12.0)  # lacks C's
    core.on_summary(C, Summary({A: 20}, frozenset({B})), 12.0)
    core.on_summary(D, Summary({A: 20}, frozenset({B})), 12.0)  # lacks C's
    core.on_summary(5, Summary({A: 20}, frozenset({B})), 12.0)  # lacks C's
    core.on_summary(6, Summary({C: 20}, frozenset({B})), 12.0)  # lacks A's
    r = core.next_forward(12.0)
    assert r is not None and r.origin == C and r.dests == (A, D, 5)
