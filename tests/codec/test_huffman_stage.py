"""The paper's Huffman / hex / run-length stage: golden bitstreams, round trips, and hostile input."""

from __future__ import annotations

import heapq
import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.codec import hexruns
from mapd.codec import huffman as hf
from mapd.errors import CodecError

GOLDEN = json.loads((Path(__file__).parent / "golden" / "huffman_stage.json").read_text())["cases"]


@pytest.mark.parametrize("case", GOLDEN, ids=[c["name"] for c in GOLDEN])
def test_golden_bitstream(case: dict) -> None:
    symbols = np.array(case["symbols"], dtype=np.uint8)
    stage = hf.encode_stage(symbols, case["alphabet"])
    assert stage.lengths.tolist() == case["lengths"]
    for sym, code in enumerate(case["codes"]):
        if code is not None:
            assert format(int(stage.codes[sym]), f"0{len(code)}b") == code
    assert hexruns.hex_string(stage.hexs) == case["hex"]
    assert [
        [int(n), "0123456789ABCDEF"[int(c)]] for n, c in zip(stage.counts, stage.chars, strict=True)
    ] == case["runs"]
    assert stage.wire.hex() == case["wire"]
    back = hf.decode(bytes.fromhex(case["wire"]), len(symbols), case["alphabet"])
    assert back.tolist() == case["symbols"]


def _reference_cost(counts: list[int]) -> int:
    """Total Huffman bits the textbook way: the sum of every merged node's weight."""
    heap = [c for c in counts if c > 0]
    if len(heap) == 1:
        return heap[0]
    heapq.heapify(heap)
    total = 0
    while len(heap) > 1:
        merged = heapq.heappop(heap) + heapq.heappop(heap)
        total += merged
        heapq.heappush(heap, merged)
    return total


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 5000), min_size=1, max_size=40).filter(lambda c: any(c)))
def test_code_lengths_are_optimal_and_prefix_free(counts: list[int]) -> None:
    lengths = hf.code_lengths(np.array(counts))
    # Same total length as a textbook Huffman tree (ties may pick other lengths, never a worse total).
    assert int(np.dot(lengths.astype(np.int64), counts)) == _reference_cost(counts)
    hf.check_lengths(lengths)
    codes = hf.canonical_codes(lengths)
    words = [format(int(codes[s]), f"0{lengths[s]}b") for s in range(len(counts)) if lengths[s]]
    for i, a in enumerate(words):
        for j, b in enumerate(words):
            assert i == j or not b.startswith(a), (a, b)  # by index: equal short strings are one object


def test_deep_trees_are_capped_at_15_bits() -> None:
    fib = [1, 1]
    while len(fib) < 24:
        fib.append(fib[-1] + fib[-2])
    counts = np.array(fib)
    assert max(hf._huffman_lengths(fib)) > hf.MAX_CODE_LEN  # the uncapped tree would be too deep
    lengths = hf.code_lengths(counts)
    assert int(lengths.max()) <= hf.MAX_CODE_LEN
    symbols = np.repeat(np.arange(len(fib), dtype=np.uint8), np.minimum(counts, 50))
    assert np.array_equal(hf.decode(hf.encode(symbols, 24), symbols.size, 24), symbols)


