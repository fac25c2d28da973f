"""Gzip CARMEN logs cut short or damaged part-way, and what a reader can still use of them.

Shared by the reader, ``mapd replay`` and ``laserlog`` source tests of a log that ends early.
"""

from __future__ import annotations

import zlib
from pathlib import Path


def blocked_gzip(text: bytes, lines_per_block: int) -> tuple[bytes, list[int]]:
    """``text`` gzip-compressed with a full flush every ``lines_per_block`` lines, and each flush's offset.

    The bytes before a flush's offset hold exactly the lines before it, so a cut there is a clean
    cut between lines and a cut between two offsets is a cut in the middle of a deflate block.
    """
    co = zlib.compressobj(9, zlib.DEFLATED, 31)
    lines = text.splitlines(keepends=True)
    out = bytearray()
    marks = []
    for i in range(0, len(lines), lines_per_block):
        out += co.compress(b"".join(lines[i : i + lines_per_block]))
        out += co.flush(zlib.Z_FULL_FLUSH)
        marks.append(len(out))
    out += co.flush()
    return bytes(out), marks


def whole_lines(gz: bytes, end: int) -> bytes:
    """The lines the first ``end`` bytes of gzip ``gz`` hold whole: what a reader cut there can use."""
    got = zlib.decompressobj(31).decompress(gz[:end])
    return got[: got.rfind(b"\n") + 1]


def scan_lines(text: bytes) -> int:
    """How many FLASER lines ``text`` holds."""
    return sum(ln.startswith(b"FLASER ") for ln in text.splitlines())


def write_prefix(path: Path, gz: bytes, end: int) -> Path:
    """A plain log of the lines the first ``end`` bytes of ``gz`` hold whole: the cut log, intact."""
    path.write_bytes(whole_lines(gz, end))
    return path
