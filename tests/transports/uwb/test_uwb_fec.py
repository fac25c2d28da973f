"""Parity repair of broadcast maps (``fec.py``, R16 with ``fec``): one parity chunk serves every
receiver that lacks any chunk of its block, so lossy broadcasts cost what the worst receiver lacks."""

from __future__ import annotations

import asyncio
import os
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import MapdError
from transports.base import TransportContext
from transports.uwb import arq, arq_acks, fec, wire
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.faults import Faults
from transports.uwb.framing import encode_frame
from transports.uwb.sending import message_hash
from transports.uwb.sim import SimNet
from transports.uwb.transport import UwbOptions, UwbTransport

RATE = 100_000.0
RECEIVERS = list(range(2, 10))


def _closed(net: SimNet, node: int, msg: int) -> bool:
    return any(isinstance(e, arq.MessageClosed) and e.msg == msg for e in net.events[node])


def _broadcast(
    use_fec: bool, drop: float, seed: int, size: int = 20_000
) -> tuple[SimNet, list[ArqEndpoint], bytes]:
    nodes = [
        ArqEndpoint(
            ArqConfig(node_id=i, rate_bps=RATE, deadline_s=60.0, fec=use_fec), session=900 + i, seed=i
        )
        for i in range(1, 10)
    ]
    net = SimNet(nodes, faults=Faults(drop=drop), seed=seed, shared=True)
    net.run(6.0)
    data = os.urandom(size)
    msg = nodes[0].send(data, net.now, dests=RECEIVERS)
    assert net.run(net.now + 60, stop=lambda: _closed(net, 1, msg))
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    return net, nodes, data


# --- the code ------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(count=st.integers(min_value=1, max_value=700), seed=st.integers(min_value=0, max_value=2**16))
def test_any_chunks_lost_come_back_from_as_many_parity_chunks(count: int, seed: int) -> None:
    rng = random.Random(seed)
    size = 40
    chunks = [rng.randbytes(size) for _ in range(count - 1)] + [rng.randbytes(rng.randint(1, size))]
    for b in range(fec.blocks(count)):
        k = fec.block_size(count, b)
        members = list(range(b, count, fec.blocks(count)))
        lost = set(rng.sample(members, rng.randint(1, k)))
        have = {i: chunks[i] for i in members if i not in lost}
        shares = rng.sample(range(k, fec.SHARES), len(lost))  # any parity shares will do
        parity = dict(zip(shares, fec.encode_parity(fec.pad_block(chunks, count, b), shares), strict=True))
        got = fec.recover(count, b, have, parity)
        assert set(got) == lost
        for i in lost:
            assert got[i][: len(chunks[i])] == chunks[i]
        assert fec.recover(count, b, have, dict(list(parity.items())[:-1])) == {}  # one short: nothing


