"""map_server files read exactly as ROS 1 ``map_server`` reads them.

:func:`read_map_yaml` reads and checks the YAML: a regular file of at most :data:`MAX_YAML_BYTES`,
resolution and origin within :func:`mapd.grid.geometry_problem`'s bounds, every problem one
:class:`~mapd.errors.MapFileError` naming the file. :func:`load_map` then follows the ROS 1
``map_server`` image loader rule for rule (``negate``, ``occupied_thresh``, ``free_thresh``, and the
modes trinary, scale and raw), including its quirks: the comparisons are strict, trinary mode
averages every channel (alpha too), scale mode marks any pixel whose alpha is 0 as unknown, and raw
mode stores the pixel value as a byte. The pixels come from :func:`mapd.imaging.read_pixels` and
are turned into cells a band of rows at a time.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mapd.errors import MapFileError
from mapd.grid import DEFAULT_MAX_CELLS, FREE, OCCUPIED, UNKNOWN, OccupancyGrid, Pose2D, geometry_problem
from mapd.grid.reprs import short_repr
from mapd.imaging import read_pixels
from mapd.imaging.pixels import one_line, open_map_file

_MODES = ("trinary", "scale", "raw")

#: Longest map_server YAML read. A real one is a few hundred bytes; a bigger file is refused unread.
MAX_YAML_BYTES = 64 * 1024
#: Cells converted at a time from pixels to occupancy: the float64 temporaries of map_server's
#: rules stay a few MiB whatever the map's size.
_BAND_CELLS = 1 << 18


def _field(meta: dict[str, Any], key: str, path: Path, kind: type, default: Any = None) -> Any:
    if key not in meta:
        if default is not None:
            return default
        raise MapFileError(f"{path}: missing key '{key}'")
    value = meta[key]
    try:
        if kind is float:
            if isinstance(value, bool):
                raise TypeError
            out = float(value)
            if not math.isfinite(out):
                raise ValueError
            return out
        if kind is int:
            if isinstance(value, bool):
                return int(value)
            if isinstance(value, float) and value.is_integer():
                return int(value)
            if not isinstance(value, int):
                raise TypeError
            return value
        if kind is str:
            if not isinstance(value, str):
                raise TypeError
            return value
    except (TypeError, ValueError, OverflowError):
        # OverflowError: a 400-digit integer does not fit a float.
        raise MapFileError(f"{path}: key '{key}' must be a {kind.__name__}, got {_short(value)}") from None
    return value


def read_map_yaml(yaml_path: str | os.PathLike[str]) -> dict[str, Any]:
    """Parse and validate a map_server YAML; returns resolved fields (image path made absolute).

    The file must be a regular file of at most :data:`MAX_YAML_BYTES`; resolution and origin must
    pass :func:`~mapd.grid.geometry_problem`. Every problem is one :class:`MapFileError` naming the file.
    """
    path = Path(yaml_path)
    try:
        fh = open_map_file(path, str(path), "map yaml")
    except FileNotFoundError:
        raise MapFileError(f"{path}: no such map file") from None
    try:
        with fh as f:
            raw = f.read(MAX_YAML_BYTES + 1)
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read map yaml: {exc.strerror}") from None
    if len(raw) > MAX_YAML_BYTES:
        raise MapFileError(
            f"{path}: map yaml is over {MAX_YAML_BYTES} bytes; a map_server yaml is a few lines"
        )
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise MapFileError(f"{path}: map yaml is not UTF-8 text") from None
    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        where = f" (line {line + 1})" if line is not None else ""
        raise MapFileError(f"{path}: malformed YAML{where}") from None
    except RecursionError:
        raise MapFileError(f"{path}: malformed YAML (nested too deeply)") from None
    except (ValueError, OverflowError, TypeError) as exc:
        # The safe constructor's own checks: a date like 2001-13-45, a bad !!float or !!int.
        raise MapFileError(f"{path}: malformed YAML ({one_line(exc)})") from None
    if not isinstance(meta, dict):
        raise MapFileError(f"{path}: expected a YAML mapping with image, resolution and origin")

    image = _field(meta, "image", path, str)
    # (a control character, a newline say, would go into every error about the image: one line
    # of mapd's own, and a line after it forged by the file)
    if not image or not image.isprintable():
        raise MapFileError(f"{path}: key 'image' must name an image file, got {_short(image)}")
    resolution = _field(meta, "resolution", path, float)
    if resolution <= 0:
        raise MapFileError(f"{path}: resolution must be positive, got {resolution}")
    origin = meta.get("origin")
    if not isinstance(origin, list | tuple) or len(origin) != 3:
        raise MapFileError(f"{path}: origin must be a list [x, y, yaw], got {_short(origin)}")
    try:
        if any(isinstance(v, bool) for v in origin):
            raise TypeError
        ox, oy, oyaw = (float(v) for v in origin)
    except (TypeError, ValueError, OverflowError):
        raise MapFileError(f"{path}: origin must hold three numbers, got {_short(origin)}") from None
    if not all(math.isfinite(v) for v in (ox, oy, oyaw)):
        raise MapFileError(f"{path}: origin must be finite, got {origin!r}")
    problem = geometry_problem(resolution, (ox, oy, oyaw))
    if problem is not None:
        raise MapFileError(f"{path}: {problem}")
    negate = _field(meta, "negate", path, int, default=0)
    if negate not in (0, 1):
        raise MapFileError(f"{path}: negate must be 0 or 1, got {_short(negate)}")
    occ = _field(meta, "occupied_thresh", path, float, default=0.65)
    free = _field(meta, "free_thresh", path, float, default=0.196)
    if not (0.0 <= free <= 1.0 and 0.0 <= occ <= 1.0):
        raise MapFileError(f"{path}: thresholds must lie in [0, 1], got free {free}, occupied {occ}")
    if free > occ:
        raise MapFileError(f"{path}: free_thresh {free} is above occupied_thresh {occ}")
    mode = _field(meta, "mode", path, str, default="trinary")
    if mode not in _MODES:
        raise MapFileError(f"{path}: unknown mode {_short(mode)} (expected one of {', '.join(_MODES)})")
    image_path = Path(image)
    if not image_path.is_absolute():
        image_path = path.parent / image_path
    fields = {
        "image": image_path,
        "resolution": resolution,
        "origin": Pose2D(ox, oy, oyaw),
        "negate": negate,
        "occupied_thresh": occ,
        "free_thresh": free,
        "mode": mode,
    }
    # Keys map_server does not read (a writer's own, as mapd's state keeps its versions), unchecked.
    fields["extra"] = {str(k): v for k, v in meta.items() if k not in fields}
    return fields


def _short(value: object) -> str:
    """:func:`short_repr` at the length of a map file's error line."""
    return short_repr(value, 60)


