"""Output plugins: map_server files, and the global map on zenoh (a real session subscribes and queries)."""

from __future__ import annotations

import asyncio
import errno
import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from mapd import plugins
from mapd.codec import decode
from mapd.demo.ports import free_endpoint, free_port
from mapd.envelope import unpack
from mapd.errors import MapFileError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map
from mapd.grid.save import save_map
from mapd.identity import Identity, Roster
from mapd.outputs.base import GlobalUpdate, OutputContext
from mapd.outputs.files import FilesOptions, FilesOutput
from mapd.outputs.zenoh import ZenohOutput, ZenohOutputOptions
from transports.zenoh.keys import global_key


def update(room_grid: OccupancyGrid, version: int = 3) -> GlobalUpdate:
    return GlobalUpdate(
        grid=room_grid.replace(version=version, robot="base"),
        frames={"robot0": Pose2D(0.0, 0.0, 0.0), "robot1": Pose2D(4.0, -1.0, 0.5)},
        stamp=1234.5,
        versions={"robot0": 7, "robot1": 9},
    )


def test_outputs_are_plugins() -> None:
    assert plugins.load("output", "files") is FilesOutput and plugins.load("output", "zenoh") is ZenohOutput


def test_files_output_writes_map_server_files_and_transforms(
    tmp_path: Path, room_grid: OccupancyGrid
) -> None:
    out = FilesOutput(FilesOptions(dir=tmp_path / "maps", name="fleet"), OutputContext("base", "f"))
    (tmp_path / "maps").mkdir()
    stale = tmp_path / "maps" / ".fleet.pgm.tmp999999.1"  # a write killed mid-way, by another pid
    stale.write_bytes(b"half a map")
    (tmp_path / "maps" / "notes.tmp").write_text("not ours")
    asyncio.run(out.start())
    assert not stale.exists() and (tmp_path / "maps" / "notes.tmp").exists()  # only our temps go
    out.publish(update(room_grid))
    back = load_map(tmp_path / "maps" / "fleet.yaml")
    assert back.same_map(room_grid)
    doc = json.loads((tmp_path / "maps" / "transforms.json").read_text())
    assert doc["frame_id"] == "map" and doc["robots"]["robot1"] == {
        "child_frame_id": "robot1/map", "x": 4.0, "y": -1.0, "yaw": 0.5, "version": 9
    }  # fmt: skip
    assert out.stats()["written"] == 1


def test_a_files_reader_between_yaml_and_image_gets_one_map(tmp_path: Path, room_grid: OccupancyGrid) -> None:
    """A reader (map_server, a web viewer) reads the YAML, then the image it names. With one fixed
    image name, an update between the two reads gave it the new image at the old origin."""
    d = tmp_path / "maps"
    d.mkdir()
    (d / "fleet.pgm").write_bytes(b"P5 the image of an earlier mapd")
    out = FilesOutput(FilesOptions(dir=d, name="fleet"), OutputContext("base", "f"))
    asyncio.run(out.start())
    first = room_grid.replace(version=1, robot="base")
    out.publish(GlobalUpdate(grid=first, frames={}, stamp=1.0, versions={}))
    held = (d / "fleet.yaml").read_text()  # the reader has read the YAML...
    grown = OccupancyGrid(np.zeros((room_grid.height + 64, room_grid.width), np.int8), room_grid.resolution,
                          Pose2D(-3.2, -5.0, 0.0), robot="base", version=2)  # fmt: skip
    out.publish(GlobalUpdate(grid=grown, frames={}, stamp=2.0, versions={}))
    (d / "held.yaml").write_text(held)  # ...and now reads the image that YAML names
    assert load_map(d / "held.yaml").same_map(first)
    assert load_map(d / "fleet.yaml").same_map(grown)
    assert not (d / "fleet.pgm").exists()  # the fixed name of before: stale, removed
    for v in (3, 4):
        out.publish(GlobalUpdate(grid=first.replace(version=v), frames={}, stamp=float(v), versions={}))
    assert sorted(p.name for p in d.glob("fleet-*.pgm")) == ["fleet-3.pgm", "fleet-4.pgm"]  # no pile-up
    # After a restart the numbers go on: the YAML a reader holds may name the last image.
    again = FilesOutput(FilesOptions(dir=d, name="fleet"), OutputContext("base", "f"))
    asyncio.run(again.start())
    again.publish(GlobalUpdate(grid=grown.replace(version=5), frames={}, stamp=5.0, versions={}))
    assert yaml.safe_load((d / "fleet.yaml").read_text())["image"] == "fleet-5.pgm"
    assert sorted(p.name for p in d.glob("fleet-*.pgm")) == ["fleet-4.pgm", "fleet-5.pgm"]


