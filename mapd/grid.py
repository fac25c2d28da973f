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

This module holds the grid type, its cell constants and geometry bounds (:func:`geometry_problem`),
the YAML reader (:func:`read_map_yaml`), those loading rules, :func:`save_map`, and
:func:`save_committed` for maps a crash must not tear. Decoding the
image itself (PNM, PNG and Pillow, hardened against truncated and hostile files) is
:mod:`mapd.imaging`'s, which hands back the pixels.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import math
import os
import reprlib
import struct
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml

from mapd.errors import MapFileError
from mapd.files import atomic_write_files
from mapd.imaging import MAX_PNM_HEADER as MAX_PNM_HEADER
from mapd.imaging import PILLOW_FORMATS as PILLOW_FORMATS
from mapd.imaging import PLAIN_PNM_MAX_CELLS as PLAIN_PNM_MAX_CELLS
from mapd.imaging import read_pixels
from mapd.imaging.pixels import one_line, open_map_file

UNKNOWN = -1
FREE = 0
OCCUPIED = 100
#: Default cap on cells for anything that allocates a grid from untrusted input (8192 x 8192).
DEFAULT_MAX_CELLS = 1 << 26
#: Longest side of a grid that travels between robots (cells): 3.3 km at 5 cm. A 1 x 67 M "map"
#: is damage, and the lossless kernels keep per-column state that such a shape would blow up.
MAX_GRID_SIDE = 1 << 16

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


def wrap_angle(a: float) -> float:
    """The angle in (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


def compose(a: Pose2D, b: Pose2D) -> Pose2D:
    """``a`` then ``b``: with ``a`` = frame B in A and ``b`` = C in B, returns C in A (SE(2))."""
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    return Pose2D(a.x + c * b.x - s * b.y, a.y + s * b.x + c * b.y, wrap_angle(a.yaw + b.yaw))


def inverse(t: Pose2D) -> Pose2D:
    """A in B, given B in A: the pose that undoes ``t``."""
    c, s = math.cos(t.yaw), math.sin(t.yaw)
    return Pose2D(-(c * t.x + s * t.y), -(-s * t.x + c * t.y), wrap_angle(-t.yaw))


class StampedPose(NamedTuple):
    """Where a robot's ``base_link`` was, in its own map frame, at ``stamp`` (wall-clock seconds)."""

    pose: Pose2D
    stamp: float


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
        # Hashed through a buffer view: tobytes() would copy the whole grid first.
        h.update(np.ascontiguousarray(self.data).data.cast("B"))
        return h.digest()

    def classes(self) -> np.ndarray:
        """Per-cell class: CLASS_FREE, CLASS_OCCUPIED or CLASS_UNKNOWN (uint8, same shape)."""
        return cell_classes(self.data)

    def counts(self) -> dict[str, int]:
        """Number of free, occupied and unknown cells."""
        hist = value_histogram(self.data)
        # By the uint8 bit pattern of a cell: 0..64 free, 65..127 occupied, 128..255 negative (unknown).
        return {
            "free": int(hist[:OCCUPIED_AT].sum()),
            "occupied": int(hist[OCCUPIED_AT:128].sum()),
            "unknown": int(hist[128:].sum()),
        }

    def is_trinary(self) -> bool:
        """True when every cell is -1, 0 or 100 (the usual SLAM map)."""
        hist = value_histogram(self.data)
        return int(hist.sum()) == int(hist[FREE] + hist[OCCUPIED] + hist[UNKNOWN & 0xFF])

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


def value_histogram(data: np.ndarray) -> np.ndarray:
    """How many cells hold each int8 value, indexed by its uint8 bit pattern (256 counts, int64).

    Counted a million cells at a time: ``np.bincount`` widens its input to int64, which for a whole
    grid would be eight bytes a cell.
    """
    flat = np.ascontiguousarray(data, dtype=np.int8).view(np.uint8).ravel()
    out = np.zeros(256, dtype=np.int64)
    step = 1 << 20
    for i in range(0, flat.size, step):
        out += np.bincount(flat[i : i + step], minlength=256)
    return out


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

#: Finest and coarsest resolution accepted from a map file or a payload (meters per cell).
MIN_RESOLUTION = 1e-4
MAX_RESOLUTION = 1e3
#: Largest ``|x|`` or ``|y|`` of a map origin accepted from a file or a payload (meters). 10,000 km
#: holds every UTM easting and northing, so real maps always pass; a larger value is damage.
MAX_ORIGIN_M = 1e7
#: Largest ``|yaw|`` of a map origin accepted from a file or a payload (radians): one full turn.
MAX_ORIGIN_YAW = 2.0 * math.pi

