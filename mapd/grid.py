"""The occupancy grid, and ROS map_server files read and written exactly.

Conventions follow ``nav_msgs/OccupancyGrid`` and REP-103:

* ``data`` is ``int8`` with shape ``(height, width)``; row 0 is at the map origin (the bottom row of
  the image), -1 is unknown and 0..100 is the occupancy probability in percent.
* ``resolution`` is meters per cell; ``origin`` is the pose (x, y in meters, yaw in radians,
  counter-clockwise) of the corner of cell (0, 0) in the robot's map frame.

:func:`load_map` follows the ROS 1 ``map_server`` image loader rule for rule (``negate``,
``occupied_thresh``, ``free_thresh``, and the modes trinary, scale and raw), including its quirks:
the comparisons are strict, trinary mode averages every channel (alpha too), scale mode marks any
pixel whose alpha is 0 as unknown, and raw mode stores the pixel value as a byte.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import struct
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError

from mapd.atomic import atomic_write_bytes
from mapd.errors import LimitError, MapFileError

UNKNOWN = -1
FREE = 0
OCCUPIED = 100
#: Default cap on cells for anything that allocates a grid from untrusted input (8192 x 8192).
DEFAULT_MAX_CELLS = 1 << 26

# map_server grey levels, used for saved trinary images and for PSNR/SSIM.
GREY_FREE = 254
GREY_OCCUPIED = 0
GREY_UNKNOWN = 205

# Cell classes for metrics and for codecs that model classes.
CLASS_FREE = 0
CLASS_OCCUPIED = 1
CLASS_UNKNOWN = 2
#: A cell at or above this occupancy is "occupied" (map_saver's default threshold, 0.65).
OCCUPIED_AT = 65


class Pose2D(NamedTuple):
    """A planar pose: x, y in meters and yaw in radians (counter-clockwise, REP-103)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0


ZERO_POSE = Pose2D()


@dataclasses.dataclass(eq=False)
class OccupancyGrid:
    """A 2D occupancy grid in the ``nav_msgs/OccupancyGrid`` layout.

    ``version`` increases with every new map a robot publishes; ``stamp`` is seconds since the epoch
    (or log time) when the map was made.
    """

    data: np.ndarray
    resolution: float
    origin: Pose2D = ZERO_POSE
    frame_id: str = "map"
    robot: str = ""
    version: int = 0
    stamp: float = 0.0

    def __post_init__(self) -> None:
        arr = np.asarray(self.data)
        if arr.ndim != 2:
            raise ValueError(f"grid data must be 2-D (height, width), got shape {arr.shape}")
        if arr.dtype != np.int8:
            raise ValueError(f"grid data must be int8, got {arr.dtype}")
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(
                f"resolution must be a positive number of meters per cell, got {self.resolution}"
            )
        self.data = arr
        self.origin = Pose2D(*(float(v) for v in self.origin))

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def cells(self) -> int:
        return int(self.data.size)

    def replace(self, **changes: Any) -> OccupancyGrid:
        """A copy with some fields changed (``data`` is shared unless given)."""
        return dataclasses.replace(self, **changes)

    def same_map(self, other: OccupancyGrid) -> bool:
        """True when cells, resolution and origin are identical (metadata such as version aside)."""
        return (
            self.data.shape == other.data.shape
            and self.resolution == other.resolution
            and tuple(self.origin) == tuple(other.origin)
            and bool(np.array_equal(self.data, other.data))
        )

    def digest(self) -> bytes:
        """16-byte BLAKE2b of cells, shape, resolution and origin: names a map version exactly."""
        h = hashlib.blake2b(digest_size=16)
        h.update(struct.pack("<IId3d", self.height, self.width, self.resolution, *self.origin))
        h.update(np.ascontiguousarray(self.data).tobytes())
        return h.digest()

    def classes(self) -> np.ndarray:
        """Per-cell class: CLASS_FREE, CLASS_OCCUPIED or CLASS_UNKNOWN (uint8, same shape)."""
        return cell_classes(self.data)

    def counts(self) -> dict[str, int]:
        """Number of free, occupied and unknown cells."""
        c = np.bincount(self.classes().ravel(), minlength=3)
        return {
            "free": int(c[CLASS_FREE]),
            "occupied": int(c[CLASS_OCCUPIED]),
            "unknown": int(c[CLASS_UNKNOWN]),
        }

    def is_trinary(self) -> bool:
        """True when every cell is -1, 0 or 100 (the usual SLAM map)."""
        d = self.data
        return bool(np.all((d == UNKNOWN) | (d == FREE) | (d == OCCUPIED)))

    def to_image(self) -> np.ndarray:
        """The map as map_server grey levels (free 254, occupied 0, unknown 205), row 0 at the top."""
        return np.flipud(grey_levels(self.data))

    def cell_to_world(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centres of cells (row, col) in the map frame, honouring the origin's yaw."""
        lx = (np.asarray(cols, dtype=np.float64) + 0.5) * self.resolution
        ly = (np.asarray(rows, dtype=np.float64) + 0.5) * self.resolution
        c, s = math.cos(self.origin.yaw), math.sin(self.origin.yaw)
        return self.origin.x + c * lx - s * ly, self.origin.y + s * lx + c * ly

    def world_to_cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) of map-frame points; floor them to index cells."""
        dx = np.asarray(x, dtype=np.float64) - self.origin.x
        dy = np.asarray(y, dtype=np.float64) - self.origin.y
        c, s = math.cos(self.origin.yaw), math.sin(self.origin.yaw)
        return (-s * dx + c * dy) / self.resolution, (c * dx + s * dy) / self.resolution


def cell_classes(data: np.ndarray) -> np.ndarray:
    """Classify int8 cells: negative is unknown, at least OCCUPIED_AT is occupied, else free."""
    d = np.asarray(data)
    out = np.full(d.shape, CLASS_FREE, dtype=np.uint8)
    out[d >= OCCUPIED_AT] = CLASS_OCCUPIED
    out[d < 0] = CLASS_UNKNOWN
    return out


def grey_levels(data: np.ndarray) -> np.ndarray:
    """map_saver's trinary grey level for each cell, same orientation as ``data`` (uint8)."""
    lut = np.array([GREY_FREE, GREY_OCCUPIED, GREY_UNKNOWN], dtype=np.uint8)
    return lut[cell_classes(data)]


