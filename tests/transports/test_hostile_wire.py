"""Hostile input against the transports' sans-I/O cores: each attack as a test, and hypothesis fuzzing
of what the other test files leave out (every frame type with valid fields against an endpoint that
has messages in flight, signed frames and replays, relay summaries and the relay core, zenoh keys
and payloads)."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import os
from types import SimpleNamespace
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.errors import MapdError, ProtocolError
from mapd.identity import SIG_LEN, Identity, Roster
from transports.base import TransportContext
from transports.uwb import fec, forwarding, wire
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.forwarding import ForwardingCore, Summary, unpack_summary
from transports.uwb.framing import encode_frame
from transports.uwb.receiving import MAX_ACKS_OWED, Partial
from transports.uwb.relaying import RelayDriver
from transports.uwb.signing import COUNTER_LEN, TAG_LEN, Signer, Verifier
from transports.zenoh.acks import pack_ack
from transports.zenoh.core import ZenohCore
from transports.zenoh.link import ZenohTransport
from transports.zenoh.session import ZenohOptions

ME = 2


def _frame(f: wire.Frame) -> bytes:
    return encode_frame(wire.pack(f))


# --- parity bookkeeping: work per frame ---------------------------------------------------------


def test_a_frame_costs_no_work_per_block_of_a_message_with_parity_in_every_block(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A forger opens a broadcast message of 12,800 chunks (100 blocks), sends its last chunk (every
    other one is now a gap) and one parity chunk for each block, then repeats a 25-byte frame. Each
    frame used to rebuild what the parity of every block stands for: 100 blocks of 128 chunks per
    frame (5 ms a frame with 500 blocks, some 100 times a normal frame's cost); it must only look at
    the block the frame touches."""
    count = 12_800
    nb = fec.blocks(count)
    assert nb == 100 and fec.max_parity(count) >= 1
    ep = ArqEndpoint(ArqConfig(node_id=ME, fec=True), session=5)

    def data(i: int) -> bytes:
        return _frame(wire.Data(1, wire.BROADCAST, 9, 1, 0, i, count, 2 * count, b"ab"))

    ep.receive_data(data(count - 1), 0.0)
    for b in range(nb):
        ep.receive_data(data(fec.parity_index(count, b, 0)), 0.0)
    part = ep._peers[1].partials[1]
    assert len(part.parity) == nb  # parity held in every block

    calls = 0
    missing = Partial._missing

    def counted(self: Partial, b: int) -> list[int]:
        nonlocal calls
        calls += 1
        return missing(self, b)

    monkeypatch.setattr(Partial, "_missing", counted)
    for _ in range(20):
        ep.receive_data(data(count - 1), 1.0)  # a duplicate: the receiver checks its gaps
    ep.handle_timer(5.0)
    while ep.data_to_send(5.0):  # and the gap report it owes
        pass
    assert ep.stats()["nacks_tx"] >= 1
    assert calls <= 20, f"{calls} block scans for 20 frames of one message"


@st.composite
def _partial_ops(draw: st.DrawFn) -> tuple[int, list[tuple[str, int]]]:
    count = draw(st.integers(1, 400))
    limit = fec.index_limit(count)
    ops = draw(
        st.lists(
            st.one_of(
                st.tuples(st.just("data"), st.integers(0, count - 1)),
                st.tuples(st.just("parity"), st.integers(count, max(count, limit - 1))),
                st.tuples(st.just("recover"), st.integers(0, fec.blocks(count) - 1)),
            ),
            max_size=60,
        )
    )
    return count, ops


def _reference_covered(part: Partial) -> set[int]:
    """What the parity held stands for, worked out from scratch (the definition in receiving.py)."""
    out: set[int] = set()
    for b, shares in part.parity.items():
        missing = part._missing(b)
        out.update(missing[len(missing) - min(len(shares), len(missing)) :])
    return out


