"""The sans-I/O core over a simulated wire with a fake clock: delivery rules under faults."""

from __future__ import annotations

import os
import random
from collections import Counter
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import MapdError
from transports.uwb import arq, wire
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.faults import Faults
from transports.uwb.framing import decode_frame, encode_frame
from transports.uwb.receiving import CHUNK_COST
from transports.uwb.signing import Signer
from transports.uwb.sim import SimNet

RATE = 100_000.0  # fast emulated line: the rules do not depend on the rate


def ep(node: int, *, session: int | None = None, **kw: Any) -> ArqEndpoint:
    kw.setdefault("rate_bps", RATE)
    kw.setdefault("deadline_s", 30.0)
    cfg = ArqConfig(node_id=node, **kw)
    return ArqEndpoint(cfg, session=session if session is not None else 1000 + node, seed=node)


def kinds(events: list[arq.Event], cls: type) -> list[Any]:
    return [e for e in events if isinstance(e, cls)]


def closed(net: SimNet, node: int, msg: int) -> bool:
    return any(isinstance(e, arq.MessageClosed) and e.msg == msg for e in net.events[node])


def test_clean_unicast_delivers_once_intact_and_paced() -> None:
    a, b = ep(1), ep(2)
    net = SimNet([a, b])
    data = os.urandom(20_000)
    msg = a.send(data, 0.0, dests=[2])
    assert net.run(30, stop=lambda: closed(net, 1, msg))
    assert [r.data for r in net.received(2)] == [data]
    assert kinds(net.events[1], arq.MessageDelivered) == [arq.MessageDelivered(msg, 2)]
    assert kinds(net.events[1], arq.MessageClosed) == [arq.MessageClosed(msg, "delivered")]
    assert arq.PeerUp(2) in net.events[1] and arq.PeerUp(1) in net.events[2]
    assert a.stats()["resends"] == 0
    # Goodput close to the frame efficiency (197 payload bytes in 223 on the wire).
    assert 8 * len(data) / net.now >= 0.8 * RATE
    log = net.tx_log[1]
    for t, _ in log:
        assert sum(n for t2, n in log if t - 1.0 < t2 <= t) * 8 <= RATE


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(min_value=0, max_value=10_000),
    drop=st.floats(min_value=0, max_value=0.3),
    dup=st.floats(min_value=0, max_value=0.3),
    flip=st.floats(min_value=0, max_value=2e-3),
    reorder=st.floats(min_value=0, max_value=0.3),
    outage=st.one_of(st.none(), st.tuples(st.floats(0, 3), st.floats(0.1, 4))),
    sizes=st.lists(st.integers(min_value=0, max_value=6000), min_size=1, max_size=4),
    split=st.booleans(),
)
def test_every_message_delivered_exactly_once_intact_or_fails_by_deadline(
    seed: int,
    drop: float,
    dup: float,
    flip: float,
    reorder: float,
    outage: tuple[float, float] | None,
    sizes: list[int],
    split: bool,
) -> None:
    faults = Faults(drop=drop, dup=dup, flip=flip, reorder=reorder, outages=(outage,) if outage else ())
    a, b = ep(1, deadline_s=8.0), ep(2)
    net = SimNet([a, b], faults=faults, seed=seed, split=split)
    rng = random.Random(seed)
    sent: dict[int, bytes] = {}
    created: dict[int, float] = {}
    for stream, n in enumerate(sizes):  # distinct streams: nothing supersedes
        data = rng.randbytes(n)
        msg = a.send(data, net.now, dests=[2], stream=stream)
        sent[msg], created[msg] = data, net.now
        net.run(net.now + rng.uniform(0, 0.5))
    net.run(net.now + 10, stop=lambda: all(closed(net, 1, m) for m in sent))
    assert all(closed(net, 1, m) for m in sent), "a message neither delivered nor failed by its deadline"
    got = net.received(2)
    assert len({r.msg for r in got}) == len(got), "a message was delivered twice"
    for r in got:
        assert r.data == sent[r.msg]
    delivered = {e.msg for e in kinds(net.events[1], arq.MessageDelivered)}
    failed = kinds(net.events[1], arq.MessageFailed)
    assert delivered <= {r.msg for r in got}, "sender heard COMPLETE for a message the receiver lacks"
    assert delivered.isdisjoint(f.msg for f in failed)
    assert delivered | {f.msg for f in failed} == set(sent)
    assert all(f.reason == "deadline" for f in failed)
    assert a.in_flight() == 0
    if not faults.drop and not faults.flip and not outage and not faults.reorder:
        assert not failed