def test_a_files_output_image_takes_the_permissions_the_operator_gave_the_map(
    tmp_path: Path, room_grid: OccupancyGrid
) -> None:
    """Each map's image has a new name, so keeping the mode of the file replaced kept nothing: under
    the unit's UMask=0007 every new image was 0660, unreadable to a map_server of another user,
    while the YAML naming it stayed as the operator made it."""
    d = tmp_path / "maps"
    out = FilesOutput(FilesOptions(dir=d, name="fleet"), OutputContext("base", "f"))
    asyncio.run(out.start())
    before = os.umask(0o007)
    try:
        out.publish(update(room_grid, 3))
        for f in d.iterdir():
            f.chmod(0o644)  # the operator: readable by the map_server's user
        out.publish(update(room_grid, 4))
    finally:
        os.umask(before)
    image = d / yaml.safe_load((d / "fleet.yaml").read_text())["image"]
    assert image.name == "fleet-2.pgm"
    assert {f.name: f.stat().st_mode & 0o777 for f in (d / "fleet.yaml", image)} == {
        "fleet.yaml": 0o644, "fleet-2.pgm": 0o644,
    }  # fmt: skip


def test_files_output_that_cannot_write_says_so_once_and_carries_on(
    tmp_path: Path, room_grid: OccupancyGrid, caplog: pytest.LogCaptureFixture
) -> None:
    """It raised on every update (about one a second), each logged by the daemon, naming the hidden
    temp file; the map was written while transforms.json stayed stale."""
    out = FilesOutput(FilesOptions(dir=tmp_path, name="fleet"), OutputContext("base", "f"))
    asyncio.run(out.start())
    (tmp_path / "transforms.json").mkdir()  # (as a full or read-only disk would, every time)
    with caplog.at_level(logging.INFO, logger="mapd.outputs.files"):
        for version in (3, 4, 5):
            out.publish(update(room_grid, version))  # never raises
        assert out.stats()["failures"] == 3 and out.stats()["written"] == 0
        errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1 and f"{tmp_path / 'transforms.json'}: Is a directory" in errors[0], errors
        assert ".tmp" not in errors[0]
        (tmp_path / "transforms.json").rmdir()
        out.publish(update(room_grid, 6))
    assert out.stats()["written"] == 1 and "writing to" in caplog.records[-1].getMessage()
    assert json.loads((tmp_path / "transforms.json").read_text())["robots"]["robot1"]["version"] == 9


