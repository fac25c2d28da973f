"""Small synthetic maps made from a seed, for the tests and the benchmarks (no shared data needed).

Each generator draws one trinary grid (-1 unknown, 0 free, 100 occupied) from
``numpy.random.default_rng(seed)``; the same arguments always give the same cells. Tests and the
lossless codec's corpus (``tests/codec/corpus_lossless``) are built from these exact cells, so a
change to any generator here changes them: add a new generator rather than editing one.

* :func:`room_grid`: one walled room with a box in it and some speckle (codec and daemon tests);
* :func:`building`: a floor plan of rooms by recursive splits, with doors and furniture (fusion tests);
* :func:`indoor_maps`: several maps of rooms on a jittered grid (``mapd bench`` without shared data).

The simulator's buildings, with rooms off a corridor and goals to drive to, are
:func:`mapd.mapping.worldgen.generate`.
"""

from __future__ import annotations

import itertools

import numpy as np

from mapd.grid import OccupancyGrid, Pose2D


def _room(d: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> None:
    """Rows r0..r1-1, columns c0..c1-1 of ``d`` become free space inside a 1-cell wall."""
    d[r0:r1, c0:c1] = 0
    d[r0, c0:c1] = d[r1 - 1, c0:c1] = 100
    d[r0:r1, c0] = d[r0:r1, c1 - 1] = 100


def room_grid(
    height: int = 60,
    width: int = 80,
    *,
    seed: int = 0,
    resolution: float = 0.05,
    origin: Pose2D | None = None,
) -> OccupancyGrid:
    """A small trinary map: unknown outside, a walled room with a box inside, some speckle."""
    rng = np.random.default_rng(seed)
    d = np.full((height, width), -1, dtype=np.int8)
    r0, r1, c0, c1 = height // 6, height - height // 6, width // 8, width - width // 8
    _room(d, r0, r1, c0, c1)
    br, bc = height // 2, width // 2
    d[br - 3 : br + 3, bc - 4 : bc + 4] = 100
    speck = rng.random((height, width)) < 0.01
    d[speck & (d == 0)] = 100
    return OccupancyGrid(data=d, resolution=resolution, origin=origin or Pose2D(-1.0, -2.0, 0.0))


def building(
    height: int = 320,
    width: int = 360,
    *,
    seed: int = 0,
    resolution: float = 0.05,
    origin: Pose2D | None = None,
) -> OccupancyGrid:
    """A random floor plan of robot ``a``: rooms by recursive splits, doors, furniture, 1-cell walls,
    unknown outside."""
    rng = np.random.default_rng(seed)
    d = np.full((height, width), -1, dtype=np.int8)
    r0, c0, r1, c1 = 10, 10, height - 10, width - 10
    _room(d, r0, r1, c0, c1)

    def split(a0: int, b0: int, a1: int, b1: int, depth: int) -> None:
        h, w = a1 - a0, b1 - b0
        if depth > 5 or (h < 60 and w < 60):
            # furniture: a couple of boxes per room
            for _ in range(int(rng.integers(0, 3))):
                bh, bw = int(rng.integers(3, 9)), int(rng.integers(3, 12))
                if h > bh + 8 and w > bw + 8:
                    y = int(rng.integers(a0 + 4, a1 - bh - 4))
                    x = int(rng.integers(b0 + 4, b1 - bw - 4))
                    d[y : y + bh, x : x + bw] = 100
            return
        if h >= w:
            cut = int(rng.integers(a0 + h // 3, a1 - h // 3))
            d[cut, b0:b1] = 100
            door = int(rng.integers(b0 + 3, b1 - 12))
            d[cut, door : door + 9] = 0
            split(a0, b0, cut, b1, depth + 1)
            split(cut + 1, b0, a1, b1, depth + 1)
        else:
            cut = int(rng.integers(b0 + w // 3, b1 - w // 3))
            d[a0:a1, cut] = 100
            door = int(rng.integers(a0 + 3, a1 - 12))
            d[door : door + 9, cut] = 0
            split(a0, b0, a1, cut, depth + 1)
            split(a0, cut + 1, a1, b1, depth + 1)

    split(r0 + 1, c0 + 1, r1 - 1, c1 - 1, 0)
    return OccupancyGrid(data=d, resolution=resolution, origin=origin or Pose2D(-3.0, -4.0, 0.0), robot="a")


def indoor_maps(count: int = 6, seed: int = 0) -> list[tuple[str, OccupancyGrid]]:
    """``count`` plausible indoor maps of 200 to 700 cells a side, labelled ``synthetic/<i>``.

    The maps are drawn one after another from one random stream, so map i is the same whatever
    ``count`` is (asking for fewer maps gives the first ones).
    """
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        h, w = int(rng.integers(200, 700)), int(rng.integers(200, 700))
        d = np.full((h, w), -1, dtype=np.int8)
        # Rooms on a jittered grid, joined by doors: free inside, walls around.
        rooms_y = np.linspace(10, h - 10, int(rng.integers(2, 5)) + 1).astype(int)
        rooms_x = np.linspace(10, w - 10, int(rng.integers(2, 5)) + 1).astype(int)
        for r0, r1 in itertools.pairwise(rooms_y):
            for c0, c1 in itertools.pairwise(rooms_x):
                if rng.random() < 0.2:
                    continue
                _room(d, r0, r1, c0, c1)
                dr = int(rng.integers(r0 + 3, max(r0 + 4, r1 - 6)))
                d[dr : dr + 4, c0] = 0
                dc = int(rng.integers(c0 + 3, max(c0 + 4, c1 - 6)))
                d[r0, dc : dc + 4] = 0
        noise = rng.random((h, w)) < 0.003
        d[noise & (d == 0)] = 100
        out.append((f"synthetic/{i}", OccupancyGrid(d, 0.05, Pose2D(-w * 0.025, -h * 0.025, 0.0))))
    return out