#: Longest map_server YAML read. A real one is a few hundred bytes; a bigger file is refused unread.
MAX_YAML_BYTES = 64 * 1024
# The image limits (MAX_PNM_HEADER, PLAIN_PNM_MAX_CELLS, PILLOW_FORMATS) live with the decoders in
# mapd.imaging and are re-exported above, so `from mapd.grid import PLAIN_PNM_MAX_CELLS` still works.
#: Cells converted at a time from pixels to occupancy: the float64 temporaries of map_server's
#: rules stay a few MiB whatever the map's size.
_BAND_CELLS = 1 << 18


def geometry_problem(resolution: float, origin: tuple[float, float, float]) -> str | None:
    """Why a map's resolution and origin cannot be right (not finite, out of the documented
    bounds :data:`MIN_RESOLUTION`, :data:`MAX_RESOLUTION`, :data:`MAX_ORIGIN_M`,
    :data:`MAX_ORIGIN_YAW`), or None when they are plausible. Shared by the map files and the codecs.
    """
    if not (math.isfinite(resolution) and MIN_RESOLUTION <= resolution <= MAX_RESOLUTION):
        return f"resolution {resolution!r} m/cell is not within [{MIN_RESOLUTION}, {MAX_RESOLUTION}]"
    x, y, yaw = origin
    for name, v, bound in (("x", x, MAX_ORIGIN_M), ("y", y, MAX_ORIGIN_M), ("yaw", yaw, MAX_ORIGIN_YAW)):
        if not (math.isfinite(v) and abs(v) <= bound):
            return f"origin {name} {v!r} is not within +-{bound:g}"
    return None


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
    pass :func:`geometry_problem`. Every problem is one :class:`MapFileError` naming the file.
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
    if not image or "\x00" in image:
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


class _BoundedRepr(reprlib.Repr):
    """A ``repr`` whose cost is bounded whatever the value.

    A YAML alias bomb (anchors nested ten deep, ten aliases each) is a few hundred bytes that
    ``repr`` expands to 10**10 items, and a hex integer of 64 KiB has more digits than Python
    converts to decimal (ValueError). Both are shown cut short instead.
    """

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel = 3
        self.maxdict = self.maxlist = self.maxtuple = self.maxset = self.maxfrozenset = 6
        self.maxstring = self.maxother = 60
        self.maxlong = 40

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 128:  # decimal conversion of a huge int is slow, or refused past 4300 digits
            return f"<{'-' if x < 0 else ''}integer of {x.bit_length()} bits>"
        return super().repr_int(x, level)


_BOUNDED_REPR = _BoundedRepr()


def short_repr(value: object, limit: int = 60) -> str:
    """``repr`` of an untrusted value cut to about ``limit`` characters, at a bounded cost.

    Nested containers are shown a few levels and items deep, huge integers by their size, so a
    hostile YAML or TOML value (an alias bomb, a 64 KiB hex number) is one short line, never a hang
    or a ValueError.
    """
    try:
        shown = _BOUNDED_REPR.repr(value)
    except Exception:  # a hostile object's own __repr__; a name is still one clear line
        shown = f"<{type(value).__name__}>"
    return shown if len(shown) <= limit else shown[: limit - 3] + "..."


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


