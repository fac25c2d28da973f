"""Procedural indoor floor plans for the simulator: rooms off a corridor, doors, some clutter.

:func:`generate` draws a building from a seed: an outer wall, one corridor across it, rooms on both
sides (deep rooms are split into a front and a back room joined by a door, some neighbours share a
door), and furniture-like boxes kept clear of doors and of the way from each door to its room's
centre. The same seed always gives the same building, cell for cell, so separate daemons that
simulate one robot each agree on the world without talking to each other.

The world frame (the fleet frame of a simulated fleet) has its origin at the building's lower-left
outer corner; the grid carries a margin of unknown cells around the building.

:func:`from_map` wraps a map_server map as a world instead; its goals are well-clear free points
spread over the largest connected free area.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from mapd.grid import FREE, OCCUPIED, OCCUPIED_AT, UNKNOWN, OccupancyGrid, Pose2D

WALL = 0.15  # m, inner wall thickness
OUTER_WALL = 0.25  # m
MARGIN = 1.0  # m of unknown around the building
CORRIDOR = 2.0  # m, corridor width


@dataclass
class Room:
    """An axis-aligned room (meters, world frame) and the doors that lead into it."""

    x0: float
    y0: float
    x1: float
    y1: float
    doors: list[tuple[float, float]] = field(default_factory=list)

    @property
    def center(self) -> tuple[float, float]:
        return (0.5 * (self.x0 + self.x1), 0.5 * (self.y0 + self.y1))


@dataclass
class World:
    """A world for simulated robots: the grid the lidar sees, places worth visiting, start poses."""

    grid: OccupancyGrid
    #: Points (world frame, m) robots should visit to see everything: room centres, corridor points.
    goals: list[tuple[float, float]]
    #: A good start pose per fleet slot when the config does not give one (see :meth:`start_for`).
    corridor: tuple[float, float, float] | None = None  # x0, x1, y of the corridor's centre line
    rooms: list[Room] = field(default_factory=list)

    def occupied(self) -> np.ndarray:
        """Cells a beam stops at (occupied; unknown counts as open space for the lidar)."""
        return np.asarray(self.grid.data >= OCCUPIED_AT)

    def free(self) -> np.ndarray:
        """Cells a robot may stand on (known free)."""
        d = self.grid.data
        return np.asarray((d >= 0) & (d < OCCUPIED_AT))


class _Painter:
    """Draws rectangles in world meters onto a cell array."""

    def __init__(self, width_m: float, height_m: float, resolution: float) -> None:
        self.res = resolution
        self.w = round((width_m + 2 * MARGIN) / resolution)
        self.h = round((height_m + 2 * MARGIN) / resolution)
        self.data = np.full((self.h, self.w), UNKNOWN, dtype=np.int8)

    def _cells(self, v: float) -> int:
        return round((v + MARGIN) / self.res)

    def rect(self, x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        c0, c1 = sorted((self._cells(x0), self._cells(x1)))
        r0, r1 = sorted((self._cells(y0), self._cells(y1)))
        self.data[max(r0, 0) : min(max(r1, r0 + 1), self.h), max(c0, 0) : min(max(c1, c0 + 1), self.w)] = (
            value
        )

    def hwall(self, x0: float, x1: float, y: float, t: float = WALL) -> None:
        self.rect(x0 - t / 2, y - t / 2, x1 + t / 2, y + t / 2, OCCUPIED)

    def vwall(self, x: float, y0: float, y1: float, t: float = WALL) -> None:
        self.rect(x - t / 2, y0 - t / 2, x + t / 2, y1 + t / 2, OCCUPIED)


def _split(rng: np.random.Generator, a: float, b: float, lo: float, hi: float) -> list[float]:
    """Cut [a, b] into pieces between lo and hi long (the last piece absorbs the remainder)."""
    cuts = [a]
    while b - cuts[-1] > hi:
        step = float(rng.uniform(lo, hi))
        if b - (cuts[-1] + step) < lo:
            step = (b - cuts[-1]) / 2
        cuts.append(cuts[-1] + step)
    cuts.append(b)
    return cuts


def _door_pos(rng: np.random.Generator, a: float, b: float, width: float) -> float | None:
    """Centre of a door of ``width`` on a wall segment [a, b], keeping clear of the corners."""
    lo, hi = a + 0.3 + width / 2, b - 0.3 - width / 2
    if hi < lo:
        return None
    return float(rng.uniform(lo, hi))


def _seg_dist(px: float, py: float, a: tuple[float, float], b: tuple[float, float]) -> float:
    ax, ay = a
    bx, by = b
    dx, dy = bx - ax, by - ay
    n = dx * dx + dy * dy
    t = 0.0 if n == 0 else max(0.0, min(1.0, ((px - ax) * dx + (py - ay) * dy) / n))
    return math.hypot(px - (ax + t * dx), py - (ay + t * dy))


def generate(
    seed: int, width_m: float = 30.0, height_m: float = 20.0, resolution: float = 0.05, clutter: float = 1.0
) -> World:
    """A building of ``width_m`` x ``height_m`` meters drawn from ``seed`` (same seed, same building)."""
    if not (6.0 <= width_m <= 500.0 and 6.0 <= height_m <= 500.0):
        raise ValueError("building sides must lie between 6 and 500 m")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5EED]))
    pt = _Painter(width_m, height_m, resolution)
    pt.rect(0, 0, width_m, height_m, FREE)
    cy = height_m / 2 + float(rng.uniform(-0.15, 0.15)) * height_m
    c0, c1 = cy - CORRIDOR / 2, cy + CORRIDOR / 2
    rooms: list[Room] = []
    # Door openings are cut after all walls are drawn; remember them as rectangles.
    openings: list[tuple[float, float, float, float]] = []

    for side in ("south", "north"):
        ya, yb = (0.0, c0) if side == "south" else (c1, height_m)
        door_y = c0 if side == "south" else c1
        cuts = _split(rng, 0.0, width_m, 3.0, 6.0)
        for x0, x1 in itertools.pairwise(cuts):
            if x0 > 0:
                pt.vwall(x0, ya, yb)
            width = float(rng.uniform(0.9, 1.2))
            dx = _door_pos(rng, x0, x1, width)
            if dx is None:
                continue
            openings.append((dx - width / 2, door_y - WALL, dx + width / 2, door_y + WALL))
            depth = yb - ya
            if depth > 7.0 and rng.random() < 0.7:
                # Front room on the corridor, back room behind it, a door between them.
                frac = float(rng.uniform(0.45, 0.6))
                ym = ya + (1 - frac) * depth if side == "south" else ya + frac * depth
                pt.hwall(x0, x1, ym)
                w2 = float(rng.uniform(0.9, 1.1))
                dx2 = _door_pos(rng, x0, x1, w2)
                front = Room(x0, ym, x1, yb) if side == "south" else Room(x0, ya, x1, ym)
                back = Room(x0, ya, x1, ym) if side == "south" else Room(x0, ym, x1, yb)
                front.doors.append((dx, door_y))
                if dx2 is not None:
                    openings.append((dx2 - w2 / 2, ym - WALL, dx2 + w2 / 2, ym + WALL))
                    front.doors.append((dx2, ym))
                    back.doors.append((dx2, ym))
                    rooms.extend([front, back])
                else:
                    rooms.append(front)
            else:
                r = Room(x0, ya, x1, yb)
                r.doors.append((dx, door_y))
                rooms.append(r)
        # Some neighbouring rooms share a door in the wall between them.
        for x in cuts[1:-1]:
            if rng.random() < 0.3:
                w3 = float(rng.uniform(0.9, 1.1))
                near = (ya, min(yb, ya + 4.0)) if side == "south" else (max(ya, yb - 4.0), yb)
                dy = _door_pos(rng, near[0], near[1], w3)
                if dy is not None:
                    openings.append((x - WALL, dy - w3 / 2, x + WALL, dy + w3 / 2))
                    for r in rooms:
                        if (
                            abs(r.x0 - x) < 1e-9 or abs(r.x1 - x) < 1e-9
                        ) and r.y0 - 1e-9 <= dy <= r.y1 + 1e-9:
                            r.doors.append((x, dy))

    pt.hwall(0, width_m, c0)
    pt.hwall(0, width_m, c1)
    for ox0, oy0, ox1, oy1 in openings:
        pt.rect(ox0, oy0, ox1, oy1, FREE)
    # Outer walls last, so no opening cuts through them.
    t = OUTER_WALL
    pt.rect(-t / 2, -t / 2, width_m + t / 2, t / 2, OCCUPIED)
    pt.rect(-t / 2, height_m - t / 2, width_m + t / 2, height_m + t / 2, OCCUPIED)
    pt.rect(-t / 2, -t / 2, t / 2, height_m + t / 2, OCCUPIED)
    pt.rect(width_m - t / 2, -t / 2, width_m + t / 2, height_m + t / 2, OCCUPIED)

    for room in rooms:
        _clutter(rng, pt, room, clutter)

    corridor_goals = [(float(x), cy) for x in np.linspace(1.5, width_m - 1.5, max(2, int(width_m // 8) + 1))]
    goals = [r.center for r in rooms] + corridor_goals
    grid = OccupancyGrid(
        data=np.ascontiguousarray(pt.data),
        resolution=resolution,
        origin=Pose2D(-MARGIN, -MARGIN, 0.0),
        frame_id="world",
    )
    return World(grid=grid, goals=goals, corridor=(1.0, width_m - 1.0, cy), rooms=rooms)


def _clutter(rng: np.random.Generator, pt: _Painter, room: Room, amount: float) -> None:
    """Boxes in a room, kept off its doors and off the way from each door to the room's centre."""
    cx, cy = room.center
    n = int(rng.poisson(2.0 * amount))
    for _ in range(n):
        for _attempt in range(12):
            w, h = (float(v) for v in rng.uniform(0.3, 1.2, size=2))
            x = float(rng.uniform(room.x0 + WALL, room.x1 - WALL - w))
            y = float(rng.uniform(room.y0 + WALL, room.y1 - WALL - h))
            bx, by = x + w / 2, y + h / 2
            reach = 0.5 * math.hypot(w, h) + 0.8
            if math.hypot(bx - cx, by - cy) < reach + 0.4:
                continue
            if any(math.hypot(bx - dx, by - dy) < reach + 0.4 for dx, dy in room.doors):
                continue
            if any(_seg_dist(bx, by, (dx, dy), (cx, cy)) < reach for dx, dy in room.doors):
                continue
            pt.rect(x, y, x + w, y + h, OCCUPIED)
            break


def from_map(grid: OccupancyGrid, seed: int = 0, spacing: float = 3.0, clearance: float = 0.5) -> World:
    """A world from an existing map: goals spread over its largest well-clear free area."""
    d = grid.data
    free = (d >= 0) & (d < OCCUPIED_AT)
    clear = ndimage.distance_transform_edt(free) * grid.resolution
    ok = clear >= clearance
    labels, n = ndimage.label(ok)
    if n == 0:
        return World(grid=grid, goals=[])
    sizes = ndimage.sum_labels(ok, labels, index=np.arange(1, n + 1))
    main = labels == (int(np.argmax(sizes)) + 1)
    rows, cols = np.nonzero(main)
    xs, ys = grid.cell_to_world(rows, cols)
    pts = np.stack([xs, ys], axis=1)
    # Farthest-point sampling from a seeded start: evenly spread goals, reproducible.
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6AA1]))
    chosen = [int(rng.integers(len(pts)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while len(chosen) < 500:
        i = int(np.argmax(dist))
        if dist[i] < spacing:
            break
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[i], axis=1))
    goals = [(float(pts[i, 0]), float(pts[i, 1])) for i in chosen]
    return World(grid=grid.replace(frame_id="world"), goals=goals)