def test_latest_wins_supersedes_the_older_version() -> None:
    a, b = ep(1), ep(2)
    net = SimNet([a, b])
    old, new = os.urandom(30_000), os.urandom(5_000)
    m1 = a.send(old, 0.0, dests=[2], stream=4)
    net.run(0.5)
    m2 = a.send(new, net.now, dests=[2], stream=4)
    assert arq.MessageClosed(m1, "superseded") in a.events() + net.events[1]
    net.run(10, stop=lambda: closed(net, 1, m2))
    assert [r.data for r in net.received(2)] == [new]
    assert b.stats()["rx_held_bytes"] == 0
    # Only what went out before the new version, plus the new version itself, used the radio.
    assert a.stats()["bytes_tx"] < 0.5 * RATE / 8 + 1.3 * len(new) + 2000


def test_reaches_says_which_receivers_a_message_still_goes_to() -> None:
    # The uwb transport asks it when a robot comes into range: a map on its way to it needs no
    # second offer (the publisher's P6).
    a, b, c = ep(1), ep(2), ep(3)
    net = SimNet([a, b, c])
    msg = a.send(os.urandom(3000), 0.0, dests=[2, 3])
    assert a.reaches(msg, 2) and a.reaches(msg, 3)
    assert not a.reaches(msg, 4)  # not among its receivers
    assert not a.reaches(msg + 1, 2)  # no such message
    assert net.run(30, stop=lambda: closed(net, 1, msg))
    assert not a.reaches(msg, 2)  # delivered: nothing more goes to it
    old = a.send(os.urandom(3000), net.now, dests=[2])
    a.send(os.urandom(100), net.now, dests=[2])  # the same stream: latest wins
    assert not a.reaches(old, 2)


def _tap(net: SimNet, node: int) -> list[bytes]:
    """Record every frame ``node`` writes."""
    frames: list[bytes] = []
    orig = net._transmit

    def tap(src: int, frame: bytes, rate: float) -> None:
        if src == node:
            frames.append(frame)
        orig(src, frame, rate)

    net._transmit = tap  # type: ignore[method-assign]
    return frames


def _data(frames: list[bytes]) -> list[wire.Data]:
    """The DATA (and DGRAM) frames among ``frames`` (unsigned wire bytes, each with its delimiter)."""
    parsed = [wire.parse(decode_frame(f[:-1])) for f in frames]
    return [p for p in parsed if isinstance(p, wire.Data)]


def _data_indices(frames: list[bytes]) -> list[int]:
    return [d.index for d in _data(frames)]


def test_outage_resumes_from_what_the_receiver_holds() -> None:
    a, b = ep(1, deadline_s=120), ep(2)
    net = SimNet([a, b], faults=Faults(outages=((1.0, 20.0),)))
    frames = _tap(net, 1)
    data = os.urandom(25_000)
    msg = a.send(data, 0.0, dests=[2])
    net.run(1.0)
    held = set(b._peers[1].partials[msg].chunks)
    progress = a._out[msg].peers[2]
    known = {i for i in held if progress.acked[i]}  # held, and the sender heard so before the cut
    assert len(held) > 30 and len(known) >= len(held) - 2
    assert net.run(60, stop=lambda: closed(net, 1, msg))
    assert [r.data for r in net.received(2)] == [data]
    sends = Counter(_data_indices(frames))
    # A chunk whose ack the outage swallowed is the timer's probe; one acked before it never goes again.
    assert all(sends[i] == 1 for i in known), "a chunk the receiver had acked was sent again"
    assert a.stats()["timeouts"] >= 3  # it kept probing through the outage, backing off
    assert 21.0 < net.now < 30.0  # and resumed promptly once the line was back


