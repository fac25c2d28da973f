"""The relay core's decisions (transports/uwb/forwarding.py): forward when a neighbour lacks a map
and does not hear its origin, not when it hears it, suppression, backoff and the rate bound."""

from __future__ import annotations

import pytest

from transports.uwb.forwarding import ForwardingCore, Summary, pack_summary, unpack_summary

A, B, C, D = 1, 2, 3, 4
KF = b"signed keyframe of A v3"


def _core(me: int = B) -> ForwardingCore:
    core = ForwardingCore(me, relay_period_s=10.0, retry_s=30.0)
    core.on_held(A, 3, KF)
    return core


def test_summary_round_trip_and_malformed() -> None:
    s = Summary({1: 7, 9: 2**32 - 1}, frozenset({2, 3}))
    assert unpack_summary(pack_summary(s)) == s
    with pytest.raises(ValueError):
        unpack_summary(pack_summary(s)[:-1])
    with pytest.raises(ValueError):
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
    core.on_held(D, 5, b"kf D")
    core.on_summary(C, Summary({}, frozenset({B})), 0.0)
    first = core.next_forward(0.0)
    assert first is not None and core.next_forward(0.0) is None  # one in flight
    core.relay_done()
    assert core.next_forward(5.0) is None and core.next_deadline() == 10.0  # one per relay_period_s
    second = core.next_forward(10.0)
    assert second is not None and second.origin != first.origin
    core.relay_done()
    assert core.next_forward(25.0) is None  # both forwarded: nothing until retry_s or a new version


def test_prefers_the_map_missing_at_most_neighbours_and_only_keeps_the_newest() -> None:
    core = _core()
    core.on_held(A, 2, b"older")  # not newer: ignored
    core.on_held(D, 5, b"kf D")
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