@settings(max_examples=150, deadline=None)
@given(_partial_ops())
def test_gaps_and_reports_say_what_they_did_when_worked_out_from_scratch(
    case: tuple[int, list[tuple[str, int]]],
) -> None:
    count, ops = case
    part = Partial(1, 0, count, 40 * count, 1, 0.0, nack=True)
    for op, i in ops:
        if op == "data":
            part.add(i, bytes(40), 0.0)
        elif op == "parity" and count <= i < fec.index_limit(count) and part.wants_parity(i):
            part.add_parity(i, bytes(40), 0.0)
        elif op == "recover":
            part.recover(i)
        covered = _reference_covered(part)
        top = min(part.top, part.base + 8 * wire.MAX_BITMAP)
        want_gaps = [j for j in range(part.base, top) if j not in part.chunks and j not in covered]
        assert part.gaps() == want_gaps
        base = part.base
        while base in part.chunks or base in covered:
            base += 1
        got_base, bitmap = part.report()
        assert got_base == base
        held = set(wire.bitmap_indices(base, bitmap))
        want = {j for j in range(base + 1, min(count, base + 1 + 8 * wire.MAX_BITMAP))}
        assert held == {j for j in want if j in part.chunks or j in covered}


# --- every frame type, valid fields, against an endpoint with messages in flight -----------------

_ids = st.integers(1, 254)
_u24 = st.integers(0, wire.MASK24)


@st.composite
def _frames(draw: st.DrawFn) -> wire.Frame:
    kind = draw(st.sampled_from(["data", "dgram", "ack", "hello", "done", "lend"]))
    src = draw(st.one_of(st.sampled_from([1, 3, 4]), _ids))
    dst = draw(st.one_of(st.sampled_from([ME, wire.BROADCAST]), st.integers(1, 255)))
    session = draw(st.one_of(st.sampled_from([11, 12]), _u24))
    if kind in ("data", "dgram"):
        count = draw(st.one_of(st.sampled_from([1, 2, 3, 130, 257]), st.integers(1, 0xFFFF)))
        limit = fec.index_limit(count) if kind == "data" else count
        index = draw(
            st.one_of(st.sampled_from([0, count - 1, min(count, limit - 1)]), st.integers(0, limit - 1))
        )
        total = draw(st.one_of(st.sampled_from([count, 40 * count]), st.integers(count, wire.MAX_TOTAL)))
        payload = draw(st.binary(min_size=1, max_size=min(total, 150)))
        msg = draw(st.one_of(st.sampled_from([0, 1, 2]), _u24))
        stream = draw(st.integers(0, 255))
        return wire.Data(src, dst, session, msg, stream, index, count, total, payload, kind == "data")
    if kind == "ack":
        return wire.Ack(
            src,
            ME if dst == wire.BROADCAST else dst,
            session,
            draw(st.one_of(st.just(77), _u24)),
            draw(st.one_of(st.integers(0, 2), _u24)),  # 0..2: one of the endpoint's own (see below)
            draw(st.integers(0, 255)),
            draw(st.sampled_from([0, 0, wire.COMPLETE, wire.REJECT, wire.COMPLETE | wire.REJECT])),
            draw(st.one_of(st.integers(0, 300), st.integers(0, 0xFFFF))),
            draw(st.binary(max_size=wire.MAX_BITMAP)),
        )
    if kind == "done":
        entry = st.tuples(
            st.one_of(st.just(ME), _ids),
            st.one_of(st.just(77), st.integers(0, 255)),
            st.one_of(st.integers(0, 2), st.integers(0, 0xFFFF)),
        )
        return wire.Done(src, wire.BROADCAST, session, tuple(draw(st.lists(entry, min_size=1, max_size=20))))
    if kind == "lend":
        return wire.Lend(src, ME if dst == wire.BROADCAST else dst, session, draw(st.integers(0, 0xFFFF)))
    return wire.Hello(src, dst, session)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    frames=st.lists(st.tuples(_frames(), st.floats(0, 2.0)), max_size=40),
    acks=st.sampled_from(["auto", "each", "nack"]),
    mac=st.sampled_from(["none", "tdma", "backoff"]),
)
def test_any_valid_frame_never_raises_and_every_table_stays_bounded(
    frames: list[tuple[wire.Frame, float]], acks: Any, mac: Any
) -> None:
    """Frames that parse, of every type and with any field values (acks and DONEs for the messages
    this node is sending, gap reports, LENDs, parity), with the endpoint sending between them."""
    cfg = ArqConfig(
        node_id=ME, max_message_bytes=20_000, fec=True, acks=acks, mac=mac, lend=True, slots=4, slot_index=1,
        max_peers=16,
    )  # fmt: skip
    ep = ArqEndpoint(cfg, session=77, seed=1)
    now = 0.0
    ours = [
        ep.send(os.urandom(3000 * (stream + 1)), now, dests=dests, stream=stream)
        for stream, dests in enumerate(([1], [1, 3, 4], [3]))
    ]
    for frame, dt in frames:
        now += dt
        # acks and DONE entries naming 0..2 name the messages in flight, whose ids are random
        if isinstance(frame, wire.Ack) and frame.msg < len(ours):
            frame = dataclasses.replace(frame, msg=ours[frame.msg])
        elif isinstance(frame, wire.Done):
            entries = tuple((s, t, ours[m] & 0xFFFF if m < len(ours) else m) for s, t, m in frame.entries)
            frame = dataclasses.replace(frame, entries=entries)
        ep.receive_data(_frame(frame), now)
        timer = ep.get_timer()
        if timer is not None and timer <= now:
            ep.handle_timer(now)
        for _ in range(4):
            if not ep.data_to_send(now):
                break
        ep.events()
        held = sum(p.cost for peer in ep._peers.values() for p in peer.partials.values())
        assert ep._rx_held == held <= ep._rx_budget
        assert len(ep._peers) <= cfg.max_peers
        for peer in ep._peers.values():
            assert len(peer.partials) <= cfg.max_partials_per_peer
            assert len(peer.acks_due) <= MAX_ACKS_OWED
        assert len(ep._done_owed) <= 64
    assert ep.get_timer() is not None  # a HELLO or the messages are still due


