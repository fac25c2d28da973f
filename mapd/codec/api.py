"""``encode`` / ``decode``: self-describing map payloads around any codec plugin.

Payload layout (little-endian), format version 1::

    magic      4s   b"MAPD"
    format     B    1
    flags      B    bit 0: delta (coded against a base)   bit 1: lossy
    name_len   B    then the codec name, ASCII (at most 32 bytes)
    var_len    B    then the codec variant, ASCII (at most 64 bytes; a model id for learned codecs)
    height     I
    width      I
    resolution d    meters per cell
    origin     3d   x, y (m), yaw (rad)
    base_ver   Q    version of the base (0 when not a delta)
    base_dig   16s  BLAKE2b-128 of the base grid (zeros when not a delta)
    check      16s  lossless: BLAKE2b-128 of the decoded grid; lossy: BLAKE2b-128 of the body
    body_len   I
    body       body_len bytes, the codec's own format

The decoder reads the header, refuses anything over the cell limit before allocating, checks the
base it was given against ``base_dig``, and checks the result against ``check``. Every failure is a
:class:`~mapd.errors.CodecError` with one readable line.

Header bounds, checked by :func:`read_header` before any codec runs and by :func:`encode` (so every
payload mapd makes is one it accepts):

* ``height * width`` at most ``max_cells`` (``limits.max_cells``), and each side at most
  :data:`MAX_SIDE` cells: a 1 x 67 M grid is not a map, and the lossless kernels keep a few rows of
  per-column state, so a degenerate shape would cost memory far beyond its cells;
* ``resolution`` finite and within [:data:`~mapd.grid.MIN_RESOLUTION`,
  :data:`~mapd.grid.MAX_RESOLUTION`] meters per cell;
* origin ``x`` and ``y`` finite and within +-:data:`~mapd.grid.MAX_ORIGIN_M` meters (10,000 km,
  every UTM coordinate), ``yaw`` within +-:data:`~mapd.grid.MAX_ORIGIN_YAW` (one turn).

These bounds catch a damaged exponent, not every damaged bit: a flipped low mantissa bit of the
resolution or origin of a *lossy* payload still decodes (``check`` covers only the body there),
which is why envelopes are signed.
"""

from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass

import numpy as np

from mapd import plugins
from mapd.codec.base import Codec, CodecOptions, Target
from mapd.errors import CodecError, LimitError, MapdError
from mapd.grid import DEFAULT_MAX_CELLS, MAX_GRID_SIDE, OccupancyGrid, Pose2D, geometry_problem

MAGIC = b"MAPD"
FORMAT_VERSION = 1
FLAG_DELTA = 0x01
FLAG_LOSSY = 0x02
_FIXED = struct.Struct("<IId3dQ16s16sI")
MAX_NAME = 32
MAX_VARIANT = 64
ZERO_DIGEST = bytes(16)
#: Longest side of a grid in a payload (cells): 3.3 km at 5 cm, twice what fusion matches.
MAX_SIDE = MAX_GRID_SIDE

_instances: dict[tuple[str, str], Codec] = {}


@dataclass(frozen=True)
class Header:
    """The decoded payload header."""

    codec: str
    variant: str
    delta: bool
    lossy: bool
    height: int
    width: int
    resolution: float
    origin: Pose2D
    base_version: int
    base_digest: bytes
    check: bytes
    body_offset: int
    body_len: int

    @property
    def cells(self) -> int:
        return self.height * self.width


def get_codec(name: str, options: CodecOptions | None = None) -> Codec:
    """The codec plugin ``name``, constructed once per distinct options and reused."""
    key = (name, options.model_dump_json() if options is not None else "")
    codec = _instances.get(key)
    if codec is None:
        try:
            cls = plugins.load("codec", name)
        except MapdError as exc:
            raise CodecError(str(exc)) from None
        codec = cls(options)
        _instances[key] = codec
    return codec


def warm_up(name: str, options: CodecOptions | None = None) -> float:
    """Encode and decode a tiny map, whole and as a delta, so one-time costs are paid now.

    The ``lossless`` codec's numba kernels compile on first use (about 30 s, then cached on disk) and
    the ``paper`` codec loads its model; a daemon or benchmark calls this before it times anything,
    and ``deploy/install.sh`` runs ``mapd warmup`` so a robot never compiles at start-up. Returns
    the seconds it took.
    """
    import time

    import numpy as np

    t0 = time.perf_counter()
    tiny = OccupancyGrid(np.full((4, 4), -1, np.int8), 0.05, version=1)
    tiny.data[1:3, 1:3] = 0
    decode(encode(tiny, name, options=options))
    nxt = tiny.replace(data=np.where(tiny.data == 0, 100, tiny.data).astype(np.int8), version=2)
    decode(encode(nxt, name, base=tiny, options=options), base=tiny)
    return time.perf_counter() - t0