@settings(max_examples=80, deadline=None)
@given(
    alphabet=st.integers(1, 40),
    data=st.data(),
)
def test_round_trip_any_symbols(alphabet: int, data: st.DataObject) -> None:
    n = data.draw(st.integers(1, 3000))
    skew = data.draw(st.floats(0.05, 3.0))
    seed = data.draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    p = rng.dirichlet(np.full(alphabet, skew))
    symbols = rng.choice(alphabet, size=n, p=p).astype(np.uint8)
    if data.draw(st.booleans()):  # long runs, like a map's uniform areas
        symbols = np.repeat(symbols[: max(1, n // 50)], 50)[:n]
    wire = hf.encode(symbols, alphabet)
    assert np.array_equal(hf.decode(wire, symbols.size, alphabet), symbols)


def test_uniform_map_features_cost_a_few_bytes() -> None:
    symbols = np.full(500_000, 7, dtype=np.uint8)
    wire = hf.encode(symbols, 16)
    assert len(wire) < 20  # one run of 125000 zero hex digits
    assert np.array_equal(hf.decode(wire, symbols.size, 16), symbols)


# --------------------------------------------------------------------------------------------
# Hostile input
# --------------------------------------------------------------------------------------------


def _table(lengths: list[int]) -> bytes:
    return hf.pack_table(np.array(lengths, dtype=np.uint8))


@pytest.mark.parametrize(
    ("lengths", "message"),
    [
        ([1, 1, 1], "over-full"),
        ([1, 2], "incomplete"),
        ([0, 2], "single symbol"),
        ([2, 2, 2, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1], "symbols, the model has"),
    ],
)
def test_corrupt_huffman_table_is_refused(lengths: list[int], message: str) -> None:
    wire = _table(lengths) + hexruns.pack_runs(np.array([3]), np.array([0]))
    with pytest.raises(CodecError, match=message):
        hf.decode(wire, 10, 16)


def test_table_padding_and_minimal_size_are_checked() -> None:
    good = _table([1, 1, 0])  # stored as 2 symbols
    assert good == bytes([1, 0x11])
    with pytest.raises(CodecError, match="not minimal"):
        hf.unpack_table(bytes([2, 0x11, 0x00]), 0, 16)
    with pytest.raises(CodecError, match="padding"):
        hf.unpack_table(bytes([2, 0x11, 0x15]), 0, 16)
    with pytest.raises(CodecError, match="truncated"):
        hf.unpack_table(bytes([5, 0x11]), 0, 16)


def test_rle_count_past_the_declared_size_is_refused_without_allocating() -> None:
    # One run of 2^30 hex digits: 4 Gbit for a declared 100 symbols.
    runs = hexruns.pack_runs(np.array([1 << 30]), np.array([0]))
    wire = _table([1, 1]) + runs
    tracemalloc.start()
    try:
        with pytest.raises(CodecError, match="more than the"):
            hf.decode(wire, 100, 2)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20


def test_many_small_runs_past_the_declared_size_are_refused() -> None:
    counts = np.full(1000, 8)
    chars = np.tile(np.array([1, 2], dtype=np.uint8), 500)
    wire = _table([1, 1]) + hexruns.pack_runs(counts, chars)
    with pytest.raises(CodecError, match=r"runs for at most|more than the"):
        hf.decode(wire, 100, 2)


def test_every_truncation_is_a_codec_error() -> None:
    rng = np.random.default_rng(3)
    symbols = rng.choice(6, size=400, p=[0.5, 0.2, 0.1, 0.1, 0.05, 0.05]).astype(np.uint8)
    wire = hf.encode(symbols, 6)
    for cut in range(len(wire)):
        with pytest.raises(CodecError):
            hf.decode(wire[:cut], symbols.size, 6)


def test_too_few_or_too_many_symbols_are_refused() -> None:
    symbols = np.array([0, 1, 2, 3, 0, 1, 2, 3, 3, 3, 3, 3], dtype=np.uint8)
    wire = hf.encode(symbols, 4)
    with pytest.raises(CodecError):
        hf.decode(wire, symbols.size + 5, 4)
    with pytest.raises(CodecError, match="trailing"):
        hf.decode(wire, symbols.size - 4, 4)


@pytest.mark.parametrize(
    ("runs", "message"),
    [
        (bytes([2, 0x11, 0x00]), "adjacent runs"),  # two runs of character 1
        (bytes([1, 0x10, 0x80]), "non-minimal"),  # count nibbles 8, 0: a zero top group
        (bytes([1, 0x15, 0x00]), "padding"),  # odd character list padded with 5
        (bytes([1, 0x10, 0x30, 0x00]), "trailing"),  # a spare byte after the last count
        (bytes([0x80, 0x00]), "non-minimal run count"),  # LEB128 with a zero top byte
        (bytes([0]), "0 runs"),
    ],
)
def test_non_canonical_run_codes_are_refused(runs: bytes, message: str) -> None:
    with pytest.raises(CodecError, match=message):
        hf.decode(_table([1, 1]) + runs, 16, 2)


def test_non_zero_bit_padding_is_refused() -> None:
    # Six 1-bit symbols "000000" pad to "00000000" = hex 00; hex 03 would carry two set pad bits.
    good = _table([1, 1]) + hexruns.pack_runs(np.array([2]), np.array([0]))
    assert hf.decode(good, 6, 2).tolist() == [0] * 6
    bad = _table([1, 1]) + hexruns.pack_runs(np.array([1, 1]), np.array([0, 3]))
    with pytest.raises(CodecError, match="padding"):
        hf.decode(bad, 6, 2)


def test_undecodable_bits_for_a_one_symbol_table_are_refused() -> None:
    # The one-symbol code is "0"; a set bit matches no code.
    wire = _table([1]) + hexruns.pack_runs(np.array([1]), np.array([8]))
    with pytest.raises(CodecError, match="corrupt"):
        hf.decode(wire, 4, 1)


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=64), st.integers(1, 300), st.integers(1, 32))
def test_random_bytes_only_ever_raise_codec_error(blob: bytes, count: int, alphabet: int) -> None:
    try:
        out = hf.decode(blob, count, alphabet)
    except CodecError:
        return
    assert out.shape == (count,) and int(out.max()) < alphabet


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_flipped_bytes_only_ever_raise_codec_error_or_decode(data: st.DataObject) -> None:
    rng = np.random.default_rng(data.draw(st.integers(0, 1000)))
    symbols = rng.choice(5, size=300, p=[0.6, 0.2, 0.1, 0.05, 0.05]).astype(np.uint8)
    wire = bytearray(hf.encode(symbols, 5))
    i = data.draw(st.integers(0, len(wire) - 1))
    wire[i] ^= data.draw(st.integers(1, 255))
    try:
        out = hf.decode(bytes(wire), symbols.size, 5)
    except CodecError:
        return
    assert out.shape == symbols.shape