# --- signing: replays, truncated tags, counters -------------------------------------------------

KEY = b"k" * 32


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([1, 3]), st.integers(0, 200)), max_size=80))
def test_a_signed_frame_is_accepted_once_and_never_further_back_than_the_window(
    sends: list[tuple[int, int]],
) -> None:
    """A recorder replays any signed frames it heard, in any order: each (sender, counter) passes
    exactly once if it is newer than its sender's newest or within the 64 counters below it, and
    never otherwise (so a verifier that refuses too much fails here as well as one too lax)."""
    v = Verifier(KEY)
    seen: set[tuple[int, int]] = set()
    top: dict[int, int] = {}
    for src, counter in sends:
        signer = Signer(KEY, counter)
        signer.confirm(counter + 1)
        body = signer.sign(wire.pack(wire.Hello(src, wire.BROADCAST, 5), signed=True))
        out = v.check(body, True)
        newest = top.get(src, -1)
        fresh = (src, counter) not in seen and (counter > newest or newest - counter <= 64)
        assert (out is not None) == fresh, (src, counter, newest)
        if fresh:
            seen.add((src, counter))
            top[src] = max(newest, counter)


def test_a_cut_or_altered_signing_trailer_never_passes() -> None:
    signer = Signer(KEY, 1000)
    signer.confirm(2000)
    body = signer.sign(wire.pack(wire.Hello(1, wire.BROADCAST, 5), signed=True))
    v = Verifier(KEY)
    for cut in range(1, COUNTER_LEN + TAG_LEN + 1):
        assert v.check(body[:-cut], True) is None  # a truncated tag or counter
    for i in range(len(body)):
        flipped = bytearray(body)
        flipped[i] ^= 0x01
        assert v.check(bytes(flipped), True) is None
    assert v.check(body, True) is not None and v.check(body, True) is None  # then a replay


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(_frames(), st.integers(0, 50), st.booleans()), max_size=30))
def test_signed_endpoint_takes_only_fresh_authentic_frames_and_never_raises(
    frames: list[tuple[wire.Frame, int, bool]],
) -> None:
    """A key holder's frames (any fields, any counters, replayed) and forgeries (the wrong key) on
    a signed link: nothing raises, forgeries and replays are only counted."""
    ep = ArqEndpoint(ArqConfig(node_id=ME, key=KEY, fec=True, max_message_bytes=20_000), session=77)
    ep.confirm_counter(ep.counter_reservation() or 0)
    ep.send(os.urandom(2000), 0.0, dests=[1, 3], stream=0)
    sent: list[tuple[bytes, bool]] = []
    bad = 0
    for i, (frame, counter, forged) in enumerate(frames):
        signer = Signer(b"x" * 32 if forged else KEY, counter)
        signer.confirm(counter + 1)
        body = signer.sign(wire.pack(frame, signed=True))
        raw = encode_frame(body, crc=False)
        bad += forged
        ep.receive_data(raw, float(i))
        if sent and i % 3 == 0:
            ep.receive_data(sent[-1][0], float(i))  # a replay
            bad += sent[-1][1]
        sent.append((raw, forged))
        ep.handle_timer(float(i))
        while ep.data_to_send(float(i)):
            pass
    s = ep.stats()
    assert s["bad_signature"] == bad
    held = sum(p.cost for peer in ep._peers.values() for p in peer.partials.values())
    assert ep._rx_held == held <= ep._rx_budget


