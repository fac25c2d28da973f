"""``paper``: the Zhang & Deng (2024) codec, CNN_feature + Huffman/hex/RLE + CNN_recovery.

Encode: the map's cells become network input (:func:`mapd.codec.paper_net.map_to_input`),
CNN_feature makes the half-resolution ``m_feature``, the quantizer turns it into integer symbols,
and Algorithm 1 (:mod:`mapd.codec.huffman`) writes them as the code table ``T`` and the run-length
coded hex string ``e``. Decode: Algorithm 2 gives the symbols back exactly, CNN_recovery makes the
full-resolution map, and every cell is snapped to the nearest value the source map could hold.

Body layout (after mapd's payload header, which carries size, resolution, origin and the model
id ``paper-v3:<sha256[:12]>`` as the codec variant)::

    u8     flags: bit 0 free cells present, bit 1 occupied present, bit 2 unknown present,
           bit 3 graded map (values other than -1/0/100); bits 4-7 zero
    T, e   the Huffman/hex/RLE stage (:mod:`mapd.codec.huffman`), m_feature row-major,
           ceil(height/2) x ceil(width/2) symbols

Snapping: a trinary map comes back as -1/0/100, each cell the class whose grey level (free 254,
occupied 0, unknown 205) is nearest the recovered grey, among the classes the source held. A graded
map comes back as the nearest of the values 0..100 (on the line from free to occupied grey) and,
when it held unknown cells, unknown (grey 205) - so a graded value near 19 and unknown are not
always told apart; the grey-level input cannot separate them.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from pydantic import Field

from mapd.codec import huffman
from mapd.codec.base import Codec, CodecOptions, Encoded, Target
from mapd.errors import CodecError
from mapd.grid import (
    CLASS_FREE,
    CLASS_OCCUPIED,
    CLASS_UNKNOWN,
    FREE,
    GREY_FREE,
    GREY_OCCUPIED,
    GREY_UNKNOWN,
    OCCUPIED,
    UNKNOWN,
    OccupancyGrid,
    cell_classes,
)

if TYPE_CHECKING:
    from mapd.codec.paper_infer import PaperModel

FLAG_FREE = 0x01
FLAG_OCCUPIED = 0x02
FLAG_UNKNOWN = 0x04
FLAG_GRADED = 0x08
_FLAGS_KNOWN = FLAG_FREE | FLAG_OCCUPIED | FLAG_UNKNOWN | FLAG_GRADED
DEFAULT_MODEL = "paper-v3"


class PaperOptions(CodecOptions):
    """``[codec.paper]``: which trained model to use, where model folders live, and torch's threads."""

    model: str = Field(
        default=DEFAULT_MODEL,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,40}$",
        description="model folder name (weights.npz + model.json)",
    )
    beside_config: ClassVar[tuple[str, ...]] = ("model_dir",)

    model_dir: Path | None = Field(
        default=None,
        description="folder holding model folders (relative: to the config's; default: $MAPD_MODELS, else <repo>/models)",
    )
    # One thread by default: a robot's CPU has other work (SLAM, planning), and two OpenMP threads
    # on two busy cores measured 2-5x slower than one (docs/paper.md, "Speed").
    threads: int = Field(
        default=1,
        ge=0,
        le=256,
        description="torch threads for the CNNs during encode/decode (0: leave torch's default)",
    )

    def check_files(self) -> None:
        """ValueError for a model ``mapd run`` could not load (missing, tampered, of another format).

        Loaded at the first map otherwise: a daemon that started, said READY and never sent a map.
        """
        from mapd.codec.paper_model import load_model

        try:
            load_model(models_root(self) / self.model)
        except CodecError as exc:
            raise ValueError(f"model: {exc}") from None


