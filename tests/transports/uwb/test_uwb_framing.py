"""COBS + CRC framing: round trips, resynchronisation, bounded memory, fuzzing."""

from __future__ import annotations

import contextlib
import os

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import ProtocolError
from transports.uwb import wire
from transports.uwb.framing import (
    MIN_FRAME,
    CobsError,
    CrcError,
    FrameReader,
    RuntFrameError,
    cobs_decode,
    cobs_encode,
    cobs_max_len,
    decode_frame,
    encode_frame,
    max_body,
)

FAST = settings(max_examples=150, deadline=None)


@FAST
@given(st.binary(max_size=1200))
def test_cobs_round_trip_has_no_zero_and_bounded_overhead(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= cobs_max_len(len(data))
    assert cobs_decode(enc) == data


@pytest.mark.parametrize("n", [0, 1, 253, 254, 255, 508, 1000])
def test_cobs_runs_of_nonzero_bytes(n: int) -> None:
    data = bytes([7]) * n
    assert cobs_decode(cobs_encode(data)) == data
    data = bytes(n)
    assert cobs_decode(cobs_encode(data)) == data


def test_cobs_decode_rejects_zero_and_truncation() -> None:
    with pytest.raises(ProtocolError):
        cobs_decode(b"\x03a\x00")
    with pytest.raises(ProtocolError):
        cobs_decode(b"\x05ab")


def test_decode_frame_says_what_was_wrong_and_the_reader_counts_the_same() -> None:
    good = encode_frame(b"body")[:-1]
    flipped = bytearray(good)
    flipped[2] ^= 0x01
    cases = [
        (b"\x05ab", CobsError, "cobs_errors"),
        (cobs_encode(b"abc"), RuntFrameError, "runts"),
        (bytes(flipped), CrcError, "crc_errors"),
    ]
    for wire_bytes, error, counter in cases:
        with pytest.raises(error):
            decode_frame(wire_bytes)
        assert issubclass(error, ProtocolError)
        reader = FrameReader(224)
        assert reader.feed(wire_bytes + b"\x00") == []
        counts = (reader.stats.cobs_errors, reader.stats.runts, reader.stats.crc_errors)
        assert counts == tuple(int(c == counter) for c in ("cobs_errors", "runts", "crc_errors"))
    assert decode_frame(good) == b"body"


def test_max_frame_below_the_minimum_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="below the minimum") as info:
        max_body(MIN_FRAME - 1)
    assert not isinstance(info.value, ProtocolError)


@pytest.mark.parametrize("max_frame", [48, 64, 100, 224, 255, 256, 300, 600, 1024])
def test_max_body_fits_worst_case_on_the_wire(max_frame: int) -> None:
    n = max_body(max_frame)
    worst = bytes(range(1, 256)) * (n // 255 + 1)
    for body in (worst[:n], os.urandom(n), bytes(n)):
        assert len(encode_frame(body)) <= max_frame
    assert decode_frame(encode_frame(worst[:n])[:-1]) == worst[:n]


def test_default_frame_fits_uwb_data_frame() -> None:
    assert len(encode_frame(os.urandom(max_body(224)))) <= 224


def _frames(n: int, seed: int = 0) -> list[bytes]:
    return [os.urandom(1 + (i * 37 + seed) % 200) for i in range(n)]


@FAST
@given(st.lists(st.integers(min_value=0, max_value=4000), max_size=12))
def test_reader_reassembles_across_any_split(cuts: list[int]) -> None:
    bodies = _frames(20)
    stream = b"".join(encode_frame(b) for b in bodies)
    points = sorted({c % (len(stream) + 1) for c in cuts})
    reader = FrameReader(224)
    out: list[bytes] = []
    prev = 0
    for p in [*points, len(stream)]:
        out += reader.feed(stream[prev:p])
        prev = p
    assert out == bodies
    assert reader.stats.frames == 20 and reader.stats.crc_errors == 0


def test_reader_recovers_after_garbage_at_next_delimiter() -> None:
    bodies = _frames(3)
    reader = FrameReader(224)
    # Garbage that ends in a delimiter costs nothing; garbage glued to a frame costs that frame only.
    assert reader.feed(b"\x13\x37junk\x00" + encode_frame(bodies[0])) == [bodies[0]]
    got = reader.feed(b"\x01\x02garbage" + encode_frame(bodies[1]) + encode_frame(bodies[2]))
    assert got == [bodies[2]]
    assert reader.stats.crc_errors + reader.stats.cobs_errors + reader.stats.runts == 2


def test_reader_counts_crc_errors_for_flipped_bits() -> None:
    body = os.urandom(100)
    wire_bytes = bytearray(encode_frame(body))
    wire_bytes[40] ^= 0x10
    if wire_bytes[40] == 0:  # a flip that made a delimiter splits the frame instead
        wire_bytes[40] ^= 0x30
    reader = FrameReader(224)
    assert reader.feed(bytes(wire_bytes)) == []
    assert reader.stats.crc_errors + reader.stats.cobs_errors + reader.stats.runts >= 1
    assert reader.feed(encode_frame(body)) == [body]


def test_endless_bytes_without_delimiter_use_constant_memory() -> None:
    reader = FrameReader(224)
    chunk = b"\x01" * 4096
    for _ in range(256):  # 1 MiB without a delimiter
        assert reader.feed(chunk) == []
        assert len(reader._buf) <= 224
    assert reader.stats.oversize == 1
    body = os.urandom(150)
    assert reader.feed(b"\x00" + encode_frame(body)) == [body]


def test_oversize_frame_is_dropped_and_next_one_kept() -> None:
    reader = FrameReader(224)
    big = encode_frame(os.urandom(400))
    small = os.urandom(50)
    assert reader.feed(big + encode_frame(small)) == [small]
    assert reader.stats.oversize == 1


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000))
def test_fuzz_reader_and_parser_only_count(data: bytes) -> None:
    reader = FrameReader(224)
    for body in reader.feed(data):
        with contextlib.suppress(ProtocolError):
            wire.parse(body)
    s = reader.stats
    assert s.bytes_in == len(data)
    assert len(reader._buf) <= 224


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=1, max_size=240))
def test_fuzz_valid_crc_frames_parse_or_raise_protocol_error(body: bytes) -> None:
    reader = FrameReader(1024)
    (got,) = reader.feed(encode_frame(body))
    assert got == body
    try:
        frame = wire.parse(got)
    except ProtocolError:
        return
    assert wire.pack(frame, signed=wire.is_signed(body)) == body
