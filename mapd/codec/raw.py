"""``raw``: the int8 cells as they are, one byte per cell (the nav_msgs baseline)."""

from __future__ import annotations

import numpy as np

from mapd.codec.base import Codec, Encoded, Target
from mapd.errors import CodecError
from mapd.grid import OccupancyGrid


class RawCodec(Codec):
    """No compression: row-major int8 cells, exactly as ``nav_msgs/OccupancyGrid`` carries them."""

    name = "raw"

    def encode_cells(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Encoded:
        return Encoded(np.ascontiguousarray(grid.data).tobytes())

    def decode_cells(self, body: bytes, target: Target, base: OccupancyGrid | None) -> np.ndarray:
        if len(body) != target.height * target.width:
            raise CodecError(f"raw body is {len(body)} bytes, expected {target.height * target.width}")
        return np.frombuffer(body, dtype=np.int8).reshape(target.height, target.width).copy()
