"""The data ``mapd train`` learns from: maps split by place, and tiles with their real surroundings.

* **Split.** Maps are split into training and validation *by place*, never by tile: maps of one
  place (``intel``, ``intel_part1``, ``intel_part2``; the two ``house_20xx`` runs) share a group, and
  whole groups go to one side (:func:`split_maps`). The split depends only on the map names.
* **Tiles.** A tile is a ``tile x tile`` output region with its real surroundings (the networks'
  receptive field, padded with unknown outside the map), so training sees exactly what whole-map
  inference sees (:func:`sample_tiles`). Each tile carries the loss weight of every output cell.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mapd.codec import paper_net as pn
from mapd.errors import ConfigError
from mapd.grid import OccupancyGrid, cell_classes

MARGIN = pn.crop_margin()


# --------------------------------------------------------------------------------------------
# Split by place
# --------------------------------------------------------------------------------------------


def map_group(path: Path, shares_folder: bool = False) -> str:
    """The place a map shows: its folder name up to the first underscore.

    ``intel_part1`` -> ``intel``; ``ipa-office_2017`` -> ``ipa-office``; a purely numeric folder
    (``aws_small_warehouse/002``) takes its parent's name. When several maps share one folder the
    file name stands in for the folder name.
    """
    name = path.stem if shares_folder else path.parent.name
    if name.isdigit():
        name = path.parent.parent.name if not shares_folder else path.parent.name
    return name.split("_")[0] or name


def split_maps(paths: list[Path], val_fraction: float) -> tuple[list[Path], list[Path], dict[str, str]]:
    """Split maps into (train, validation) by group; also return each map's group.

    Groups are ordered by the sha256 of their name and the first ``round(val_fraction * groups)``
    (at least one, when there are two or more groups) go to validation.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ConfigError(f"--val-fraction must be in [0, 1), got {val_fraction}")
    per_folder: dict[Path, int] = {}
    for p in paths:
        per_folder[p.parent] = per_folder.get(p.parent, 0) + 1
    groups = {str(p): map_group(p, per_folder[p.parent] > 1) for p in paths}
    names = sorted(set(groups.values()), key=lambda g: hashlib.sha256(g.encode()).hexdigest())
    n_val = 0
    if len(names) >= 2 and val_fraction > 0:
        n_val = min(len(names) - 1, max(1, round(val_fraction * len(names))))
    val_groups = set(names[:n_val])
    train = [p for p in paths if groups[str(p)] not in val_groups]
    val = [p for p in paths if groups[str(p)] in val_groups]
    return train, val, groups


# --------------------------------------------------------------------------------------------
# Tiles
# --------------------------------------------------------------------------------------------


@dataclass
class PreparedMap:
    """One map padded for crop sampling, with its edge-tile candidates."""

    label: str
    x: np.ndarray  # network input, padded by MARGIN (and up to whole tiles) with unknown
    height: int
    width: int
    origins: np.ndarray  # (n, 2) even full-resolution tile origins
    content: np.ndarray  # (n,) True where the tile holds an edge
    boundary: np.ndarray  # like x: True for cells with a 4-neighbour of another class (both sides)


