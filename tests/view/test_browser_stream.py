"""The page's stream in a real headless Chromium against the real view server: refused, then let in;
its token rotated; its daemon restarted.

An answer other than 200 on ``/events`` (a 503 at the viewer cap, a 401 after the token changed)
makes the browser close an EventSource for good: the page must try again by itself, and say so.
A page whose daemon restarted must not show the old daemon's map as live. A page whose map grew
draws it from the new tiles alone, cell for cell the same as the whole map.
"""

from __future__ import annotations

import asyncio
import base64
import io
import re
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from PIL import Image

from mapd.grid import OccupancyGrid, Pose2D
from mapd.outputs.base import GlobalUpdate
from mapd.view.model import MapModel
from mapd.view.server import ViewServer
from mapd.view.tiles import PALETTE, class_image

TOKEN = "s3cret-token-0123456789"
CONN = "document.getElementById('conn').textContent"
#: The page says it is disconnected and when it tries again (the text, truthy, once it does).
DISCONNECTED = f"(t => t.startsWith('disconnected, retrying in ') && t)({CONN})"
#: The same, when the daemon refused the page's token (its token was rotated).
TOKEN_REFUSED = f"(t => t.startsWith('token refused (rotated?), retrying in ') && t)({CONN})"
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
    on the stream for good), then the page retries on its own. It says why (before: only
    "disconnected", as for a daemon that was down, which sent people looking at the wrong thing)."""
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
                said = await b.wait(TOKEN_REFUSED, 60, "the page saying its token was refused")
                assert re.fullmatch(r"token refused \(rotated\?\), retrying in \d+ s", said), said
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


async def _cells(b: Any) -> np.ndarray:
    """The page's canvas of cells (one pixel per cell), read back through the DevTools protocol."""
    url = await b.eval("mapdView.cells().toDataURL('image/png')")
    with Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))) as im:
        return np.asarray(im.convert("RGB")).copy()


def _rgb(grid: OccupancyGrid) -> np.ndarray:
    lut = np.array([PALETTE[i] for i in range(3)], np.uint8)
    return lut[class_image(grid)]


@pytest.mark.slow
def test_a_page_draws_a_grown_map_from_its_new_tiles_exactly_as_the_whole_map(
    chromium: str, vk: Any, tmp_path: Path
) -> None:
    """Before: every growth re-sent the whole map. Now only new and changed tiles come, and the page
    copies its old cells into a bigger canvas: its pixels must still be the map's, cell for cell,
    also when growths follow each other before the page has decoded the tiles of the one before."""
    rng = np.random.default_rng(5)
    d = np.full((200, 300), -1, np.int8)  # lattice columns -64..235, rows -136..63: clipped all round
    d[10:-10, 10:-10] = 0
    d[rng.random(d.shape) < 0.02] = 100
    origin = [-3.2, -3.2]

    def grow(side: str) -> OccupancyGrid:
        nonlocal d
        h, w = d.shape
        k = 64
        out = np.full((h + k * (side in "-y+y"), w + k * (side in "-x+x")), -1, np.int8)
        r, c = (k if side == "-y" else 0), (k if side == "-x" else 0)
        out[r : r + h, c : c + w] = d
        out[rng.random(out.shape) < 0.001] = 100  # and some cells change, old ones and new ones
        d = out
        origin[0] -= k * 0.05 if side == "-x" else 0.0
        origin[1] -= k * 0.05 if side == "-y" else 0.0
        return OccupancyGrid(d, 0.05, Pose2D(origin[0], origin[1], 0.0))

    async def main() -> None:
        server = ViewServer("127.0.0.1", 0)
        await server.start()
        model = MapModel()
        g = OccupancyGrid(d, 0.05, Pose2D(origin[0], origin[1], 0.0))
        server.post(model.global_map(GlobalUpdate(g, {}, 1.0)), model.robots(), full_map=model.full_map())
        try:
            async with vk.Browser(chromium, tmp_path) as b:
                await b.goto(server.url)
                await b.wait(LIVE_AND_DRAWN, 60, "the map drawn")
                assert np.array_equal(await _cells(b), _rgb(g))
                for i, sides in enumerate((["-x"], ["+y"], ["+x", "-y"], ["-x", "+y", "+x"])):
                    for side in sides:  # several at once: tiles of one still decoding at the next
                        g = grow(side)
                        delta = model.global_map(GlobalUpdate(g, {}, 2.0 + i))
                        assert b'"full":false' in delta.frame
                        server.post(delta, full_map=model.full_map())
                    await b.wait(
                        f"mapdView.drawnSeq === {model.seq} && mapdView.seq === {model.seq}",
                        60,
                        f"growth {sides} drawn",
                    )
                    got = await _cells(b)
                    assert got.shape == (g.height, g.width, 3), sides
                    wrong = np.argwhere((got != _rgb(g)).any(axis=2))
                    assert len(wrong) == 0, (sides, len(wrong), wrong[:5].tolist())
                assert await b.eval("mapdView.restarts") == 0
        finally:
            await server.close()

    asyncio.run(main())
