"""JPEG files walked marker by marker before Pillow decodes them, to bound their scans.

libjpeg decodes a progressive JPEG one scan at a time, and every scan costs work in proportion to
the image's area, however few bytes it holds. A small file that repeats a refinement scan thousands
of times (each scan a few dozen bytes) kept ``mapd info`` busy for minutes on an 8192 x 8192 map.
libjpeg has no scan limit of its own (libjpeg-turbo's ``djpeg -maxscan`` is the application's job)
and Pillow offers none, so :func:`check_jpeg` counts the SOS markers first, without decoding
anything, and refuses a file with more than :data:`MAX_JPEG_SCANS`.

The walk finds markers as libjpeg does, so that it sees every scan libjpeg would decode: after SOI,
a marker is an 0xFF byte (any run of 0xFF fill bytes) followed by a code other than 0x00 (a stuffed
0xFF in entropy-coded data), RST0-RST7 or TEM (both without parameters, ignored by libjpeg); bytes
that are no marker (a scan's entropy-coded data, or junk libjpeg would skip with a warning) are
passed over. Every other marker but EOI carries a length, and its segment is skipped whole. The
file is read forward in pieces and searched in C (:mod:`re`), once: O(file size) time, at most a
piece held.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path
from typing import Any

from mapd.errors import LimitError, MapFileError

#: The first three bytes of every JPEG file (SOI, then the first marker's 0xFF), as Pillow sniffs it.
JPEG_SIGNATURE = b"\xff\xd8\xff"
#: Most scans (SOS markers) a JPEG may hold. libjpeg's own progressive script writes 10 scans for
#: colour, 6 for grey and 18 for CMYK, and encoders that tune the script (mozjpeg) stay in the
#: tens; a baseline image has 1 to 4. libjpeg-turbo's ``djpeg -maxscan`` and nvImageCodec (its
#: default is 256) guard against scan bombs the same way. 100 scans of the largest map loaded by
#: default (8192 x 8192) decode in under 5 s (its own 6 scans, 1 s), where 3000 took minutes.
MAX_JPEG_SCANS = 100

# A marker: 0xFF then a code that is not 0x00 (stuffing), 0xFF (a fill byte: the marker is the
# last 0xFF of the run), TEM (0x01) or RST0-RST7, which carry nothing and start no scan. Two fixed
# bytes, so the search never backtracks, whatever runs of 0xFF a file holds.
_MARKER = re.compile(b"\xff[^\x00\x01\xd0-\xd7\xff]")
_SOI, _EOI, _SOS = 0xD8, 0xD9, 0xDA
#: Bytes read at a time while walking the file.
_PIECE = 1 << 16


def check_jpeg(f: Any, where: str, image: Path) -> int:
    """Walk a JPEG's markers without decoding it; return how many scans it holds.

    Raises :class:`LimitError` for more than :data:`MAX_JPEG_SCANS` scans, and
    :class:`MapFileError` for a file that ends before its EOI marker (Pillow refuses one as
    truncated too, after decoding it), a segment length under 2 (impossible: it counts its own two
    bytes; libjpeg passes over such a COM or APPn segment without a word), or a second SOI (libjpeg
    refuses one too). Bytes after EOI are left alone, as libjpeg does.
    """
    name = f"{where}: image '{image}'"
    f.seek(0)
    if f.read(2) != JPEG_SIGNATURE[:2]:
        raise MapFileError(f"{name} is corrupt (it does not start with a JPEG SOI marker)")
    base, buf = 2, b""  # buf holds the file's bytes from offset base on
    at = 2  # file offset where the next marker is looked for
    scans = 0

    def refill(start: int, need: int) -> bool:
        """Hold the file's bytes from ``start`` on; False if fewer than ``need`` are left."""
        nonlocal base, buf
        f.seek(start)
        buf, base = f.read(max(need, _PIECE)), start
        return len(buf) >= need

    while True:
        found = _MARKER.search(buf, at - base) if base <= at <= base + len(buf) else None
        if found is None:
            # Not in the bytes held: go on from their end, keeping a last 0xFF not yet passed (it
            # may be the first half of a marker).
            end = base + len(buf)
            if at <= end:
                at = end - 1 if buf.endswith(b"\xff") and end - 1 >= at else end
            if not refill(at, 2):
                raise MapFileError(f"{name} is truncated (ends before its EOI marker)")
            continue
        code = buf[found.start() + 1]
        at = base + found.end()
        if code == _EOI:
            return scans
        if code == _SOI:
            raise MapFileError(f"{name} is corrupt (a second SOI marker)")
        if at + 2 > base + len(buf) and not refill(at, 2):
            raise MapFileError(f"{name} is truncated (ends before its EOI marker)")
        (length,) = struct.unpack_from(">H", buf, at - base)
        if length < 2:
            raise MapFileError(f"{name} is corrupt (a marker segment of length {length})")
        if code == _SOS:
            scans += 1
            if scans > MAX_JPEG_SCANS:
                raise LimitError(
                    f"{name} has more than {MAX_JPEG_SCANS} scans, the most mapd decodes "
                    "(a progressive JPEG has about 10)"
                )
        at += length  # the segment, its length bytes included; a scan's data follows it