def test_a_map_whose_yaml_cannot_be_written_keeps_its_old_image(
    tmp_path: Path, room_grid: OccupancyGrid, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The image was renamed into place before the YAML was written: a full disk (or an immutable
    YAML) left the new image beside the old YAML, a map with another map's size and origin."""
    import mapd.files

    old = OccupancyGrid(np.zeros((20, 30), np.int8), 0.1, (-1.0, -2.0, 0.0))
    save_map(old, tmp_path / "m.yaml")
    real_fsync, calls = os.fsync, []

    def fsync_fails_on_the_second_file(fd: int) -> None:
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(mapd.files.os, "fsync", fsync_fails_on_the_second_file)
    with pytest.raises(MapFileError, match="No space left"):
        save_map(room_grid, tmp_path / "m.yaml")
    real_replace = os.replace

    def yaml_is_immutable(src: Any, dst: Any) -> None:
        if Path(dst).name == "m.yaml" and ".old." not in str(src):
            raise PermissionError(errno.EPERM, "Operation not permitted")
        real_replace(src, dst)

    calls.clear()
    monkeypatch.setattr(mapd.files.os, "fsync", real_fsync)
    monkeypatch.setattr(mapd.files.os, "replace", yaml_is_immutable)
    with pytest.raises(MapFileError, match="not permitted"):
        save_map(room_grid, tmp_path / "m.yaml")
    monkeypatch.undo()
    assert load_map(tmp_path / "m.yaml").same_map(old)  # image and YAML both the old map's
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pgm", "m.yaml"]  # no temp file left


def test_zenoh_output_puts_a_signed_lossless_map_and_answers_late_joiners(
    room_grid: OccupancyGrid, zenoh_linked: Callable[..., None]
) -> None:
    zenoh = pytest.importorskip("zenoh")
    port = free_port()
    me = Identity.generate("base")
    out = ZenohOutput(
        ZenohOutputOptions(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False),
        OutputContext("base", "f", identity=me),
    )
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")

    async def main() -> None:
        await out.start()
        try:
            got: list[bytes] = []
            with zenoh.open(conf) as z:
                sub = z.declare_subscriber(
                    global_key("f", "base"), lambda s: got.append(s.payload.to_bytes())
                )
                zenoh_linked(z)  # the subscription reaches the output's session
                out.publish(update(room_grid, 3))
                end = time.monotonic() + 5
                while not got and time.monotonic() < end:
                    await asyncio.sleep(0.05)
                sub.undeclare()
                assert got, "no global map arrived"
                env = unpack(got[0], roster=Roster({"base": me.public_key}))  # signed by the base
                assert (env.robot, env.version, env.codec, env.frame_id) == ("base", 3, "lossless", "map")
                assert decode(env.payload, None).same_map(room_grid)  # exact
                out.publish(update(room_grid, 4))
                replies = [
                    r.ok.payload.to_bytes() for r in z.get(global_key("f", "base"), timeout=5.0) if r.ok
                ]
                assert [unpack(r).version for r in replies] == [4]  # a late joiner gets the newest
        finally:
            await out.close()
        assert out.stats()["published"] == 2 and out.stats()["queries"] == 1

    asyncio.run(main())


def test_a_zenoh_output_whose_router_is_not_up_waits_and_puts_the_newest_map_once_it_is(
    room_grid: OccupancyGrid, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A base station whose router came up after it stopped (and took its links down) at start.
    zenoh = pytest.importorskip("zenoh")
    from mapd.commands.status_text import render_status
    from mapd.daemon.headline import status_line
    from mapd.ros2 import zenoh_config

    monkeypatch.setattr(zenoh_config, "RETRY_FIRST_S", 0.2)
    ep = free_endpoint()
    out = ZenohOutput(
        ZenohOutputOptions(mode="client", connect=[ep], multicast_scouting=False), OutputContext("base", "f")
    )

    def session(mode: str, key: str) -> Any:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5(key, json.dumps([ep]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        return zenoh.open(conf)

    async def main() -> None:
        await out.start()  # no router: returns, and tries again
        try:
            out.publish(update(room_grid, 5))  # kept for when it is open
            await asyncio.sleep(0.6)
            doc = {"outputs": {"zenoh": out.stats()}}
            assert out.stats()["session_open"] is False
            assert "output  zenoh: FAULTS zenoh session not open yet" in render_status(doc)
            assert status_line(doc).startswith("FAULTS output.zenoh zenoh session not open yet")
            router = await asyncio.to_thread(session, "router", "listen/endpoints")
            try:
                end = time.monotonic() + 20
                while not out.stats()["session_open"]:
                    assert time.monotonic() < end, "the output never opened its session"
                    await asyncio.sleep(0.1)
                with session("client", "connect/endpoints") as z:
                    replies = [
                        r.ok.payload.to_bytes() for r in z.get(global_key("f", "base"), timeout=5.0) if r.ok
                    ]
                assert [unpack(r).version for r in replies] == [5]  # the map published while waiting
            finally:
                router.close()
        finally:
            await out.close()

    asyncio.run(main())


def test_a_session_that_opens_after_close_is_closed_not_leaked(
    room_grid: OccupancyGrid, monkeypatch: pytest.MonkeyPatch
) -> None:
    # close() cancels the retry's wait, but not a try under way on its thread: a session that
    # opened after close() stayed open (and zenoh threads left at exit abort the process).
    import threading

    from mapd.errors import UnreachableError
    from mapd.ros2 import zenoh_config

    monkeypatch.setattr(zenoh_config, "RETRY_FIRST_S", 0.05)
    opening, release = threading.Event(), threading.Event()
    tries: list[int] = []

    class Session:
        closed = False

        def put(self, key: str, data: bytes) -> None:
            raise AssertionError("nothing is put after close")

        def close(self) -> None:
            self.closed = True

    late = Session()

    def fake_open(conf: Any) -> Any:
        tries.append(1)
        if len(tries) == 1:
            raise UnreachableError("output.zenoh: cannot open a session: Unable to connect to any of [x]")
        opening.set()
        release.wait(10)
        return late

    out = ZenohOutput(ZenohOutputOptions(mode="client", connect=["tcp/127.0.0.1:9"]), OutputContext("b", "f"))
    monkeypatch.setattr(out, "_open", fake_open)
    monkeypatch.setattr(out, "_close", lambda session: session.close())

    async def main() -> None:
        await out.start()
        out.publish(update(room_grid, 2))
        await asyncio.to_thread(opening.wait, 10)  # the retry's second try is under way
        await out.close()
        release.set()  # ... and opens after the close
        for _ in range(100):
            if late.closed:
                break
            await asyncio.sleep(0.02)

    asyncio.run(main())
    assert late.closed and out.stats()["session_open"] is False
