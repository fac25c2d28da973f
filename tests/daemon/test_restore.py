"""What a restart brings back from the state directory: every saved peer map, the pose it reported,
and the bound on its next version (the daemon's ``_restore``, on real daemons and files)."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mapd import config as configmod
from mapd.daemon.intake import Decode, Drop
from mapd.daemon.server import Daemon
from mapd.daemon.state import StateStore
from mapd.daemon.state_lock import lock_state_dir
from mapd.daemon.versions import incarnation_at, make, split
from mapd.envelope import Envelope
from mapd.errors import StateError
from mapd.grid import OccupancyGrid, Pose2D


def _config(dk: SimpleNamespace, tmp_path: Path, robot: str, channel: str) -> Path:
    return dk.write_config(  # type: ignore[no-any-return]
        tmp_path,
        robot,
        extra='[transports]\nuse = ["virtual"]\n',
        **{"transports.virtual": f'channel = "{channel}"'},
    )


def _run(dk: SimpleNamespace, *daemons: Daemon, until: Callable[[], bool]) -> None:
    dk.run_until(*daemons, until=until, timeout=30)


def _env(version: int) -> Envelope:
    return Envelope(
        fleet="default", robot="robot1", version=version, base_version=0, codec="raw", width=10,
        height=10, resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"",
    )  # fmt: skip


def test_a_first_map_saved_just_before_a_kill_is_restored_though_state_json_never_named_it(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    # The kill came after robot1's first map was written whole (its YAML holds its version and
    # digest) and before state.json named it: start-up looked at state.json only, and lost it.
    cfg = configmod.load(_config(dk, tmp_path, "robot0", dk.channel()))
    store = StateStore(cfg.state.dir)
    store.open()
    version = make(incarnation_at(time.time() - 3600), 3)
    grid = dk.growing_map(3).replace(robot="robot1", version=version)
    store.save_peer(grid, key=cfg.fleet.roster["robot1"])  # (as Inbound saves a signed map)
    store.save_peer(grid.replace(robot="robot9"))  # not on the roster: never restored
    # robot2's, saved under a key the roster no longer has, and one with no key (an earlier
    # release's, whose revocations left the files): state.json does not vouch for either
    store.save_peer(grid.replace(robot="robot2"), key="ed25519:an-old-key")
    doc = json.loads((cfg.state.dir / "state.json").read_text())
    doc["peers"] = {}  # state.json as it was before the kill
    (cfg.state.dir / "state.json").write_text(json.dumps(doc))

    d0 = Daemon(cfg, source=dk.QueueSource("robot0"))
    _run(dk, d0, until=lambda: d0.fusion._loaded)
    held = d0.receiver.maps.get("robot1")
    assert held is not None and held.version == version and held.same_map(grid)
    assert d0.store.data.peers["robot1"].version == version  # and state.json names it from now on
    assert "robot1" in d0.fusion.status()["robots"]
    for other in ("robot9", "robot2"):
        assert other not in d0.receiver.maps and not (cfg.state.dir / "peers" / other).exists()

    store = StateStore(cfg.state.dir)
    store.open()
    store.save_peer(grid.replace(robot="robot2"))  # no key
    store.forget_peer("robot2")
    store.flush()
    d0 = Daemon(cfg, source=dk.QueueSource("robot0"))
    _run(dk, d0, until=lambda: d0.fusion._loaded)
    assert "robot2" not in d0.receiver.maps and not (cfg.state.dir / "peers" / "robot2").exists()


def test_a_restored_peers_next_version_is_bound_from_when_its_map_was_saved(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    # A map read back had stamp 0: after a restart the bound was 1000 + 10 per second since 1970,
    # over the 2^32 numbers a version has, for every restored peer.
    cfg = configmod.load(_config(dk, tmp_path, "robot0", dk.channel()))
    store = StateStore(cfg.state.dir)
    store.open()
    inc = incarnation_at(time.time() - 3600)
    store.save_peer(OccupancyGrid(np.zeros((10, 10), np.int8), 0.05, robot="robot1", version=make(inc, 5)))
    saved = cfg.state.dir / "peers" / "robot1" / "map.yaml"
    os.utime(saved, (time.time() - 60, time.time() - 60))  # held a minute before the restart

    d0 = Daemon(cfg, source=dk.QueueSource("robot0"))
    _run(dk, d0, until=lambda: d0.fusion._loaded)
    now = time.time()
    assert isinstance(d0.receiver.plan(_env(make(inc, 5 + 1500)), "robot1", now), Decode)  # as if never down
    far = d0.receiver.plan(_env(make(inc, (1 << 32) - 1)), "robot1", now)
    assert isinstance(far, Drop) and "jumps" in far.reason and far.forget


class _PoseSource:
    """A queue source whose robot knows where its map frame lies (a start pose)."""

    def __init__(self, dk: SimpleNamespace, robot: str, pose: Pose2D) -> None:
        self.source = dk.QueueSource(robot)
        self.source.start_pose = lambda: pose  # type: ignore[method-assign]


def test_a_peer_placed_by_the_pose_it_reported_is_placed_by_it_after_a_restart(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    # The pose came with each map and went straight to fusion, never to the state directory: after
    # a restart robot1 was searched for instead, and dropped from the global map when its map
    # overlaps no other (what start poses are for).
    channel = dk.channel()
    path0 = _config(dk, tmp_path, "robot0", channel)
    pose = Pose2D(12.0, -3.0, 0.5)
    d1 = Daemon(
        configmod.load(_config(dk, tmp_path, "robot1", channel)),
        source=_PoseSource(dk, "robot1", pose).source,
    )
    source1 = d1.source
    assert isinstance(source1, dk.QueueSource)
    source1.queue.put_nowait(dk.growing_map(1).replace(robot="robot1"))
    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    # (the pose goes to fusion once the map is saved: wait for both, not the save alone)
    _run(dk, d0, d1, until=lambda: "robot1" in d0.store.data.peers and "robot1" in d0.fusion.placer.poses)
    assert d0.fusion.placer.poses.get("robot1") == pose  # live: placed by the pose it reported

    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))

    def placed() -> bool:
        p = d0.fusion.status()["robots"].get("robot1", {})
        return bool(p.get("accepted")) and p.get("source") == "pose"

    _run(dk, d0, until=placed)
    p = d0.fusion.status()["robots"]["robot1"]
    assert p["reason"].startswith("start pose reported by the robot")
    assert (p["x"], p["y"], p["yaw"]) == tuple(pose)
    assert split(d0.receiver.maps["robot1"].version)[1] == 1


def test_a_restore_that_fails_lets_go_of_the_state_directory(tmp_path: Path, dk: SimpleNamespace) -> None:
    # run() took the state directory's lock, then the restore failed (a file where `own` goes):
    # the restore ran outside the try whose shutdown lets go, so the daemon held the lock for
    # the rest of the process and a daemon started again in it found the directory "in use".
    cfg = configmod.load(_config(dk, tmp_path, "robot0", dk.channel()))
    cfg.state.dir.mkdir(parents=True)
    (cfg.state.dir / "own").write_text("not a folder")
    d0 = Daemon(cfg, source=dk.QueueSource("robot0"))
    with pytest.raises(StateError, match="is not writable"):
        asyncio.run(d0.run())
    assert not (cfg.state.dir / "state.json").exists()  # the shutdown saved no state it never read
    os.close(lock_state_dir(cfg.state.dir))  # free again
    (cfg.state.dir / "own").unlink()
    d1 = Daemon(cfg, source=dk.QueueSource("robot0"))
    _run(dk, d1, until=lambda: d1.fusion._loaded)


def _running_with(word: str) -> list[int]:
    """The processes whose command line holds ``word``."""
    found = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                if word.encode() in (proc / "cmdline").read_bytes():
                    found.append(int(proc.name))
            except OSError:  # gone meanwhile
                pass
    return found


@pytest.mark.parametrize("damage", ["in use", "a file where own goes"])
def test_mapd_run_on_a_state_directory_it_cannot_take_is_one_line_and_leaves_nothing(
    tmp_path: Path, dk: SimpleNamespace, damage: str
) -> None:
    path = _config(dk, tmp_path, "robot0", dk.channel())
    cfg = configmod.load(path)
    store = StateStore(cfg.state.dir)
    store.open()
    store.save_own(dk.growing_map(1).replace(version=5))
    before = (cfg.state.dir / "state.json").read_bytes()
    held = None
    if damage == "in use":
        held = lock_state_dir(cfg.state.dir)
        want = f"mapd: error: state directory {cfg.state.dir} is in use by another mapd (pid {os.getpid()})"
    else:
        shutil.rmtree(cfg.state.dir / "own")
        (cfg.state.dir / "own").write_text("not a folder")
        want = f"mapd: error: state directory {cfg.state.dir} is not writable: File exists"
    try:
        with dk.mapd_run(path, tmp_path / "run.log") as proc:
            assert proc.wait(60) != 0
        out = (tmp_path / "run.log").read_text()
        assert out.splitlines() == [want], out  # that line alone: no traceback, no other line
        # nothing left, nothing written: state.json as it was (in use: the holder's), no control
        # socket, no process
        assert (cfg.state.dir / "state.json").read_bytes() == before
        assert not cfg.control_socket().exists()
        assert not _running_with(str(path))
    finally:
        if held is not None:
            os.close(held)
    os.close(lock_state_dir(cfg.state.dir))  # and the lock is free once its holder lets go


def test_mapd_run_with_a_file_where_a_links_state_folder_goes_is_one_line(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    """Found by the check-config audit: a file at state/links (where each transport keeps its
    state) ended mapd run with a NotADirectoryError traceback."""
    path = _config(dk, tmp_path, "robot0", dk.channel())
    cfg = configmod.load(path)
    cfg.state.dir.mkdir(parents=True, exist_ok=True)
    (cfg.state.dir / "links").write_text("not a folder")
    with dk.mapd_run(path, tmp_path / "run.log") as proc:
        assert proc.wait(60) != 0
    out = (tmp_path / "run.log").read_text()
    assert "Traceback" not in out, out
    want = f"mapd: error: state directory {cfg.state.dir} is not writable: "
    assert out.splitlines()[-1].startswith(want), out
    assert not _running_with(str(path))
