"""Frame layouts, absurd fields, signing (tags, replay window, persisted counter) and pacing bounds."""

from __future__ import annotations

import contextlib
import random
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import ProtocolError, StateError
from transports.uwb import wire
from transports.uwb.pacing import ByteWindow, MediumAccess, Pacer
from transports.uwb.signing import COUNTER_MAX, CounterStore, ReplayStore, Signer, Verifier, clock_floor

KEY = bytes(range(32))


def test_frames_round_trip() -> None:
    frames: list[wire.Frame] = [
        wire.Data(1, 2, 0xADBEEF, 0xFFFFFE, 3, 4, 10, wire.MAX_TOTAL, b"payload"),
        wire.Ack(2, 1, 5, 0xADBEEF, 0x7, 9, wire.COMPLETE, 3, b"\x01\x80"),
        wire.Hello(3, wire.BROADCAST, 42),
        wire.Data(1, wire.BROADCAST, 5, 6, 254, 0, 1, 4, b"pose", False),  # a DGRAM
        wire.Lend(4, 7, 0x123456, 0xFFFF),  # the rest of slot 65535 (mod 2^16) goes to node 7
    ]
    for f in frames:
        assert wire.parse(wire.pack(f)) == f
    # 24-bit fields: a value that does not fit is the caller's mistake, not silently cut
    with pytest.raises(ValueError, match="24-bit"):
        wire.pack(wire.Hello(3, wire.BROADCAST, 1 << 24))


def test_msg_ids_compare_across_the_wrap() -> None:
    assert wire.msg_before(wire.MASK24, 0) and not wire.msg_before(0, wire.MASK24)
    assert wire.msg_before(5, 6) and not wire.msg_before(6, 5) and not wire.msg_before(6, 6)


@pytest.mark.parametrize(
    ("frame", "why"),
    [
        (wire.Data(1, 2, 1, 7, 0, 256, 10, 1000, b"x"), "index"),  # past a 10-chunk message's parity
        (wire.Data(1, 2, 1, 7, 0, 10, 10, 1000, b"x", reliable=False), "index"),  # DGRAMs have none
        (wire.Data(1, 2, 1, 7, 0, 0, 0, 1000, b"x"), "index"),
        (wire.Data(1, 2, 1, 7, 0, 0, 500, 100, b"x"), "inconsistent"),
        (wire.Data(1, 2, 1, 7, 0, 0, 1, 2, b"xyz"), "inconsistent"),
        (wire.Data(0, 2, 1, 7, 0, 0, 1, 5, b"x"), "source"),
        (wire.Data(255, 2, 1, 7, 0, 0, 1, 5, b"x"), "source"),
        (wire.Data(1, 0, 1, 7, 0, 0, 1, 5, b"x"), "destination"),
        (wire.Ack(1, 255, 1, 1, 7, 0, 0, 0, b""), "broadcast"),
        (wire.Ack(1, 2, 1, 1, 7, 0, 0x80, 0, b""), "flags"),
        (wire.Ack(1, 2, 1, 1, 7, 0, 0, 0, b"\x01" * 33), "bitmap"),
        (wire.Lend(1, 255, 1, 3), "broadcast"),
    ],
)
def test_absurd_fields_are_protocol_errors(frame: wire.Frame, why: str) -> None:
    with pytest.raises(ProtocolError, match=why):
        wire.parse(wire.pack(frame))


def test_bad_version_type_and_truncation() -> None:
    body = bytearray(wire.pack(wire.Hello(1, 2, 3)))
    with pytest.raises(ProtocolError, match="version"):
        wire.parse(bytes([body[0] & 0x8F | 0x10]) + bytes(body[1:]))  # version 1, the old layout
    with pytest.raises(ProtocolError, match="type"):
        wire.parse(bytes([0x2F]) + bytes(body[1:]))
    with pytest.raises(ProtocolError, match="shorter"):
        wire.parse(bytes(body[:5]))
    with pytest.raises(ProtocolError, match="no payload"):
        wire.parse(wire.pack(wire.Data(1, 2, 1, 7, 0, 0, 1, 5, b"")))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80))
def test_fuzz_parse_raises_only_protocol_error(body: bytes) -> None:
    with contextlib.suppress(ProtocolError):
        wire.parse(body)


def test_bitmap_indices() -> None:
    assert wire.bitmap_indices(10, b"\x05\x80") == [11, 13, 26]
    assert wire.bitmap_indices(0, b"") == []


# --- signing ------------------------------------------------------------------------------------


