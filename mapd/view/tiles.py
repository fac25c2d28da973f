"""The global map as square PNG tiles on a lattice fixed in the fleet frame, and which tiles changed.

The browser keeps the map as one canvas of ``width x height`` pixels, one per cell, and draws each
tile it is sent into it, so a new map version costs only the tiles whose cells changed. A tile
holds palette indices (free, occupied, unknown) in a 3-colour PNG: a 128 x 128 tile of a real
building is a few hundred bytes. Rows are flipped here (image row 0 is the map's top, its highest
``y``), so the browser draws tiles without any transform of its own.

Tiles lie on a lattice of the fleet frame's cells, not on the image's corner, so a map that grows
(as the fused map does while robots explore: its origin moves by whole cells) keeps its tiles'
indices and bytes, and only the tiles that changed or are new go out. A cell's lattice column is
``round(origin_x / resolution)`` plus its image column; its lattice row counts *downwards* (as image
rows do) from the fleet frame's ``y = 0``: ``-(round(origin_y / resolution) + height)`` plus its image
row. Tile ``(tx, ty)`` covers lattice columns ``[tx * TILE, tx * TILE + TILE)`` and rows likewise,
clipped to the image (edge tiles, on any side, are smaller, never padded), so it is drawn at canvas
pixel ``(max(tx * TILE, col0) - col0, max(ty * TILE, row0) - row0)`` where ``(col0, row0)`` is the
lattice cell of the image's top-left cell (``Geometry.lattice``). Indices may be negative.

Pure functions of numpy arrays: no I/O, no clock, no threads. The caller runs them off the event
loop (the daemon's output thread).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image

from mapd.grid import CLASS_FREE, CLASS_OCCUPIED, CLASS_UNKNOWN, OccupancyGrid, cell_classes

#: Side of a tile in cells. 128 keeps a 2000 x 2000 map at 256 to 289 tiles (as it lies on the
#: lattice) and a one-cell change at ~300 B.
TILE = 128

#: Palette index -> RGB: free light, occupied dark, unknown mid grey (the page's legend says so too).
PALETTE: dict[int, tuple[int, int, int]] = {
    CLASS_FREE: (244, 244, 238),
    CLASS_OCCUPIED: (34, 38, 43),
    CLASS_UNKNOWN: (163, 167, 173),
}
_PALETTE_BYTES = b"".join(bytes(PALETTE[i]) for i in range(3))

#: Two origins whose distance is within this many cells of a whole number share the cell lattice
#: (merge.py's global map lies on it exactly, up to float noise; merge.py allows the same 1e-6).
_ALIGN_EPS = 1e-6


@dataclass(frozen=True)
class Geometry:
    """Where the global map lies: its size in cells and the fleet-frame pose of cell (0, 0).

    ``col0``, ``row0``: the lattice cell of the image's top-left cell (see the module docstring).
    """

    width: int
    height: int
    resolution: float
    origin_x: float
    origin_y: float
    col0: int
    row0: int

    @staticmethod
    def of(grid: OccupancyGrid) -> Geometry:
        """The geometry of ``grid``, placed on the fleet frame's tile lattice."""
        res = grid.resolution
        col0 = round(grid.origin.x / res)
        row0 = -(round(grid.origin.y / res) + grid.height)
        return Geometry(grid.width, grid.height, res, grid.origin.x, grid.origin.y, col0, row0)

    @property
    def span(self) -> tuple[int, int, int, int]:
        """Tile indices ``(tx0, tx1, ty0, ty1)`` covering the map: ``tx0 <= tx < tx1``, likewise ``ty``."""
        return (
            self.col0 // TILE,
            -(-(self.col0 + self.width) // TILE),
            self.row0 // TILE,
            -(-(self.row0 + self.height) // TILE),
        )

    @property
    def cols(self) -> int:
        """Tiles across."""
        tx0, tx1, _, _ = self.span
        return tx1 - tx0

    @property
    def rows(self) -> int:
        """Tiles down."""
        _, _, ty0, ty1 = self.span
        return ty1 - ty0

    def block(self, tx: int, ty: int) -> tuple[slice, slice]:
        """The image rows and columns tile ``(tx, ty)`` holds (empty for a tile off the map)."""
        r0 = min(max(ty * TILE - self.row0, 0), self.height)
        c0 = min(max(tx * TILE - self.col0, 0), self.width)
        r1 = min(max(ty * TILE + TILE - self.row0, 0), self.height)
        c1 = min(max(tx * TILE + TILE - self.col0, 0), self.width)
        return slice(r0, r1), slice(c0, c1)

    def lines_up_with(self, other: Geometry) -> bool:
        """True when both maps' cells lie on one lattice, so tiles of one stand for the other's.

        Same resolution, and origins a whole number of cells apart, the very number their lattice
        cells say (a half-cell origin may round either way: then it is False, and all goes anew).
        """
        if self.resolution != other.resolution:
            return False
        dx = (self.origin_x - other.origin_x) / self.resolution
        dy = (self.origin_y - other.origin_y) / self.resolution
        # bottom rows' lattice y = -(row0 + height): their difference is the origins' in cells
        ly = (other.row0 + other.height) - (self.row0 + self.height)
        return abs(dx - (self.col0 - other.col0)) <= _ALIGN_EPS and abs(dy - ly) <= _ALIGN_EPS

    def as_dict(self) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "resolution": self.resolution,
            "origin": [self.origin_x, self.origin_y],
            "tile": TILE,
            "lattice": [self.col0, self.row0],
        }


def class_image(grid: OccupancyGrid) -> np.ndarray:
    """Palette indices (uint8), top row first: what the browser's canvas shows, cell for cell."""
    return np.ascontiguousarray(cell_classes(grid.data)[::-1])


def all_tiles(geometry: Geometry) -> list[tuple[int, int]]:
    """Every tile ``(tx, ty)`` of a map, row by row from the top."""
    tx0, tx1, ty0, ty1 = geometry.span
    return [(tx, ty) for ty in range(ty0, ty1) for tx in range(tx0, tx1)]


def _extents(lo: int, size: int, first: int, end: int) -> np.ndarray:
    """Per tile index ``first..end-1`` on one axis, the (start, stop) lattice cells it holds of a map
    covering ``[lo, lo + size)`` (both 0 for a tile off the map)."""
    starts = np.arange(first, end, dtype=np.int64) * TILE
    a = np.clip(starts, lo, lo + size)
    b = np.clip(starts + TILE, lo, lo + size)
    off = a >= b
    a[off] = b[off] = 0
    return np.stack([a, b], axis=1)


def changed_tiles(
    old: np.ndarray | None,
    new: np.ndarray,
    geometry: Geometry,
    old_geometry: Geometry | None = None,
) -> list[tuple[int, int]]:
    """Tiles ``(tx, ty)`` of ``new`` (a class image of ``geometry``) that a viewer holding ``old``
    (of ``old_geometry``, default the same) must be sent, row by row from the top.

    Those with a changed cell, and those whose extent changed: new tiles, and edge tiles that grew
    or shrank (their PNG is of another size). ``old`` None, or on another lattice (see
    :meth:`Geometry.lines_up_with`): every tile. One vectorised comparison of the cells both maps
    hold and a block reduction, so a 4 M-cell map is compared in a few milliseconds.
    """
    og = geometry if old_geometry is None else old_geometry
    if old is None or old.shape != (og.height, og.width) or not geometry.lines_up_with(og):
        return all_tiles(geometry)
    tx0, tx1, ty0, ty1 = geometry.span
    rows, cols = ty1 - ty0, tx1 - tx0
    # the image inside its tiles' lattice block, and the old image inside the new one
    top, left = geometry.row0 - ty0 * TILE, geometry.col0 - tx0 * TILE
    dr, dc = og.row0 - geometry.row0, og.col0 - geometry.col0
    r0, r1 = max(0, dr), min(geometry.height, dr + og.height)
    c0, c1 = max(0, dc), min(geometry.width, dc + og.width)
    padded = np.zeros((rows * TILE, cols * TILE), dtype=bool)
    if r0 < r1 and c0 < c1:
        padded[top + r0 : top + r1, left + c0 : left + c1] = (
            new[r0:r1, c0:c1] != old[r0 - dr : r1 - dr, c0 - dc : c1 - dc]
        )
    blocks = padded.reshape(rows, TILE, cols, TILE).any(axis=(1, 3))
    if og != geometry:
        # a tile whose extent changed on either axis has new cells, or lost some: its PNG differs
        col_moved = (
            _extents(geometry.col0, geometry.width, tx0, tx1) != _extents(og.col0, og.width, tx0, tx1)
        ).any(axis=1)
        row_moved = (
            _extents(geometry.row0, geometry.height, ty0, ty1) != _extents(og.row0, og.height, ty0, ty1)
        ).any(axis=1)
        blocks |= row_moved[:, None] | col_moved[None, :]
    return [(int(tx) + tx0, int(ty) + ty0) for ty, tx in zip(*np.nonzero(blocks), strict=True)]


def encode_tile(image: np.ndarray, geometry: Geometry, tx: int, ty: int) -> bytes:
    """Tile ``(tx, ty)`` of a class image of ``geometry`` as a palette PNG (edge tiles are clipped)."""
    rows, cols = geometry.block(tx, ty)
    block = image[rows, cols]
    im = Image.frombytes("P", (block.shape[1], block.shape[0]), np.ascontiguousarray(block).tobytes())
    im.putpalette(_PALETTE_BYTES, rawmode="RGB")
    buf = io.BytesIO()
    im.save(buf, format="PNG", optimize=False, compress_level=6)
    return buf.getvalue()


def decode_tile(png: bytes) -> np.ndarray:
    """The palette indices of a tile PNG (for tests and tools)."""
    with Image.open(io.BytesIO(png)) as im:
        if im.mode != "P":
            raise ValueError(f"tile is {im.mode}, not a palette image")
        return np.asarray(im).copy()


__all__ = [
    "CLASS_FREE",
    "CLASS_OCCUPIED",
    "CLASS_UNKNOWN",
    "PALETTE",
    "TILE",
    "Geometry",
    "all_tiles",
    "changed_tiles",
    "class_image",
    "decode_tile",
    "encode_tile",
]
