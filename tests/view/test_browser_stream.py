"""The page's stream in a real headless Chromium against the real view server: refused, then let in;
its token rotated; its daemon restarted.

An answer other than 200 on ``/events`` (a 503 at the viewer cap, a 401 after the token changed)
makes the browser close an EventSource for good: the page must try again by itself, and say so.
A page whose daemon restarted must not show the old daemon's map as live.
"""

from __future__ import annotations

import asyncio
import re
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest

from mapd.grid import OccupancyGrid, Pose2D
from mapd.outputs.base import GlobalUpdate
from mapd.view.model import MapModel
from mapd.view.server import ViewServer

TOKEN = "s3cret-token-0123456789"
CONN = "document.getElementById('conn').textContent"
#: The page says it is disconnected and when it tries again (the text, truthy, once it does).
DISCONNECTED = f"(t => t.startsWith('disconnected, retrying in ') && t)({CONN})"
LIVE_AND_DRAWN = f"{CONN} === 'live' && mapdView.seq > 0 && mapdView.drawnSeq === mapdView.seq"


def post_a_map(server: ViewServer) -> None:
    model = MapModel()
    grid = OccupancyGrid(np.zeros((50, 60), np.int8), 0.05, Pose2D(-1.0, -1.0, 0.0))
    delta = model.global_map(GlobalUpdate(grid, {}, 1.0))
    server.post(delta, model.robots(), full_map=model.full_map())


@pytest.mark.slow
def test_a_page_refused_at_the_viewer_cap_tries_again_until_it_is_let_in(
    chromium: str, vk: Any, tmp_path: Path
) -> None:
    """Before: after the one 503 the page said "reconnecting" for ever and never came back."""

    async def main() -> None:
        server = ViewServer("127.0.0.1", 0, max_viewers=1)
        await server.start()
        post_a_map(server)
        try:
            async with aiohttp.ClientSession() as s, vk.Browser(chromium, tmp_path) as b:
                hog = await s.get(server.url + "events")  # takes the only place
                assert hog.status == 200
                await b.goto(server.url)
                said = await b.wait(DISCONNECTED, 60, "the page saying it is disconnected")
                assert re.fullmatch(r"disconnected, retrying in \d+ s", said), said
                assert server.counters["refused_busy"] >= 1 and server.viewers == 1
                hog.close()
                await b.wait(LIVE_AND_DRAWN, 60, "the page let in, the map drawn")
                assert server.viewers == 1
        finally:
            await server.close()

    asyncio.run(main())


@pytest.mark.slow
def test_a_page_whose_token_was_rotated_says_so_and_comes_back_with_it(
    chromium: str, vk: Any, tmp_path: Path
) -> None:
    """A reload with a new token ends the page's stream; its next try is a 401 (the browser gives up
    on the stream for good), then the page retries on its own."""
    new = "n3w-token-9876543210"

    async def main() -> None:
        server = ViewServer("127.0.0.1", 0, token=TOKEN)
        await server.start()
        post_a_map(server)
        try:
            async with vk.Browser(chromium, tmp_path) as b:
                await b.goto(server.url + f"?token={TOKEN}")
                await b.wait(LIVE_AND_DRAWN, 60, "the page live")
                refused = server.counters["refused_token"]
                server.set_token(new)
                await b.wait(DISCONNECTED, 60, "the page saying it is disconnected")
                assert server.counters["refused_token"] > refused and server.viewers == 0
                server.set_token(TOKEN)  # (the page holds only the token it was opened with)
                await b.wait(f"{CONN} === 'live'", 60, "the page back")
                assert server.viewers == 1
        finally:
            await server.close()

    asyncio.run(main())


@pytest.mark.slow
def test_a_page_drops_the_map_of_a_daemon_that_restarted(chromium: str, vk: Any, tmp_path: Path) -> None:
    """Before: the page reconnected to the new daemon and went on showing the old one's map as live."""

    async def main() -> None:
        first = ViewServer("127.0.0.1", 0)
        await first.start()
        post_a_map(first)
        port = first.port
        second: ViewServer | None = None
        try:
            async with vk.Browser(chromium, tmp_path) as b:
                await b.goto(first.url)
                await b.wait(LIVE_AND_DRAWN, 60, "the first daemon's map drawn")
                assert await b.eval("mapdView.instance") == first.instance
                await first.close()
                second = ViewServer("127.0.0.1", port)  # restarted, with no map yet
                await second.start()
                await b.wait(
                    f"mapdView.instance === '{second.instance}' && {CONN} === 'live'",
                    60,
                    "the page on the new daemon",
                )
                state = await b.eval(
                    "[mapdView.geometry, mapdView.seq, Object.keys(mapdView.robots).length, "
                    "mapdView.status, mapdView.restarts, document.getElementById('mapinfo').textContent]"
                )
                assert state == [None, 0, 0, None, 1, ""]
                post_a_map(second)  # and the new daemon's map, once it has one, is drawn
                await b.wait(LIVE_AND_DRAWN, 60, "the new daemon's map drawn")
        finally:
            await first.close()
            if second is not None:
                await second.close()

    asyncio.run(main())