# --- relay summaries and the relay core ---------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600))
def test_a_malformed_summary_is_one_protocol_error(data: bytes) -> None:
    """A summary is a payload from a link: malformed, it raises a mapd.errors exception (it raised a
    bare ValueError) and the relay driver counts it."""
    try:
        s = unpack_summary(data)
    except ProtocolError as exc:
        assert isinstance(exc, MapdError) and str(exc).startswith("uwb: ")
        driver = RelayDriver(1, summary_period_s=15.0, relay_period_s=5.0, stream_of=lambda o: o)
        driver.summary(3, data, 0.0)
        assert driver.bad_summaries == 1 and driver.summaries_rx == 0
        return
    assert unpack_summary(forwarding.pack_summary(s)) == s  # what parses means one thing


@settings(max_examples=120, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.tuples(
                st.just("summary"),
                _ids,
                st.dictionaries(st.integers(0, 255), st.integers(0, 2**64 - 1), max_size=6),
                st.frozensets(st.integers(0, 255), max_size=6),
            ),
            st.tuples(st.just("held"), st.sampled_from([1, 3, 5]), st.integers(1, 30), st.integers(0, 30)),
            st.tuples(st.just("overheard"), st.sampled_from([1, 3, 5]), st.integers(0, 2**64 - 1)),
            st.tuples(st.just("tick"), st.floats(0, 40)),
        ),
        max_size=60,
    )
)
def test_lying_summaries_cost_at_most_one_relay_per_period_and_bounded_state(ops: list[Any]) -> None:
    """Key holders' summaries claim anything (any origin, any version, any link ids heard, from any
    source id): the relay starts at most one forward per relay period, keeps only summaries heard
    lately, and its per-neighbour tables stay within what those summaries and its chain can name."""
    core = ForwardingCore(2, relay_period_s=5.0, summary_timeout_s=45.0, retry_s=30.0)
    now = 0.0
    starts: list[float] = []
    for op in ops:
        if op[0] == "summary":
            core.on_summary(op[1], Summary(op[2], op[3]), now)
        elif op[0] == "held":
            _, origin, version, base = op
            if base < version:
                core.on_held(origin, version, base, bytes(50))
        elif op[0] == "overheard":
            core.on_overheard(op[1], op[2], now)
        else:
            now += op[1]
        r = core.next_forward(now)
        if r is not None:
            starts.append(now)
            assert r.dests and 2 not in r.dests and r.origin not in r.dests
            core.relay_done()
        core.keyframes_wanted(now, {1, 3})
        assert all(now - h.at <= core.summary_timeout_s for h in core._heard.values())
        versions = sum(len(core._candidates(o)) for o in core._chain)
        assert len(core._need_since) <= len(core._heard) * versions
        assert all(len(c) <= forwarding.CHAIN for c in core._chain.values())
    assert all(b - a >= 5.0 for a, b in itertools.pairwise(starts))


