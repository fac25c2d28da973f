"""Map images decoded from untrusted files: PNM, PNG and what Pillow reads, hardened.

Works on paths and bytes and returns numpy arrays; it knows nothing of occupancy grids (turning
grey levels into cells by map_server's rules is :func:`mapd.grid.load.load_map`'s part). Every problem is
one :class:`~mapd.errors.MapFileError` (truncated, half-written or corrupt file, never a padded
image) or a :class:`~mapd.errors.LimitError` (more pixels than allowed, known from the header,
before any pixel is decoded).

* :func:`read_pixels`: the one entry point; sniffs the format and hands the file to one of:
* :mod:`~mapd.imaging.pnm`: PNM header parser and reader (P5/P6 with numpy, P1-P4 checked for Pillow);
* :mod:`~mapd.imaging.png`: PNG chunk, CRC, IEND, PLTE and data-length verifier, run before Pillow
  decodes;
* :mod:`~mapd.imaging.jpeg`: JPEG marker walker, run before Pillow decodes: a progressive JPEG's
  scans are counted and bounded (each costs a pass over the whole image);
* :mod:`~mapd.imaging.pixels`: the Pillow wrapper for everything else (only map_server's formats,
  one error per failure), :class:`Pixels` (grey levels a band of rows at a time) and the helpers the
  readers share (regular-file open, the cell check).
"""

from __future__ import annotations

import os
from pathlib import Path

from mapd.errors import MapFileError
from mapd.imaging.pixels import PILLOW_FORMATS, Pixels, open_map_file, pillow_pixels
from mapd.imaging.png import PNG_SIGNATURE, check_png
from mapd.imaging.pnm import MAX_PNM_HEADER, PLAIN_PNM_MAX_CELLS, PNM_WS, read_pnm

__all__ = ["MAX_PNM_HEADER", "PILLOW_FORMATS", "PLAIN_PNM_MAX_CELLS", "Pixels", "read_pixels"]


def read_pixels(image_path: Path, where: str, max_cells: int) -> Pixels:
    """The image's pixels, its size checked against ``max_cells`` from the header before decoding.

    ``where`` starts every error message (the map YAML that names the image).
    """
    try:
        fh = open_map_file(image_path, where, "image")
    except FileNotFoundError:
        raise MapFileError(f"{where}: image '{image_path}' does not exist") from None
    try:
        with fh as f:
            size = os.fstat(f.fileno()).st_size
            magic = f.read(8)
            f.seek(0)
            if len(magic) >= 3 and magic[0] == ord("P") and magic[1] in b"123456" and magic[2] in PNM_WS:
                pixels = read_pnm(f, size, where, image_path, max_cells)
                if pixels is not None:
                    return pixels
                f.seek(0)
                return pillow_pixels(f, ("PPM",), where, image_path, max_cells)
            if magic == PNG_SIGNATURE:
                palette = check_png(f, where, image_path, max_cells)
                f.seek(0)
                return pillow_pixels(f, ("PNG",), where, image_path, max_cells, palette=palette)
            if PNG_SIGNATURE.startswith(magic) or (magic[:1] == b"P" and len(magic) < 3):
                raise MapFileError(f"{where}: image '{image_path}' is truncated ({len(magic)} bytes)")
            return pillow_pixels(f, PILLOW_FORMATS, where, image_path, max_cells)
    except OSError as exc:
        raise MapFileError(f"{where}: cannot read image '{image_path}': {exc.strerror or exc}") from None