def _data_streams(frames: list[bytes]) -> list[int]:
    return [d.stream for d in _data(frames)]


def test_a_background_message_yields_to_maps() -> None:
    # A pose queued after a map goes out only once the map has no chunk left to send, and a pose
    # queued while a map is in flight never takes one of its frames (latest wins between poses).
    a, b = ep(1, rate_bps=12_500), ep(2, rate_bps=12_500)
    net = SimNet([a, b], rate_bps=12_500)
    frames = _tap(net, 1)
    pose1 = a.send(b"p" * 100, 0.0, dests=[2], stream=254, background=True)
    big = a.send(os.urandom(8_000), 0.0, dests=[2], stream=0)
    pose2 = a.send(b"q" * 100, 0.0, dests=[2], stream=254, background=True)
    assert net.run(30, stop=lambda: closed(net, 1, big) and closed(net, 1, pose2))
    streams = _data_streams(frames)
    assert streams.index(254) > max(i for i, s in enumerate(streams) if s == 0)  # after every map chunk
    assert streams.count(254) == 1  # pose1 was superseded by pose2 before it got a frame
    assert [(r.stream, r.data) for r in net.received(2)] == [(0, net.received(2)[0].data), (254, b"q" * 100)]
    assert closed(net, 1, pose1)


def test_a_reliable_message_says_once_when_every_chunk_has_been_on_the_air() -> None:
    # The publisher holds an offer on a paced link until then (P1): MessageFlushed comes once, when
    # the last new chunk went, before any delivery, however many repairs follow; never for DGRAMs.
    a, b, c = ep(1), ep(2), ep(3)
    net = SimNet([a, b, c], shared=True, faults=Faults(drop=0.2), seed=3)
    net.run(6.0)
    frames = _tap(net, 1)
    msg = a.send(os.urandom(3_000), net.now, dests=[2, 3])
    assert net.run(net.now + 30, stop=lambda: closed(net, 1, msg))
    order = [type(e) for e in net.events[1] if getattr(e, "msg", None) == msg]
    assert order.count(arq.MessageFlushed) == 1
    assert order.index(arq.MessageFlushed) < order.index(arq.MessageDelivered)
    data = [wire.parse(decode_frame(f[:-1])) for f in frames]
    chunks = [d for d in data if isinstance(d, wire.Data) and d.msg == msg]
    assert len(chunks) > chunks[0].count  # repairs went after the flush and said nothing more
    dgram = a.send(os.urandom(500), net.now, dests=[2, 3], stream=254, reliable=False)
    assert net.run(net.now + 5, stop=lambda: closed(net, 1, dgram))
    assert not [e for e in net.events[1] if isinstance(e, arq.MessageFlushed) and e.msg == dgram]


def test_an_unreliable_message_goes_once_and_costs_the_receiver_no_ack() -> None:
    a, b, c = ep(1), ep(2), ep(3)
    net = SimNet([a, b, c], shared=True)
    net.run(6.0)  # HELLOs: everyone knows everyone
    acks_before = b.stats()["acks_tx"] + c.stats()["acks_tx"]
    frames = _tap(net, 1)
    data = os.urandom(500)  # three DGRAM chunks, broadcast
    msg = a.send(data, net.now, dests=[2, 3], stream=254, reliable=False)
    assert net.run(net.now + 5, stop=lambda: closed(net, 1, msg))
    assert [e.outcome for e in net.events[1] if isinstance(e, arq.MessageClosed) and e.msg == msg] == ["sent"]
    net.run(net.now + 3)  # the last chunk is still on the air when the sender closes it
    assert [r.data for r in net.received(2)] == [data] and [r.data for r in net.received(3)] == [data]
    assert b.stats()["acks_tx"] + c.stats()["acks_tx"] == acks_before  # nobody acked
    kinds = [wire.parse(decode_frame(f[:-1])) for f in frames]
    sent = [k for k in kinds if isinstance(k, wire.Data)]
    assert len(sent) == 3 and not any(k.reliable for k in sent)  # each chunk once, as DGRAM
    assert not any(isinstance(e, arq.MessageDelivered) for e in net.events[1])


