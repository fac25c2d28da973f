"""The occupancy grid: its type, its cells, its origin's pose and the bounds of its geometry.

Conventions follow ``nav_msgs/OccupancyGrid`` and REP-103:

* ``data`` is ``int8`` with shape ``(height, width)``; row 0 is at the map origin (the bottom row of
  the image), -1 is unknown and 0..100 is the occupancy probability in percent.
* ``resolution`` is meters per cell; ``origin`` is the pose (x, y in meters, yaw in radians,
  counter-clockwise) of the corner of cell (0, 0) in the robot's map frame.

This module holds the grid type, its cell constants and classes, the planar pose (:class:`Pose2D`,
composed and inverted in SE(2)) and the geometry bounds every map from a file or a payload must
pass (:func:`geometry_problem`). The rest of the package:

* :mod:`~mapd.grid.load`: a map_server YAML and its image read as ROS 1 ``map_server`` reads them;
* :mod:`~mapd.grid.save`: maps written as ``map_saver`` writes them, and committed saves for maps a
  crash must not tear;
* :mod:`~mapd.grid.reprs`: an untrusted value shown in one short line, at a bounded cost (the map
  files' errors, and the config's).

Decoding the image itself (PNM, PNG and Pillow, hardened against truncated and hostile files) is
:mod:`mapd.imaging`'s, which hands back the pixels.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import struct
from typing import Any, NamedTuple

import numpy as np

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
# Geometry bounds
# --------------------------------------------------------------------------------------------

#: Finest and coarsest resolution accepted from a map file or a payload (meters per cell).
MIN_RESOLUTION = 1e-4
MAX_RESOLUTION = 1e3
#: Largest ``|x|`` or ``|y|`` of a map origin accepted from a file or a payload (meters). 10,000 km
#: holds every UTM easting and northing, so real maps always pass; a larger value is damage.
MAX_ORIGIN_M = 1e7
#: Largest ``|yaw|`` of a map origin accepted from a file or a payload (radians): one full turn.
MAX_ORIGIN_YAW = 2.0 * math.pi


def on_lattice(origin: Pose2D, resolution: float, ref: Pose2D) -> Pose2D:
    """``origin`` moved (by at most half a cell on each axis) onto the cell lattice of a map whose
    origin is ``ref``, for maps of one resolution and yaw; unchanged otherwise.

    A SLAM that sets its map's origin to the corner of its scans' bounding box (slam_toolbox, from
    Karto) moves it by a fraction of a cell as the map grows: no delta aligns such maps cell for
    cell, and each version went whole. On the first map's lattice, the next ones do.
    """
    if resolution <= 0 or abs(wrap_angle(origin.yaw - ref.yaw)) > 1e-9:
        return origin
    dx, dy = (origin.x - ref.x) / resolution, (origin.y - ref.y) / resolution
    cos, sin = math.cos(ref.yaw), math.sin(ref.yaw)
    fc, fr = cos * dx + sin * dy, -sin * dx + cos * dy  # in the reference's cell axes
    if not (math.isfinite(fc) and math.isfinite(fr)):
        return origin
    c, r = round(fc), round(fr)
    return Pose2D(ref.x + (cos * c - sin * r) * resolution, ref.y + (sin * c + cos * r) * resolution, ref.yaw)


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
