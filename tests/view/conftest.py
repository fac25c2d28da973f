"""Helpers for the view's end-to-end tests: real ``mapd run`` processes and a real headless Chromium.

Chromium is driven over the DevTools protocol with aiohttp's websocket client (no extra package).
Its background-networking flags are needed on a closed network, or its own connections fail.
"""

from __future__ import annotations

import asyncio
import base64
import io
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import aiohttp
import numpy as np
import pytest
from PIL import Image

from mapd.daemon.status_socket import query
from mapd.demo.ports import free_port
from mapd.errors import DaemonError
from mapd.grid import OCCUPIED, UNKNOWN, OccupancyGrid, Pose2D
from mapd.grid.save import save_map
from mapd.identity import Identity

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--hide-scrollbars",
    "--mute-audio",
]


def chromium_path() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


class Browser:
    """One headless Chromium page, driven over the DevTools protocol (async)."""

    def __init__(self, exe: str, tmp: Path, width: int = 1280, height: int = 800) -> None:
        self.exe, self.tmp, self.width, self.height = exe, tmp, width, height
        self._ids = itertools.count(1)
        self.proc: subprocess.Popen[bytes] | None = None
        self.session: aiohttp.ClientSession | None = None
        self.ws: aiohttp.ClientWebSocketResponse | None = None

    async def __aenter__(self) -> Browser:
        port = free_port()
        self.proc = subprocess.Popen(
            [
                self.exe,
                *CHROMIUM_FLAGS,
                f"--remote-debugging-port={port}",
                f"--user-data-dir={self.tmp / 'chromium-profile'}",
                f"--window-size={self.width},{self.height}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=open(self.tmp / "chromium.log", "wb"),  # noqa: SIM115 - lives as long as the process
        )
        self.session = aiohttp.ClientSession()
        deadline = time.monotonic() + 30
        pages: list[dict[str, Any]] = []
        while time.monotonic() < deadline:
            try:
                async with self.session.get(f"http://127.0.0.1:{port}/json/list") as r:
                    pages = [p for p in await r.json() if p.get("type") == "page"]
                if pages:
                    break
            except aiohttp.ClientError:
                pass
            await asyncio.sleep(0.2)
        if not pages:
            raise AssertionError("chromium did not start: " + (self.tmp / "chromium.log").read_text()[-1500:])
        self.ws = await self.session.ws_connect(pages[0]["webSocketDebuggerUrl"], max_msg_size=0)
        await self.send(
            "Emulation.setDeviceMetricsOverride",
            width=self.width,
            height=self.height,
            deviceScaleFactor=1,
            mobile=False,
        )
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self.ws is not None:
            await self.ws.close()
        if self.session is not None:
            await self.session.close()
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()

    async def send(self, method: str, **params: Any) -> dict[str, Any]:
        assert self.ws is not None
        msg_id = next(self._ids)
        await self.ws.send_str(json.dumps({"id": msg_id, "method": method, "params": params}))
        while True:
            reply = await asyncio.wait_for(self.ws.receive_json(), 60)
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise AssertionError(f"{method}: {reply['error']}")
                return dict(reply.get("result", {}))

    async def eval(self, expr: str) -> Any:
        r = await self.send("Runtime.evaluate", expression=expr, returnByValue=True)
        if "exceptionDetails" in r:
            raise AssertionError(f"{expr}: {r['exceptionDetails']}")
        return r["result"].get("value")

    async def goto(self, url: str) -> None:
        await self.send("Page.navigate", url=url)

    async def wait(self, expr: str, timeout: float, what: str) -> Any:
        deadline = time.monotonic() + timeout
        value = None
        while time.monotonic() < deadline:
            try:
                value = await self.eval(expr)
            except AssertionError:
                value = None  # the page is still loading
            if value:
                return value
            await asyncio.sleep(0.25)
        raise AssertionError(f"{what} not within {timeout} s (last: {value!r})")

    async def screenshot(self) -> tuple[bytes, np.ndarray]:
        r = await self.send("Page.captureScreenshot", format="png")
        png = base64.b64decode(r["data"])
        with Image.open(io.BytesIO(png)) as im:
            return png, np.asarray(im.convert("RGB")).copy()


# ------------------------------------------------------------------------ a fleet of real daemons

RES = 0.05
#: Where each robot's map frame lies in the fleet frame (configured: fusion places them as given).
FRAMES = {"robot0": (0.0, 0.0, 0.0), "robot1": (12.0, 0.0, 0.0)}


def box_map(robot: str, blocks: list[tuple[float, float, float, float, int]]) -> OccupancyGrid:
    """A 10 x 8 m walled room whose cell (0, 0) lies at (-1, -1) m in the robot's map frame.

    ``blocks``: ``(x0, y0, x1, y1, value)`` rectangles in the *fleet* frame, metres.
    """
    fx, fy, _ = FRAMES[robot]
    d = np.zeros((160, 200), np.int8)
    d[:3, :] = d[-3:, :] = d[:, :3] = d[:, -3:] = OCCUPIED
    for x0, y0, x1, y1, value in blocks:
        c0, c1 = round((x0 - fx + 1) / RES), round((x1 - fx + 1) / RES)
        r0, r1 = round((y0 - fy + 1) / RES), round((y1 - fy + 1) / RES)
        d[r0:r1, c0:c1] = value
    return OccupancyGrid(d, RES, Pose2D(-1.0, -1.0, 0.0))


#: What the maps hold at first (fleet frame): an occupied block each and an unknown patch in robot0's.
BLOCKS = {
    "robot0": [(1.0, 4.0, 3.0, 6.0, UNKNOWN), (5.0, 4.0, 6.0, 5.0, OCCUPIED)],
    "robot1": [(16.0, 4.0, 17.0, 5.0, OCCUPIED)],
}


class MapFleet:
    """Two ``mapd run`` processes over zenoh on loopback, each watching a map file the test writes."""

    def __init__(self, root: Path, view_port: int, view_extra: str = "") -> None:
        self.root = root
        self.view_port = view_port
        self.names = list(FRAMES)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        keys = root / "keys"
        keys.mkdir(parents=True)
        roster = []
        for name in self.names:
            Identity.generate(name).write(keys / f"{name}.key")
            from mapd.identity import read_identity

            roster.append(f'{name} = "{read_identity(keys / f"{name}.key", name).public_text}"')
        ports = {n: free_port() for n in self.names}
        for name in self.names:
            d = root / name
            (d / "state").mkdir(parents=True)
            self.write_map(name, box_map(name, BLOCKS[name]))
            connect = ", ".join(f'"tcp/127.0.0.1:{p}"' for n, p in ports.items() if n != name)
            poses = "\n".join(f"{n} = [{x}, {y}, {yaw}]" for n, (x, y, yaw) in FRAMES.items())
            view = f'[view]\nlisten = "127.0.0.1:{view_port}"\n{view_extra}\n' if name == "robot0" else ""
            (d / "config.toml").write_text(
                f'[robot]\nname = "{name}"\nfleet = "viewtest"\nkey_file = "{keys / f"{name}.key"}"\n'
                f"[fleet]\n[fleet.roster]\n" + "\n".join(roster) + "\n"
                f'[state]\ndir = "{d / "state"}"\nruntime_dir = "{d / "run"}"\n'
                f'[source]\nuse = "mapfile"\n[source.mapfile]\npath = "{d / "map.yaml"}"\n'
                f"poll_s = 0.2\nsettle_s = 0.1\n"
                f'[codec]\nuse = "lossless"\n'
                f'[transports]\nuse = ["zenoh"]\n[transports.zenoh]\nmode = "peer"\n'
                f'listen = ["tcp/127.0.0.1:{ports[name]}"]\nconnect = [{connect}]\nmulticast_scouting = false\n'
                f"[fusion]\ndebounce_s = 0.2\n[fusion.poses]\n{poses}\n{view}"
            )

    def write_map(self, name: str, grid: OccupancyGrid) -> None:
        save_map(grid, self.root / name / "map.yaml")

    def start(self) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        for name in self.names:
            d = self.root / name
            self.procs[name] = subprocess.Popen(
                [sys.executable, "-m", "mapd", "run", "--config", str(d / "config.toml")],
                stdout=open(d / "daemon.log", "wb"),  # noqa: SIM115 - lives as long as the process
                stderr=subprocess.STDOUT,
                env=env,
            )

    def status(self, name: str) -> dict[str, Any]:
        try:
            return query(self.root / name / "run" / "mapd.sock", timeout=2.0)
        except DaemonError:
            return {}

    def check_alive(self) -> None:
        for name, p in self.procs.items():
            if p.poll() is not None:
                log = (self.root / name / "daemon.log").read_text(errors="replace")[-2000:]
                raise AssertionError(f"{name} exited with {p.returncode}: {log}")

    def wait_merged(self, timeout: float = 60.0) -> dict[str, Any]:
        """Until robot0's global map holds both robots' maps."""
        deadline = time.monotonic() + timeout
        snap: dict[str, Any] = {}
        while time.monotonic() < deadline:
            self.check_alive()
            snap = self.status("robot0")
            if (snap.get("fusion") or {}).get("maps") == 2:
                return snap
            time.sleep(0.3)
        raise AssertionError(f"robot0 did not merge both maps: {json.dumps(snap)[:2000]}")

    def stop(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in self.procs.values():
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.fixture
def chromium() -> str:
    exe = chromium_path()
    if exe is None:
        pytest.skip("chromium is not installed (make test installs it: apt-get install -y chromium)")
    return exe


@pytest.fixture
def map_fleet(tmp_path: Path) -> Iterator[MapFleet]:
    fleet = MapFleet(tmp_path / "fleet", free_port())
    fleet.start()
    try:
        yield fleet
    finally:
        fleet.stop()


@pytest.fixture
def vk() -> SimpleNamespace:
    """The helpers above, for test modules (importlib mode keeps conftest out of reach of imports)."""
    return SimpleNamespace(
        Browser=Browser, box_map=box_map, BLOCKS=BLOCKS, FRAMES=FRAMES, free_port=free_port, MapFleet=MapFleet
    )