@given(count=st.integers(min_value=1, max_value=0xFFFF))
def test_parity_indices_say_their_block_and_stay_on_the_wire(count: int) -> None:
    nb, top = fec.blocks(count), fec.index_limit(count)
    assert top <= 0x10000
    assert fec.max_parity(count) >= min(128, (0x10000 - count) // nb)
    for b in {0, nb - 1}:
        for j in {0, fec.max_parity(count) - 1} if fec.max_parity(count) else ():  # none left: resends
            i = fec.parity_index(count, b, j)
            assert count <= i < top
            assert fec.parity_of(count, i) == (b, fec.block_size(count, b) + j)


def test_parity_frames_parse_and_indices_past_the_limit_are_refused() -> None:
    ok = wire.Data(1, wire.BROADCAST, 5, 9, 0, fec.parity_index(10, 0, 3), 10, 2_000, bytes(190))
    assert wire.parse(wire.pack(ok)) == ok
    for bad in (
        wire.Data(1, wire.BROADCAST, 5, 9, 0, fec.index_limit(10), 10, 2_000, bytes(190)),
        wire.Data(
            1, wire.BROADCAST, 5, 9, 0, 10, 10, 2_000, bytes(190), reliable=False
        ),  # no parity in DGRAMs
    ):
        with pytest.raises(MapdError):
            wire.parse(wire.pack(bad))


# --- the ARQ core ---------------------------------------------------------------------------------


@pytest.mark.parametrize("drop", [0.05, 0.2, 0.35])
def test_a_lossy_broadcast_is_repaired_with_parity_in_fewer_frames(drop: float) -> None:
    net, nodes, data = _broadcast(True, drop, seed=3)
    plain_net, plain_nodes, plain_data = _broadcast(False, drop, seed=3)
    for r in RECEIVERS:
        assert [m.data for m in net.received(r)] == [data]
        assert [m.data for m in plain_net.received(r)] == [plain_data]
    s, plain = nodes[0].stats(), plain_nodes[0].stats()
    assert s["parity_tx"] > 0 and plain["parity_tx"] == 0
    assert sum(n.stats()["recovered"] for n in nodes[1:]) > 0
    assert s["resends"] < plain["resends"]
    if drop >= 0.2:  # where several receivers lose different chunks, the union is most of the map
        assert s["data_tx"] < 0.8 * plain["data_tx"], (s["data_tx"], plain["data_tx"])


def _late_reports(drop: float, seed: int) -> tuple[float, dict[str, object]]:
    """Twelve 8 kB broadcasts to 8 receivers that report gaps late (a long backoff, as a TDMA turn
    would make them), after each message's first pass: how long all twelve took, and the sender's
    stats (the receivers' gap reports under ``nacks``)."""
    nodes = [
        ArqEndpoint(
            ArqConfig(node_id=i, rate_bps=RATE, deadline_s=60.0, fec=True, nack_backoff_s=1.5),
            session=900 + i,
            seed=i,
        )
        for i in range(1, 10)
    ]
    net = SimNet(nodes, faults=Faults(drop=drop), seed=seed, shared=True)
    net.run(6.0)
    start = net.now
    for k in range(12):
        msg = nodes[0].send(os.urandom(8_000), net.now, dests=RECEIVERS, stream=k % 3)
        assert net.run(net.now + 60, stop=lambda: _closed(net, 1, msg))  # noqa: B023 (run at once)
        assert arq.MessageClosed(msg, "delivered") in net.events[1]
    stats: dict[str, object] = dict(nodes[0].stats())
    stats["nacks"] = sum(n.stats()["nacks_tx"] for n in nodes[1:])
    return net.now - start, stats


def test_parity_goes_behind_the_first_pass_once_losses_are_seen_and_never_on_a_clean_channel(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On a lossy channel the sender learns to send parity behind each first pass, which spares
    the round trip of a repair: its maps get there sooner than in the same runs with that share held
    at 0. On a clean channel it sends no parity and the receivers no gap report. Summed over six
    seeds: one run is too few to show it (the test first said later maps of one run needed fewer
    gap reports than earlier ones, which held for its seed only; the reports themselves fall by
    about 5 % over sixteen seeds, too little to tell from one draw to the next)."""
    _, clean = _late_reports(0.0, 5)
    assert clean["nacks"] == 0 and clean["parity_tx"] == 0 and clean["fec_proactive"] == 0.0
    seeds = range(1, 7)
    learned = [_late_reports(0.2, seed) for seed in seeds]
    assert all(float(s["fec_proactive"]) > 0 for _, s in learned)  # type: ignore[arg-type]
    monkeypatch.setattr(arq_acks, "PROACTIVE_MAX", 0.0)
    without = [_late_reports(0.2, seed)[0] for seed in seeds]
    took = [round(t, 1) for t, _ in learned]
    assert sum(took) < 0.9 * sum(without), (took, [round(t, 1) for t in without])


def test_once_parity_is_seen_a_report_asking_for_as_many_chunks_suppresses_ours() -> None:
    """Our gaps are chunks 1 and 2 (3 is covered by the parity we hold); another receiver's report
    asks for 3 and 4, other chunks but as many of the block: the sender's parity answer serves us
    too, so our report is dropped. Without parity held, only a report asking for our very chunks
    would do (R16's rule before parity)."""
    count, size = 6, 100
    total = count * size

    def data(i: int) -> bytes:
        return _frame(wire.Data(1, wire.BROADCAST, 1001, 7, 0, i, count, total, bytes(size)))

    parity = _frame(
        wire.Data(1, wire.BROADCAST, 1001, 7, 0, fec.parity_index(count, 0, 0), count, total, bytes(size))
    )
    # holds 0, 1, 2 and 5: asks for 3 and 4
    other = encode_frame(wire.pack(wire.Ack(3, 1, 1003, 1001, 7, 1, 0, 3, b"\x02")))
    for with_parity in (True, False):
        rx = ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE), session=2, seed=2)
        rx.receive_data(data(0) + data(4) + data(5), 0.0)
        if with_parity:
            rx.receive_data(parity, 0.0)
            assert rx._peers[1].partials[7].gaps() == [1, 2]
        rx.receive_data(other, 0.01)
        assert rx.stats()["nacks_suppressed"] == (1 if with_parity else 0)


def _frame(d: wire.Data) -> bytes:
    return encode_frame(wire.pack(d))


def test_forged_parity_never_yields_a_wrong_map_and_useless_parity_is_not_held() -> None:
    """A forger with a valid CRC sends parity of the right length but wrong bytes, of the wrong
    length, and far more than a block lacks: the receiver delivers nothing wrong, holds no more
    parity than chunks missing, and still takes the true map when it comes whole."""
    rx = ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE), session=2, seed=2)
    count, size = 6, 100
    body = os.urandom(count * size - 16)
    data = body + message_hash(body)

    def chunk(i: int) -> wire.Data:
        return wire.Data(1, wire.BROADCAST, 1001, 7, 0, i, count, len(data), data[i * size : (i + 1) * size])

    for i in (0, 1, 2):
        rx.receive_data(_frame(chunk(i)), 0.0)
    part = rx._peers[1].partials[7]
    for j in range(50):  # wrong bytes, right length: more than the three chunks missing
        forged = wire.Data(
            1, wire.BROADCAST, 1001, 7, 0, fec.parity_index(count, 0, j), count, len(data), os.urandom(size)
        )
        rx.receive_data(_frame(forged), 0.1)
        assert part.parity_held <= 3 * size
    odd = wire.Data(1, wire.BROADCAST, 1001, 7, 0, fec.parity_index(count, 0, 60), count, len(data), bytes(7))
    rx.receive_data(_frame(odd), 0.2)
    assert not [e for e in rx.events() if isinstance(e, arq.MessageReceived)]  # nothing wrong delivered
    assert rx.stats()["hash_errors"] >= 1  # the forged parity rebuilt a block the hash refused
    for i in range(count):
        rx.receive_data(_frame(chunk(i)), 1.0)
    got = [e.data for e in rx.events() if isinstance(e, arq.MessageReceived)]
    assert got == [body]


