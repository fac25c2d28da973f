"""The paper's entropy stage: Huffman code, hex string, run-length code (Algorithms 1 and 2).

Zhang & Deng (2024), Algorithm 1: collect the quantized feature values and their probabilities,
build a Huffman tree by merging the two least probable nodes (code table ``T``), write the values
as a bit string with ``T``, read the bit string as a hex string ``h``, and run-length code ``h``
(each run of one hex character becomes its count and its character) into ``e``. Algorithm 2 undoes
the three steps. This module does exactly that, vectorised with numpy (no Python loop over cells);
the hex string and the run-length code are :mod:`mapd.codec.hexruns`.

What the paper leaves open, and our choice (documented in ``models/paper-v3/MODEL_CARD.md``):

* ``T`` on the wire is a *canonical* Huffman code (DEFLATE style): only the code length of each
  symbol is sent, and both ends derive the same codes from the lengths. Lengths are capped at
  :data:`MAX_CODE_LEN` (15) so one length fits in a nibble; in the rare case a tree is deeper,
  counts are halved and the tree rebuilt (as zlib does). A single distinct value gets the code ``0``.
* The bit string is padded with zero bits to whole hex digits; the decoder knows the number of
  symbols from the payload header and refuses any other padding.
* ``e`` is stored column-wise: the number of runs, then every run's hex character (one nibble
  each), then every run's count minus one as a nibble varint (3 value bits, bit 3 = "more
  nibbles follow", least significant group first). A run of 1..8 characters costs one byte.

Wire form of the stage (``T`` then ``e``)::

    u8          alphabet size - 1 (A; symbols 0..A-1; trailing unused symbols are dropped)
    ceil(A/2)   code lengths, 4 bits each, high nibble first (0 = symbol absent); pad nibble 0
    varint      R, the number of runs (LEB128, at most 5 bytes)
    ceil(R/2)   the runs' hex characters, 4 bits each, high nibble first; pad nibble 0
    rest        the runs' counts - 1, nibble varints, high nibble first; pad nibble 0

The form is canonical: the decoder refuses non-minimal varints, adjacent runs of the same character,
non-zero padding, an incomplete or over-full code table and trailing bytes, so one symbol array has
exactly one encoding (which the golden tests pin).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np
from numba import njit

from mapd.codec.hexruns import bits_to_hex, pack_runs, run_lengths, unpack_runs
from mapd.errors import CodecError

MAX_CODE_LEN = 15
MAX_ALPHABET = 256


# --------------------------------------------------------------------------------------------
# Code table T
# --------------------------------------------------------------------------------------------


def _huffman_lengths(counts: list[int]) -> list[int]:
    """Code lengths of a Huffman tree over the non-zero ``counts`` (merge the two least probable)."""
    live = [(c, i) for i, c in enumerate(counts) if c > 0]
    lengths = [0] * len(counts)
    if len(live) == 1:
        lengths[live[0][1]] = 1
        return lengths
    # Heap items: (weight, tie-break id, member symbols). The id keeps ties deterministic.
    heap: list[tuple[int, int, list[int]]] = [(c, i, [i]) for c, i in live]
    heapq.heapify(heap)
    next_id = len(counts)
    while len(heap) > 1:
        w1, _, s1 = heapq.heappop(heap)
        w2, _, s2 = heapq.heappop(heap)
        for s in s1:
            lengths[s] += 1
        for s in s2:
            lengths[s] += 1
        heapq.heappush(heap, (w1 + w2, next_id, s1 + s2))
        next_id += 1
    return lengths


def code_lengths(counts: np.ndarray, max_len: int = MAX_CODE_LEN) -> np.ndarray:
    """Huffman code lengths for symbol ``counts`` (uint8), capped at ``max_len`` bits.

    A deeper tree only arises from extremely skewed counts; then the counts are halved (keeping
    every used symbol at least 1) and the tree rebuilt until it fits, as zlib does.
    """
    c = [int(v) for v in np.asarray(counts).ravel()]
    if not c or len(c) > MAX_ALPHABET or min(c) < 0 or max(c) == 0:
        raise CodecError("huffman: need 1..256 symbol counts with at least one non-zero")
    while True:
        lengths = _huffman_lengths(c)
        if max(lengths) <= max_len:
            return np.array(lengths, dtype=np.uint8)
        c = [0 if v == 0 else max(1, v >> 1) for v in c]


def canonical_codes(lengths: np.ndarray) -> np.ndarray:
    """Canonical code of each symbol (uint32; meaningless where the length is 0).

    Symbols sorted by (length, symbol) take consecutive code values; a longer code continues from
    the previous one shifted left. Both ends derive the same codes from the lengths alone.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    codes = np.zeros(lengths.size, dtype=np.uint32)
    code = 0
    prev = 0
    for sym in sorted((int(s) for s in np.flatnonzero(lengths)), key=lambda s: (lengths[s], s)):
        code <<= int(lengths[sym]) - prev
        prev = int(lengths[sym])
        codes[sym] = code
        code += 1
    return codes