def test_receiver_restart_gets_a_clean_start() -> None:
    a, b = ep(1), ep(2, session=5)
    net = SimNet([a, b])
    data = os.urandom(30_000)
    msg = a.send(data, 0.0, dests=[2])
    net.run(1.0)
    assert not net.received(2)
    b2 = ep(2, session=6)  # same id, new session, nothing held
    net.replace(2, b2)
    assert net.run(30, stop=lambda: closed(net, 1, msg))
    assert arq.PeerRestarted(2) in net.events[1]
    assert [r.data for r in net.received(2)] == [data]
    assert kinds(net.events[1], arq.MessageDelivered) == [arq.MessageDelivered(msg, 2)]


def test_sender_restart_drops_the_stale_half_message() -> None:
    a, b = ep(1, session=7), ep(2)
    net = SimNet([a, b])
    a.send(os.urandom(30_000), 0.0, dests=[2], stream=0)
    net.run(1.0)
    assert b.stats()["rx_held_bytes"] > 0
    a2 = ep(1, session=8)
    net.replace(1, a2)
    data = os.urandom(3_000)
    msg = a2.send(data, net.now, dests=[2], stream=0)
    assert net.run(30, stop=lambda: closed(net, 1, msg))
    assert arq.PeerRestarted(1) in net.events[2]
    assert [r.data for r in net.received(2)] == [data]
    assert b.stats()["rx_held_bytes"] == 0


def test_absent_peer_fails_by_deadline() -> None:
    a = ep(1, deadline_s=5.0)
    net = SimNet([a])
    msg = a.send(os.urandom(3000), 0.0, dests=[9])
    net.run(20, stop=lambda: closed(net, 1, msg))
    assert kinds(net.events[1], arq.MessageFailed) == [arq.MessageFailed(msg, 9, "deadline")]
    assert 5.0 <= net.now <= 5.01
    assert a.stats()["timeouts"] >= 2


def test_broadcast_needs_every_peer_and_a_dead_one_does_not_block_others() -> None:
    a, b, c = ep(1, deadline_s=10), ep(2), ep(3)
    net = SimNet([a, b, c, ep(4)], faults=Faults(drop=0.05), seed=3, shared=True)
    net.replace(4, None)  # intended but never there
    data = os.urandom(12_000)
    msg = a.send(data, 0.0, dests=[2, 3, 4])
    assert net.run(30, stop=lambda: closed(net, 1, msg))
    assert [r.data for r in net.received(2)] == [data]
    assert [r.data for r in net.received(3)] == [data]
    done = kinds(net.events[1], arq.MessageDelivered)
    assert sorted(e.peer for e in done) == [2, 3]
    assert kinds(net.events[1], arq.MessageFailed) == [arq.MessageFailed(msg, 4, "deadline")]
    assert kinds(net.events[1], arq.MessageClosed) == [arq.MessageClosed(msg, "failed")]


def test_broadcast_closes_only_when_all_acked() -> None:
    nodes = [ep(i) for i in (1, 2, 3, 4)]
    net = SimNet(nodes, faults=Faults(drop=0.1, flip=1e-4), seed=11, shared=True)
    data = os.urandom(8_000)
    msg = nodes[0].send(data, 0.0, dests=[2, 3, 4])
    assert net.run(30, stop=lambda: closed(net, 1, msg))
    closes = [i for i, e in enumerate(net.events[1]) if isinstance(e, arq.MessageClosed)]
    delivers = [i for i, e in enumerate(net.events[1]) if isinstance(e, arq.MessageDelivered)]
    assert len(delivers) == 3 and max(delivers) < closes[0]
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    for n in (2, 3, 4):
        assert [r.data for r in net.received(n)] == [data]