@settings(max_examples=60, deadline=None)
@given(
    frames=st.lists(
        st.tuples(
            st.integers(0, 2),  # which message: 3, 6 or 130 chunks of 40 bytes
            st.integers(0, 600),  # index: data, parity, or past both
            st.sampled_from([40, 40, 40, 13, 60]),  # payload length: mostly a whole chunk
            st.integers(0, 255),  # payload byte
        ),
        max_size=150,
    )
)
def test_hostile_data_and_parity_never_raise_deliver_or_grow_memory(
    frames: list[tuple[int, int, int, int]],
) -> None:
    """A forger with a valid CRC sends DATA and parity chunks of three messages, at any index and
    of any length: the receiver never raises, delivers nothing (no hash can match), and holds no
    more than its budget, with its tally equal to what its partial messages hold."""
    rx = ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE, max_message_bytes=20_000), session=2, seed=2)
    for msg, index, length, byte in frames:
        count = (3, 6, 130)[msg]
        d = wire.Data(1, wire.BROADCAST, 1001, msg, 0, index, count, 40 * count, bytes([byte]) * length)
        rx.receive_data(_frame(d), 0.0)  # an index past the parity is refused as malformed
    assert not [e for e in rx.events() if isinstance(e, arq.MessageReceived)]
    held = sum(p.cost for peer in rx._peers.values() for p in peer.partials.values())
    assert rx._rx_held == held <= rx._rx_budget


def test_parity_for_a_unicast_message_is_refused() -> None:
    rx = ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE), session=2, seed=2)
    uni = wire.Data(1, 2, 1001, 7, 0, 0, 4, 400, bytes(100))
    rx.receive_data(_frame(uni), 0.0)
    par = wire.Data(1, 2, 1001, 7, 0, fec.parity_index(4, 0, 0), 4, 400, bytes(100))
    rx.receive_data(_frame(par), 0.0)
    assert rx.stats()["bad_frames"] == 1 and rx.stats()["parity_rx"] == 0


def test_fec_option_reaches_the_core() -> None:
    ctx = TransportContext(robot="zed", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    loop = asyncio.new_event_loop()
    try:
        assert UwbTransport(UwbOptions(nodes={"zed": 1, "b": 2}), ctx)._config(loop).fec is True
        off = UwbTransport(UwbOptions(nodes={"zed": 1, "b": 2}, fec=False), ctx)._config(loop)
        assert off.fec is False
    finally:
        loop.close()
    assert ArqConfig(node_id=1).fec is False  # the core's default: frames exactly as before
