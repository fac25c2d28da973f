"""The live view as one of the daemon's outputs: maps and poses in on the output thread, out over HTTP.

The daemon builds a :class:`LiveView` when ``[view] listen`` is set and adds it to its outputs, so
:meth:`publish` and :meth:`publish_poses` run on the daemon's output thread (latest wins there: a
slow view skips global maps, it never queues them). That is where the CPU work happens, the tile
diff and the PNG encodes, and each result is handed to the event loop with
``call_soon_threadsafe`` as ready-made bytes. :meth:`robot_map` is called on the loop for every
robot map the daemon holds and only notes its size, for the outlines.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Callable
from typing import Any

from mapd.config import ViewSection, split_listen
from mapd.grid import OccupancyGrid
from mapd.outputs.base import GlobalUpdate, Output, OutputContext, PoseUpdate
from mapd.view.model import MapModel, RobotMap
from mapd.view.queue import Message
from mapd.view.server import ViewServer

log = logging.getLogger("mapd.view")


class LiveView(Output):
    """The ``[view]`` web page of this daemon: global map, robots, links (read-only)."""

    name = "view"

    def __init__(
        self,
        section: ViewSection,
        ctx: OutputContext,
        *,
        token: str | None = None,
        snapshot: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        super().__init__(None, ctx)
        if section.listen is None:
            raise ValueError("LiveView needs [view] listen")
        host, port = split_listen(section.listen)
        self.server = ViewServer(host, port, token=token, max_viewers=section.max_viewers, snapshot=snapshot)
        self.model = MapModel()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._maps_lock = threading.Lock()  # robot_map (loop) -> publish (output thread)
        self._new_maps: dict[str, RobotMap] = {}
        self._published = 0

    @property
    def url(self) -> str:
        return self.server.url

    @property
    def token(self) -> str | None:
        """The token every request is checked against (None: none, a loopback listen)."""
        return self.server.token

    def set_token(self, token: str | None) -> bool:
        """A new token (a reload): in force from the next request; True when it changed (on the loop)."""
        return self.server.set_token(token)

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        await self.server.start()

    async def close(self) -> None:
        await self.server.close()

    # ------------------------------------------------------------------ on the loop
    def robot_map(self, grid: OccupancyGrid) -> None:
        """A robot's map as the daemon now holds it: only its size and origin are kept (cheap)."""
        if grid.robot:
            with self._maps_lock:
                self._new_maps[grid.robot] = RobotMap.of(grid)

    # ------------------------------------------------------------------ on the output thread
    def publish(self, update: GlobalUpdate) -> None:
        """A new global map: diff and encode the changed tiles here, then hand them to the loop."""
        with self._maps_lock:
            maps, self._new_maps = self._new_maps, {}
        self.model.robot_maps(maps)
        delta = self.model.global_map(update)
        full = self.model.full_map()
        self._published += 1
        self._hand_over(delta, self.model.robots(), full_map=full)

    def publish_poses(self, update: PoseUpdate) -> None:
        """New robot poses: the robots message (positions and trails in the fleet frame)."""
        self._hand_over(self.model.poses(update.poses, update.frames))

    def _hand_over(self, *msgs: Message, full_map: Message | None = None) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        # RuntimeError: the loop closed in between (the daemon is stopping)
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(lambda: self.server.post(*msgs, full_map=full_map))

    def stats(self) -> dict[str, int | float | str]:
        return {
            "url": self.server.url,
            "viewers": self.server.viewers,
            "maps": self._published,
            "tiles_encoded": self.model.tiles_encoded,
            **self.server.counters,
        }