def test_oversized_message_is_refused_not_retried() -> None:
    a, b = ep(1, max_message_bytes=100_000), ep(2, max_message_bytes=2048)
    net = SimNet([a, b])
    msg = a.send(os.urandom(10_000), 0.0, dests=[2])
    assert net.run(10, stop=lambda: closed(net, 1, msg))
    (f,) = kinds(net.events[1], arq.MessageFailed)
    assert f.peer == 2 and "refused" in f.reason
    assert f.final  # the same message would be refused again: not worth offering twice
    assert net.now < 1.0
    assert b.stats()["rejected"] == 1 and b.stats()["rx_held_bytes"] == 0


def test_tdma_nodes_send_only_in_their_slots() -> None:
    nodes = [ep(i, mac="tdma", slots=3, slot_index=i - 1, slot_s=0.05, guard_s=0.005) for i in (1, 2, 3)]
    net = SimNet(nodes, shared=True)
    data = os.urandom(4000)
    msg = nodes[0].send(data, 0.0, dests=[2, 3])
    assert net.run(20, stop=lambda: closed(net, 1, msg))
    assert [r.data for r in net.received(3)] == [data]
    for i in (1, 2, 3):
        for t, n in net.tx_log[i]:
            phase = t % 0.15
            start = (i - 1) * 0.05
            assert start - 1e-6 <= phase and phase + n * 8 / RATE <= start + 0.045 + 1e-6


def _raw(src: int, frame: wire.Frame) -> bytes:
    return encode_frame(wire.pack(frame))


def test_one_byte_chunks_hold_no_more_memory_than_the_budget_says() -> None:
    # A chunk's dict entry and bytes object take some 100 bytes whatever its length: counted by
    # payload bytes alone, a forger's 1-byte chunks held 72 times the budget in memory.
    b = ep(2, max_message_bytes=20_000, max_partials_per_peer=4)
    budget = b._rx_budget
    for msg in range(4):
        for index in range(10_000):  # 1-byte chunks of a 20,000-byte message: consistent lengths
            b.receive_data(_raw(7, wire.Data(7, 2, 77, msg, 0, index, 20_000, 20_000, b"x")), 0.0)
    held = [p for peer in b._peers.values() for p in peer.partials.values()]
    entries = sum(len(p.chunks) for p in held)
    payload = sum(p.held for p in held)
    # What the chunks take in memory (their bytes and about CHUNK_COST each) stays within the budget.
    assert payload + CHUNK_COST * entries <= budget and b.stats()["rx_held_bytes"] <= budget
    assert entries >= budget // (CHUNK_COST + 1) - 1  # the budget is used, not refused outright


