"""Hostile ``lossless`` payloads: every one is a CodecError (or, for a harmless change, the same map).

Never a crash, a hang, another exception type, or a wrong map.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.codec import decode, encode, read_header
from mapd.codec.api import _FIXED
from mapd.codec.base import Target
from mapd.codec.ctx_kernels import MODEL_VERSION
from mapd.codec.lossless import LosslessCodec
from mapd.errors import CodecError
from mapd.grid import OccupancyGrid, Pose2D

CORPUS = Path(__file__).parent / "corpus_lossless"
CODEC = LosslessCodec()


def _pair() -> tuple[OccupancyGrid, OccupancyGrid, OccupancyGrid]:
    rng = np.random.default_rng(11)
    d = np.full((40, 52), -1, np.int8)
    d[5:35, 4:48] = 0
    d[5, 4:48] = d[34, 4:48] = 100
    d[rng.random(d.shape) < 0.02] = 100
    base = OccupancyGrid(d, 0.05, Pose2D(1.0, -1.0, 0.0), version=7)
    d2 = np.full((44, 52), -1, np.int8)
    d2[4:, :] = d
    d2[0:6, 10:20] = 0
    new = OccupancyGrid(d2, 0.05, Pose2D(1.0, -1.2, 0.0), version=8)
    odd = OccupancyGrid(rng.integers(-128, 128, (9, 13)).astype(np.int8), 0.05)
    return base, new, odd


BASE, NEW, ODD = _pair()
PAYLOADS = {
    "whole": (encode(BASE, "lossless"), None, BASE),
    "delta": (encode(NEW, "lossless", base=BASE), BASE, NEW),
    "escape": (encode(ODD, "lossless"), None, ODD),
}


def with_body(payload: bytes, body: bytes) -> bytes:
    """``payload`` with its body replaced and the header's body length fixed to match."""
    h = read_header(payload)
    head = bytearray(payload[: h.body_offset])
    fields = list(_FIXED.unpack_from(head, h.body_offset - _FIXED.size))
    fields[-1] = len(body)
    _FIXED.pack_into(head, h.body_offset - _FIXED.size, *fields)
    return bytes(head) + body


def decodes_exactly_or_refuses(payload: bytes, base: OccupancyGrid | None, grid: OccupancyGrid) -> bool:
    """True if it decoded to ``grid``; False if it raised CodecError. Anything else fails the test."""
    try:
        back = decode(payload, base=base)
    except CodecError:
        return False
    assert back.same_map(grid), "a corrupt payload decoded to a wrong map"
    return True


def test_payloads_are_what_the_tests_think() -> None:
    assert read_header(PAYLOADS["delta"][0]).delta
    assert not read_header(PAYLOADS["whole"][0]).delta


@pytest.mark.parametrize("kind", sorted(PAYLOADS))
def test_truncated_body_at_every_offset_is_refused(kind: str) -> None:
    payload, base, grid = PAYLOADS[kind]
    h = read_header(payload)
    body = payload[h.body_offset :]
    for n in range(len(body)):
        assert not decodes_exactly_or_refuses(with_body(payload, body[:n]), base, grid), n
        # The raw payload cut short, header untouched, is refused too.
        with pytest.raises(CodecError):
            decode(payload[: h.body_offset + n], base=base)


@pytest.mark.parametrize("kind", sorted(PAYLOADS))
def test_every_single_bit_flip_in_the_body_is_refused_or_harmless(kind: str) -> None:
    payload, base, grid = PAYLOADS[kind]
    h = read_header(payload)
    body = bytearray(payload[h.body_offset :])
    harmless = 0
    for i in range(len(body)):
        for bit in range(8):
            body[i] ^= 1 << bit
            harmless += decodes_exactly_or_refuses(with_body(payload, bytes(body)), base, grid)
            body[i] ^= 1 << bit
    # a flip the decoder takes gives the same map (checked above); only spare bits allow it (the
    # last byte's padding, an unused flag bit): 1 or 2 of a body's hundreds of bits
    assert harmless <= 2, harmless


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(sorted(PAYLOADS)),
    edits=st.lists(
        st.tuples(st.integers(0, 10_000), st.integers(0, 255), st.sampled_from("sid")), max_size=6
    ),
)
def test_mutated_bodies_never_crash(kind: str, edits: list[tuple[int, int, str]]) -> None:
    payload, base, grid = PAYLOADS[kind]
    body = bytearray(payload[read_header(payload).body_offset :])
    for at, value, op in edits:
        i = at % (len(body) + 1)
        if op == "s" and i < len(body):
            body[i] = value
        elif op == "i":
            body[i:i] = bytes([value])
        elif op == "d" and i < len(body):
            del body[i]
    decodes_exactly_or_refuses(with_body(payload, bytes(body)), base, grid)


@settings(max_examples=200, deadline=None)
@given(
    body=st.binary(max_size=80),
    h=st.integers(1, 64),
    w=st.integers(1, 64),
    use_base=st.booleans(),
    our_version=st.booleans(),
)
def test_arbitrary_bodies_give_a_grid_of_the_right_shape_or_a_codec_error(
    body: bytes, h: int, w: int, use_base: bool, our_version: bool
) -> None:
    if our_version and body:
        # Mostly past the version check, so that the stream decoder itself sees the garbage.
        body = bytes([(MODEL_VERSION << 3) | (body[0] & 7)]) + body[1:]
    target = Target(h, w, 0.05, Pose2D(1.0, -1.0, 0.0), "")
    try:
        out = CODEC.decode_cells(body, target, BASE if use_base else None)
    except CodecError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert out.shape == (h, w) and out.dtype == np.int8


def test_huge_target_with_a_tiny_body_stops_early() -> None:
    # 4096 x 4096 cells from 17 bytes: the decoder runs out of stream long before the last cell.
    with pytest.raises(CodecError, match="truncated or corrupt"):
        fmt = (MODEL_VERSION << 3) | 4  # whole map, trinary
        CODEC.decode_cells(bytes([fmt]) + bytes(16), Target(4096, 4096, 0.05, Pose2D(), ""), None)


def test_wrong_base_is_refused_never_a_wrong_map() -> None:
    payload, _, _ = PAYLOADS["delta"]
    with pytest.raises(CodecError, match="delta against version 7"):
        decode(payload, base=NEW)
    with pytest.raises(CodecError, match="no base was given"):
        decode(payload)
    shifted = BASE.replace(origin=Pose2D(1.05, -1.0, 0.0))  # same cells, another origin
    with pytest.raises(CodecError, match="delta against version 7"):
        decode(payload, base=shifted)


def test_unknown_codec_name_is_refused() -> None:
    payload, _, _ = PAYLOADS["whole"]
    forged = payload.replace(b"\x08lossless", b"\x08lossles2", 1)
    with pytest.raises(CodecError):
        decode(forged)


CASES = json.loads((CORPUS / "manifest.json").read_text())


@pytest.mark.parametrize("case", CASES, ids=[c["file"] for c in CASES])
def test_regression_corpus(case: dict[str, str | None]) -> None:
    payload = (CORPUS / str(case["file"])).read_bytes()
    base = decode((CORPUS / case["base"]).read_bytes()) if case["base"] else None
    if base is not None:
        base = base.replace(version=1)
    with pytest.raises(CodecError, match=str(case["error"])):
        decode(payload, base=base)
