"""LEB128 varints, the one implementation behind the Huffman stage's run count and lossless's offsets.

A value is written seven bits a byte, least significant group first; bit 7 says "more bytes
follow". The reader is strict, because the codecs promise one encoding per map (the golden tests
pin it): it refuses a non-minimal form (a last byte of zero after the first), a value longer than
``max_bytes`` and a buffer that ends inside the varint. Signed values go through zigzag
(0, -1, 1, -2, ... -> 0, 1, 2, 3, ...) so that small offsets of either sign stay short.
"""

from __future__ import annotations

from typing import NamedTuple

from mapd.errors import CodecError


class VarintErrors(NamedTuple):
    """What a reader says for each way a varint can be bad; each caller names its own field."""

    truncated: str
    non_minimal: str
    overlong: str


def put_uvarint(value: int) -> bytes:
    """``value`` (>= 0) as an unsigned LEB128 varint."""
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def get_uvarint(buf: bytes, pos: int, max_bytes: int, errors: VarintErrors) -> tuple[int, int]:
    """Read an unsigned varint at ``pos``: ``(value, position after it)``.

    Raises :class:`~mapd.errors.CodecError` with the matching message of ``errors`` when the buffer
    ends inside it, it is not minimal, or it runs over ``max_bytes`` bytes.
    """
    value = 0
    for i in range(max_bytes):
        if pos + i >= len(buf):
            raise CodecError(errors.truncated)
        byte = buf[pos + i]
        value |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            if byte == 0 and i > 0:
                raise CodecError(errors.non_minimal)
            return value, pos + i + 1
    raise CodecError(errors.overlong)


def zigzag(n: int) -> int:
    """A signed 64-bit integer as the unsigned number zigzag order gives it."""
    return (n << 1) ^ (n >> 63)


def unzigzag(z: int) -> int:
    """The signed integer of zigzag number ``z``."""
    return (z >> 1) ^ -(z & 1)