def _signer(start: int = 100) -> Signer:
    s = Signer(KEY, start, block=4096)
    r = s.reservation()
    assert r is not None
    s.confirm(r)
    return s


def test_sign_and_verify() -> None:
    s, v = _signer(), Verifier(KEY)
    body = wire.pack(wire.Hello(1, 2, 3), signed=True)
    signed = s.sign(body)
    assert v.check(signed, True) == body


def test_tampered_unsigned_and_wrong_key_are_counted() -> None:
    s, v = _signer(), Verifier(KEY)
    body = wire.pack(wire.Hello(1, 2, 3), signed=True)
    signed = bytearray(s.sign(body))
    signed[3] ^= 1
    assert v.check(bytes(signed), True) is None
    assert v.check(wire.pack(wire.Hello(1, 2, 3)), False) is None
    other = Signer(b"k" * 32, 5, block=64)
    other.confirm(other.reservation() or 0)
    assert v.check(other.sign(body), True) is None
    assert (v.stats.bad_signature, v.stats.unsigned) == (2, 1)


def test_replays_dropped_reordering_accepted_once() -> None:
    s, v = _signer(), Verifier(KEY)
    body = wire.pack(wire.Hello(1, 2, 3), signed=True)
    frames = [s.sign(body) for _ in range(10)]
    order = [0, 2, 1, 5, 3, 4, 9, 6, 8, 7]
    assert all(v.check(frames[i], True) is not None for i in order)
    assert all(v.check(f, True) is None for f in frames)
    assert v.stats.replayed == 10
    for _ in range(100):  # push the window past the first frames
        assert v.check(s.sign(body), True) is not None
    assert v.check(frames[9], True) is None


def test_a_key_holder_counter_from_the_future_cannot_silence_the_real_sender() -> None:
    """Measured on main: one frame with counter 2^48-2 as another node dropped its frames until restart."""
    wall = 1.8e9
    real = _signer(clock_floor(wall))
    v = Verifier(KEY)
    body = wire.pack(wire.Hello(1, 2, 3), signed=True)
    assert v.check(real.sign(body), True, wall) is not None
    forger = Signer(KEY, COUNTER_MAX - 1, block=1)
    forger.confirm(COUNTER_MAX)
    forged = forger.sign(body)
    assert v.check(forged, True, wall) is None and v.stats.future == 1
    assert all(v.check(real.sign(body), True, wall + i) is not None for i in range(5))
    # without the receiver's clock (simulations), the same frame would have won
    blind = Verifier(KEY)
    assert blind.check(forged, True) is not None
    assert blind.check(real.sign(body), True) is None


def test_signer_needs_confirmed_reservation() -> None:
    s = Signer(KEY, 1000, block=8)
    assert not s.can_sign()
    upto = s.reservation()
    assert upto == 1008
    s.confirm(upto)
    for _ in range(8):
        s.sign(b"\x91\x01\x02\x00\x00\x00\x00")
    assert not s.can_sign()


def test_counter_store_persists_and_never_reuses(tmp_path: Path) -> None:
    path = tmp_path / "uwb-1.counter"
    store = CounterStore(path)
    used: list[int] = []
    start = store.load()
    for _run in range(3):  # three "boots", each crashing without a clean shutdown
        s = Signer(KEY, max(store.load(), start), block=16)
        for _ in range(21):
            if (r := s.reservation()) is not None:
                store.save(r)
                s.confirm(r)
            used.append(s.next)
            s.sign(b"\x91\x01\x02\x00\x00\x00\x00")
    assert len(used) == len(set(used)) and used == sorted(used)
    path.write_text("garbage")
    with pytest.raises(StateError, match="corrupt"):
        CounterStore(path).load()
    path.write_text("7" * 10_000_000)  # read no further than a counter can be long
    with pytest.raises(StateError, match=r"holds 7{65}, out of range"):
        CounterStore(path).load()


def test_a_counter_store_never_makes_the_state_directory_again(tmp_path: Path) -> None:
    # The state directory gone (its disk unmounted, or removed): the save made the whole path again,
    # on the disk under the mount point. It makes the link's own folder only, in a state directory
    # that is there (the daemon's state store makes the layout again once it can be written).
    state = tmp_path / "state"
    with pytest.raises(StateError, match="cannot write signing counter"):
        CounterStore(state / "links" / "uwb" / "uwb-1.counter").save(5)
    assert not state.exists()
    (state / "links").mkdir(parents=True)
    CounterStore(state / "links" / "uwb" / "uwb-1.counter").save(5)
    assert CounterStore(state / "links" / "uwb" / "uwb-1.counter").load() == 5