def test_hostile_frames_are_counted_and_bounded() -> None:
    b = ep(2, max_message_bytes=50_000, max_partials_per_peer=3)
    now = 0.0
    b.receive_data(os.urandom(5000), now)  # noise
    b.receive_data(b"\x01" * 100_000, now)  # endless bytes, no delimiter
    b.receive_data(b"\x00", now)
    # Valid CRC, absurd fields.
    b.receive_data(encode_frame(wire.pack(wire.Data(1, 2, 9, 1, 0, 0, 1, 5, b"x"))[:-1]), now)
    b.receive_data(encode_frame(b"\x21\x01\x02" + bytes(20)), now)  # index 0 of count 0
    # A forger opens many messages of 50 KB and sends one chunk each: memory stays bounded.
    for msg in range(200):
        d = wire.Data(7, 2, 77, msg, msg % 256, 0, 250, 50_000, os.urandom(190))
        b.receive_data(_raw(7, d), now)
    # A message over the limit is refused.
    b.receive_data(_raw(8, wire.Data(8, 2, 88, 5, 0, 0, 60_000, wire.MAX_TOTAL, b"x" * 100)), now)
    # A flood of acks for messages nobody sent.
    for msg in range(500):
        b.receive_data(_raw(9, wire.Ack(9, 2, 99, b.session, msg, 0, 0, 3, b"\xff")), now)
    s = b.stats()
    assert s["bad_frames"] >= 2
    assert s["oversize"] >= 1
    assert s["unknown_acks"] == 500
    assert s["rejected"] == 1
    assert s["rx_held_bytes"] <= 3 * (190 + CHUNK_COST)  # three partials of one chunk each
    assert len(b._peers[7].partials) <= 3
    assert len(b._peers[7].acks_due) <= 16
    # ...and a real peer still gets through afterwards.
    a = ep(1)
    net = SimNet([a, b])
    net.now = 1.0
    data = os.urandom(10_000)
    msg = a.send(data, net.now, dests=[2])
    assert net.run(20, stop=lambda: closed(net, 1, msg))
    assert [r.data for r in net.received(2)] == [data]


def test_hash_mismatch_is_never_delivered() -> None:
    b = ep(2)
    payload = os.urandom(100) + b"\x00" * 16  # a wrong hash trailer
    b.receive_data(_raw(1, wire.Data(1, 2, 5, 3, 0, 0, 1, len(payload), payload)), 0.0)
    assert b.stats()["hash_errors"] == 1
    assert not [e for e in b.events() if isinstance(e, arq.MessageReceived)]


def test_duplicate_after_completion_is_acked_not_redelivered() -> None:
    a, b = ep(1), ep(2)
    net = SimNet([a, b])
    frames = _tap(net, 1)
    msg = a.send(os.urandom(3000), 0.0, dests=[2])
    assert net.run(10, stop=lambda: closed(net, 1, msg))
    for f in frames:  # replay the whole exchange
        b.receive_data(f, net.now)
    assert len(net.received(2)) == 1 and not kinds(b.events(), arq.MessageReceived)
    assert b.stats()["duplicates"] >= len(frames) - 2


KEY = os.urandom(32)


def test_signed_link_drops_unsigned_forged_and_replayed_frames() -> None:
    a, b = ep(1, key=KEY), ep(2, key=KEY)
    for e in (a, b):
        e.confirm_counter(e.counter_reservation() or 0)
    intruder, forger = ep(3), ep(4, key=os.urandom(32))
    forger.confirm_counter(forger.counter_reservation() or 0)
    net = SimNet([a, b, intruder, forger], shared=True)
    frames = _tap(net, 1)
    data = os.urandom(5000)
    msg = a.send(data, 0.0, dests=[2])
    intruder.send(os.urandom(500), 0.0, dests=[2])
    forger.send(os.urandom(500), 0.0, dests=[2])
    assert net.run(10, stop=lambda: closed(net, 1, msg))
    assert [r.data for r in net.received(2)] == [data]
    s = b.stats()
    assert s["unsigned"] > 0 and s["bad_signature"] > 0
    assert arq.PeerUp(3) not in net.events[2] and arq.PeerUp(4) not in net.events[2]
    for f in frames:
        b.receive_data(f, net.now)
    assert b.stats()["replayed"] >= len(frames)
    assert len(net.received(2)) == 1 and not kinds(b.events(), arq.MessageReceived)


def test_signing_waits_for_persisted_counter() -> None:
    a = ep(1, key=KEY, counter_start=500)
    assert a.data_to_send(0.0) == b""
    upto = a.counter_reservation()
    assert upto is not None and upto > 500
    a.confirm_counter(upto)
    assert a.data_to_send(0.0) != b""


