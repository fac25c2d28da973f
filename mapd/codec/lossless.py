"""``lossless``: a context-mixing arithmetic coder made for occupancy grids, with delta coding.

Every cell comes back exactly. Trinary maps (-1/0/100) are coded as cell classes predicted from
their causal neighbours (see :mod:`mapd.codec.ctx_kernels`); any other int8 value takes an escape
path that codes its exact byte, so Cartographer-style 0..100 grids and odd values round-trip too.
Against a base version both ends hold, a grid is coded as "what changed", after aligning the two
grids by their origins; the encoder also codes the whole map and sends whichever is smaller. A base
that cannot be aligned cell for cell (other resolution or yaw, or an origin off by a fraction of a
cell) gets the whole map.

The model and coder are numba-compiled (``cache=True``: the first call on a machine compiles for
some seconds and stores the result beside the package; later processes load it in a fraction of a
second). Integer arithmetic only, so robots of different architectures decode each other exactly.

Body layout (after the header of :mod:`mapd.codec.api`)::

    format   u8   bits 0-1 mode (0 whole map, 1 delta), bit 2 trinary (no escape path),
                  bits 3-7 the model version (:data:`~mapd.codec.ctx_kernels.MODEL_VERSION`)
    [delta]  off_r, off_c: zigzag LEB128 varints (at most 5 bytes each): new cell (r, c) lies on
             base cell (r + off_r, c + off_c)
    stream   the arithmetic-coded cells (see :mod:`mapd.codec.ctx_kernels` for its end rule)
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field

from mapd.codec.base import Codec, CodecOptions, Encoded, Target
from mapd.codec.ctx_kernels import (
    MODEL_VERSION,
    QUIET_LIMIT,
    build_rates,
    build_tables,
    code_delta,
    code_whole,
    hash_bits,
)
from mapd.codec.varint import VarintErrors, get_uvarint, put_uvarint, unzigzag, zigzag
from mapd.errors import CodecError
from mapd.grid import OccupancyGrid, Pose2D

MODE_WHOLE = 0
MODE_DELTA = 1
MODE_MASK = 0x03
FLAG_TRINARY = 0x04
VERSION_SHIFT = 3
#: Offsets must fit in 32 signed bits (a grid is at most 2**26 cells, so real ones are far smaller).
MAX_OFFSET = (1 << 31) - 1
#: A zigzagged offset of 32 bits takes at most five varint bytes.
_MAX_OFFSET_BYTES = 5
#: How far from a whole cell an origin offset may be and still align (in cells).
ALIGN_TOL = 1e-3

_SQ, _ST = build_tables()
_RATES = build_rates(QUIET_LIMIT)
_EMPTY = np.zeros(0, np.uint8)


def _writable(cells: np.ndarray) -> np.ndarray:
    """``cells`` as the kernels take them: contiguous int8, and writable (one kernel both codes and
    decodes, so numba refuses a read-only view, as a map decoded in place from a message's bytes is)."""
    out = np.ascontiguousarray(cells, dtype=np.int8)
    return out if out.flags.writeable else out.copy()


class LosslessOptions(CodecOptions):
    """Options of the ``[codec.lossless]`` table."""

    delta: Literal["auto", "always", "never"] = Field(
        default="auto",
        description="with a base: 'auto' sends the smaller of delta and whole map, 'always' the "
        "delta whenever the grids align, 'never' the whole map",
    )


@njit(cache=True, nogil=True)
def _is_trinary(data: np.ndarray) -> bool:
    for v in data.ravel():  # noqa: SIM110 (numba compiles the loop, not all() over a generator)
        if v != -1 and v != 0 and v != 100:
            return False
    return True


def alignment(resolution: float, origin: Pose2D, base: OccupancyGrid) -> tuple[int, int] | None:
    """``(off_r, off_c)`` such that cell (r, c) of a grid with this resolution and origin is cell
    (r + off_r, c + off_c) of ``base``; None when the two cannot be aligned cell for cell (different
    resolution or yaw, or origins that differ by a fraction of a cell)."""
    res = resolution
    if not math.isclose(res, base.resolution, rel_tol=1e-9, abs_tol=0.0):
        return None
    if not math.isclose(origin.yaw, base.origin.yaw, rel_tol=0.0, abs_tol=1e-9):
        return None
    base_origin = base.origin
    dx = (origin.x - base_origin.x) / res
    dy = (origin.y - base_origin.y) / res
    cos, sin = math.cos(base_origin.yaw), math.sin(base_origin.yaw)
    fc = cos * dx + sin * dy  # the new origin in the base's cell axes
    fr = -sin * dx + cos * dy
    if not (math.isfinite(fc) and math.isfinite(fr)):
        return None
    oc, orow = round(fc), round(fr)
    if abs(fc - oc) > ALIGN_TOL or abs(fr - orow) > ALIGN_TOL:
        return None
    if abs(oc) > MAX_OFFSET or abs(orow) > MAX_OFFSET:
        return None
    return int(orow), int(oc)


_OFFSET_ERRORS = VarintErrors(
    truncated="body is truncated in its delta offsets",
    non_minimal="body has a non-minimal offset varint",
    overlong="body has an overlong offset varint",
)


def _put_offset(n: int) -> bytes:
    """One delta offset on the wire: zigzag, then LEB128."""
    return put_uvarint(zigzag(n))


def _get_offset(body: bytes, pos: int) -> tuple[int, int]:
    """Read one delta offset at ``pos``; refuse any that no aligned base could give."""
    z, pos = get_uvarint(body, pos, _MAX_OFFSET_BYTES, _OFFSET_ERRORS)
    n = unzigzag(z)
    if abs(n) > MAX_OFFSET:
        raise CodecError(f"body has an absurd delta offset {n}")
    return n, pos


class LosslessCodec(Codec):
    """Exact context-model coding of occupancy grids, as whole maps or as deltas against a base."""

    name = "lossless"
    lossless = True
    uses_base = True
    Options = LosslessOptions

    def encode_cells(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Encoded:
        assert isinstance(self.options, LosslessOptions)
        data = _writable(grid.data)
        trinary = bool(_is_trinary(data))
        flags = (MODEL_VERSION << VERSION_SHIFT) | (FLAG_TRINARY if trinary else 0)
        hbits = hash_bits(data.size)
        delta: bytes | None = None
        if base is not None and self.options.delta != "never":
            off = alignment(grid.resolution, grid.origin, base)
            if off is not None:
                bdata = _writable(base.data)
                buf, n = code_delta(
                    False, data, bdata, off[0], off[1], trinary, _EMPTY, hbits, _SQ, _ST, _RATES
                )
                head = bytes([MODE_DELTA | flags]) + _put_offset(off[0]) + _put_offset(off[1])
                delta = head + buf[:n].tobytes()
                if self.options.delta == "always":
                    return Encoded(delta, delta=True)
        buf, n = code_whole(False, data, trinary, _EMPTY, hbits, _SQ, _ST, _RATES)
        whole = bytes([MODE_WHOLE | flags]) + buf[:n].tobytes()
        if delta is not None and len(delta) < len(whole):
            return Encoded(delta, delta=True)
        return Encoded(whole, delta=False)

    def decode_cells(self, body: bytes, target: Target, base: OccupancyGrid | None) -> np.ndarray:
        if not body:
            raise CodecError("body is empty")
        fmt = body[0]
        version = fmt >> VERSION_SHIFT
        if version != MODEL_VERSION:
            raise CodecError(
                f"body was coded by lossless model version {version}, but this mapd decodes version "
                f"{MODEL_VERSION} (update mapd on both robots)"
            )
        mode = fmt & MODE_MASK
        trinary = bool(fmt & FLAG_TRINARY)
        out = np.empty((target.height, target.width), dtype=np.int8)
        hbits = hash_bits(out.size)
        if mode == MODE_WHOLE:
            if base is not None:
                raise CodecError("body is a whole map, but the header says it is a delta")
            stream = np.frombuffer(body, np.uint8, offset=1).copy()
            _, status = code_whole(True, out, trinary, stream, hbits, _SQ, _ST, _RATES)
        elif mode == MODE_DELTA:
            if base is None:
                raise CodecError("body is a delta, but the header says it is a whole map")
            off_r, pos = _get_offset(body, 1)
            off_c, pos = _get_offset(body, pos)
            expect = alignment(target.resolution, target.origin, base)
            if expect != (off_r, off_c):
                raise CodecError(
                    f"delta offset ({off_r}, {off_c}) does not match the origins of the map "
                    f"and its base ({'not aligned' if expect is None else expect})"
                )
            stream = np.frombuffer(body, np.uint8, offset=pos).copy()
            bdata = np.ascontiguousarray(base.data, dtype=np.int8)
            _, status = code_delta(True, out, bdata, off_r, off_c, trinary, stream, hbits, _SQ, _ST, _RATES)
        else:
            raise CodecError(f"body has an unknown mode {mode}")
        if status != 0:
            raise CodecError("coded stream is truncated or corrupt (it does not end where it should)")
        return out
