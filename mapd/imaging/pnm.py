"""PNM (netpbm) images, the format map_saver writes (P5), parsed and read without surprises.

The header is parsed here so that a truncated or malformed file is one clear error and the size is
checked before anything is allocated; P5 and P6 pixels are read with numpy (Pillow converts maxval
other than 255 one sample at a time in Python), with Pillow's rounding kept exactly. Plain (ASCII)
P1-P3 and bitmap P4 files are validated and their length checked here, then decoded by Pillow.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mapd.errors import LimitError, MapFileError
from mapd.imaging.pixels import Pixels, check_cells

#: Longest PNM header (magic, sizes, maxval and comments) searched for the start of the pixels.
MAX_PNM_HEADER = 64 * 1024
#: Plain (ASCII) PNM is decoded by Pillow one number at a time (about 0.5 s per million pixels);
#: above this many pixels it is refused, so that a large ASCII file cannot take minutes to load.
PLAIN_PNM_MAX_CELLS = 1 << 22

#: What netpbm counts as white space between header fields.
PNM_WS = b" \t\n\r\x0b\x0c"
_PNM_DIGITS = b"0123456789"


def _pnm_header(head: bytes, where: str, image: Path) -> tuple[int, list[int], int]:
    """``(kind 1..6, [width, height(, maxval)], offset of the first pixel byte)`` of a PNM header."""
    kind = head[1] - ord("0")
    need = 2 if kind in (1, 4) else 3
    values: list[int] = []
    pos = 2
    bad = f"{where}: image '{image}' has a malformed PNM header"
    cut = f"{where}: image '{image}' is truncated in its PNM header"
    while len(values) < need:
        while True:  # white space and comments before the number
            if pos >= len(head):
                raise MapFileError(cut)
            c = head[pos]
            if c in PNM_WS:
                pos += 1
            elif c == ord("#"):
                ends = [i for i in (head.find(b"\n", pos), head.find(b"\r", pos)) if i >= 0]
                if not ends:
                    raise MapFileError(cut)
                pos = min(ends) + 1
            else:
                break
        start = pos
        while pos < len(head) and head[pos] in _PNM_DIGITS:
            pos += 1
        if pos == start:
            raise MapFileError(f"{bad} (expected a number at byte {start})")
        if pos >= len(head):
            raise MapFileError(cut)  # the number may go on in the bytes that are missing
        if pos - start > 9:
            raise MapFileError(f"{bad} (a number of {pos - start} digits)")
        values.append(int(head[start:pos]))
    # Exactly one white-space byte ends the header (a comment there ends with its newline).
    if pos >= len(head):
        raise MapFileError(cut)
    if head[pos] == ord("#"):
        ends = [i for i in (head.find(b"\n", pos), head.find(b"\r", pos)) if i >= 0]
        if not ends:
            raise MapFileError(cut)
        pos = min(ends)
    if head[pos] not in PNM_WS:
        raise MapFileError(f"{bad} (no white space after the last number)")
    if need == 3 and not 1 <= values[2] <= 65535:
        raise MapFileError(f"{where}: image '{image}' has PNM maxval {values[2]}; it must be 1..65535")
    return kind, values, pos + 1


def _pnm_lut(kind: int, maxval: int) -> np.ndarray:
    """Grey level (0..255, float64) of every possible sample, with Pillow's rounding for maxval != 255
    (the rule mapd has always loaded PNM with): 8-bit output ``min(255, round(v / maxval * 255))``;
    a 16-bit grey image keeps 16 bits, ``min(65535, round(v / maxval * 65535))``, then scales to 255."""
    v = np.arange(256 if maxval < 256 else 65536, dtype=np.float64)
    if kind == 5 and maxval > 255:
        return np.minimum(65535.0, np.rint(v / maxval * 65535.0)) * (255.0 / 65535.0)
    if maxval == 255:
        return v
    return np.minimum(255.0, np.rint(v / maxval * 255.0))


def read_pnm(f: Any, size: int, where: str, image: Path, max_cells: int) -> Pixels | None:
    """PNM pixels (P5, P6); None when Pillow should decode the validated file (P1-P4)."""
    head = f.read(MAX_PNM_HEADER)
    try:
        kind, values, offset = _pnm_header(head, where, image)
    except MapFileError:
        if len(head) >= MAX_PNM_HEADER:
            raise MapFileError(
                f"{where}: image '{image}' has no PNM header in its first {MAX_PNM_HEADER} bytes"
            ) from None
        raise
    width, height = values[0], values[1]
    check_cells(width, height, where, image, max_cells)
    maxval = values[2] if len(values) == 3 else 1
    sample = 1 if maxval < 256 else 2
    channels = 3 if kind in (3, 6) else 1
    if kind in (1, 2, 3):
        if width * height > PLAIN_PNM_MAX_CELLS:
            raise LimitError(
                f"{where}: image '{image}' is a plain (ASCII) PNM of {width * height} pixels, over the "
                f"{PLAIN_PNM_MAX_CELLS} mapd decodes in that form; save it as binary P5"
            )
        # Each sample takes at least one digit and (but P1) one separator.
        least = width * height if kind == 1 else 2 * width * height * channels - 1
    elif kind == 4:
        least = (width + 7) // 8 * height
    else:
        least = width * height * channels * sample
    have = size - offset
    if have < least:
        raise MapFileError(
            f"{where}: image '{image}' ends early: {max(have, 0)} of {least} pixel bytes "
            "(truncated or still being written)"
        )
    if kind in (1, 2, 3, 4):
        return None
    f.seek(offset)
    raw = f.read(least)
    if len(raw) != least:
        raise MapFileError(f"{where}: image '{image}' ends early (it changed while being read)")
    dtype = np.dtype(np.uint8) if sample == 1 else np.dtype(">u2")
    shape = (height, width, channels)
    arr = np.frombuffer(raw, dtype=dtype).reshape(shape)
    if maxval != (255 if sample == 1 else 65535) and (top := int(arr.max(initial=0))) > maxval:
        # Netpbm: every sample is at most maxval. Clamped (Pillow's rule for the lut) such a
        # sample read as white, free space, though the file is damaged; the plain forms refuse it.
        raise MapFileError(f"{where}: image '{image}' has a sample of {top}, over its PNM maxval {maxval}")
    return Pixels(arr, has_alpha=False, lut=_pnm_lut(kind, maxval))
