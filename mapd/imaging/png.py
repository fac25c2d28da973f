"""PNG files checked whole before Pillow decodes them.

Pillow pads an image whose compressed data ends early (a complete zlib stream that holds too few
rows) with black, which map_server's rules read as walls. So :func:`check_png` walks the chunks
first: every CRC checked, IEND present, IHDR's size held against the cell limit before any pixel data
is inflated, and the IDAT stream inflated (in bounded pieces, counted, not kept) to at least the
size IHDR implies. A palette image must hold one well-formed PLTE chunk before its pixel data, as
libpng requires: without it Pillow decodes every pixel as black, which map_server's rules read as
walls. Its pixels' indices are checked against the palette after decoding
(:func:`mapd.imaging.pixels.pillow_pixels`), for the same reason.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

from mapd.errors import MapFileError
from mapd.imaging.pixels import check_cells, one_line

#: The eight bytes every PNG file starts with.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: colour type -> (samples per pixel, allowed bit depths)
_PNG_TYPES = {
    0: (1, (1, 2, 4, 8, 16)),
    2: (3, (8, 16)),
    3: (1, (1, 2, 4, 8)),
    4: (2, (8, 16)),
    6: (4, (8, 16)),
}
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
_PIECE = 1 << 20


def _png_raw_size(width: int, height: int, bits: int, interlaced: bool) -> int:
    """Bytes of filtered scanlines (a filter byte per row) IHDR's size and format imply."""
    if not interlaced:
        return height * (1 + (width * bits + 7) // 8)
    total = 0
    for xs, ys, dx, dy in _ADAM7:
        cols = (width - xs + dx - 1) // dx if width > xs else 0
        rows = (height - ys + dy - 1) // dy if height > ys else 0
        if cols and rows:
            total += rows * (1 + (cols * bits + 7) // 8)
    return total


def check_png(f: Any, where: str, image: Path, max_cells: int) -> int | None:
    """Walk a PNG's chunks: raise MapFileError unless it is complete and consistent, LimitError when
    IHDR's size is over ``max_cells`` (before any pixel data is inflated).

    Returns how many colours a palette image's PLTE holds (None for other colour types).
    """
    name = f"{where}: image '{image}'"
    cut = f"{name} is truncated (ends before its IEND chunk)"
    f.seek(len(PNG_SIGNATURE))
    inflater = zlib.decompressobj()
    expect = -1
    got = 0
    first = True
    colour = -1
    palette: int | None = None
    seen_idat = False
    while True:
        head = f.read(8)
        if len(head) < 8:
            raise MapFileError(cut)
        length, ctype = struct.unpack(">I4s", head)
        if length > 0x7FFFFFFF or not ctype.isalpha():
            raise MapFileError(f"{name} is corrupt (bad chunk header)")
        if first and (ctype != b"IHDR" or length != 13):
            raise MapFileError(f"{name} is corrupt (it does not start with IHDR)")
        if colour == 3 and ctype == b"PLTE":
            # libpng's rules: one PLTE, before the pixel data, of 1 to 256 whole RGB entries.
            if palette is not None or seen_idat:
                raise MapFileError(f"{name} is corrupt (a second PLTE chunk, or one after its pixel data)")
            if length == 0 or length % 3 or length > 3 * 256:
                raise MapFileError(f"{name} is corrupt (a PLTE chunk of {length} bytes)")
            palette = length // 3
        if ctype == b"IDAT":
            if colour == 3 and palette is None:
                raise MapFileError(
                    f"{name} is corrupt (a palette image without a PLTE chunk before its pixels)"
                )
            seen_idat = True
        crc = zlib.crc32(ctype)
        left = length
        ihdr = b""
        while left:
            piece = f.read(min(left, _PIECE))
            if not piece:
                raise MapFileError(cut)
            left -= len(piece)
            crc = zlib.crc32(piece, crc)
            if first:
                ihdr += piece
            elif ctype == b"IDAT" and got < expect:
                got += _inflate_count(inflater, piece, expect - got, name)
        tail = f.read(4)
        if len(tail) < 4:
            raise MapFileError(cut)
        if struct.unpack(">I", tail)[0] != crc:
            raise MapFileError(f"{name} is corrupt (CRC mismatch in its {ctype.decode()} chunk)")
        if first:
            width, height, depth, colour, comp, filt, interlace = struct.unpack(">IIBBBBB", ihdr)
            if (
                colour not in _PNG_TYPES
                or depth not in _PNG_TYPES[colour][1]
                or comp
                or filt
                or interlace > 1
            ):
                raise MapFileError(f"{name} is corrupt (impossible IHDR)")
            check_cells(width, height, where, image, max_cells)
            expect = _png_raw_size(width, height, depth * _PNG_TYPES[colour][0], bool(interlace))
            first = False
        if ctype == b"IEND":
            break
    if got < expect:
        raise MapFileError(
            f"{name} ends early: its pixel data holds {got} of {expect} bytes (truncated or cut short)"
        )
    return palette


def _inflate_count(inflater: Any, data: bytes, want: int, name: str) -> int:
    """Inflate ``data`` into the running stream, counting output up to ``want`` bytes (not kept)."""
    got = 0
    buf = data
    try:
        while True:
            out = inflater.decompress(buf, _PIECE)
            got += len(out)
            buf = inflater.unconsumed_tail
            if inflater.eof or got >= want or (not buf and len(out) < _PIECE):
                return got
    except zlib.error as exc:
        raise MapFileError(f"{name} is corrupt (its pixel data: {one_line(exc)})") from None