def check_lengths(lengths: np.ndarray) -> None:
    """Refuse a code table that is not a complete prefix code (or the one-symbol code ``0``)."""
    used = lengths[lengths > 0].astype(np.int64)
    if used.size == 0:
        raise CodecError("huffman table is corrupt (no symbols)")
    if used.size == 1:
        if int(used[0]) != 1:
            raise CodecError("huffman table is corrupt (a single symbol must have a 1-bit code)")
        return
    kraft = int(np.sum(np.left_shift(1, MAX_CODE_LEN - used)))
    if kraft != 1 << MAX_CODE_LEN:
        state = "over-full" if kraft > 1 << MAX_CODE_LEN else "incomplete"
        raise CodecError(f"huffman table is corrupt ({state} prefix code)")


def pack_table(lengths: np.ndarray) -> bytes:
    """``T`` on the wire: alphabet size - 1, then one nibble per symbol's code length."""
    lengths = np.asarray(lengths, dtype=np.uint8)
    used = np.flatnonzero(lengths)
    size = int(used[-1]) + 1
    nib = lengths[:size]
    if size % 2:
        nib = np.append(nib, np.uint8(0))
    packed = (nib[0::2] << 4) | nib[1::2]
    return bytes([size - 1]) + packed.astype(np.uint8).tobytes()


def unpack_table(buf: bytes, pos: int, alphabet: int) -> tuple[np.ndarray, int]:
    """Read ``T`` at ``pos``; return the code lengths (size ``alphabet``) and the next position."""
    if pos >= len(buf):
        raise CodecError("huffman table is truncated")
    size = buf[pos] + 1
    if size > alphabet:
        raise CodecError(f"huffman table is corrupt ({size} symbols, the model has {alphabet})")
    nbytes = (size + 1) // 2
    raw = (
        np.frombuffer(buf, dtype=np.uint8, count=nbytes, offset=pos + 1)
        if pos + 1 + nbytes <= len(buf)
        else None
    )
    if raw is None:
        raise CodecError("huffman table is truncated")
    nib = np.empty(2 * nbytes, dtype=np.uint8)
    nib[0::2] = raw >> 4
    nib[1::2] = raw & 0x0F
    if size % 2 and nib[-1] != 0:
        raise CodecError("huffman table is corrupt (non-zero padding)")
    if nib[size - 1] == 0:
        raise CodecError("huffman table is corrupt (alphabet size not minimal)")
    lengths = np.zeros(alphabet, dtype=np.uint8)
    lengths[:size] = nib[:size]
    check_lengths(lengths)
    return lengths, pos + 1 + nbytes


# --------------------------------------------------------------------------------------------
# Symbols -> bits (bits <-> hex <-> runs: mapd.codec.hexruns)
# --------------------------------------------------------------------------------------------


