"""What the page says when its daemon stops answering, and of a robot last heard long ago, in a real
headless Chromium against the real view server.

Found by review: a daemon stopped (SIGSTOP, a hung loop) or a network that dropped without a word
left the stream open and silent, and the page said "live" for ever over a frozen map. And a robot
whose link had gone quiet was drawn and listed as if it were where it was last heard.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.outputs.base import GlobalUpdate
from mapd.view.model import MapModel
from mapd.view.server import ViewServer

CONN = "document.getElementById('conn').textContent"

#: A view server of its own process (so that it can be stopped as a daemon is), printing its URL.
SERVER = textwrap.dedent(
    """
    import asyncio, numpy as np
    from mapd.grid import OccupancyGrid, Pose2D
    from mapd.outputs.base import GlobalUpdate
    from mapd.view.model import MapModel
    from mapd.view.server import ViewServer

    async def main():
        server = ViewServer("127.0.0.1", 0, snapshot=lambda: {"robot": "base", "fleet": "f"})
        await server.start()
        model = MapModel()
        grid = OccupancyGrid(np.zeros((50, 60), np.int8), 0.05, Pose2D(-1.0, -1.0, 0.0))
        server.post(model.global_map(GlobalUpdate(grid, {}, 1.0)), model.robots(), full_map=model.full_map())
        print(server.url, flush=True)
        await asyncio.Event().wait()

    asyncio.run(main())
    """
)


@pytest.mark.slow
def test_a_page_whose_daemon_stops_answering_says_so_and_is_live_again_when_it_does(
    chromium: str, vk: Any, tmp_path: Path
) -> None:
    proc = subprocess.Popen([sys.executable, "-c", SERVER], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:"), url

        async def main() -> None:
            async with vk.Browser(chromium, tmp_path) as b:
                await b.goto(url)
                await b.wait(f"{CONN} === 'live' && mapdView.status !== null", 60, "the page live")
                os.kill(proc.pid, signal.SIGSTOP)  # the stream stays open: nothing comes
                said = await b.wait(
                    f"(t => t.startsWith('no update for ') && t)({CONN})", 30, "the page saying it is stale"
                )
                assert said.endswith("s (daemon stopped, or the network?)"), said
                assert await b.eval("document.getElementById('conn').className") == "bad"
                os.kill(proc.pid, signal.SIGCONT)
                await b.wait(f"{CONN} === 'live'", 30, "the page live again")

        asyncio.run(main())
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        proc.kill()
        proc.wait(10)


@pytest.mark.slow
def test_a_robot_last_heard_long_ago_is_faded_with_its_age(chromium: str, vk: Any, tmp_path: Path) -> None:
    heard = {"robot1": True}

    def snapshot() -> dict[str, Any]:
        age = 3.0 if heard["robot1"] else 45.0
        return {
            "robot": "robot0",
            "fleet": "f",
            "peers": {"robot1": {"present": heard["robot1"], "age_s": age, "link": "uwb"}},
            "fusion": {"placements": {"robot1": {"accepted": True}}},
            "poses": {"robots": {"robot1": {"age_s": age}, "robot0": {"age_s": 0.5}}},
        }

    async def main() -> None:
        server = ViewServer("127.0.0.1", 0, snapshot=snapshot, status_every_s=0.2)
        await server.start()
        model = MapModel()
        grid = OccupancyGrid(np.zeros((50, 60), np.int8), 0.05, Pose2D(-1.0, -1.0, 0.0))
        frames = {"robot0": Pose2D(), "robot1": Pose2D(1.0, 0.5, 0.0)}
        delta = model.global_map(GlobalUpdate(grid, frames, 1.0))
        robots = model.poses({"robot1": StampedPose(Pose2D(0.2, 0.1, 0.0), 1.0)}, frames)
        server.post(delta, robots, full_map=model.full_map())
        try:
            async with vk.Browser(chromium, tmp_path) as b:
                await b.goto(server.url)
                await b.wait(
                    "mapdView.status !== null && mapdView.robots.robot1 && mapdView.robots.robot1.pose",
                    60,
                    "robot1 drawn",
                )
                assert await b.eval("mapdView.staleRobot('robot1')") is False
                heard["robot1"] = False  # its link silent: present false, its pose 45 s old
                await b.wait("mapdView.staleRobot('robot1')", 30, "robot1 marked stale")
                row = await b.eval(
                    "(() => { for (const tr of document.getElementById('robots').tBodies[0].rows) "
                    "if (tr.cells[1].textContent === 'robot1') return [tr.cells[2].textContent, tr.cells[2].className]; })()"
                )
                assert row == ["45 s", "warn"], row
                assert await b.eval("mapdView.staleRobot('robot0')") is False
                heard["robot1"] = True
                await b.wait("!mapdView.staleRobot('robot1')", 30, "robot1 live again")
        finally:
            await server.close()

    asyncio.run(main())


def test_the_status_message_gives_each_robots_pose_age() -> None:
    from mapd.view.model import StatusModel

    snap = {"robot": "robot0", "peers": {"robot1": {}}, "poses": {"robots": {"robot1": {"age_s": 12.5}}}}
    doc = json.loads(StatusModel().message(snap, 0.0).frame.decode().split("data: ", 1)[1])
    assert doc["robots"]["robot1"]["pose_age_s"] == 12.5 and doc["robots"]["robot0"]["pose_age_s"] is None
