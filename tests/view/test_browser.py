"""The live view in a real headless Chromium, served by a real daemon of a two-robot fleet.

The fleet's maps are files the test writes, so it knows which cell is free, occupied or unknown and
checks the screenshot's pixels there; then it changes a map file and checks the change is drawn
without a reload. A second test runs ``mapd demo --view`` (the simulated building) and saves its
screenshot (``MAPD_VIEW_SCREENSHOT=docs/img/view.png`` writes the README's picture).
"""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.grid import OCCUPIED, OccupancyGrid, Pose2D
from mapd.view.tiles import PALETTE

FREE_RGB, OCC_RGB, UNK_RGB = PALETTE[0], PALETTE[1], PALETTE[2]


def hex_rgb(colour: str) -> tuple[int, int, int]:
    return int(colour[1:3], 16), int(colour[3:5], 16), int(colour[5:7], 16)


def near(px: np.ndarray, rgb: tuple[int, int, int], tol: int = 24) -> bool:
    return bool(np.abs(px.astype(int) - np.array(rgb)).max() <= tol)


async def pixel_at(b: Any, shot: np.ndarray, x: float, y: float, dy: int = 0) -> np.ndarray:
    """The screenshot's pixel where the fleet-frame point (x, y) m is drawn (``dy`` CSS px lower)."""
    sx, sy = await b.eval(f"mapdView.toScreen({x}, {y})")
    return shot[round(sy) + dy, round(sx)]


DRAWN = (
    "mapdView.geometry && mapdView.drawnSeq === mapdView.seq && mapdView.drawnSeq > 0 && "
    "Object.values(mapdView.robots).filter(r => r.outline).length === 2 && mapdView.status !== null"
)


@pytest.mark.slow
def test_browser_draws_the_fleet_map_robots_and_a_live_update(
    chromium: str, map_fleet: Any, vk: Any, tmp_path: Path
) -> None:
    map_fleet.wait_merged()
    url = f"http://127.0.0.1:{map_fleet.view_port}/"

    async def main() -> None:
        async with vk.Browser(chromium, tmp_path) as b:
            await b.goto(url)
            await b.wait(DRAWN, 60, "the map drawn with both robots' outlines")
            await asyncio.sleep(0.5)  # one animation frame at least
            png, shot = await b.screenshot()
            (tmp_path / "first.png").write_bytes(png)
            loaded_at = await b.eval("mapdView.loadedAt")
            seq = await b.eval("mapdView.seq")

            # known cells, in the fleet frame (see conftest.BLOCKS)
            for x, y in ((2.0, 1.5), (7.5, 2.5), (14.0, 2.0)):
                assert near(await pixel_at(b, shot, x, y), FREE_RGB), ("free", x, y)
            for x, y in ((5.5, 4.5), (16.5, 4.5)):
                assert near(await pixel_at(b, shot, x, y), OCC_RGB), ("occupied", x, y)
            for x, y in ((2.0, 5.0), (10.0, 3.0)):  # the patch in robot0's map, the gap between maps
                assert near(await pixel_at(b, shot, x, y), UNK_RGB), ("unknown", x, y)

            # each robot's marker (no poses from a map file: at its map frame's origin), own colour
            robots = await b.eval("mapdView.robots")
            colours = {name: hex_rgb(r["colour"]) for name, r in robots.items()}
            assert len(set(colours.values())) == 2
            for name, (fx, fy, _) in vk.FRAMES.items():
                assert robots[name]["frame"][:2] == [fx, fy]
                assert near(await pixel_at(b, shot, fx, fy, dy=-5), colours[name], tol=40), name

            # the panel lists both robots and the link
            text = await b.eval("document.getElementById('panel').innerText")
            assert "robot0" in text and "robot1" in text and "zenoh" in text

            # a new occupied block in robot0's map file shows up without a reload
            assert near(await pixel_at(b, shot, 7.5, 1.5), FREE_RGB)
            blocks = [*vk.BLOCKS["robot0"], (7.0, 1.0, 8.0, 2.0, OCCUPIED)]
            map_fleet.write_map("robot0", vk.box_map("robot0", blocks))
            await b.wait(
                f"mapdView.drawnSeq > {seq} && mapdView.drawnSeq === mapdView.seq", 60, "the update drawn"
            )
            deadline = time.monotonic() + 30
            while True:
                await asyncio.sleep(0.5)
                png, shot = await b.screenshot()
                if near(await pixel_at(b, shot, 7.5, 1.5), OCC_RGB) or time.monotonic() > deadline:
                    break
            (tmp_path / "updated.png").write_bytes(png)
            assert near(await pixel_at(b, shot, 7.5, 1.5), OCC_RGB), "the new block is not drawn"
            assert near(await pixel_at(b, shot, 5.5, 4.5), OCC_RGB)  # the rest is still there
            assert await b.eval("mapdView.loadedAt") == loaded_at  # the same page: no reload

    asyncio.run(main())


