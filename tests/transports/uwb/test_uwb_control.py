"""Keyframe requests over UWB: the control message and its throttle (the serial test is in test_uwb_serial)."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.commands.status_text import render_status
from mapd.errors import ProtocolError
from mapd.identity import Identity, Roster
from transports.base import KeyframeNeeded, TransportContext
from transports.uwb import arq
from transports.uwb import keyframe_requests as control
from transports.uwb.transport import UwbOptions, UwbTransport


def test_request_round_trips_sorted_and_deduplicated() -> None:
    data = control.pack_request(["robot1", "robot0", "robot1"], nonce=7, sig=bytes(range(64)))
    assert data.startswith(control.MAGIC)
    assert control.parse_request(data) == control.Request(["robot0", "robot1"], 7, bytes(range(64)))
    assert control.parse_request(control.pack_request(["r"], nonce=3)) == control.Request(["r"], 3, b"")
    # A node from before signatures sends version 1: read, with neither nonce nor signature.
    assert control.parse_request(b"MKFR\x01robot0\nrobot1") == control.Request(["robot0", "robot1"])
    with pytest.raises(ValueError):
        control.pack_request([], nonce=1)
    with pytest.raises(ValueError):
        control.pack_request(["r"], nonce=1, sig=b"short")


def test_request_too_large_to_build_is_a_value_error() -> None:
    # Too many names is the caller's problem (nothing was on a link), not a protocol fault.
    with pytest.raises(ValueError, match="over 1024") as info:
        control.pack_request([f"robot{i:04d}" for i in range(200)], nonce=1)
    assert not isinstance(info.value, ProtocolError)


def _transport_with_stub_link(sent: list[bytes]) -> UwbTransport:
    ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    t = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2}), ctx)
    t._link = SimpleNamespace(  # type: ignore[assignment]
        core=SimpleNamespace(peers_up=lambda: [2]),
        send=lambda data, dests, stream: sent.append(data),
        stats=dict,
    )
    return t


def test_transport_drops_a_request_too_large_to_build() -> None:
    sent: list[bytes] = []
    t = _transport_with_stub_link(sent)
    asyncio.run(t.request_keyframe("b"))
    assert control.parse_request(sent[0]).robots == ["b"] and t.stats()["keyframe_requests_tx"] == 1
    t = _transport_with_stub_link(sent)
    asyncio.run(t.request_keyframe("x" * 2000))  # logged and dropped, never raised
    assert len(sent) == 1 and t.stats()["keyframe_requests_tx"] == 0


def test_a_robot_that_comes_into_range_arrives_unless_the_map_in_flight_goes_to_it() -> None:
    """P6: the publisher offers the newest map to a robot that comes into range (a late joiner, or one
    back from out of range), but only when the transport says no map on its way reaches it (the link
    may send to every robot configured). The robot that comes is not asked for its map: it offers
    its own the same way (before P6 it was asked, and at a fleet's start every robot asked every
    other while their first maps were on the air to them)."""
    from transports import base
    from transports.uwb import arq

    events: list[object] = []
    ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=events.append)
    t = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2, "c": 3}), ctx)
    t._msgs = {7: ("a", 3)}  # own v3 in flight, still going to b only
    sent: list[bytes] = []
    t._link = SimpleNamespace(  # type: ignore[assignment]
        core=SimpleNamespace(reaches=lambda m, p: (m, p) == (7, 2)),
        send=lambda data, dests, stream: sent.append(data),
        stats=dict,
    )
    t._on_event(arq.PeerUp(2))
    t._on_event(arq.PeerUp(3))
    t._on_event(arq.PeerUp(9))  # a link id of no robot in nodes: nothing to offer it
    assert events == [
        base.PeerUp("uwb", "b"),
        base.PeerUp("uwb", "c"),
        base.Arrived("uwb", "c"),
        base.PeerUp("uwb", "uwb-9"),
    ]
    assert not sent and t.stats()["keyframe_requests_tx"] == 0


def test_an_offer_that_goes_to_nobody_is_on_the_air_at_once() -> None:
    """The publisher holds an offer on uwb until it is wholly on the air (P1); an offer that sends
    nothing, to no peer or over the size limit, must not hold it four timeouts for a word that
    never comes."""
    from mapd.envelope import Envelope
    from mapd.errors import LimitError
    from mapd.grid import Pose2D
    from transports.base import Failed, OnAir

    env = Envelope(
        fleet="f", robot="a", version=3, base_version=0, codec="lossless", width=1, height=1,
        resolution=0.05, origin=Pose2D(0.0, 0.0, 0.0), payload=b"x",
    )  # fmt: skip
    events: list[object] = []
    ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=events.append)
    t = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2}, send_to="heard"), ctx)
    t._link = SimpleNamespace(core=SimpleNamespace(peers_up=lambda: []))  # type: ignore[assignment]
    t.offer(env)  # b is not heard: no message
    assert events == [OnAir("uwb", "a", 3)]

    def too_large(data: bytes, dests: list[int], stream: int) -> int:
        raise LimitError("uwb: message over the limit")

    events.clear()
    t._link = SimpleNamespace(core=SimpleNamespace(peers_up=lambda: [2]), send=too_large)  # type: ignore[assignment]
    t.offer(env)
    assert events == [
        Failed("uwb", "b", "a", 3, "uwb: message over the limit", again=False),
        OnAir("uwb", "a", 3),
    ]


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"MKFR",
        b"MKFR\x01",
        b"MKFR\x02robot0",
        b"XKFR\x01robot0",
        b"MKFR\x01robot0\n",
        b"MKFR\x01\xff\xfe",
        b"MKFR\x01" + b"a" * 2000,
        control.pack_request(["r"], nonce=1)[:-1],  # no name left
        control.pack_request(["r"], nonce=1, sig=bytes(64))[:-2],  # cut inside the signature
        b"MKFR\x02" + bytes(8) + b"\x05abcde" + b"robot0",  # a signature of 5 bytes
        b"MKFR\x03" + bytes(9) + b"robot0",
    ],
)
def test_bad_control_messages_raise_protocol_error(data: bytes) -> None:
    with pytest.raises(ProtocolError):
        control.parse_request(data)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=1100))
def test_fuzz_parse_only_returns_names_or_raises_protocol_error(data: bytes) -> None:
    try:
        req = control.parse_request(data)
    except ProtocolError:
        return
    assert req.robots and all(isinstance(n, str) and n for n in req.robots)
    assert len(req.sig) in (0, 64) and (req.nonce is None) == (data[4] == 1)


def test_throttle_names_every_robot_still_wanted() -> None:
    r = control.KeyframeRequests(hold_s=5.0)
    assert r.want("a", 0.0) == ["a"]
    assert r.want("a", 1.0) is None  # throttled: one request per robot per hold_s
    assert r.want("b", 2.0) == ["a", "b"]  # supersedes the first message, so it names both
    assert r.want("a", 5.5) == ["a", "b"]
    assert r.want("c", 11.0) == ["c"]  # a and b expired


# --- who may ask: signed, fresh requests (a holder of the link key cannot speak for another robot) --

IDS = {n: Identity.generate(n) for n in ("a", "b", "c")}
ROSTER = Roster({n: i.public_key for n, i in IDS.items()})
NODES = {"a": 1, "b": 2, "c": 3}


def _asked_robot(roster: Roster = ROSTER) -> tuple[UwbTransport, list[object]]:
    """Robot a's transport, signed fleet by default, taking control messages off the link."""
    events: list[object] = []
    ctx = TransportContext("a", "f", 1 << 20, events.append, identity=IDS["a"], roster=roster)
    return UwbTransport(UwbOptions(nodes=NODES), ctx), events