def _occupancy(px: np.ndarray, has_alpha: bool, meta: dict[str, Any]) -> np.ndarray:
    """map_server's rules on a band of pixels (float64, (rows, W, C), 0..255): int8 cells, image order."""
    n = px.shape[2]
    mode = meta["mode"]
    # map_server: trinary averages all channels (alpha included); other modes skip alpha.
    avg_channels = n if (mode == "trinary" or not has_alpha) else n - 1
    color_avg = px[:, :, :avg_channels].sum(axis=2) / avg_channels
    # map_server reads "alpha" from the last channel of any multi-channel image (blue for RGB).
    alpha = px[:, :, n - 1] if n > 1 else None
    if meta["negate"]:
        color_avg = 255.0 - color_avg
    if mode == "raw":
        # unsigned char value = color_avg; then stored into the int8 data array.
        return color_avg.astype(np.uint8).view(np.int8)
    occ = (255.0 - color_avg) / 255.0
    occ_th, free_th = meta["occupied_thresh"], meta["free_thresh"]
    values = np.full(color_avg.shape, UNKNOWN, dtype=np.int8)
    is_occ = occ > occ_th
    is_free = ~is_occ & (occ < free_th)
    values[is_occ] = OCCUPIED
    values[is_free] = FREE
    if mode == "scale":
        mid = ~is_occ & ~is_free
        if alpha is not None:
            mid &= ~(alpha < 1.0)
        span = occ_th - free_th
        ratio = (occ[mid] - free_th) / span if span > 0 else np.zeros(int(mid.sum()))
        values[mid] = (1 + 98 * ratio).astype(np.int8)
    return values


def load_map(
    yaml_path: str | os.PathLike[str], *, max_cells: int = DEFAULT_MAX_CELLS, robot: str = ""
) -> OccupancyGrid:
    """Read a map_server YAML and its image into an :class:`OccupancyGrid`, as map_server would.

    Raises :class:`MapFileError` naming the file and the problem (a truncated, half-written or
    malformed YAML or image, never a padded map), or :class:`LimitError` when the image has more
    than ``max_cells`` pixels (read from its header, before any pixel is decoded). Memory stays a
    small multiple of the image: pixels are turned into cells a band of rows at a time.
    """
    path = Path(yaml_path)
    return map_from_yaml_fields(read_map_yaml(path), path, max_cells=max_cells, robot=robot)


def map_from_yaml_fields(
    meta: dict[str, Any], yaml_path: Path, *, max_cells: int = DEFAULT_MAX_CELLS, robot: str = ""
) -> OccupancyGrid:
    """:func:`load_map` of a YAML already read by :func:`read_map_yaml` (its own keys wanted too)."""
    path = yaml_path
    pixels = read_pixels(meta["image"], str(path), max_cells)
    height, width = pixels.arr.shape[:2]
    data = np.empty((height, width), dtype=np.int8)
    step = max(1, _BAND_CELLS // width)
    for r0 in range(0, height, step):
        r1 = min(height, r0 + step)
        band = _occupancy(pixels.grey(r0, r1), pixels.has_alpha, meta)
        # Image row 0 is the top; nav_msgs row 0 is at the origin (the bottom row of the image).
        data[height - r1 : height - r0] = band[::-1]
    return OccupancyGrid(data=data, resolution=meta["resolution"], origin=meta["origin"], robot=robot)
