"""Keyframe queries: only a signed, fresh query from a robot on the roster forces a keyframe."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import EnvelopeError, SignatureError
from mapd.identity import Identity, Roster
from transports import signed_requests
from transports.base import KeyframeNeeded
from transports.zenoh import answers, queries
from transports.zenoh.core import ZenohCore

IDS = {n: Identity.generate(n) for n in ("a", "b")}
ROSTER = Roster({n: i.public_key for n, i in IDS.items()})
NEEDED = [KeyframeNeeded("zenoh", "b", "a")]


def core(signed: bool = True) -> ZenohCore:
    return ZenohCore(
        robot="a",
        fleet="testfleet",
        identity=IDS["a"] if signed else None,
        roster=ROSTER if signed else Roster.open(),
        max_message_bytes=1 << 20,
    )


def asked(c: ZenohCore, params: str):  # type: ignore[no-untyped-def]
    """Feed ``c`` a query with these selector parameters, parsed as zenoh's Parameters does."""
    p = dict(kv.split("=", 1) for kv in params.split(";"))
    return c.on_query(p.get("from"), p.get("n"), p.get("sig")).events


def test_the_asker_signs_its_query_and_the_robot_asked_checks_it() -> None:
    b, a = (
        ZenohCore(robot="b", fleet="testfleet", identity=IDS["b"], roster=ROSTER, max_message_bytes=1),
        core(),
    )
    params = b.query_parameters("a", wall_ns=1_000)
    assert params.startswith("from=b;n=1000;sig=") and len(params.split("sig=")[1]) == 128
    assert asked(a, params) == NEEDED
    # Played back, the same query is answered (by the adapter) but forces nothing.
    assert asked(a, params) == []
    assert a.counters.replayed == 1
    # The next query is fresh even when the asker's clock stepped back.
    assert asked(a, b.query_parameters("a", wall_ns=5)) == NEEDED
    assert a.counters.queries_served == 3 and a.counters.bad_signature == 0


def test_a_query_in_another_robots_name_is_refused() -> None:
    a = core()
    forged = queries.parameters(IDS["a"], fleet="testfleet", asker="a", robot="a", nonce=7).replace(
        "from=a", "from=b"
    )
    assert asked(a, forged) == []  # b's name, a's key
    with pytest.raises(SignatureError, match="bad signature on keyframe query from 'b'"):
        queries.verify(
            ROSTER, fleet="testfleet", asker="b", robot="a", nonce="7", sig=forged.split("sig=")[1]
        )
    assert asked(a, "from=b;n=8") == []  # unsigned where the fleet signs
    other = Identity.generate("b")  # a key named b that is not on the roster
    assert asked(a, queries.parameters(other, fleet="testfleet", asker="b", robot="a", nonce=9)) == []
    # Signed for another robot, or another fleet: the signature covers both.
    for fleet, robot in (("testfleet", "c"), ("otherfleet", "a")):
        signed = queries.parameters(IDS["b"], fleet=fleet, asker="b", robot=robot, nonce=10)
        assert asked(a, signed) == []
    assert a.counters.bad_signature == 5 and a.counters.replayed == 0
    # None of these moved b's nonce on: b's own query with a lower nonce is still heeded.
    assert asked(a, queries.parameters(IDS["b"], fleet="testfleet", asker="b", robot="a", nonce=2)) == NEEDED


def test_a_query_with_no_valid_nonce_is_dropped_not_heeded() -> None:
    a = core()
    for n in ("", "x", "-1", "0", str(1 << 63), "١٢", "9" * 40):
        assert asked(a, f"from=b;n={n}") == []
    assert a.counters.dropped == 7 and a.counters.bad_signature == 0


def test_an_unsigned_fleet_heeds_unsigned_queries_once_each() -> None:
    a = core(signed=False)
    params = ZenohCore(
        robot="b", fleet="testfleet", identity=None, roster=Roster.open(), max_message_bytes=1
    ).query_parameters("a", 3)
    assert params == "from=b;n=3"
    assert asked(a, params) == NEEDED and asked(a, params) == []


def test_nonces_always_grow() -> None:
    clock = signed_requests.NonceClock()
    got = [clock.next(t) for t in (10, 10, 3, 50, 0, 1 << 70)]
    assert got == [10, 11, 12, 50, 51, (1 << 63) - 1]
    with pytest.raises(ValueError):
        queries.parameters(None, fleet="f", asker="b", robot="a", nonce=0)
    with pytest.raises(ValueError):
        queries.parameters(IDS["a"], fleet="f", asker="b", robot="a", nonce=1)


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.none(), st.text(max_size=30)), st.one_of(st.none(), st.text(max_size=140)))
def test_the_query_check_takes_any_parameters(nonce: str | None, sig: str | None) -> None:
    try:
        n = queries.verify(ROSTER, fleet="f", asker="b", robot="a", nonce=nonce, sig=sig)
    except EnvelopeError as exc:  # SignatureError is one
        assert "\n" not in str(exc)
    else:
        raise AssertionError(f"a query with n={nonce!r} sig={sig!r} verified ({n})")


def test_answers_are_rationed_a_burst_then_a_steady_rate() -> None:
    a = core()
    assert all(a.may_reply(now=100.0) for _ in range(answers.REPLY_BURST))
    assert not a.may_reply(now=100.0)  # the burst is spent
    assert a.may_reply(now=100.0 + 1.0 / answers.REPLY_RATE_HZ)  # one more after its share of a second
    assert not a.may_reply(now=100.0 + 1.0 / answers.REPLY_RATE_HZ)
    assert not a.may_reply(now=1000.0, slot_free=False)  # the adapter has no room for another
    assert sum(a.may_reply(now=1000.0) for _ in range(100)) == answers.REPLY_BURST  # refilled, capped
    assert a.counters.queries_shed == 2 + 1 + 100 - answers.REPLY_BURST
    assert not a.may_reply(now=5.0)  # a clock that steps back refills nothing
