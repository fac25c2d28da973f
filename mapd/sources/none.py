"""``[source] use = "none"``: no map of its own, for a base station that receives, fuses and outputs.

A daemon with this source sends no map (its publisher never has a version to code); it hears the
fleet's maps over its transports, acks them, and fuses them into the global map. Its fleet frame is
``fusion.anchor``'s map frame, or, when neither poses nor an anchor are configured, the map frame
of the first robot by name among those it has heard.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

from mapd.grid import OccupancyGrid
from mapd.sources.base import MapSource


class NoneSource(MapSource):
    """Never yields a map; runs until the daemon stops."""

    name = "none"

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        await asyncio.Event().wait()  # until cancelled at shutdown
        nothing: tuple[OccupancyGrid, ...] = ()
        for grid in nothing:  # an async generator that yields nothing
            yield grid