# --------------------------------------------------------------------------------------------
# map_server YAML + image
# --------------------------------------------------------------------------------------------

_MODES = ("trinary", "scale", "raw")


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
    except (TypeError, ValueError):
        raise MapFileError(f"{path}: key '{key}' must be a {kind.__name__}, got {value!r}") from None
    return value


def read_map_yaml(yaml_path: str | os.PathLike[str]) -> dict[str, Any]:
    """Parse and validate a map_server YAML; returns resolved fields (image path made absolute)."""
    path = Path(yaml_path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MapFileError(f"{path}: no such map file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MapFileError(f"{path}: cannot read map yaml: {exc}") from None
    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        where = f" (line {line + 1})" if line is not None else ""
        raise MapFileError(f"{path}: malformed YAML{where}") from None
    if not isinstance(meta, dict):
        raise MapFileError(f"{path}: expected a YAML mapping with image, resolution and origin")

    image = _field(meta, "image", path, str)
    resolution = _field(meta, "resolution", path, float)
    if resolution <= 0:
        raise MapFileError(f"{path}: resolution must be positive, got {resolution}")
    origin = meta.get("origin")
    if not isinstance(origin, list | tuple) or len(origin) != 3:
        raise MapFileError(f"{path}: origin must be a list [x, y, yaw], got {origin!r}")
    try:
        ox, oy, oyaw = (float(v) for v in origin)
    except (TypeError, ValueError):
        raise MapFileError(f"{path}: origin must hold three numbers, got {origin!r}") from None
    if not all(math.isfinite(v) for v in (ox, oy, oyaw)):
        raise MapFileError(f"{path}: origin must be finite, got {origin!r}")
    negate = _field(meta, "negate", path, int, default=0)
    if negate not in (0, 1):
        raise MapFileError(f"{path}: negate must be 0 or 1, got {negate}")
    occ = _field(meta, "occupied_thresh", path, float, default=0.65)
    free = _field(meta, "free_thresh", path, float, default=0.196)
    if not (0.0 <= free <= 1.0 and 0.0 <= occ <= 1.0):
        raise MapFileError(f"{path}: thresholds must lie in [0, 1], got free {free}, occupied {occ}")
    if free > occ:
        raise MapFileError(f"{path}: free_thresh {free} is above occupied_thresh {occ}")
    mode = _field(meta, "mode", path, str, default="trinary")
    if mode not in _MODES:
        raise MapFileError(f"{path}: unknown mode '{mode}' (expected one of {', '.join(_MODES)})")
    image_path = Path(image)
    if not image_path.is_absolute():
        image_path = path.parent / image_path
    return {
        "image": image_path,
        "resolution": resolution,
        "origin": Pose2D(ox, oy, oyaw),
        "negate": negate,
        "occupied_thresh": occ,
        "free_thresh": free,
        "mode": mode,
    }


def _read_pixels(image_path: Path, yaml_path: Path, max_cells: int) -> tuple[np.ndarray, bool]:
    """Pixels as float64 (H, W, C) on a 0..255 scale, and whether the last channel is alpha."""
    img: Image.Image
    try:
        img = Image.open(image_path)
    except FileNotFoundError:
        raise MapFileError(f"{yaml_path}: image '{image_path}' does not exist") from None
    except Image.DecompressionBombError as exc:
        raise LimitError(f"{yaml_path}: image '{image_path}' is too large: {exc}") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise MapFileError(f"{yaml_path}: cannot read image '{image_path}': {exc}") from None
    with img:
        width, height = img.size
        if width <= 0 or height <= 0:
            raise MapFileError(f"{yaml_path}: image '{image_path}' has no pixels ({width}x{height})")
        if width * height > max_cells:
            raise LimitError(
                f"{yaml_path}: image '{image_path}' is {width}x{height} = {width * height} cells, "
                f"over the limit of {max_cells} cells"
            )
        try:
            mode = img.mode
            if mode == "P":
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
            elif mode == "1":
                img = img.convert("L")
            elif mode in ("PA",):
                img = img.convert("RGBA")
            elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                img = img.convert("RGB")
            mode = img.mode
            if mode.startswith("I;16") or mode == "I":
                arr = np.asarray(img, dtype=np.float64)
                top = 65535.0 if mode.startswith("I;16") or arr.max(initial=0) > 255 else 255.0
                arr = arr * (255.0 / top)
            elif mode == "F":
                arr = np.asarray(img, dtype=np.float64)
            else:
                arr = np.asarray(img, dtype=np.float64)
        except (OSError, ValueError, SyntaxError) as exc:
            raise MapFileError(f"{yaml_path}: image '{image_path}' is truncated or corrupt: {exc}") from None
    if arr.ndim == 2:
        arr = arr[:, :, None]
    has_alpha = img.mode in ("LA", "RGBA", "La", "RGBa")
    return arr, has_alpha


def load_map(
    yaml_path: str | os.PathLike[str], *, max_cells: int = DEFAULT_MAX_CELLS, robot: str = ""
) -> OccupancyGrid:
    """Read a map_server YAML and its image into an :class:`OccupancyGrid`, as map_server would.

    Raises :class:`MapFileError` naming the file and the problem, or :class:`LimitError` when the
    image has more than ``max_cells`` pixels (checked from the header, before decoding).
    """
    path = Path(yaml_path)
    meta = read_map_yaml(path)
    pixels, has_alpha = _read_pixels(meta["image"], path, max_cells)
    n = pixels.shape[2]
    mode = meta["mode"]
    # map_server: trinary averages all channels (alpha included); other modes skip alpha.
    avg_channels = n if (mode == "trinary" or not has_alpha) else n - 1
    color_avg = pixels[:, :, :avg_channels].sum(axis=2) / avg_channels
    # map_server reads "alpha" from the last channel of any multi-channel image (blue for RGB).
    alpha = pixels[:, :, n - 1] if n > 1 else np.full(color_avg.shape, 255.0)
    if meta["negate"]:
        color_avg = 255.0 - color_avg

    if mode == "raw":
        # unsigned char value = color_avg; then stored into the int8 data array.
        values = color_avg.astype(np.uint8).view(np.int8)
    else:
        occ = (255.0 - color_avg) / 255.0
        occ_th, free_th = meta["occupied_thresh"], meta["free_thresh"]
        values = np.full(color_avg.shape, UNKNOWN, dtype=np.int8)
        is_occ = occ > occ_th
        is_free = ~is_occ & (occ < free_th)
        values[is_occ] = OCCUPIED
        values[is_free] = FREE
        if mode == "scale":
            mid = ~is_occ & ~is_free & ~(alpha < 1.0)
            span = occ_th - free_th
            ratio = (occ[mid] - free_th) / span if span > 0 else np.zeros(int(mid.sum()))
            values[mid] = (1 + 98 * ratio).astype(np.int8)
    data = np.ascontiguousarray(np.flipud(values))
    return OccupancyGrid(data=data, resolution=meta["resolution"], origin=meta["origin"], robot=robot)


def save_map(grid: OccupancyGrid, yaml_path: str | os.PathLike[str], *, mode: str | None = None) -> Path:
    """Write ``grid`` as map_server YAML plus PGM next to it; returns the YAML path.

    Trinary grids are saved the way ``map_saver`` does (254 free, 0 occupied, 205 unknown). Grids
    with intermediate values are saved in raw mode, one byte per cell, so that :func:`load_map`
    gives back exactly the same data. Both files are written atomically (image first).
    """
    path = Path(yaml_path)
    if mode is None:
        mode = "trinary" if grid.is_trinary() else "raw"
    if mode not in ("trinary", "raw"):
        raise MapFileError(f"{path}: save_map writes trinary or raw maps, not '{mode}'")
    if mode == "trinary" and not grid.is_trinary():
        raise MapFileError(f"{path}: grid has values other than -1/0/100; save it in raw mode")
    pixels = grid.to_image() if mode == "trinary" else np.flipud(grid.data.view(np.uint8))
    image_path = path.with_suffix(".pgm")
    header = f"P5\n# CREATOR: mapd {grid.resolution:.3f} m/pix\n{grid.width} {grid.height}\n255\n".encode()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(image_path, header + np.ascontiguousarray(pixels).tobytes())
        meta = {
            "image": image_path.name,
            "mode": mode,
            "resolution": float(grid.resolution),
            "origin": [float(v) for v in grid.origin],
            "negate": 0,
            "occupied_thresh": 0.65,
            "free_thresh": 0.196,
        }
        atomic_write_bytes(path, yaml.safe_dump(meta, sort_keys=False).encode())
    except OSError as exc:
        raise MapFileError(f"{path}: cannot write map: {exc}") from None
    return path