def models_root(options: PaperOptions) -> Path:
    """Where model folders are looked up: option, else ``$MAPD_MODELS``, else ``<repo>/models``."""
    if options.model_dir is not None:
        return options.model_dir
    env = os.environ.get("MAPD_MODELS")
    if env:
        return Path(env)
    from mapd.data import REPO_ROOT

    return REPO_ROOT / "models"


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads, then restore the previous count.

    ``torch.set_num_threads`` is process-wide; restoring it keeps the codec from changing the
    thread count of anything else in the process (``mapd train`` evaluates through the codec).
    ``n == 0`` leaves torch alone.
    """
    import torch

    before = torch.get_num_threads()
    if n <= 0 or n == before:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def source_flags(data: np.ndarray) -> int:
    """Which classes a map holds, and whether it is graded (flags byte of the body)."""
    present = np.bincount(cell_classes(data).ravel(), minlength=3)
    flags = 0
    flags |= FLAG_FREE if present[CLASS_FREE] else 0
    flags |= FLAG_OCCUPIED if present[CLASS_OCCUPIED] else 0
    flags |= FLAG_UNKNOWN if present[CLASS_UNKNOWN] else 0
    d = np.asarray(data)
    if not np.all((d == UNKNOWN) | (d == FREE) | (d == OCCUPIED)):
        flags |= FLAG_GRADED
    return flags


def snap(values: np.ndarray, flags: int) -> np.ndarray:
    """Recovered input-scale values to int8 cells the source map could hold (see module doc)."""
    grey = values.astype(np.float32) * 255.0 + GREY_UNKNOWN
    if flags & FLAG_GRADED:
        step = (GREY_FREE - GREY_OCCUPIED) / 100.0
        v = np.clip(np.rint((GREY_FREE - grey) / step), 0, 100)
        out = v.astype(np.int8)
        if flags & FLAG_UNKNOWN:
            err_v = np.abs(grey - (GREY_FREE - v * step))
            out[np.abs(grey - GREY_UNKNOWN) < err_v] = UNKNOWN
        return out
    cands = [
        (flag, g, cell)
        for flag, g, cell in (
            (FLAG_FREE, GREY_FREE, FREE),
            (FLAG_OCCUPIED, GREY_OCCUPIED, OCCUPIED),
            (FLAG_UNKNOWN, GREY_UNKNOWN, UNKNOWN),
        )
        if flags & flag
    ]
    dist = np.stack([np.abs(grey - g) for _, g, _ in cands])
    pick = np.argmin(dist, axis=0)
    lut = np.array([cell for _, _, cell in cands], dtype=np.int8)
    return lut[pick]


class PaperCodec(Codec):
    """The paper's learned codec. Lossy; the payload names the model, and other weights refuse it.

    ``last_timings`` holds the stage times (ms) of the latest call: ``cnn_encode_ms`` and
    ``huffman_encode_ms`` after an encode, ``huffman_decode_ms`` and ``cnn_decode_ms`` after a decode.
    """

    name = "paper"
    lossless = False
    Options = PaperOptions

    def __init__(self, options: CodecOptions | None = None) -> None:
        super().__init__(options)
        self.last_timings: dict[str, float] = {}
        self._model: PaperModel | None = None
        self._lock = threading.Lock()

    @property
    def model_path(self) -> Path:
        assert isinstance(self.options, PaperOptions)
        return models_root(self.options) / self.options.model

    @property
    def threads(self) -> int:
        """Torch threads for this codec's inference (``[codec.paper] threads``; 0: torch's default)."""
        assert isinstance(self.options, PaperOptions)
        return self.options.threads

    def model(self) -> PaperModel:
        """The loaded model (lazily, once, on CPU; torch is imported only here)."""
        with self._lock:
            if self._model is None:
                from mapd.codec import paper_model

                assert isinstance(self.options, PaperOptions)
                model = paper_model.load_model(self.model_path)
                model.name = self.options.model
                self._model = model
            return self._model

    def variant(self) -> str:
        return self.model().variant

    def encode_cells(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Encoded:
        from mapd.codec.paper_net import map_to_input

        model = self.model()
        t0 = time.perf_counter()
        with torch_threads(self.threads):
            sym = model.encode_symbols(map_to_input(grid.data))
        t1 = time.perf_counter()
        body = bytes([source_flags(grid.data)]) + huffman.encode(sym, model.levels)
        t2 = time.perf_counter()
        self.last_timings = {"cnn_encode_ms": 1000 * (t1 - t0), "huffman_encode_ms": 1000 * (t2 - t1)}
        return Encoded(body)

    def decode_cells(self, body: bytes, target: Target, base: OccupancyGrid | None) -> np.ndarray:
        model = self.model()
        if not body:
            raise CodecError("paper body is empty")
        flags = body[0]
        if flags & ~_FLAGS_KNOWN or not flags & (FLAG_FREE | FLAG_OCCUPIED | FLAG_UNKNOWN):
            raise CodecError(f"paper body has bad flags 0x{flags:02x}")
        h2, w2 = (target.height + 1) // 2, (target.width + 1) // 2
        t0 = time.perf_counter()
        sym = huffman.decode(body, h2 * w2, model.levels, pos=1).reshape(h2, w2)
        t1 = time.perf_counter()
        with torch_threads(self.threads):
            # Snapped band by band: the float32 values of the whole map are never held at once.
            cells = model.decode_values(sym, target.height, target.width, lambda band: snap(band, flags))
        t2 = time.perf_counter()
        self.last_timings = {"huffman_decode_ms": 1000 * (t1 - t0), "cnn_decode_ms": 1000 * (t2 - t1)}
        return cells
