"""Peers' maps (and the acks) a full disk kept from being saved are saved once there is room.

A peer map whose save failed is still used and acked, so its robot never sends that version again:
saved only with the robot's next map, it was lost to a restart of this robot whenever that robot
went out of reach or stopped first, although the disk had room again long before. The receiving
half holds the newest unsaved map of each robot and saves it again every ``WRITE_RETRY_S``, as the
own map, the global map and the files output are; the base and ``state.json`` (acks) likewise.

The disk is made full by making the state directory's writes fail (``save_committed`` for map
files, ``atomic_write_json`` for ``state.json``), then succeed again; the receiving half
(:class:`~mapd.daemon.inbound.Inbound`) is driven with the events a transport would put in.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import re
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import mapd.daemon.peer_saves as peer_saves_mod
import mapd.daemon.state as state_mod
from mapd.codec.api import encode
from mapd.daemon.server import Daemon
from mapd.daemon.state import StateStore
from mapd.daemon.state_records import SavedPeer
from mapd.daemon.status_socket import query
from mapd.daemon.versions import incarnation_at, make
from mapd.demo.ports import free_ports
from mapd.envelope import Envelope
from mapd.errors import StateError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import read_identity
from transports.base import Delivered, Received

#: Seconds between tries in these tests (the daemon's is WRITE_RETRY_S, 5 s).
RETRY_S = 0.05


class FullDisk:
    """The state directory's writes of peer maps (``peers``) and of ``state.json`` (``state``)
    fail while set, as they do on a full disk; whatever else is written goes through."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.peers = True
        self.state = False
        #: map files written while there was room: path -> times
        self.written: dict[str, int] = {}
        real_committed, real_json = state_mod.save_committed, state_mod.atomic_write_json

        def committed(grid: OccupancyGrid, path: Path, *rest: Any, **kw: Any) -> str:
            if self.peers and "peers" in path.parts:
                raise StateError(f"{path}: cannot write map: No space left on device")
            self.written[str(path)] = self.written.get(str(path), 0) + 1
            return real_committed(grid, path, *rest, **kw)

        def state_json(path: Path, obj: Any) -> None:
            if self.state:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real_json(path, obj)

        monkeypatch.setattr(state_mod, "save_committed", committed)
        monkeypatch.setattr(state_mod, "atomic_write_json", state_json)


def _daemon(tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch) -> tuple[Daemon, Any]:
    """robot0's daemon, its state directory open, a link that keeps its acks, and its receiving
    half trying again every RETRY_S."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    d.store.open()
    link = dk.AckingLink()
    d.transports.append(link)
    d.inbound.look_every_s = RETRY_S
    monkeypatch.setattr(peer_saves_mod, "WRITE_RETRY_S", RETRY_S)
    return d, link


def _map(tmp_path: Path, robot: str, n: int) -> Received:
    """Version ``n`` of ``robot``'s map (a keyframe, signed with its key under ``tmp_path``, with
    the pose of its frame), as the virtual link hands it in."""
    ident = read_identity(tmp_path / "keys" / f"{robot}.key", robot)
    data = np.zeros((20, 30), np.int8)
    data[:, : 5 * n] = 100
    grid = OccupancyGrid(data, 0.05)
    env = Envelope(
        fleet="default", robot=robot, version=make(incarnation_at(time.time() - 60), n),
        base_version=0, codec="raw", width=30, height=20, resolution=0.05,
        origin=Pose2D(0, 0, 0), payload=encode(grid, "raw"), frame_pose=Pose2D(1.0 + n, 2.0, 0.5),
    ).signed(ident)  # fmt: skip
    return Received("virtual", robot, env.pack())


def _saved(root: Path, robot: str) -> SavedPeer | None:
    """``robot``'s map as a restart of the daemon reads it from ``root`` (None: not there)."""
    store = StateStore(root)
    store.open()
    return store.saved_peer(robot)


def _said(caplog: pytest.LogCaptureFixture, line: str) -> bool:
    return any(r.getMessage() == line for r in caplog.records)


async def _stop(task: asyncio.Task[None]) -> None:
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