def _blake(data: bytes) -> bytes:
    return hashlib.blake2b(data, digest_size=16).digest()


def encode(
    grid: OccupancyGrid,
    codec: str = "raw",
    base: OccupancyGrid | None = None,
    *,
    options: CodecOptions | None = None,
) -> bytes:
    """Encode ``grid`` with the codec named ``codec``; a delta against ``base`` when it pays.

    ``base`` must be a grid the receiver holds (same robot, an earlier version). Codecs that cannot
    use a base ignore it and send the whole map.
    """
    problem = encode_problem(grid)
    if problem is not None:
        raise CodecError(f"cannot encode this map: {problem}")
    impl = get_codec(codec, options)
    if len(impl.name.encode("ascii")) > MAX_NAME or len(impl.variant().encode("ascii")) > MAX_VARIANT:
        raise CodecError(f"codec '{codec}': name or variant too long for the header")
    use_base = base if impl.uses_base else None
    out = impl.encode_cells(grid, use_base)
    delta = bool(out.delta and use_base is not None)
    assert use_base is not None or not delta
    return pack_payload(
        impl.name,
        impl.variant(),
        height=grid.height,
        width=grid.width,
        resolution=grid.resolution,
        origin=grid.origin,
        body=out.body,
        delta=delta,
        lossy=not impl.lossless,
        base_version=use_base.version if delta and use_base is not None else 0,
        # The receiver holds the base as it decoded it (the same grid, unless the codec is lossy).
        base_digest=impl.held(use_base).digest() if delta and use_base is not None else ZERO_DIGEST,
        check=grid.digest() if impl.lossless else None,
    )


def pack_payload(
    codec: str,
    variant: str,
    *,
    height: int,
    width: int,
    resolution: float,
    origin: tuple[float, float, float],
    body: bytes,
    delta: bool = False,
    lossy: bool = False,
    base_version: int = 0,
    base_digest: bytes = ZERO_DIGEST,
    check: bytes | None = None,
) -> bytes:
    """The header (layout in the module doc) followed by ``body``, as :func:`encode` writes it.

    No field is checked here: :func:`encode` checks the grid before, and tests use this to forge
    hostile payloads (a header claiming any size, resolution or origin) that :func:`decode` must
    refuse. ``check`` defaults to the BLAKE2b of the body for a lossy payload, zeros otherwise.
    """
    name = codec.encode("ascii")
    var = variant.encode("ascii")
    flags = (FLAG_DELTA if delta else 0) | (FLAG_LOSSY if lossy else 0)
    if check is None:
        check = _blake(body) if lossy else ZERO_DIGEST
    fixed = _FIXED.pack(height, width, resolution, *origin, base_version, base_digest, check, len(body))
    head = MAGIC + bytes([FORMAT_VERSION, flags, len(name)]) + name + bytes([len(var)]) + var
    return head + fixed + body


def encode_problem(grid: OccupancyGrid) -> str | None:
    """Why :func:`encode` would refuse ``grid`` (empty, a side over :data:`MAX_SIDE`, resolution or
    origin out of the header bounds), or None. Lets a caller skip such a map instead of failing."""
    return _shape_problem(grid.height, grid.width) or geometry_problem(grid.resolution, grid.origin)


def _shape_problem(height: int, width: int) -> str | None:
    """Why a grid of this shape cannot travel in a payload (besides the cell limit), or None."""
    if height == 0 or width == 0:
        return f"the grid is empty ({width}x{height})"
    if max(height, width) > MAX_SIDE:
        return f"the grid is {width}x{height} cells, over {MAX_SIDE} cells a side"
    return None


