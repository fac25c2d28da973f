"""The sans-I/O core and the key expressions: every rule, without a network."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.envelope import unpack
from mapd.errors import EnvelopeError, SignatureError
from mapd.identity import Identity, Roster
from transports.base import Delivered, KeyframeNeeded, PeerDown, PeerUp, Received
from transports.zenoh import keys
from transports.zenoh.acks import pack_ack, unpack_ack
from transports.zenoh.core import ZenohCore

# The fleet: each robot's own key, and the roster of their public keys.
IDS = {n: Identity.generate(n) for n in ("a", "b", "c", "d", "m", "p", "q", "r")}
ROSTER = Roster({n: i.public_key for n, i in IDS.items()})


def core(robot: str = "b", signed: bool = False, **kw: object) -> ZenohCore:
    return ZenohCore(
        robot=robot,
        fleet="testfleet",
        identity=IDS[robot] if signed else None,
        roster=ROSTER if signed else Roster.open(),
        max_message_bytes=1 << 20,
        **kw,  # type: ignore[arg-type]
    )


def upd(zk, robot: str, v: int, base: int = 0, signer: Identity | None = None) -> tuple[str, bytes]:
    return keys.update_key("testfleet", robot), zk.envelope(robot, v, base, signer=signer).pack()


def versions(step) -> list[int]:
    return [unpack(e.data).version for e in step.events if isinstance(e, Received)]


# -- key expressions -------------------------------------------------------------------------------


def test_keys_round_trip() -> None:
    assert keys.update_key("f", "r1") == "mapd/f/r1/update"
    assert keys.presence_key("f", "r1") == "mapd/f/r1"
    assert keys.latest_key("f", "r1") == "mapd/f/r1/latest"
    assert keys.ack_key("f", "p", "r1") == "mapd/f/p/ack/r1"
    assert keys.parse_update("f", keys.update_key("f", "r-1_x")) == "r-1_x"
    assert keys.parse_presence("f", keys.presence_key("f", "r1")) == "r1"
    assert keys.parse_ack("f", "r1", keys.ack_key("f", "p", "r1")) == "p"
    # Other fleets, other robots' acks and other shapes are not ours.
    assert keys.parse_update("g", "mapd/f/r1/update") is None
    assert keys.parse_ack("f", "r2", "mapd/f/p/ack/r1") is None
    assert keys.parse_presence("f", "mapd/f/r1/update") is None
    with pytest.raises(ValueError):
        keys.update_key("f", "a/b")
    with pytest.raises(ValueError):
        keys.presence_key("f", "*")


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=80))
def test_key_parsers_take_any_string(text: str) -> None:
    for got in (
        keys.parse_update("f", text),
        keys.parse_presence("f", text),
        keys.parse_ack("f", "me", text),
    ):
        assert got is None or (keys.valid_name(got) and text.startswith("mapd/f/"))


# -- acks ------------------------------------------------------------------------------------------


def test_ack_round_trip_and_signature() -> None:
    signed = pack_ack(7, identity=IDS["p"], fleet="f", peer="p", robot="r")
    assert unpack_ack(signed, roster=ROSTER, fleet="f", peer="p", robot="r") == 7
    assert len(signed) == 8 + 64
    # The signature binds the peer and the robot: a replay under another name fails.
    with pytest.raises(SignatureError, match="bad signature"):
        unpack_ack(signed, roster=ROSTER, fleet="f", peer="q", robot="r")
    with pytest.raises(SignatureError, match="unsigned"):
        unpack_ack(
            pack_ack(7, identity=None, fleet="f", peer="p", robot="r"),
            roster=ROSTER,
            fleet="f",
            peer="p",
            robot="r",
        )
    assert (
        unpack_ack(
            pack_ack(9, identity=None, fleet="f", peer="p", robot="r"),
            roster=Roster.open(),
            fleet="f",
            peer="p",
            robot="r",
        )
        == 9
    )
    with pytest.raises(EnvelopeError) as info:
        unpack_ack(bytes(8), roster=Roster.open(), fleet="f", peer="p", robot="r")  # version 0
    assert not isinstance(info.value, SignatureError)  # damage, not forgery: counted apart


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=40), st.booleans())
def test_ack_parser_takes_any_bytes(data: bytes, signed: bool) -> None:
    try:
        v = unpack_ack(data, roster=ROSTER if signed else Roster.open(), fleet="f", peer="p", robot="r")
    except EnvelopeError as exc:
        assert "\n" not in str(exc)
    else:
        assert 0 < v < 1 << 63


# -- receive rules ---------------------------------------------------------------------------------


def test_keyframe_then_deltas_on_known_bases(zk) -> None:
    c = core(base_window=2)
    assert versions(c.on_update(*upd(zk, "a", 1), now=0)) == [1]
    assert versions(c.on_update(*upd(zk, "a", 2, 1), now=0)) == [2]
    # Coded against an older acked version still in the window: fine.
    assert versions(c.on_update(*upd(zk, "a", 3, 1), now=0)) == [3]
    # Version 1 has left the window of two (2, 3): an unknown base is a gap and a query.
    step = c.on_update(*upd(zk, "a", 4, 1), now=0)
    assert versions(step) == [] and step.queries == ["a"]
    assert c.counters.gaps == 1 and c.counters.updates_rx == 3


def test_gap_queries_once_per_timeout_and_reply_recovers(zk) -> None:
    c = core(query_timeout_s=2.0)
    c.on_update(*upd(zk, "a", 1), now=0)
    assert c.on_update(*upd(zk, "a", 5, 4), now=0).queries == ["a"]
    assert c.on_update(*upd(zk, "a", 6, 5), now=1.0).queries == []  # one query in flight
    assert c.counters.gaps == 2 and c.counters.keyframe_queries == 1
    # The reply is a keyframe newer than what we hold: accepted, and deltas on it follow.
    assert versions(c.on_reply("a", zk.envelope("a", 6).pack(), now=1.1)) == [6]
    assert versions(c.on_update(*upd(zk, "a", 7, 6), now=1.2)) == [7]
    # After the timeout (or the end of the query) a new gap queries again.
    assert c.on_update(*upd(zk, "a", 9, 8), now=3.5).queries == ["a"]
    assert c.query_done("a", now=3.55).queries == []
    assert c.on_update(*upd(zk, "a", 10, 8), now=3.6).queries == ["a"]


def test_a_gap_during_a_query_asks_again_when_it_ends(zk) -> None:
    c = core()
    step = c.on_presence(keys.presence_key("testfleet", "a"), True, now=0)  # late join: query 1
    assert step.queries == ["a"]
    assert versions(c.on_update(*upd(zk, "a", 1), now=0.01)) == [1]
    assert c.on_update(*upd(zk, "a", 3, 2), now=0.02).queries == []  # gap while query 1 is out
    # Query 1's reply (v1) predates the gap, so its end triggers one more query, and only one.
    assert versions(c.on_reply("a", zk.envelope("a", 1).pack(), now=0.03)) == []
    assert c.query_done("a", now=0.04).queries == ["a"]
    assert c.query_done("a", now=0.05).queries == []
    assert c.counters.keyframe_queries == 2


def test_stale_and_duplicate_versions_are_dropped(zk) -> None:
    c = core()
    c.on_update(*upd(zk, "a", 3), now=0)
    assert versions(c.on_update(*upd(zk, "a", 3), now=0)) == []
    assert versions(c.on_reply("a", zk.envelope("a", 2).pack(), now=0)) == []
    assert c.counters.stale == 2


def test_request_keyframe_forgets_so_an_older_keyframe_is_taken(zk) -> None:
    c = core()
    c.on_update(*upd(zk, "a", 1), now=0)
    c.on_update(*upd(zk, "a", 2, 1), now=0)
    step = c.request_keyframe("a", now=0)
    assert step.queries == ["a"]
    assert c.last_version("a") == 0
    assert versions(c.on_reply("a", zk.envelope("a", 1).pack(), now=0.1)) == [1]
    # The delta on 2 must not reach a daemon that asked for a keyframe because 2 was unusable.
    assert versions(c.on_update(*upd(zk, "a", 3, 2), now=0.2)) == []


def test_signatures_spoofing_and_garbage(zk) -> None:
    c = core(signed=True)
    assert versions(c.on_update(*upd(zk, "a", 1, signer=IDS["a"]), now=0)) == [1]
    c.on_update(*upd(zk, "a", 2, 1, signer=Identity.generate("a")), now=0)  # signed with another key
    c.on_update(*upd(zk, "a", 3, 1), now=0)  # unsigned
    assert c.counters.bad_signature == 2
    # A valid envelope of robot "a" published on robot "m"'s key is not m's update.
    c.on_update(keys.update_key("testfleet", "m"), zk.envelope("a", 4, signer=IDS["a"]).pack(), now=0)
    c.on_update(keys.update_key("testfleet", "a"), b"\x93garbage", now=0)
    c.on_update("mapd/otherfleet/a/update", zk.envelope("a", 5, signer=IDS["a"]).pack(), now=0)
    assert c.counters.dropped == 3
    assert c.counters.updates_rx == 1 and c.last_version("a") == 1


def test_signature_failures_are_told_apart_by_type(zk) -> None:
    # Any SignatureError from unpack counts as a forgery (here a signature of the wrong length),
    # damage of any other kind as dropped; nothing is parsed twice to tell them apart.
    c = core(signed=True)
    odd = dataclasses.replace(zk.envelope("a", 1, signer=IDS["a"]), sig=b"short")
    c.on_update(keys.update_key("testfleet", "a"), odd.pack(), now=0)
    assert (c.counters.bad_signature, c.counters.dropped) == (1, 0)
    c.on_update(keys.update_key("testfleet", "a"), zk.envelope("a", 1, signer=IDS["a"]).pack()[:-3], now=0)
    assert (c.counters.bad_signature, c.counters.dropped) == (1, 1)


def test_presence_events_and_late_join_query(zk) -> None:
    c = core()
    step = c.on_presence(keys.presence_key("testfleet", "a"), True, now=0)
    assert step.events == [PeerUp("zenoh", "a")] and step.queries == ["a"]
    assert c.on_presence(keys.presence_key("testfleet", "a"), True, now=0).events == []  # no repeat
    assert c.on_presence(keys.presence_key("testfleet", "b"), True, now=0).events == []  # ourselves
    c.on_reply("a", zk.envelope("a", 4).pack(), now=0.1)
    assert c.peers() == ["a"] and c.stats()["peers"] == 1
    assert c.on_presence(keys.presence_key("testfleet", "a"), False, now=1).events == [PeerDown("zenoh", "a")]
    assert c.peers() == [] and c.last_version("a") == 0
    # A restarted robot counts from 1 again and is heard.
    c.on_presence(keys.presence_key("testfleet", "a"), True, now=2)
    assert versions(c.on_update(*upd(zk, "a", 1), now=2)) == [1]


def test_max_peers_bounds_state(zk) -> None:
    c = core(max_peers=2)
    for name in ("a", "c", "d"):
        c.on_update(*upd(zk, name, 1), now=0)
    assert c.counters.updates_rx == 2 and c.counters.dropped == 1


def test_acks_become_delivered_only_for_offered_versions(zk) -> None:
    c = core(robot="a", signed=True)
    c.offered(zk.envelope("a", 5))
    good = pack_ack(5, identity=IDS["b"], fleet="testfleet", peer="b", robot="a")
    step = c.on_ack(keys.ack_key("testfleet", "b", "a"), good)
    assert step.events == [Delivered("zenoh", "b", "a", 5)]
    assert (
        c.on_ack(
            keys.ack_key("testfleet", "b", "a"),
            pack_ack(6, identity=IDS["b"], fleet="testfleet", peer="b", robot="a"),
        ).events
        == []
    )
    assert (
        c.on_ack(
            keys.ack_key("testfleet", "b", "a"),
            pack_ack(5, identity=Identity.generate("b"), fleet="testfleet", peer="b", robot="a"),
        ).events
        == []
    )
    assert c.counters.bad_signature == 1 and c.counters.dropped == 1 and c.counters.acks_rx == 1
    # Our own ack, as built for publishing, parses back at the robot it is for.
    k, payload = core(robot="b", signed=True).ack("a", 5)
    assert c.on_ack(k, payload).events == [Delivered("zenoh", "b", "a", 5)]


def test_acks_under_made_up_names_stop_at_max_peers(zk) -> None:
    # Unsigned, anyone can ack under any name: each Delivered became a row the publisher and
    # state.json kept for ever (100,000 names: 22 MB and a 1.8 MB state.json rewritten per ack).
    c = core(robot="a", max_peers=4)
    c.offered(zk.envelope("a", 5))
    delivered = []
    for i in range(100):
        name = f"ghost{i}"
        step = c.on_ack(
            keys.ack_key("testfleet", name, "a"),
            pack_ack(5, identity=None, fleet="testfleet", peer=name, robot="a"),
        )
        delivered += [e.peer for e in step.events if isinstance(e, Delivered)]
    assert delivered == [f"ghost{i}" for i in range(4)]
    assert c.counters.acks_rx == 4 and c.counters.dropped == 96


def test_queries_name_the_asker() -> None:
    c = core(robot="a")
    assert c.on_query("b", "1").events == [KeyframeNeeded("zenoh", "b", "a")]
    assert c.on_query(None).events == [] and c.on_query("a/*").events == []
    assert c.counters.queries_served == 3


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["a", "c"]),
            st.integers(1, 12),
            st.integers(0, 12),
            st.sampled_from(["update", "reply", "forget", "down"]),
        ),
        max_size=40,
    )
)
def test_never_a_delta_on_a_base_not_passed_on(zk, ops) -> None:
    """Whatever arrives, every emitted delta's base was emitted before (since the last forget),
    and each robot's emitted versions strictly increase."""
    c = core(base_window=3)
    emitted: dict[str, list[int]] = {"a": [], "c": []}
    for robot, v, base, kind in ops:
        if kind == "forget":
            c.request_keyframe(robot, now=0)
            emitted[robot] = []
            continue
        if kind == "down":
            c.on_presence(keys.presence_key("testfleet", robot), True, now=0)
            c.on_presence(keys.presence_key("testfleet", robot), False, now=0)
            emitted[robot] = []
            continue
        base = base if base < v else 0
        data = zk.envelope(robot, v, base).pack()
        step = (
            c.on_update(keys.update_key("testfleet", robot), data, 0)
            if kind == "update"
            else c.on_reply(robot, data, 0)
        )
        for e in step.events:
            if isinstance(e, Received):
                env = unpack(e.data)
                seen = emitted[robot]
                assert not seen or env.version > seen[-1]
                assert env.base_version == 0 or env.base_version in seen
                seen.append(env.version)
    # and not by passing nothing on: whatever came before, a newer keyframe goes through, and then
    # a delta on it
    for robot in ("a", "c"):
        c.on_presence(keys.presence_key("testfleet", robot), True, now=0)
        for v, base in ((100, 0), (101, 100)):
            step = c.on_update(keys.update_key("testfleet", robot), zk.envelope(robot, v, base).pack(), 0)
            got = [unpack(e.data) for e in step.events if isinstance(e, Received)]
            assert [(g.version, g.base_version) for g in got] == [(v, base)], (robot, v, step.events)


