"""Decoded pixels, Pillow's decoding of them, and what every image reader here shares.

* :class:`Pixels`: an image's samples ``(H, W, C)`` as the file holds them, turned into map_server's
  0..255 grey scale a band of rows at a time.
* :func:`pillow_pixels`: Pillow restricted to the formats asked for (only those map_server also
  reads, :data:`PILLOW_FORMATS`), the size checked from the header before decoding, the pixels handed
  over as map_server's SDL_image would (palette to RGB(A), 1-bit to grey, 16-bit scaled to 0..255),
  a JPEG's scans counted first (:mod:`mapd.imaging.jpeg`), and every failure one error.
* :func:`check_cells`: an empty image, or one over the caller's cell limit, refused from its header
  before a pixel is decoded.
* :func:`open_map_file`: a regular file, opened so that a FIFO or a device named as a
  map can neither block nor be read for ever.
* :func:`one_line`: an exception's message on one line, for the errors the readers raise.
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from PIL import Image, UnidentifiedImageError

from mapd.errors import LimitError, MapFileError
from mapd.files.reading import NotRegularFileError, open_regular
from mapd.imaging.jpeg import JPEG_SIGNATURE, check_jpeg

#: Image formats handed to Pillow (the ones ROS map_server's SDL_image also reads). Anything else is
#: refused before a decoder runs: no Ghostscript for EPS, no rarely used decoders on untrusted bytes.
PILLOW_FORMATS = ("BMP", "GIF", "JPEG", "TIFF", "TGA", "PCX", "WEBP", "XPM")
#: What Pillow raises on bytes it cannot decode (its plugins are not uniform about it).
_PIL_ERRORS: tuple[type[BaseException], ...] = (
    OSError,
    ValueError,
    SyntaxError,
    EOFError,
    struct.error,
    IndexError,
    KeyError,
    TypeError,
    ZeroDivisionError,
    NotImplementedError,
    MemoryError,
    Image.DecompressionBombError,
)


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (a CLI error is one line per problem)."""
    return " ".join(str(exc).split()) or type(exc).__name__


def open_map_file(path: Path, where: str, what: str) -> BinaryIO:
    """``path`` opened for reading, refusing anything but a regular file (FileNotFoundError as raised).

    A FIFO named as a map cannot block the open, and a device (``/dev/zero`` would be read
    forever) or a directory is refused: each is one :class:`MapFileError` starting with ``where``.
    """
    try:
        return open_regular(path)
    except FileNotFoundError:
        raise
    except NotRegularFileError:
        raise MapFileError(f"{where}: {what} '{path}' is not a regular file") from None
    except OSError as exc:
        raise MapFileError(f"{where}: cannot open {what} '{path}': {exc.strerror}") from None


@dataclasses.dataclass
class Pixels:
    """Decoded pixels ``(H, W, C)`` in the file's own sample type, and how samples become grey.

    ``lut`` maps an integer sample to its grey level on map_server's 0..255 scale (float64); without
    it a sample times ``scale`` is the grey level. Conversion happens a band of rows at a time, so
    the float64 arrays of the loading rules never exist for the whole image.
    """

    arr: np.ndarray
    has_alpha: bool
    lut: np.ndarray | None = None
    scale: float = 1.0

    def grey(self, r0: int, r1: int) -> np.ndarray:
        band = self.arr[r0:r1]
        if self.lut is not None:
            return self.lut[band]
        out = band.astype(np.float64)
        if self.scale != 1.0:
            out *= self.scale
        return out


def check_cells(width: int, height: int, where: str, image: Path, max_cells: int) -> None:
    """Refuse an empty image or one over ``max_cells``, from its header, before any pixel is decoded."""
    if width <= 0 or height <= 0:
        raise MapFileError(f"{where}: image '{image}' has no pixels ({width}x{height})")
    if width * height > max_cells:
        raise LimitError(
            f"{where}: image '{image}' is {width}x{height} = {width * height} cells, "
            f"over the limit of {max_cells} cells"
        )