def to_bits(symbols: np.ndarray, lengths: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Concatenate the codes of ``symbols`` into a bit array (uint8 0/1)."""
    sym = np.asarray(symbols).ravel()
    lens = lengths[sym].astype(np.int64)
    if np.any(lens == 0):
        raise CodecError("huffman: a symbol has no code")
    width = int(lens.max())
    # Left-justify every code in 16 bits (codes are at most 15), unpack the big-endian bytes to a
    # (n, 16) bit matrix and keep the first `len` bits of each row.
    just = (codes.astype(np.uint16)[sym] << (16 - lens).astype(np.uint16)).astype(">u2")
    mat = np.unpackbits(just.view(np.uint8).reshape(-1, 2), axis=1)[:, :width]
    keep = np.arange(width, dtype=np.int64)[None, :] < lens[:, None]
    return mat[keep]


# --------------------------------------------------------------------------------------------
# Algorithm 1 and 2
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stage:
    """Every intermediate of Algorithm 1, for tests and for explaining a payload."""

    lengths: np.ndarray
    codes: np.ndarray
    bits: np.ndarray
    hexs: np.ndarray
    counts: np.ndarray
    chars: np.ndarray
    wire: bytes


def encode_stage(symbols: np.ndarray, alphabet: int) -> Stage:
    """Algorithm 1 on integer ``symbols`` in ``0..alphabet-1``; ``wire`` is ``T`` followed by ``e``."""
    sym = np.asarray(symbols).ravel()
    if sym.size == 0:
        raise CodecError("huffman: nothing to encode")
    if not 1 <= alphabet <= MAX_ALPHABET:
        raise CodecError(f"huffman: alphabet of {alphabet} symbols (1..{MAX_ALPHABET} supported)")
    if int(sym.min()) < 0 or int(sym.max()) >= alphabet:
        raise CodecError("huffman: symbol outside the alphabet")
    counts = np.bincount(sym, minlength=alphabet)
    lengths = code_lengths(counts)
    codes = canonical_codes(lengths)
    bits = to_bits(sym, lengths, codes)
    hexs = bits_to_hex(bits)
    run_counts, chars = run_lengths(hexs)
    wire = pack_table(lengths) + pack_runs(run_counts, chars)
    return Stage(lengths, codes, bits, hexs, run_counts, chars, wire)


def encode(symbols: np.ndarray, alphabet: int) -> bytes:
    """Algorithm 1: integer symbols to the wire form of (T, e)."""
    return encode_stage(symbols, alphabet).wire


def _decode_table(lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Lookup tables indexed by the next ``width`` bits: (symbol, code length; 0 = invalid)."""
    width = int(lengths.max())
    codes = canonical_codes(lengths)
    order = sorted((int(s) for s in np.flatnonzero(lengths)), key=lambda s: (lengths[s], s))
    order_a = np.array(order, dtype=np.int64)
    lens = lengths[order_a].astype(np.int64)
    spans = np.left_shift(1, width - lens)
    firsts = codes[order_a].astype(np.int64) << (width - lens)
    size = 1 << width
    sym_t = np.zeros(size, dtype=np.uint8)
    len_t = np.zeros(size, dtype=np.int64)
    # Canonical codes left-justified are consecutive, so each symbol owns one contiguous span.
    covered = int(spans.sum())
    assert int(firsts[0]) == 0
    sym_t[:covered] = np.repeat(order_a, spans).astype(np.uint8)
    len_t[:covered] = np.repeat(lens, spans)
    return sym_t, len_t, width


# Outcomes of :func:`_decode_runs` besides 0 (all symbols decoded, the rest is valid padding).
_FEWER, _LAST, _TRAILING, _PADDING = 1, 2, 3, 4


@njit(cache=True, nogil=True)
def _decode_runs(
    counts: np.ndarray,
    chars: np.ndarray,
    sym_t: np.ndarray,
    len_t: np.ndarray,
    width: int,
    out: np.ndarray,
) -> int:
    """Decode ``out.size`` symbols straight from the runs (hex character, count), one code at a time.

    The bit string is never expanded: a run of 63 million hex digits costs no memory, and the only
    array the size of the map is ``out``. The code at each position is read from the next ``width``
    bits (zeros past the end), as the tables expect. Returns 0, or why the bit string is bad:
    ``_FEWER`` (it ends, or a code is invalid, before the last symbol), ``_LAST`` (the last code is
    invalid or runs past the end), ``_TRAILING`` (four or more bits after the last code) or
    ``_PADDING`` (the bits after it are not zero).
    """
    count = out.size
    nruns = counts.size
    mask = (1 << width) - 1
    acc = 0  # bits read but not yet consumed, in the low `have` bits
    have = 0
    run = 0
    left = counts[0] if nruns > 0 else 0  # hex digits left in the current run
    for m in range(count):
        while have < width and run < nruns:
            acc = (acc << 4) | chars[run]
            have += 4
            left -= 1
            if left == 0:
                run += 1
                if run < nruns:
                    left = counts[run]
        if have == 0:
            return _FEWER
        window = (acc >> (have - width)) if have >= width else (acc << (width - have))
        window &= mask
        n = len_t[window]
        if n == 0 or n > have:
            return _LAST if m == count - 1 else _FEWER
        out[m] = sym_t[window]
        have -= n
        acc &= (1 << have) - 1
    rest = 0
    if run < nruns:
        rest = left
        for j in range(run + 1, nruns):
            rest += counts[j]
    if have + 4 * rest >= 4:
        return _TRAILING
    if acc != 0:
        return _PADDING
    return 0


def decode(buf: bytes, count: int, alphabet: int, pos: int = 0) -> np.ndarray:
    """Algorithm 2: the wire form of (T, e) from ``pos`` to the end back to ``count`` symbols (uint8).

    Raises :class:`CodecError` on a corrupt table, a run-length code that would expand past what
    ``count`` symbols can occupy, a truncated bit string, or trailing data. Memory is the ``count``
    output symbols plus the runs as sent: the hex string and the bits are never built, so a few
    bytes claiming millions of hex digits cost time in proportion to ``count`` and nothing more.
    """
    if count <= 0:
        raise CodecError("huffman: nothing to decode")
    lengths, pos = unpack_table(buf, pos, alphabet)
    width = int(lengths.max())
    min_len = int(lengths[lengths > 0].min())
    max_hex = -(-count * width // 4)
    min_hex = -(-count * min_len // 4)
    run_counts, chars = unpack_runs(buf, pos, max_hex)
    total = int(run_counts.sum())
    if total < min_hex:
        raise CodecError(f"bit string is truncated ({total} hex digits for {count} symbols)")
    sym_t, len_t, width = _decode_table(lengths)
    out = np.empty(count, dtype=np.uint8)
    status = _decode_runs(
        np.ascontiguousarray(run_counts, dtype=np.int64),
        np.ascontiguousarray(chars, dtype=np.uint8),
        sym_t,
        len_t,
        width,
        out,
    )
    if status == _FEWER:
        raise CodecError(f"bit string is truncated or corrupt (fewer than {count} codes)")
    if status == _LAST:
        raise CodecError("bit string is truncated or corrupt (in its last code)")
    if status == _TRAILING:
        raise CodecError("bit string has trailing data after the last code")
    if status == _PADDING:
        raise CodecError("bit string is corrupt (non-zero padding)")
    return out
