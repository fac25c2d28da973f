"""Which placed maps the global map can hold: bounded in extent and in cells, never frozen.

One damaged map must not stop the fleet's map. A map whose origin is corrupt (1e6 m), or that lies
so far out that the global grid would exceed the cell limit, would make every merge fail until its
robot sent a sane version, and the global map would freeze for everyone. These functions leave such
maps out instead, with the reason in their placement (for ``mapd status``) and one warning; the
placer keeps its held transform, so the robot's next sane map goes straight back in. Pure functions
of their arguments: the fusion worker calls them on its merge thread.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np

from mapd.fusion.merge import NO_OWNER, Bounds, extent
from mapd.fusion.placement import Placement
from mapd.fusion.transforms import transformed_corners
from mapd.fusion.views import MAX_SIDE
from mapd.grid import OccupancyGrid

log = logging.getLogger(__name__)
LEFT_OUT = "left out of the global map: "


def within_extent(
    maps: dict[str, OccupancyGrid], placements: dict[str, Placement], names: list[str], limit_m: float
) -> list[str]:
    """``names`` whose placed maps lie within ``limit_m`` of the fleet frame's origin.

    The others are marked left out in ``placements`` (which this updates), with the reason.
    """
    keep = []
    for r in names:
        reach = _reach(maps[r], placements[r])
        if math.isfinite(reach) and reach <= limit_m:
            keep.append(r)
            continue
        leave_out(
            placements,
            r,
            f"it reaches {reach:.4g} m from the fleet frame's origin, beyond fusion.max_extent_m = "
            f"{limit_m:g} m (a damaged map origin or a wrong pose?)",
        )
    return keep


def within_cell_limit(
    maps: dict[str, OccupancyGrid],
    placements: dict[str, Placement],
    names: list[str],
    *,
    resolution: float,
    bounds: Bounds | None,
    max_cells: int,
) -> list[str]:
    """``names`` less the farthest maps, while the global map would exceed the cell limit.

    Within ``max_extent_m`` a map can still make the global grid bigger than ``max_cells`` (10 km at
    5 cm is 200,000 cells a side); merging would then fail as a whole, so the maps reaching farthest
    from the fleet frame's origin are left out, with the reason, until the rest fits. ``bounds``
    (the previous global map's, kept unless far larger than its maps) counts toward the size.
    """
    keep = list(names)
    while keep:
        box = extent([maps[r] for r in keep], [placements[r].transform for r in keep], resolution)
        if box is not None and bounds is not None:
            box = box.union(bounds)
        if box is None or (box.width * box.height <= max_cells and max(box.width, box.height) <= MAX_SIDE):
            break
        far = max(keep, key=lambda r: _reach(maps[r], placements[r]))
        keep.remove(far)
        leave_out(
            placements,
            far,
            f"with it the global map would be {box.width} x {box.height} cells, over the limit of "
            f"{max_cells} cells ({MAX_SIDE} a side)",
        )
    return keep


def within_merge_limits(
    maps: dict[str, OccupancyGrid], placements: dict[str, Placement], names: list[str], *, resolution: float
) -> list[str]:
    """``names`` less the maps one merge cannot take: a map over :data:`MAX_SIDE` cells a side at
    the resolution it is merged at (OpenCV's warp refuses sources past 32,767, and the whole merge
    failed with it), and the maps past the :data:`NO_OWNER` the owner grid can name (a fleet of
    255 robots failed every merge). The others are marked left out, with the reason.
    """
    keep: list[str] = []
    for r in names:
        g = maps[r]
        pooled = resolution / g.resolution >= 1.5  # merge._at_most_as_fine
        side = max(g.width, g.height) * (g.resolution / resolution if pooled else 1.0)
        if side > MAX_SIDE:
            leave_out(placements, r, f"it is {g.width} x {g.height} cells, over {MAX_SIDE} a side merged")
        elif len(keep) >= NO_OWNER - 1:
            leave_out(placements, r, f"at most {NO_OWNER - 1} maps are merged at once")
        else:
            keep.append(r)
    return keep


def leave_out(placements: dict[str, Placement], robot: str, why: str) -> None:
    """Mark ``robot``'s placement as left out of the global map, with the reason (which the
    fusion worker says once, not at every merge: :func:`say_left_out`)."""
    placements[robot] = replace(placements[robot], accepted=False, reason=f"{LEFT_OUT}{why}")


def say_left_out(placements: dict[str, Placement], said: dict[str, str]) -> None:
    """Warn of each map left out, once for as long as it is left out for the same reason.

    ``said`` (robot -> the reason last said) is the caller's memory across merges: a map left out
    was said again at every merge, a line a second from one robot's map.
    """
    for robot in list(said):
        if not placements.get(robot, Placement(robot)).reason.startswith(LEFT_OUT):
            del said[robot]  # merged again: said again if it is left out again
    for robot, p in placements.items():
        if p.reason.startswith(LEFT_OUT) and said.get(robot) != p.reason:
            said[robot] = p.reason
            log.warning("fusion: %s: %s", robot, p.reason)


def _reach(grid: OccupancyGrid, placement: Placement) -> float:
    """How far from the fleet frame's origin the placed map's farthest corner lies, in meters."""
    assert placement.transform is not None
    c = transformed_corners(grid, placement.transform)
    return float(np.hypot(c[:, 0], c[:, 1]).max())


__all__ = ["leave_out", "say_left_out", "within_cell_limit", "within_extent", "within_merge_limits"]