def pillow_pixels(
    f: Any, formats: tuple[str, ...], where: str, image: Path, max_cells: int, *, palette: int | None = None
) -> Pixels:
    """Decode with Pillow (after any header checks of our own); every failure is one MapFileError.

    ``palette``: how many colours the file's palette holds, as the caller's own check read it (a
    PNG's PLTE); a pixel whose index lies beyond it is refused. Pillow would decode it as black, a
    wall by map_server's rules, where libpng refuses the file.

    A JPEG's markers are walked first (:func:`mapd.imaging.jpeg.check_jpeg`): one with more scans
    than :data:`mapd.imaging.jpeg.MAX_JPEG_SCANS` is a LimitError before libjpeg decodes any.

    ``max_cells`` is checked right after ``Image.open``, which reads only the header, so nothing over
    the limit is decoded. Pillow's own decompression-bomb guard (``Image.MAX_IMAGE_PIXELS``, about
    89 M pixels, refused at twice that) is deliberately left at its process-wide default: it is above
    the default ``max_cells`` (67 M), so it only ever acts as a second fence, and mapd does not
    change a global that other code in the process may rely on. Its refusal is a LimitError.
    """
    name = f"{where}: image '{image}'"
    if "JPEG" in formats:
        # libjpeg has no limit on a progressive JPEG's scans, each as costly as the image is large:
        # they are counted first (a file Pillow's JPEG plugin would take starts with these bytes).
        head = f.read(len(JPEG_SIGNATURE))
        if head == JPEG_SIGNATURE:
            check_jpeg(f, where, image)
        f.seek(0)
    try:
        img = Image.open(f, formats=list(formats))
    except Image.DecompressionBombError as exc:
        raise LimitError(f"{name} is too large: {one_line(exc)}") from None
    except UnidentifiedImageError:
        raise MapFileError(
            f"{name} is not an image mapd reads (PGM/PNM, PNG, {', '.join(PILLOW_FORMATS[:-1])} "
            f"or {PILLOW_FORMATS[-1]}), or its header is damaged"
        ) from None
    except _PIL_ERRORS as exc:
        raise MapFileError(f"{name} cannot be read: {one_line(exc)}") from None
    try:
        with img:
            check_cells(img.size[0], img.size[1], where, image, max_cells)
            return _pillow_array(img, palette)
    except (MapFileError, LimitError):
        raise
    except _PIL_ERRORS as exc:
        raise MapFileError(f"{name} is truncated or corrupt: {one_line(exc)}") from None


def _pillow_array(img: Image.Image, palette: int | None = None) -> Pixels:
    """Pixels of a Pillow image, converted as map_server's SDL_image would hand them over.

    Raises ValueError for a palette image with an index at or beyond ``palette`` colours.
    """
    mode = img.mode
    if mode == "P" and palette is not None:
        top = int(np.asarray(img).max(initial=0))
        if top >= palette:
            raise ValueError(f"pixel index {top} lies beyond its palette of {palette} colours")
    if mode == "P":
        img = img.convert("RGBA" if "transparency" in img.info else "RGB")
    elif mode == "1":
        img = img.convert("L")
    elif mode == "PA":
        img = img.convert("RGBA")
    elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
        img = img.convert("RGB")
    mode = img.mode
    arr = np.asarray(img)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.dtype.kind not in "uif":
        raise ValueError(f"pixel mode {mode} is not supported")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():  # a NaN loaded as free space
        raise ValueError("it holds samples that are not numbers (NaN or infinity)")
    has_alpha = mode in ("LA", "RGBA", "La", "RGBa")
    if mode.startswith("I;16"):
        return Pixels(arr, has_alpha, scale=255.0 / 65535.0)
    if mode == "I":
        # A 32-bit integer image (Pillow's 16-bit PNG): 16-bit samples unless none is above 255.
        return Pixels(arr, has_alpha, scale=255.0 / 65535.0 if int(arr.max(initial=0)) > 255 else 1.0)
    return Pixels(arr, has_alpha)