def _request_of(asker: str, *, signed: bool, nonce: int, fleet: str = "f") -> bytes:
    """The request ``asker``'s transport sends asking a (its link stubbed), signed or not."""
    sent: list[bytes] = []
    ctx = TransportContext(
        asker, fleet, 1 << 20, lambda e: None,
        identity=IDS[asker] if signed else None, roster=ROSTER if signed else Roster.open(),
    )  # fmt: skip
    t = UwbTransport(UwbOptions(nodes=NODES), ctx)
    t._link = SimpleNamespace(  # type: ignore[assignment]
        core=SimpleNamespace(peers_up=lambda: [1]),
        send=lambda data, dests, stream: sent.append(data),
        stats=dict,
    )
    t._nonces = SimpleNamespace(next=lambda wall_ns: nonce)  # type: ignore[assignment]
    asyncio.run(t.request_keyframe("a"))
    assert len(sent) == 1, "the request was not sent"
    return sent[0]


def _feed(t: UwbTransport, src: str, data: bytes) -> None:
    t._on_event(arq.MessageReceived(NODES[src], control.CONTROL_STREAM, 1, data))


def test_a_signed_request_is_heeded_once_and_a_replay_is_not() -> None:
    t, events = _asked_robot()
    req = _request_of("b", signed=True, nonce=7 * 10**17)
    assert len(control.parse_request(req).sig) == 64
    _feed(t, "b", req)
    assert events == [KeyframeNeeded("uwb", "b", "a")]
    _feed(t, "b", req)  # recorded and played back by a holder of the link key
    assert len(events) == 1 and t.stats()["keyframe_requests_replayed"] == 1
    _feed(t, "b", _request_of("b", signed=True, nonce=7 * 10**17 + 5))  # b's next request
    assert len(events) == 2 and t.stats()["keyframe_requests_forged"] == 0


def test_a_request_not_signed_by_the_robot_its_link_id_names_is_not_heeded() -> None:
    t, events = _asked_robot()
    # c holds the link key and sends from b's link id, but can sign only as itself.
    _feed(t, "b", _request_of("c", signed=True, nonce=7 * 10**17))
    _feed(t, "b", _request_of("b", signed=False, nonce=7 * 10**17))
    _feed(t, "b", b"MKFR\x01a")  # version 1: no signature at all
    _feed(t, "c", _request_of("c", signed=True, nonce=7 * 10**17, fleet="other"))  # another fleet's
    assert events == [] and t.stats()["keyframe_requests_forged"] == 4
    assert t.stats()["keyframe_requests_rx"] == 4
    # mapd status says so on a line of its own: the sender holds the fleet's link key.
    shown = render_status({"links": {"uwb": t.stats()}}).splitlines()
    assert any("FAULTS" in ln and "4 keyframe requests in another robot's name" in ln for ln in shown)
    # c's own, properly signed request still is heeded: the refusals cost c nothing.
    _feed(t, "c", _request_of("c", signed=True, nonce=7 * 10**17))
    assert events == [KeyframeNeeded("uwb", "c", "a")]


def test_a_fleet_that_allows_unsigned_messages_heeds_unsigned_requests() -> None:
    t, events = _asked_robot(Roster.open())
    _feed(t, "b", _request_of("b", signed=False, nonce=5))
    _feed(t, "c", b"MKFR\x01a")  # a node from before signatures
    assert events == [KeyframeNeeded("uwb", "b", "a"), KeyframeNeeded("uwb", "c", "a")]
    _feed(t, "b", _request_of("b", signed=False, nonce=5))  # still no replay
    assert len(events) == 2 and t.stats()["keyframe_requests_replayed"] == 1