def test_marks_from_a_previous_run_refuse_every_frame_up_to_them(tmp_path: Path) -> None:
    s, v = _signer(), Verifier(KEY)
    body = wire.pack(wire.Hello(1, 2, 3), signed=True)
    frames = [s.sign(body) for _ in range(10)]
    assert all(v.check(f, True) is not None for f in frames[:6])  # frames 6..9 never heard
    store = ReplayStore(tmp_path / "uwb-2.replay")
    store.save(v.marks())
    again = Verifier(KEY, store.load())  # a restart
    assert all(again.check(f, True) is None for f in frames[:6])  # nothing heard before comes again
    assert all(again.check(f, True) is not None for f in frames[6:])  # what came after is taken
    assert again.check(s.sign(body), True) is not None and again.stats.replayed == 6


@pytest.mark.parametrize(
    ("text", "kept"),
    [
        ("{not json", {}),
        ('{"1": 5, "2": -1, "300": 7, "x": 1, "3": 1e3, "4": 281474976710656}', {1: 5}),
        ("[1, 2]", {}),
        ("7" * 100_000, {}),
    ],
)
def test_damaged_replay_marks_cost_what_they_held_not_the_start(
    tmp_path: Path, text: str, kept: dict[int, int], caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "uwb-2.replay"
    path.write_text(text)
    assert ReplayStore(path).load() == kept
    assert "replay marks" in caplog.text and len(caplog.records) == 1


def test_clock_floor_rises() -> None:
    assert clock_floor(1.8e9) < clock_floor(1.8e9 + 0.001)
    assert clock_floor(0) == 0


# --- pacing -------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    rate=st.sampled_from([2000.0, 12500.0, 57600.0, 250000.0]),
    sizes=st.lists(st.integers(min_value=10, max_value=224), min_size=20, max_size=200),
    jitter=st.lists(st.floats(min_value=0, max_value=0.3), min_size=1, max_size=20),
)
def test_pacer_never_exceeds_rate_in_any_window(rate: float, sizes: list[int], jitter: list[float]) -> None:
    p = Pacer(rate, 2 * 224) if rate / 8 >= 448 else Pacer(rate, 224)
    now, sends = 0.0, []
    for i, n in enumerate(sizes):
        now = p.ready_at(n, now + jitter[i % len(jitter)] * (i % 3 == 0) * 0.1)
        p.consume(n, now)
        sends.append((now, n))
    budget = rate / 8
    for t, _ in sends:  # every window ending at a send holds the most bytes
        assert sum(n for t2, n in sends if t - 1.0 < t2 <= t) <= budget + 1e-9


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.floats(min_value=0, max_value=0.7), st.integers(0, 300)), max_size=60))
def test_byte_window_peak_is_the_most_in_any_window_ending_at_a_write(gaps: list[tuple[float, int]]) -> None:
    w, now, writes = ByteWindow(1.0), 0.0, []
    for gap, n in gaps:
        now += gap
        w.add(n, now)
        writes.append((now, n))
        assert w.bytes == sum(n2 for t2, n2 in writes if t2 > now - 1.0)
    assert w.peak == max((sum(n2 for t2, n2 in writes if t - 1.0 < t2 <= t) for t, _ in writes), default=0)


def test_pacer_keeps_up_with_the_rate() -> None:
    p = Pacer(12500, 448)
    now, total = 0.0, 0
    while now < 60:
        now = p.ready_at(223, now)
        p.consume(223, now)
        total += 223
    assert total * 8 / now >= 0.99 * 12500


def test_tdma_sends_only_in_own_slot() -> None:
    mac = MediumAccess("tdma", 12500, slot_s=0.5, slots=3, slot_index=1, guard_s=0.02, clock_offset=100.25)
    rng = random.Random(1)
    for _ in range(200):
        now = rng.uniform(0, 50)
        t = mac.ready_at(223, now)
        assert t >= now
        phase = (t + 100.25) % 1.5
        assert phase >= 0.5 - 1e-6 and phase + 223 * 8 / 12500 <= 1.0 - 0.02 + 1e-6


def test_backoff_waits_for_idle_channel() -> None:
    mac = MediumAccess("backoff", 12500, sense_s=0.02, backoff_min_s=0.01, backoff_max_s=0.05)
    mac.heard(10.0)
    t = mac.ready_at(100, 10.001)
    assert 10.03 <= t <= 10.07
    mac.sent(100, t)
    assert mac.ready_at(100, 11.0) == 11.0  # quiet channel: no wait