def read_header(payload: bytes, *, max_cells: int = DEFAULT_MAX_CELLS) -> Header:
    """Parse and sanity-check a payload header without touching the body's contents."""
    mv = memoryview(payload)
    if len(mv) < 7 or bytes(mv[:4]) != MAGIC:
        raise CodecError("not a mapd payload (bad magic)")
    if mv[4] != FORMAT_VERSION:
        raise CodecError(f"unsupported payload format version {mv[4]} (this mapd reads {FORMAT_VERSION})")
    flags = mv[5]
    if flags & ~(FLAG_DELTA | FLAG_LOSSY):
        raise CodecError(f"payload has unknown flags 0x{flags:02x}")
    pos = 6
    fields = []
    for limit in (MAX_NAME, MAX_VARIANT):
        if pos >= len(mv):
            raise CodecError("payload truncated in its header")
        n = mv[pos]
        if n > limit or pos + 1 + n > len(mv):
            raise CodecError("payload header is corrupt (bad name length)")
        raw = bytes(mv[pos + 1 : pos + 1 + n])
        try:
            fields.append(raw.decode("ascii"))
        except UnicodeDecodeError:
            raise CodecError("payload header is corrupt (non-ASCII codec name)") from None
        pos += 1 + n
    if pos + _FIXED.size > len(mv):
        raise CodecError("payload truncated in its header")
    h, w, res, ox, oy, oyaw, base_ver, base_dig, check, body_len = _FIXED.unpack_from(mv, pos)
    pos += _FIXED.size
    if h == 0 or w == 0:
        raise CodecError(f"payload declares an empty grid ({w}x{h})")
    if h * w > max_cells:
        raise LimitError(f"payload declares {w}x{h} = {w * h} cells, over the limit of {max_cells}")
    shape = _shape_problem(h, w)
    if shape is not None:
        raise CodecError(f"payload header is corrupt: {shape}")
    if not (math.isfinite(res) and res > 0) or not all(math.isfinite(v) for v in (ox, oy, oyaw)):
        raise CodecError("payload header has a non-finite or non-positive resolution or origin")
    geometry = geometry_problem(res, (ox, oy, oyaw))
    if geometry is not None:
        raise CodecError(f"payload header is corrupt: {geometry}")
    if not flags & FLAG_DELTA and (base_ver != 0 or base_dig != ZERO_DIGEST):
        raise CodecError("payload header is corrupt (base fields set on a whole-map payload)")
    if pos + body_len != len(mv):
        raise CodecError(f"payload body is {len(mv) - pos} bytes but the header says {body_len} (truncated?)")
    return Header(
        codec=fields[0],
        variant=fields[1],
        delta=bool(flags & FLAG_DELTA),
        lossy=bool(flags & FLAG_LOSSY),
        height=h,
        width=w,
        resolution=res,
        origin=Pose2D(ox, oy, oyaw),
        base_version=base_ver,
        base_digest=base_dig,
        check=check,
        body_offset=pos,
        body_len=body_len,
    )


def decode(
    payload: bytes,
    base: OccupancyGrid | None = None,
    *,
    max_cells: int = DEFAULT_MAX_CELLS,
    options: CodecOptions | None = None,
) -> OccupancyGrid:
    """Decode a payload made by :func:`encode` back into an :class:`OccupancyGrid`.

    ``base`` must be the grid the payload was coded against when it is a delta; a missing or
    different base raises :class:`CodecError`, never a wrong map. For a lossy codec that takes a
    base, that is the base as its receiver decoded it, or the sender's original of it.
    """
    try:
        head = read_header(payload, max_cells=max_cells)
    except LimitError as exc:
        raise CodecError(str(exc)) from None
    impl = get_codec(head.codec, options)
    if head.lossy == impl.lossless:
        raise CodecError(f"payload's lossy flag does not match codec '{head.codec}'")
    if head.variant != impl.variant():
        have = impl.variant() or "none"
        raise CodecError(
            f"payload was made with {head.codec} variant '{head.variant}', but this mapd has '{have}'"
        )
    body = bytes(payload[head.body_offset :])
    if head.lossy and _blake(body) != head.check:
        raise CodecError("payload body checksum mismatch (corrupted in transit?)")
    use_base = None
    if head.delta:
        if base is None:
            raise CodecError(f"payload is a delta against version {head.base_version}, but no base was given")
        given = base.digest()
        if given != head.base_digest:
            # A lossy codec's base may be given as the sender's original: the header names the
            # codec's rendering of it, which is what a receiver holds (for lossless codecs the same).
            held = impl.held(base)
            if held is base or held.digest() != head.base_digest:
                raise CodecError(
                    f"payload is a delta against version {head.base_version} "
                    f"(digest {head.base_digest.hex()[:12]}), but the base given is version "
                    f"{base.version} (digest {given.hex()[:12]})"
                )
            base = held
        use_base = base
    target = Target(head.height, head.width, head.resolution, head.origin, head.variant)
    try:
        cells = impl.decode_cells(body, target, use_base)
    except MapdError as exc:
        raise CodecError(f"{head.codec}: {exc}") from None
    except (ValueError, IndexError, KeyError, OverflowError, struct.error, EOFError, MemoryError) as exc:
        # A codec that trips over corrupt input is still reporting corrupt input.
        raise CodecError(f"{head.codec}: corrupt payload body ({type(exc).__name__}: {exc})") from None
    cells = np.asarray(cells)
    if cells.shape != (head.height, head.width) or cells.dtype != np.int8:
        raise CodecError(
            f"{head.codec}: decoded cells have shape {cells.shape}, expected {(head.height, head.width)}"
        )
    grid = OccupancyGrid(data=cells, resolution=head.resolution, origin=head.origin)
    if not head.lossy and grid.digest() != head.check:
        raise CodecError(f"{head.codec}: decoded map does not match its checksum (corrupted in transit?)")
    return grid