def test_ack_rtt_is_offer_to_ack_time_smoothed(zk) -> None:
    c = core(robot="a")
    assert c.stats()["rtt_ms"] is None
    k = keys.ack_key("testfleet", "b", "a")
    c.offered(zk.envelope("a", 1), now=10.0)
    c.on_ack(k, pack_ack(1, identity=None, fleet="testfleet", peer="b", robot="a"), now=10.4)
    assert c.stats()["rtt_ms"] == 400.0
    c.offered(zk.envelope("a", 2), now=20.0)
    c.on_ack(k, pack_ack(2, identity=None, fleet="testfleet", peer="b", robot="a"), now=20.8)
    assert c.stats()["rtt_ms"] == 450.0  # 7/8 of 400 + 1/8 of 800
    # an ack with no clock, or of a version whose offer time was forgotten, gives no sample
    for v in range(3, 3 + 20):
        c.offered(zk.envelope("a", v), now=30.0)
    c.on_ack(k, pack_ack(3, identity=None, fleet="testfleet", peer="b", robot="a"), now=99.0)
    c.on_ack(k, pack_ack(22, identity=None, fleet="testfleet", peer="b", robot="a"))
    assert c.stats()["rtt_ms"] == 450.0


def test_signed_fleet_waits_only_for_robots_that_showed_a_signed_message(zk) -> None:
    """64 fake liveliness tokens cut a fleet to one update per 30 s: the publisher waited for all."""
    c = core(robot="b", signed=True)
    for i in range(64):  # made-up robots: not on the roster, so no state at all
        assert c.on_presence(keys.presence_key("testfleet", f"ghost{i}"), True, now=0).events == []
    assert c.stats()["peers"] == 0 and c.counters.dropped == 64
    # a roster robot's token is presence, not proof: it is not waited for until it signs something
    assert c.on_presence(keys.presence_key("testfleet", "a"), True, now=0).events == [PeerUp("zenoh", "a")]
    c.on_presence(keys.presence_key("testfleet", "c"), True, now=0)
    assert c.peers() == []
    c.on_update(*upd(zk, "a", 1, signer=Identity.generate("a")), now=1)  # forged: still not proof
    assert c.peers() == []
    c.on_update(*upd(zk, "a", 1, signer=IDS["a"]), now=1)
    assert c.peers() == ["a"]
    c.offered(zk.envelope("b", 3))
    c.on_ack(
        keys.ack_key("testfleet", "c", "b"),
        pack_ack(3, identity=IDS["c"], fleet="testfleet", peer="c", robot="b"),
    )
    assert c.peers() == ["a", "c"]
    # an unsigned fleet lists every token, as before
    lax = core(robot="b")
    lax.on_presence(keys.presence_key("testfleet", "ghost"), True, now=0)
    assert lax.peers() == ["ghost"]
