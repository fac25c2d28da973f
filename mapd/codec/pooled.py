"""``pooled``: the lossless codec on the map at a coarser resolution, for the thinnest radios.

The paper's codec halves the map's resolution before it codes it; this codec does the same without
a network. Each block of ``factor`` x ``factor`` cells becomes one cell that takes the block's
largest value, so an occupied cell wins over free and free over unknown: walls come back whole
(at most ``factor - 1`` cells thicker), never a gap a planner could pass through. The pooled grid
is then coded exactly by :mod:`mapd.codec.lossless`, whole or as a delta, and the decoder spreads
each cell back over its block, so a receiver gets a grid of the sender's size, resolution and
origin.

A delta needs the base both ends hold. The receiver holds what it decoded, which is the base
pooled and spread back (:meth:`PooledCodec.held`); pooling that again gives the pooled base
exactly, so both ends pool their base and code against the same grid. Blocks sit on the map
frame's cell lattice (cell indices that are multiples of ``factor``), not on the grid's corner,
so a map that grows by a cell to the left keeps its blocks where they were and its deltas stay
small.

Body layout (after the header of :mod:`mapd.codec.api`)::

    factor   u8   2 to 4
    rest     a ``lossless`` body of the pooled grid
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from mapd.codec.base import Codec, CodecOptions, Encoded, Target
from mapd.codec.lossless import LosslessCodec, LosslessOptions
from mapd.errors import CodecError
from mapd.grid import UNKNOWN, OccupancyGrid, Pose2D

MIN_FACTOR = 2
MAX_FACTOR = 4


class PooledOptions(LosslessOptions):
    """Options of the ``[codec.pooled]`` table (``delta`` as ``[codec.lossless]``)."""

    factor: int = Field(
        default=2,
        ge=MIN_FACTOR,
        le=MAX_FACTOR,
        description="cells per block side: 2 sends a 5 cm map at 10 cm (about a third of the bytes)",
    )


class _Lattice:
    """Where the blocks of a ``height`` x ``width`` grid with this resolution and origin lie."""

    def __init__(self, height: int, width: int, resolution: float, origin: Pose2D, factor: int) -> None:
        cos, sin = math.cos(origin.yaw), math.sin(origin.yaw)
        # The grid's cell (0, 0) in the map frame's cell lattice, along the grid's own axes: grids
        # whose origins differ by whole cells (a map that grew) get the same blocks.
        col0 = (cos * origin.x + sin * origin.y) / resolution
        row0 = (-sin * origin.x + cos * origin.y) / resolution
        if not (math.isfinite(col0) and math.isfinite(row0)) or max(abs(col0), abs(row0)) > 1 << 52:
            raise CodecError(f"map origin ({origin.x}, {origin.y}) is out of range")
        self.factor = factor
        self.pad_r = round(row0) % factor
        self.pad_c = round(col0) % factor
        self.height, self.width = height, width
        self.rows = -(-(height + self.pad_r) // factor)
        self.cols = -(-(width + self.pad_c) // factor)
        self.resolution = resolution * factor
        # The pooled grid's corner is the corner of the block holding cell (0, 0).
        dx, dy = -self.pad_c * resolution, -self.pad_r * resolution
        self.origin = Pose2D(origin.x + cos * dx - sin * dy, origin.y + sin * dx + cos * dy, origin.yaw)

    def pool(self, data: np.ndarray) -> np.ndarray:
        """Each block's largest value: occupied wins over free, free over unknown."""
        f = self.factor
        padded = np.full((self.rows * f, self.cols * f), UNKNOWN, dtype=np.int8)
        padded[self.pad_r : self.pad_r + self.height, self.pad_c : self.pad_c + self.width] = data
        return np.ascontiguousarray(padded.reshape(self.rows, f, self.cols, f).max(axis=(1, 3)))

    def spread(self, pooled: np.ndarray) -> np.ndarray:
        """Each pooled cell over its block, cut back to the grid's own cells."""
        f = self.factor
        full = np.repeat(np.repeat(pooled, f, axis=0), f, axis=1)
        return np.ascontiguousarray(
            full[self.pad_r : self.pad_r + self.height, self.pad_c : self.pad_c + self.width]
        )

    def grid(self, pooled: np.ndarray) -> OccupancyGrid:
        return OccupancyGrid(data=pooled, resolution=self.resolution, origin=self.origin)


def _lattice(grid: OccupancyGrid, factor: int) -> _Lattice:
    return _Lattice(grid.height, grid.width, grid.resolution, grid.origin, factor)


class PooledCodec(Codec):
    """Lossy: ``factor`` x ``factor`` blocks, occupied first, then coded exactly (see the module doc)."""

    name = "pooled"
    lossless = False
    uses_base = True
    Options = PooledOptions

    def __init__(self, options: CodecOptions | None = None) -> None:
        super().__init__(options)
        assert isinstance(self.options, PooledOptions)
        self._inner = LosslessCodec(LosslessOptions(delta=self.options.delta))

    @property
    def factor(self) -> int:
        assert isinstance(self.options, PooledOptions)
        return self.options.factor

    def held(self, grid: OccupancyGrid) -> OccupancyGrid:
        lat = _lattice(grid, self.factor)
        return grid.replace(data=lat.spread(lat.pool(grid.data)))

    def encode_cells(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Encoded:
        lat = _lattice(grid, self.factor)
        pooled_base = None
        if base is not None:
            blat = _lattice(base, self.factor)
            pooled_base = blat.grid(blat.pool(base.data))
        out = self._inner.encode_cells(lat.grid(lat.pool(grid.data)), pooled_base)
        return Encoded(bytes([self.factor]) + out.body, delta=out.delta)

    def decode_cells(self, body: bytes, target: Target, base: OccupancyGrid | None) -> np.ndarray:
        if not body:
            raise CodecError("body is empty")
        factor = body[0]
        if not MIN_FACTOR <= factor <= MAX_FACTOR:
            raise CodecError(f"body has a pooling factor of {factor}, not {MIN_FACTOR} to {MAX_FACTOR}")
        lat = _Lattice(target.height, target.width, target.resolution, target.origin, factor)
        pooled_base = None
        if base is not None:
            blat = _lattice(base, factor)
            pooled_base = blat.grid(blat.pool(base.data))
        inner = Target(lat.rows, lat.cols, lat.resolution, lat.origin, target.variant)
        return lat.spread(self._inner.decode_cells(body[1:], inner, pooled_base))