def prepare_map(label: str, grid: OccupancyGrid, tile: int) -> PreparedMap:
    h, w = grid.height, grid.width
    he = max(h + (h % 2), tile)
    we = max(w + (w % 2), tile)
    x = np.zeros((he + 2 * MARGIN, we + 2 * MARGIN), dtype=np.float32)
    x[MARGIN : MARGIN + h, MARGIN : MARGIN + w] = pn.map_to_input(grid.data)
    cls = cell_classes(grid.data).astype(np.int16)
    edge = np.zeros((he + 1, we + 1), dtype=np.int64)
    e = np.zeros((h, w), dtype=bool)
    e[:, 1:] |= cls[:, 1:] != cls[:, :-1]
    e[1:, :] |= cls[1:, :] != cls[:-1, :]
    edge[1 : h + 1, 1 : w + 1] = e
    # Both cells of every differing 4-neighbour pair (``e`` above marks only the later one).
    horiz = cls[:, 1:] != cls[:, :-1]
    vert = cls[1:, :] != cls[:-1, :]
    both = np.zeros((h, w), dtype=bool)
    both[:, 1:] |= horiz
    both[:, :-1] |= horiz
    both[1:, :] |= vert
    both[:-1, :] |= vert
    boundary = np.zeros(x.shape, dtype=bool)
    boundary[MARGIN : MARGIN + h, MARGIN : MARGIN + w] = both
    integral = edge.cumsum(0).cumsum(1)
    step = max(2, (tile // 2) & ~1)
    rows = sorted({*range(0, he - tile + 1, step), he - tile})
    cols = sorted({*range(0, we - tile + 1, step), we - tile})
    origins = np.array([(r, c) for r in rows for c in cols], dtype=np.int64)
    r, c = origins[:, 0], origins[:, 1]
    count = integral[r + tile, c + tile] - integral[r, c + tile] - integral[r + tile, c] + integral[r, c]
    return PreparedMap(label, x, h, w, origins, count > 0, boundary)


@dataclass
class TileBatch:
    """A batch of training tiles.

    ``x``: crops (B, 1, tile + 2 MARGIN, ...); ``fmask``: where m_feature lies inside the map
    (B, 1, tile/2 + 12, ...); ``lmask``: output cells inside the map (B, 1, tile, tile).
    """

    x: torch.Tensor
    fmask: torch.Tensor
    lmask: torch.Tensor


def _crop(
    pm: PreparedMap, r0: int, c0: int, tile: int, k: int, flip: bool, edge_weight: float = 1.0
) -> tuple[np.ndarray, ...]:
    size = tile + 2 * MARGIN
    x = pm.x[r0 : r0 + size, c0 : c0 + size]
    half = tile // 2
    p = pn.RECOVERY_PAD
    fr = np.arange(r0 // 2 - p, r0 // 2 + half + p)
    fc = np.arange(c0 // 2 - p, c0 // 2 + half + p)
    fmask = ((fr >= 0) & (fr < (pm.height + 1) // 2))[:, None] & ((fc >= 0) & (fc < (pm.width + 1) // 2))[
        None, :
    ]
    lr = np.arange(r0, r0 + tile)
    lc = np.arange(c0, c0 + tile)
    lmask = ((lr < pm.height)[:, None] & (lc < pm.width)[None, :]).astype(np.float32)
    if edge_weight != 1.0:
        b = pm.boundary[r0 + MARGIN : r0 + MARGIN + tile, c0 + MARGIN : c0 + MARGIN + tile]
        lmask = lmask * np.where(b, np.float32(edge_weight), np.float32(1.0))
    out = []
    for a in (x, fmask, lmask):
        a = np.rot90(a, k)
        out.append(np.ascontiguousarray(a[:, ::-1] if flip else a))
    return tuple(out)


def sample_tiles(
    maps: list[PreparedMap], n: int, tile: int, rng: np.random.Generator, edge_weight: float = 1.0
) -> TileBatch:
    """``n`` tiles drawn from ``maps`` with ``rng`` (nine in ten on an edge), randomly rotated.

    ``lmask`` weighs each output cell in the loss: 0 outside the map, ``edge_weight`` on a class
    boundary, 1 elsewhere.
    """
    weights = np.array([math.sqrt(max(1, int(m.content.sum()))) for m in maps])
    weights /= weights.sum()
    xs, fms, lms = [], [], []
    for _ in range(n):
        pm = maps[int(rng.choice(len(maps), p=weights))]
        he, we = pm.x.shape[0] - 2 * MARGIN, pm.x.shape[1] - 2 * MARGIN
        pool = np.flatnonzero(pm.content)
        if rng.random() < 0.9 and pool.size:
            r0, c0 = (int(v) for v in pm.origins[int(rng.choice(pool))])
            jitter = tile // 4
            r0 = int(np.clip(r0 + 2 * int(rng.integers(-jitter // 2, jitter // 2 + 1)), 0, he - tile))
            c0 = int(np.clip(c0 + 2 * int(rng.integers(-jitter // 2, jitter // 2 + 1)), 0, we - tile))
        else:
            r0 = 2 * int(rng.integers(0, (he - tile) // 2 + 1))
            c0 = 2 * int(rng.integers(0, (we - tile) // 2 + 1))
        x, fm, lm = _crop(pm, r0, c0, tile, int(rng.integers(0, 4)), bool(rng.integers(0, 2)), edge_weight)
        xs.append(x)
        fms.append(fm)
        lms.append(lm)
    return TileBatch(
        torch.from_numpy(np.stack(xs))[:, None],
        torch.from_numpy(np.stack(fms))[:, None],
        torch.from_numpy(np.stack(lms))[:, None],
    )


__all__ = ["MARGIN", "PreparedMap", "TileBatch", "map_group", "prepare_map", "sample_tiles", "split_maps"]
