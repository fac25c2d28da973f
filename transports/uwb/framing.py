"""Self-synchronising framing for a byte stream: COBS with a 0x00 delimiter and a check per frame.

On the wire a frame is ``COBS(body || crc32_le(body)) || 0x00`` on an unkeyed link, and
``COBS(body) || 0x00`` on a keyed one. COBS removes every zero byte from the encoded part, so the
only zero on the line is the delimiter: a reader that joins mid-stream, or that saw garbage, a cut
line or a flipped bit, loses at most the frame it was in and recovers at the next delimiter. The CRC
catches what COBS cannot (flipped bits inside a frame). A keyed link's bodies end with a 48-bit
HMAC tag (:mod:`transports.uwb.signing`) that the verifier checks before anything reads the body:
it catches damage at least as surely as a CRC-32 (2^-48 against 2^-32 for a random error), so a
CRC there would spend 4 of a frame's bytes saying the same thing twice.

:class:`FrameReader` is a pure, bounded parser: it never holds more than ``max_frame`` bytes, counts
every kind of bad input instead of raising, and hands out frame bodies that passed COBS (and the CRC
when ``crc`` is set).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

from mapd.errors import ProtocolError

DELIM = 0
CRC_LEN = 4
#: Smallest frame worth configuring: the largest header plus a useful payload.
MIN_FRAME = 48


class CobsError(ProtocolError):
    """A frame's COBS encoding is broken (a zero code, a block past the end, a zero inside)."""


class RuntFrameError(ProtocolError):
    """A frame too short to hold its CRC."""


class CrcError(ProtocolError):
    """A frame whose CRC does not match its body (bits flipped on the line)."""


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data``: the result has no zero byte and is at most ``1 + len // 254`` longer."""
    out = bytearray()
    for part in data.split(b"\x00"):
        # A run of 254 non-zero bytes gets code 0xFF, which implies no zero after it.
        while len(part) >= 254:
            out.append(0xFF)
            out += part[:254]
            part = part[254:]
        out.append(len(part) + 1)
        out += part
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Invert :func:`cobs_encode`; raise :class:`CobsError` on a zero or truncated block."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise CobsError("uwb: COBS block code is zero")
        j = i + code
        if j > n:
            raise CobsError("uwb: COBS block runs past the end of the frame")
        block = data[i + 1 : j]
        if b"\x00" in block:
            raise CobsError("uwb: zero byte inside a COBS block")
        out += block
        if code < 0xFF and j < n:
            out.append(0)
        i = j
    return bytes(out)


def cobs_max_len(n: int) -> int:
    """The longest COBS encoding of ``n`` bytes."""
    return n + 1 + n // 254


def check_len(crc: bool) -> int:
    """Bytes a frame's check adds to its body: the CRC-32, or nothing on a keyed link."""
    return CRC_LEN if crc else 0


def max_body(max_frame: int, *, crc: bool = True) -> int:
    """The largest frame body whose wire form (COBS + check + delimiter) fits in ``max_frame`` bytes."""
    if max_frame < MIN_FRAME:
        raise ValueError(f"uwb: max_frame {max_frame} is below the minimum of {MIN_FRAME}")
    extra = check_len(crc)
    n = max_frame - 2 - extra
    while cobs_max_len(n + extra) + 1 > max_frame:
        n -= 1
    return n


def encode_frame(body: bytes, *, crc: bool = True) -> bytes:
    """The wire form of one frame body (with its CRC-32 unless the link is keyed)."""
    if crc:
        body += zlib.crc32(body).to_bytes(CRC_LEN, "little")
    return cobs_encode(body) + b"\x00"


def decode_frame(wire: bytes, *, crc: bool = True) -> bytes:
    """The body of one frame given without its delimiter.

    Raises a :class:`ProtocolError` whose type says what was wrong (:class:`CobsError`,
    :class:`RuntFrameError`, :class:`CrcError`), so :class:`FrameReader` counts each apart.
    """
    raw = cobs_decode(wire)
    if not crc:
        if not raw:
            raise RuntFrameError("uwb: empty frame")
        return raw
    if len(raw) <= CRC_LEN:
        raise RuntFrameError("uwb: frame shorter than its CRC")
    body, crc_bytes = raw[:-CRC_LEN], raw[-CRC_LEN:]
    if zlib.crc32(body).to_bytes(CRC_LEN, "little") != crc_bytes:
        raise CrcError("uwb: frame CRC mismatch")
    return body


@dataclass
class ReaderStats:
    """What a :class:`FrameReader` has seen; every bad input lands in exactly one counter."""

    bytes_in: int = 0
    frames: int = 0
    crc_errors: int = 0
    cobs_errors: int = 0
    oversize: int = 0
    runts: int = 0


class FrameReader:
    """Split a byte stream into verified frame bodies, holding at most ``max_frame`` bytes.

    Bytes past ``max_frame`` without a delimiter are dropped until the next delimiter (counted once
    as ``oversize``), so an endless stream without zeros costs constant memory.
    """

    def __init__(self, max_frame: int, *, crc: bool = True) -> None:
        self.max_frame = max_frame
        self.crc = crc
        self.stats = ReaderStats()
        self._buf = bytearray()
        self._skipping = False

    def feed(self, data: bytes) -> list[bytes]:
        """Consume ``data``; return the bodies of the complete frames that passed COBS and the CRC."""
        self.stats.bytes_in += len(data)
        bodies: list[bytes] = []
        start = 0
        limit = self.max_frame - 1  # the delimiter is part of the frame's wire size
        while True:
            end = data.find(b"\x00", start)
            piece = data[start:] if end < 0 else data[start:end]
            if not self._skipping:
                if len(self._buf) + len(piece) > limit:
                    self._buf.clear()
                    self._skipping = True
                    self.stats.oversize += 1
                else:
                    self._buf += piece
            if end < 0:
                return bodies
            if not self._skipping and self._buf:
                body = self._one(bytes(self._buf))
                if body is not None:
                    bodies.append(body)
            self._buf.clear()
            self._skipping = False
            start = end + 1

    def _one(self, wire: bytes) -> bytes | None:
        try:
            body = decode_frame(wire, crc=self.crc)
        except CobsError:
            self.stats.cobs_errors += 1
            return None
        except RuntFrameError:
            self.stats.runts += 1
            return None
        except CrcError:
            self.stats.crc_errors += 1
            return None
        self.stats.frames += 1
        return body