def test_a_peer_map_not_saved_for_a_full_disk_is_saved_once_there_is_room_without_another_map(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """robot1 sends v4 once (it got our ack) and then nothing: once the disk has room, v4 is saved
    with its frame pose and key, and a restart of robot0 restores it."""
    caplog.set_level(logging.INFO, logger="mapd.daemon")
    d, link = _daemon(tmp_path, dk, monkeypatch)
    disk = FullDisk(monkeypatch)
    ev = _map(tmp_path, "robot1", 4)
    v4 = make(incarnation_at(time.time() - 60), 4)

    async def main() -> None:
        await d.inbound.handle(ev)
        assert link.acks == [("robot1", v4)]  # used and acked though unsaved
        assert d.receiver.maps["robot1"].version == v4
        task = asyncio.create_task(d.inbound.run())
        try:
            await asyncio.sleep(5 * RETRY_S)  # tries that fail: said once, the map kept
            assert _saved(d.cfg.state.dir, "robot1") is None
            disk.peers = False  # room again; robot1 sends nothing more
            # (the line, not the files: it comes once the save's worker is done, after them)
            await dk.wait_for(lambda: _said(caplog, "state saved again"), 10, what="robot1's v4 saved")
        finally:
            await _stop(task)

    asyncio.run(main())
    saved = _saved(d.cfg.state.dir, "robot1")
    assert saved is not None and saved.grid.version == v4 and saved.grid.same_map(d.receiver.maps["robot1"])
    assert saved.frame_pose == Pose2D(5.0, 2.0, 0.5)
    assert saved.key is not None and saved.key == d.inbound.key_of("robot1")
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]
    failures = [m for m in said if "No space left on device" in m]
    assert len(failures) == 1 and f"again every {peer_saves_mod.WRITE_RETRY_S:g} s" in failures[0], said
    assert said.count("state saved again") == 1, said
    assert "Traceback" not in caplog.text


