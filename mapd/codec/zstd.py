"""``zstd``: Zstandard over the raw int8 cells, the general-purpose baseline."""

from __future__ import annotations

import io

import numpy as np
import zstandard
from pydantic import Field

from mapd.codec.base import Codec, CodecOptions, Encoded, Target
from mapd.errors import CodecError
from mapd.grid import OccupancyGrid


class ZstdOptions(CodecOptions):
    level: int = Field(default=19, ge=1, le=22, description="zstd compression level")


class ZstdCodec(Codec):
    """Zstandard at level 19 (configurable) over row-major int8 cells."""

    name = "zstd"
    Options = ZstdOptions

    def encode_cells(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Encoded:
        assert isinstance(self.options, ZstdOptions)
        cctx = zstandard.ZstdCompressor(level=self.options.level)
        return Encoded(cctx.compress(np.ascontiguousarray(grid.data).tobytes()))

    def decode_cells(self, body: bytes, target: Target, base: OccupancyGrid | None) -> np.ndarray:
        n = target.height * target.width
        try:
            # Stream and read at most n + 1 bytes: a frame that claims a huge content size
            # cannot make us allocate past what the header declared.
            with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(body)) as reader:
                out = reader.read(n + 1)
        except zstandard.ZstdError as exc:
            raise CodecError(f"zstd body is corrupt: {exc}") from None
        if len(out) != n:
            raise CodecError(f"zstd body holds {len(out)} cells, expected {n}")
        return np.frombuffer(out, dtype=np.int8).reshape(target.height, target.width).copy()