async def _drag(b: Any, start: tuple[int, int], end: tuple[int, int]) -> None:
    """A real mouse drag on the page (the pointer events a user's hand makes)."""
    await b.send(
        "Input.dispatchMouseEvent", type="mousePressed", x=start[0], y=start[1], button="left", clickCount=1
    )
    for k in range(1, 6):
        x = start[0] + (end[0] - start[0]) * k // 5
        y = start[1] + (end[1] - start[1]) * k // 5
        await b.send("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y, button="left", buttons=1)
    await b.send(
        "Input.dispatchMouseEvent", type="mouseReleased", x=end[0], y=end[1], button="left", clickCount=1
    )


@pytest.mark.slow
def test_a_panned_view_stays_put_when_the_map_grows_toward_minus_y(
    chromium: str, map_fleet: Any, vk: Any, tmp_path: Path
) -> None:
    """Once the user has panned, a map growing downward (toward -y) must not move what is under the
    cursor: the page shifts its view by the growth, with the sign REP-103's y-up asks for."""
    map_fleet.wait_merged()
    url = f"http://127.0.0.1:{map_fleet.view_port}/"
    block = (5.5, 4.5)  # the middle of robot0's occupied block (conftest.BLOCKS), fleet frame

    async def main() -> None:
        async with vk.Browser(chromium, tmp_path) as b:
            await b.goto(url)
            await b.wait(DRAWN, 60, "the map drawn with both robots' outlines")
            await _drag(b, (400, 300), (460, 340))
            assert await b.eval("mapdView.view.moved") is True
            at = await b.eval(f"mapdView.toScreen({block[0]}, {block[1]})")
            oy = await b.eval("mapdView.geometry.origin[1]")
            seq = await b.eval("mapdView.seq")
            await asyncio.sleep(0.5)
            _, shot = await b.screenshot()
            assert near(shot[round(at[1]), round(at[0])], OCC_RGB)

            # robot0 explores 6 m further toward -y, beyond the global map's margin: 120 free rows
            # below its map (row 0 is the lowest y)
            room = vk.box_map("robot0", vk.BLOCKS["robot0"])
            grown = np.vstack([np.zeros((120, room.width), np.int8), room.data])
            map_fleet.write_map("robot0", OccupancyGrid(grown, room.resolution, Pose2D(-1.0, -7.0, 0.0)))
            await b.wait(
                f"mapdView.seq > {seq} && mapdView.geometry.origin[1] < {oy} - 1.5 && "
                "mapdView.drawnSeq === mapdView.seq",
                60,
                "the grown map drawn",
            )
            await asyncio.sleep(0.5)
            _, shot = await b.screenshot()
            after = await b.eval(f"mapdView.toScreen({block[0]}, {block[1]})")
            assert after == pytest.approx(at, abs=0.5)
            assert near(shot[round(at[1]), round(at[0])], OCC_RGB), "the block moved on the screen"

    asyncio.run(main())


def _demo_args(out: Path, port: int) -> SimpleNamespace:
    return SimpleNamespace(
        robots=2, transport="uwb" if shutil.which("socat") else "zenoh", codec="lossless", log=None, duration=60.0, seed=7, out=out,
        view=port, record=None, drop=0.0, flip=0.0, outage=[], router=False,
    )  # fmt: skip


@pytest.mark.slow
def test_browser_shows_the_demo_fleet(chromium: str, vk: Any, fk: Any, tmp_path: Path) -> None:
    from mapd.demo.fleet import Fleet

    port = vk.free_port()
    fleet = Fleet(_demo_args(tmp_path / "out", port))  # type: ignore[arg-type]
    fleet.prepare()
    fleet.start()
    try:

        def merged(snaps: dict[str, Any]) -> bool:
            s = snaps.get("robot0", {})
            return (s.get("fusion") or {}).get("maps") == 2 and s.get("source", {}).get(
                "version", 0
            ) & 0xFFFFFFFF >= 6

        fk.wait_for(merged, 90, fleet)

        async def main() -> tuple[bytes, np.ndarray, dict[str, Any]]:
            async with vk.Browser(chromium, tmp_path) as b:
                await b.goto(f"http://127.0.0.1:{port}/")
                await b.wait(DRAWN, 60, "the demo's map drawn")
                await b.wait(
                    "mapdView.status.links.length && mapdView.status.links[0].tx_bps !== null",
                    20,
                    "link rates",
                )
                await asyncio.sleep(1.0)
                png, shot = await b.screenshot()
                return png, shot, await b.eval("mapdView.robots")

        png, shot, robots = asyncio.run(main())
    finally:
        fleet.stop()
    (tmp_path / "demo.png").write_bytes(png)
    # the building: mostly free and unknown cells, walls, and both robots' colours somewhere
    flat = shot[:, :900].reshape(-1, 3).astype(int)
    share = {
        name: float((np.abs(flat - np.array(rgb)).max(axis=1) <= 6).mean())
        for name, rgb in (("free", FREE_RGB), ("occupied", OCC_RGB), ("unknown", UNK_RGB))
    }
    assert share["free"] > 0.2 and share["occupied"] > 0.005 and share["unknown"] > 0.02, share
    for name, r in robots.items():
        if r["pose"] is not None:  # the robot's marker is where its trail ends
            assert r["trail"] and np.hypot(*np.subtract(r["trail"][-1], r["pose"][:2])) < 0.1, name
        rgb = np.array(hex_rgb(r["colour"]))
        assert (np.abs(shot.reshape(-1, 3).astype(int) - rgb).max(axis=1) <= 10).sum() > 50, name
    assert len(png) < 200_000
    target = os.environ.get("MAPD_VIEW_SCREENSHOT")
    if target:
        shutil.copyfile(tmp_path / "demo.png", target)


def test_mapd_demo_accepts_view(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "mapd", "demo", "--help"], capture_output=True, text=True, timeout=60
    )
    assert "--view PORT" in proc.stdout