def test_the_newest_unsaved_map_of_each_robot_is_saved_and_a_revoked_ones_never(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """robot1's v4 then v5 unsaved: v5 is saved, never v4 after it. robot2's unsaved map, its
    robot revoked by a reload meanwhile, is dropped, not written back once there is room."""
    d, _ = _daemon(tmp_path, dk, monkeypatch)
    disk = FullDisk(monkeypatch)
    config = d.cfg.state.dir.parent / "config.toml"
    v5 = make(incarnation_at(time.time() - 60), 5)

    async def main() -> None:
        for ev in (_map(tmp_path, "robot2", 3), _map(tmp_path, "robot1", 4), _map(tmp_path, "robot1", 5)):
            await d.inbound.handle(ev)
        assert set(d.receiver.maps) == {"robot1", "robot2"}
        text = config.read_text()
        config.write_text(re.sub(r'^robot2 = "[^"]*"\n', "", text, flags=re.M))
        assert await d.reload()
        assert "robot2" not in d.receiver.maps
        task = asyncio.create_task(d.inbound.run())
        try:
            disk.peers = False
            await dk.wait_for(
                lambda: _saved(d.cfg.state.dir, "robot1") is not None, 10, what="robot1's map saved"
            )
            await dk.wait_for(lambda: d.store.health()["writing"], 10, what="status writing again")
            await asyncio.sleep(5 * RETRY_S)  # (further tries, had anything been left to try)
        finally:
            await _stop(task)

    asyncio.run(main())
    saved = _saved(d.cfg.state.dir, "robot1")
    assert saved is not None and saved.grid.version == v5
    robot1 = [p for p in disk.written if "robot1" in Path(p).parts]
    assert len(robot1) == 1 and disk.written[robot1[0]] == 1, disk.written  # v5, once: never v4
    assert not any("robot2" in Path(p).parts for p in disk.written), disk.written  # not even for a while
    assert not (d.cfg.state.dir / "peers" / "robot2").exists()
    assert _saved(d.cfg.state.dir, "robot2") is None and "robot2" not in d.store.data.peers


def test_status_shows_the_state_not_writing_while_a_peer_map_is_held_unsaved(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another write going through (the own map: smaller, or a folder of its own) does not end the
    outage ``mapd status`` shows while a peer's map is held unsaved; saving that map does."""
    d, _ = _daemon(tmp_path, dk, monkeypatch)
    disk = FullDisk(monkeypatch)

    async def main() -> None:
        await d.inbound.handle(_map(tmp_path, "robot1", 4))
        health = d.store.health()
        assert health["writing"] is False and "No space left on device" in health["error"]
        own = dk.growing_map(1).replace(version=make(incarnation_at(time.time()), 1))
        await asyncio.to_thread(d.store.save_own, own)
        health = d.store.health()
        assert health["writing"] is False and "peers" in health["error"], health
        assert isinstance(health["failing_s"], float)
        task = asyncio.create_task(d.inbound.run())
        try:
            await asyncio.sleep(5 * RETRY_S)
            assert d.store.health()["writing"] is False
            disk.peers = False
            await dk.wait_for(lambda: d.store.health()["writing"], 10, what="status writing again")
        finally:
            await _stop(task)
        assert _saved(d.cfg.state.dir, "robot1") is not None
        assert d.store.health()["error"] is None and d.store.health()["failing_s"] is None

    asyncio.run(main())


def test_acks_not_saved_for_a_full_disk_are_saved_once_there_is_room_without_another_ack(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """robot1 acks our v3 while ``state.json`` cannot be written, and nothing comes after (a fleet
    at rest): the ack is in ``state.json`` once there is room, not only with the next map or ack."""
    caplog.set_level(logging.INFO, logger="mapd.daemon")
    d, _ = _daemon(tmp_path, dk, monkeypatch)
    disk = FullDisk(monkeypatch)
    disk.peers, disk.state = False, True
    v3 = make(incarnation_at(time.time() - 60), 3)

    def acked_on_disk() -> dict[str, int]:
        store = StateStore(d.cfg.state.dir)
        return store.open().acked

    async def main() -> None:
        await d.inbound.handle(Delivered("virtual", "robot1", "robot0", v3))
        assert d.store.acked() == {"robot1": v3} and acked_on_disk() == {}
        assert d.store.health()["writing"] is False
        task = asyncio.create_task(d.inbound.run())
        try:
            await asyncio.sleep(5 * RETRY_S)
            assert acked_on_disk() == {}
            disk.state = False
            await dk.wait_for(lambda: _said(caplog, "state saved again"), 10, what="the ack saved")
            assert acked_on_disk() == {"robot1": v3} and d.store.health()["writing"]
        finally:
            await _stop(task)

    asyncio.run(main())
    said = [r.getMessage() for r in caplog.records]
    failures = [m for m in said if "No space left on device" in m]
    assert len(failures) == 1 and f"again every {peer_saves_mod.WRITE_RETRY_S:g} s" in failures[0], said
    assert said.count("state saved again") == 1, said


def test_a_map_revoked_while_it_is_saved_again_is_removed_again(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The revocation (a reload, on the loop) comes while the try that finally saves robot1's map
    runs on its worker: the revocation removed the files first, the save then put them back."""
    import threading

    d, _ = _daemon(tmp_path, dk, monkeypatch)
    disk = FullDisk(monkeypatch)
    config = d.cfg.state.dir.parent / "config.toml"
    inside, go_on, done = threading.Event(), threading.Event(), threading.Event()
    tries = []
    real = d.store.save_peer

    def save_peer(*args: Any) -> None:
        tries.append(args[0].version)
        if not disk.peers:  # the try that goes through: held up until the revocation is done
            inside.set()
            go_on.wait(20)
        try:
            real(*args)
        finally:
            done.set()

    monkeypatch.setattr(d.store, "save_peer", save_peer)

    async def main() -> None:
        await d.inbound.handle(_map(tmp_path, "robot1", 4))
        task = asyncio.create_task(d.inbound.run())
        try:
            disk.peers = False
            await dk.wait_for(inside.is_set, 10, what="the try that goes through")
            text = config.read_text()
            config.write_text(re.sub(r'^robot1 = "[^"]*"\n', "", text, flags=re.M))
            assert await d.reload()
            go_on.set()
            await dk.wait_for(lambda: d.store.health()["writing"], 10, what="status writing again")
            n = len(tries)
            await asyncio.sleep(5 * RETRY_S)  # (further tries, had the map been held still)
            assert len(tries) == n
        finally:
            go_on.set()
            await _stop(task)

    asyncio.run(main())
    assert not (d.cfg.state.dir / "peers" / "robot1").exists()
    assert _saved(d.cfg.state.dir, "robot1") is None and "robot1" not in d.store.data.peers


# ---------------------------------------------------------------------- a real daemon, a real disk


@pytest.mark.slow
def test_a_peer_map_taken_on_a_full_disk_is_saved_once_there_is_room_though_its_robot_is_gone(
    tmp_path: Path,
) -> None:
    """robot1's state directory on a tmpfs that fills (see tests/daemon/test_disk_full.py): robot0
    sends a new map, robot1 takes and acks it without saving it, and robot0 stops. Room again:
    robot1 saves that map on its own, so its next start has it."""
    from tests.daemon import test_disk_full as on  # the namespace, its disk and two robots
    from tests.daemon.test_disk_full import _status, _wait

    if problem := on._namespace_problem(tmp_path / "probe"):
        pytest.skip(problem)
    roster = on._roster(tmp_path, ("robot0", "robot1"))
    p0, p1 = free_ports(2)
    disk = tmp_path / "disk"
    c0 = on._config(tmp_path, "robot0", (p0, p1), tmp_path / "robot0" / "state", roster)
    c1 = on._config(tmp_path, "robot1", (p1, p0), disk / "state", roster)
    sock0, sock1 = (tmp_path / r / "run" / "mapd.sock" for r in ("robot0", "robot1"))
    log1 = tmp_path / "robot1.log"
    first = {r: on._publish(tmp_path, r, 1) for r in ("robot0", "robot1")}
    ns = on.FullDisk(disk, "4m")

    def held(sock: Path, of: str) -> int:
        s = _status(sock)
        return int(((s or {}).get("peers", {}).get(of) or {}).get("version") or 0)

    def saved(snap: Path) -> SavedPeer | None:
        return _saved(snap / "state", "robot0")

    try:
        ns.start("robot0", c0, tmp_path / "robot0.log")
        ns.start("robot1", c1, log1)
        v1 = _wait("robot1 holding robot0's first map", lambda: held(sock1, "robot0"), 60)
        _wait(
            "robot0's first map saved",
            lambda: (s := saved(ns.snapshot(tmp_path / "s0"))) and s.grid.version == v1,
        )
        ns.fill()
        second = on._publish(tmp_path, "robot0", 2)
        v2 = _wait("robot1 holding robot0's second map", lambda: (v := held(sock1, "robot0")) > v1 and v, 60)
        during = _wait(
            "robot1's failed save in status",
            lambda: (s := _status(sock1)) and s["state"]["writing"] is False and s,
        )
        assert "No space left on device" in during["state"]["error"]

        def acked() -> bool:
            s = query(sock0)
            return (s["peers"].get("robot1") or {}).get("acked_our_version") == s["source"]["version"]

        _wait("robot0 told that robot1 holds its second map", acked)
        assert ns.stop("robot0") == 0  # out of reach: it sends nothing more
        ns.free()
        _wait("robot1 writing again", lambda: (s := _status(sock1)) and s["state"]["writing"], 30)
        _wait("robot1 saying so", lambda: on._count(on._log_lines(log1), "state saved again"))
        assert ns.stop("robot1") == 0
        final = ns.snapshot(tmp_path / "final")
    finally:
        ns.close()
    back = saved(final)
    assert back is not None and back.grid.version == v2 and back.grid.same_map(second)
    assert not back.grid.same_map(first["robot0"]) and back.frame_pose is not None and back.key is not None
    lines = on._log_lines(log1)
    assert not any("Traceback" in line for line in lines), lines
    assert on._count(lines, "saving peers' maps and acks again every") == 1, lines
    assert on._count(lines, "state saved again") == 1, lines
    assert on._temps(final) == []