def save_map(
    grid: OccupancyGrid,
    yaml_path: str | os.PathLike[str],
    *,
    mode: str | None = None,
    image_name: str | None = None,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``grid`` as map_server YAML plus PGM next to it; returns the YAML path.

    Trinary grids are saved the way ``map_saver`` does (254 free, 0 occupied, 205 unknown). Grids
    with intermediate values are saved in raw mode, one byte per cell, so that :func:`load_map`
    gives back exactly the same data. Both files are written together (:func:`~mapd.files.atomic_write_files`).
    The image is ``NAME.pgm`` unless ``image_name`` names another file in the same folder; ``extra``
    keys are written after map_server's own (which map_server ignores, :func:`read_map_yaml` returns).
    """
    path = Path(yaml_path)
    if mode is None:
        mode = "trinary" if grid.is_trinary() else "raw"
    if mode not in ("trinary", "raw"):
        raise MapFileError(f"{path}: save_map writes trinary or raw maps, not '{mode}'")
    if mode == "trinary" and not grid.is_trinary():
        raise MapFileError(f"{path}: grid has values other than -1/0/100; save it in raw mode")
    pixels = grid.to_image() if mode == "trinary" else np.flipud(grid.data.view(np.uint8))
    if path.is_dir() or path.name in ("", ".", ".."):
        # Checked first: the image would otherwise be written beside it (DIR.pgm) before the YAML fails.
        raise MapFileError(f"{path}: is a directory; name the map's YAML file")
    image_path = path.with_suffix(".pgm") if image_name is None else path.with_name(image_name)
    if image_path == path:  # the YAML would be written over the image it names: the map lost
        raise MapFileError(f"{path}: the map's image is written as NAME.pgm; name the YAML NAME.yaml")
    header = f"P5\n# CREATOR: mapd {grid.resolution:.3f} m/pix\n{grid.width} {grid.height}\n255\n".encode()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            "image": image_path.name,
            "mode": mode,
            "resolution": float(grid.resolution),
            "origin": [float(v) for v in grid.origin],
            "negate": 0,
            "occupied_thresh": 0.65,
            "free_thresh": 0.196,
        }
        meta.update({k: v for k, v in (extra or {}).items() if k not in meta})
        # Together: a full disk (or an immutable YAML) left the new image beside the old YAML, a
        # map that loads with another map's size and origin.
        atomic_write_files(
            [
                (image_path, header + np.ascontiguousarray(pixels).tobytes()),
                (path, yaml.safe_dump(meta, sort_keys=False).encode()),
            ],
            # an image under a name of its own (map-<n>.pgm) is a new file each time: it takes the
            # permissions the operator gave the map's YAML
            like={image_path: path},
        )
    except OSError as exc:
        # strerror, not str(exc): that names the hidden temp file, which means nothing to the user.
        raise MapFileError(f"{path}: cannot write map: {exc.strerror or one_line(exc)}") from None
    return path


#: The YAML fields that commit a map saved by :func:`save_committed`.
VERSION_KEY = "mapd_version"
DIGEST_KEY = "mapd_digest"
_COUNT_LIMIT = 1 << 63  # versions are whole numbers below this, as envelopes carry them


def save_committed(grid: OccupancyGrid, yaml_path: Path, extra: dict[str, Any] | None = None) -> str:
    """Save ``grid`` so that no crash can tear it, and return its digest (hex).

    The daemon's state maps and the fusion worker's global map are saved this way: the image under
    a name of its own (``<stem>-<version>.pgm``), then the YAML that names it and holds the map's
    version and digest (:data:`VERSION_KEY`, :data:`DIGEST_KEY`), then the images no YAML names any
    more are removed. A kill at any point leaves the old map or the new one whole (a fixed image
    name renamed before its YAML left the old YAML's origin over the new image: a shifted map), and
    a reader that checks the digest (:func:`committed_record`) never takes a mismatched image for
    the map. :class:`MapFileError` with one line when the disk refuses.
    """
    digest = grid.digest().hex()
    image = f"{yaml_path.stem}-{grid.version}.pgm"
    try:
        save_map(
            grid,
            yaml_path,
            image_name=image,
            extra={VERSION_KEY: grid.version, DIGEST_KEY: digest, **(extra or {})},
        )
    except OSError as exc:  # what save_map looks at before it writes (a stat that fails)
        raise MapFileError(f"{yaml_path}: cannot write map: {exc.strerror or one_line(exc)}") from None
    with contextlib.suppress(OSError):  # best effort (a listing that fails): the next save removes them
        for old in [yaml_path.with_suffix(".pgm"), *yaml_path.parent.glob(f"{yaml_path.stem}-*.pgm")]:
            if old.name != image:
                with contextlib.suppress(OSError):  # one that cannot go stops none of the others
                    old.unlink(missing_ok=True)
    return digest


def committed_record(extra: dict[str, Any]) -> tuple[int, str] | None:
    """The version and digest a committed map's YAML holds (its ``extra`` fields, as
    :func:`read_map_yaml` gives them), or None when it holds none that could be (a YAML written
    before they were kept, or hand-edited)."""
    version, digest = extra.get(VERSION_KEY), extra.get(DIGEST_KEY)
    if type(version) is int and 0 <= version < _COUNT_LIMIT and isinstance(digest, str):
        return version, digest
    return None