# --- zenoh ---------------------------------------------------------------------------------------

IDS = {n: Identity.generate(n) for n in ("a", "b", "c")}
ROSTER = Roster({n: i.public_key for n, i in IDS.items()})


class _Payload:
    """A zenoh payload that says whether it was read."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.read = False

    def __len__(self) -> int:
        return self.n

    def to_bytes(self) -> bytes:
        self.read = True
        return bytes(self.n)


def test_an_oversized_ack_sample_is_refused_unread() -> None:
    """zenoh accepts samples up to max_message_bytes: an 8 MiB sample on an ack key was copied and
    queued on the event loop for the core to refuse its length there (an ack is 8 or 72 bytes)."""
    ctx = TransportContext(robot="b", fleet="f", max_message_bytes=8 << 20, emit=lambda e: None)
    t = ZenohTransport(ZenohOptions(), ctx)
    loop = asyncio.new_event_loop()
    try:
        t._loop = loop
        big = _Payload(8 << 20)
        t._cb_ack(SimpleNamespace(key_expr="mapd/f/a/ack/b", payload=big))
        ok = _Payload(8 + SIG_LEN)  # the longest ack: a version and a signature
        t._cb_ack(SimpleNamespace(key_expr="mapd/f/a/ack/b", payload=ok))
        loop.run_until_complete(asyncio.sleep(0))
    finally:
        loop.close()
    assert not big.read and ok.read
    assert t.core.counters.dropped == 2  # the oversized one, and the 72 zero bytes (bad signature form)


_names = st.one_of(
    st.sampled_from(["a", "b", "c", "zz", "x" * 33, "a/b", "*", "**", "", "é"]), st.text(max_size=8)
)


@settings(max_examples=200, deadline=None)
@given(
    signed=st.booleans(),
    ops=st.lists(
        st.tuples(
            st.integers(0, 5),
            _names,
            st.sampled_from(["update", "presence", "ack", "other"]),
            st.one_of(st.binary(max_size=120), st.integers(1, 9)),
            st.booleans(),
        ),
        max_size=40,
    ),
)
def test_zenoh_core_takes_any_key_and_payload_without_raising(signed: bool, ops: list[Any]) -> None:
    """Keys and payloads from the network: any key expression, any bytes, acks of any version, any
    asker: the core only counts, and tracks no more robots than max_peers."""
    core = ZenohCore(
        robot="b",
        fleet="f",
        identity=IDS["b"] if signed else None,
        roster=ROSTER if signed else Roster.open(),
        max_message_bytes=4096,
        max_peers=3,
    )
    core.offered(SimpleNamespace(robot="b", version=5), 0.0)  # type: ignore[arg-type]
    for i, (op, name, shape, payload, alive) in enumerate(ops):
        key = {
            "update": f"mapd/f/{name}/update",
            "presence": f"mapd/f/{name}",
            "ack": f"mapd/f/{name}/ack/b",
            "other": f"mapd/{name}/{name}/ack/{name}",
        }[shape]
        if isinstance(payload, int):
            payload = pack_ack(payload, identity=IDS["a"] if signed else None, fleet="f", peer="a", robot="b")
        now = float(i)
        if op == 0:
            core.on_update(key, payload, now)
        elif op == 1:
            core.on_ack(key, payload, now)
        elif op == 2:
            core.on_presence(key, alive, now)
        elif op == 3:
            core.on_query(name)
        elif op == 4:
            core.on_reply(name, payload, now)
        else:
            core.query_done(name, now)
            core.request_keyframe(name, now)
        assert len(core._robots) <= 3