def test_silent_peer_goes_down_and_comes_back_up() -> None:
    a, b = ep(1, peer_timeout_s=3.0, beacon_s=1.0), ep(2, beacon_s=1.0)
    net = SimNet([a, b])
    net.run(2.0)
    assert net.events[1] == [arq.PeerUp(2)]
    net.replace(2, None)
    net.run(6.0)
    assert net.events[1] == [arq.PeerUp(2), arq.PeerDown(2)]
    net.replace(2, b)  # same session: it was only out of range
    net.run(9.0)
    assert net.events[1] == [arq.PeerUp(2), arq.PeerDown(2), arq.PeerUp(2)]
    assert a.peers_up() == [2]


@pytest.mark.parametrize("bad", [{"node_id": 0}, {"node_id": 255}, {"window": 0}, {"window": 257}])
def test_bad_config_is_a_value_error(bad: dict[str, int]) -> None:
    # A caller's mistake, not bytes breaking the protocol: no MapdError, so it is never counted.
    with pytest.raises(ValueError) as info:
        ArqConfig(**{"node_id": 1, **bad})
    assert not isinstance(info.value, MapdError)


def test_bad_send_arguments_are_value_errors() -> None:
    a = ep(1)
    with pytest.raises(ValueError, match="stream 256"):
        a.send(b"x", 0.0, dests=[2], stream=256)
    for dests in ([], [1], [0], [2, 255]):
        with pytest.raises(ValueError, match="no valid peer") as info:
            a.send(b"x", 0.0, dests=dests)
        assert not isinstance(info.value, MapdError)
    assert a.in_flight() == 0


def test_a_node_without_the_key_drops_signed_frames() -> None:
    # Signed frames carry no CRC (the tag is their check), so a node that cannot check the tag
    # cannot tell a signed frame from damage: it drops them, counted apart from damage.
    signer, b = Signer(KEY, 0), ep(2)
    signer.confirm(10)
    b.receive_data(encode_frame(signer.sign(wire.pack(wire.Hello(1, 255, 7), signed=True)), crc=False), 0.0)
    b.receive_data(encode_frame(bytes([wire.SIGNED]) + bytes(5)), 0.0)
    s = b.stats()
    # the real signed frame has no CRC, so to this node it is damage; a CRC'd one marked signed is counted apart
    assert s["crc_errors"] == 1 and s["signed_no_key"] == 1 and s["frames_rx"] == 0
    assert b.peers_up() == []


def test_a_tdma_peer_heard_once_a_cycle_is_not_taken_for_gone() -> None:
    """A TDMA robot speaks only in its own slot, once a cycle. With 36 slots of the default length
    at 12.5 kb/s the cycle (21 s) outgrew the 20 s peer timeout: every robot saw every other go down
    and up again each cycle, and each PeerDown freed the publisher to supersede the map on the air
    (P1), so 36 robots' maps stopped arriving (p95 staleness 2.2 -> 17.2 periods in the bench). A
    peer is down only when it was silent for beacon_s and two whole cycles, if that is longer."""
    rate = 12_500.0  # the UWB channel (this module's RATE is faster)
    slot, slots = 4 * 224 * 8 / rate + 0.01, 36  # the daemon's default slot: 0.583 s, cycle 21 s
    cfg: dict[str, Any] = {"mac": "tdma", "slots": slots, "slot_s": slot, "rate_bps": rate}
    cfg.update(beacon_s=5.0, peer_timeout_s=20.0)
    a, b = ep(1, slot_index=0, **cfg), ep(2, slot_index=1, **cfg)
    net = SimNet([a, b], shared=True)
    net.run(200.0)
    assert net.events[1] == [arq.PeerUp(2)] and net.events[2] == [arq.PeerUp(1)]
    net.replace(2, None)  # out of range for good: still found gone, within beacon_s + 2 cycles
    gone_by = net.now + 5.0 + 2 * slot * slots + 1.0
    net.run(gone_by)
    assert net.events[1] == [arq.PeerUp(2), arq.PeerDown(2)]
