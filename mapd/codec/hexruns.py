"""The hex and run-length steps of the paper's entropy stage: bits to hex string ``h`` to runs ``e``.

Zhang & Deng (2024), Algorithm 1 reads the Huffman-coded bit string (:mod:`mapd.codec.huffman`) as
a hex string ``h``, padding the last digit with zero bits, and run-length codes ``h`` into ``e``:
each run of one hex character becomes its count and its character. Algorithm 2 undoes the two steps
(the Huffman decoder reads its codes straight from the runs, so the bits are never expanded).
Vectorised with numpy, as the rest of the stage.

``e`` on the wire is column-wise and canonical (the reader refuses any other form)::

    varint      R, the number of runs (LEB128, at most 5 bytes)
    ceil(R/2)   the runs' hex characters, 4 bits each, high nibble first; pad nibble 0
    rest        the runs' counts - 1 as nibble varints (3 value bits, bit 3 = "more nibbles
                follow", least significant group first), high nibble first; pad nibble 0

A run of 1..8 characters costs one byte; adjacent runs of one character, non-minimal varints,
non-zero padding and trailing bytes are refused, and so is a code that expands past ``max_hex``.
"""

from __future__ import annotations

import numpy as np

from mapd.codec.varint import VarintErrors, get_uvarint, put_uvarint
from mapd.errors import CodecError

#: A run count is at most 10 nibbles (30 bits), far above any count a legal map needs.
MAX_COUNT_NIBBLES = 10
_MAX_VARINT_BYTES = 5


def bits_to_hex(bits: np.ndarray) -> np.ndarray:
    """Read bits as hex digits (uint8 0..15), padding the last digit with zero bits."""
    pad = (-bits.size) % 4
    if pad:
        bits = np.concatenate([bits, np.zeros(pad, dtype=np.uint8)])
    return (bits.reshape(-1, 4) @ np.array([8, 4, 2, 1], dtype=np.uint8)).astype(np.uint8)


def hex_string(hexs: np.ndarray) -> str:
    """The hex digits as the paper writes ``h`` (for logs and tests; the wire form is nibbles)."""
    return "".join("0123456789ABCDEF"[int(v)] for v in hexs)


def run_lengths(hexs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Runs of equal hex characters: (counts int64, characters uint8)."""
    if hexs.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.uint8)
    starts = np.concatenate([[0], np.flatnonzero(hexs[1:] != hexs[:-1]) + 1])
    counts = np.diff(np.append(starts, hexs.size)).astype(np.int64)
    return counts, hexs[starts].astype(np.uint8)


def _pack_nibbles(nib: np.ndarray) -> bytes:
    if nib.size % 2:
        nib = np.append(nib, np.uint8(0))
    return ((nib[0::2] << 4) | nib[1::2]).astype(np.uint8).tobytes()


def _unpack_nibbles(buf: bytes, start: int, nbytes: int) -> np.ndarray:
    raw = np.frombuffer(buf, dtype=np.uint8, count=nbytes, offset=start)
    nib = np.empty(2 * nbytes, dtype=np.uint8)
    nib[0::2] = raw >> 4
    nib[1::2] = raw & 0x0F
    return nib


#: How the run count (the one LEB128 varint of the stage) reports a bad form.
_RUN_COUNT_ERRORS = VarintErrors(
    truncated="run-length code is truncated (in the run count)",
    non_minimal="run-length code is corrupt (non-minimal run count)",
    overlong="run-length code is corrupt (run count too long)",
)


def pack_runs(counts: np.ndarray, chars: np.ndarray) -> bytes:
    """``e`` on the wire: run count, character nibbles, then count-1 nibble varints."""
    v = np.asarray(counts, dtype=np.int64) - 1
    if v.size and (v.min() < 0 or int(v.max()) >= 1 << (3 * MAX_COUNT_NIBBLES)):
        raise CodecError("run-length code: run count out of range")
    groups = np.ones(v.size, dtype=np.int64)
    rest = v >> 3
    while np.any(rest):
        groups += rest > 0
        rest >>= 3
    width = int(groups.max()) if v.size else 1
    j = np.arange(width, dtype=np.int64)
    mat = ((v[:, None] >> (3 * j)[None, :]) & 7) | np.where(j[None, :] < groups[:, None] - 1, 8, 0)
    nib = mat[j[None, :] < groups[:, None]].astype(np.uint8)
    return put_uvarint(int(v.size)) + _pack_nibbles(np.asarray(chars, dtype=np.uint8)) + _pack_nibbles(nib)


def unpack_runs(buf: bytes, pos: int, max_hex: int) -> tuple[np.ndarray, np.ndarray]:
    """Read ``e`` from ``pos`` to the end of ``buf``; refuse more than ``max_hex`` characters in all."""
    runs, pos = get_uvarint(buf, pos, _MAX_VARINT_BYTES, _RUN_COUNT_ERRORS)
    if runs == 0 or runs > max_hex:
        raise CodecError(f"run-length code is corrupt ({runs} runs for at most {max_hex} hex digits)")
    nbytes = (runs + 1) // 2
    if pos + nbytes > len(buf):
        raise CodecError("run-length code is truncated (in the characters)")
    chars = _unpack_nibbles(buf, pos, nbytes)
    if runs % 2 and chars[-1] != 0:
        raise CodecError("run-length code is corrupt (non-zero padding)")
    chars = chars[:runs]
    if np.any(chars[1:] == chars[:-1]):
        raise CodecError("run-length code is corrupt (two adjacent runs of one character)")
    pos += nbytes
    nib = _unpack_nibbles(buf, pos, len(buf) - pos)
    ends = np.flatnonzero(nib < 8)
    if ends.size < runs:
        raise CodecError("run-length code is truncated (in the counts)")
    ends = ends[:runs]
    used = int(ends[-1]) + 1
    if not (used == nib.size or (used == nib.size - 1 and nib[-1] == 0)):
        raise CodecError("run-length code has trailing bytes")
    starts = np.concatenate([[0], ends[:-1] + 1])
    sizes = ends - starts + 1
    if int(sizes.max()) > MAX_COUNT_NIBBLES:
        raise CodecError("run-length code is corrupt (run count too long)")
    if np.any((sizes > 1) & (nib[ends] == 0)):
        raise CodecError("run-length code is corrupt (non-minimal run count)")
    j = np.arange(used, dtype=np.int64) - np.repeat(starts, sizes)
    vals = np.add.reduceat((nib[:used] & 7).astype(np.int64) << (3 * j), starts)
    counts = vals + 1
    total = int(counts.sum())
    if total > max_hex:
        raise CodecError(f"run-length code expands to {total} hex digits, more than the {max_hex} allowed")
    return counts, chars
