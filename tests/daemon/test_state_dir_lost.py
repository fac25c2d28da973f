"""A state directory that goes away or is replaced under a running daemon, and comes back.

A robot's SD card or USB disk unmounted (and mounted again, empty), its state directory emptied by
an operator (``rm -rf /var/lib/mapd/*``, a tmpfs cleared) or removed, or its disk remounted
read-only after an I/O error (ext4 ``errors=remount-ro``). What must hold: the daemon runs on,
using and fusing maps; the fault is said once, with what it costs, and shown in ``mapd status``
(``state.writing`` false); nothing is written to a folder the daemon would have to make in the
directory's place (on the wrong disk); once the directory can be written again, the daemon writes
everything it holds again, without a restart and also while no new map comes (a fleet at rest),
with its layout and lock; and a restart then restores what was saved after the recovery.

The fast tests hold one part at a time on an ordinary folder; the last runs two real daemons, one
with its state directory on a tmpfs in a user + mount namespace (``unshare -rm``, as
tests/daemon/test_disk_full.py does), which is emptied, remounted read-only, unmounted and mounted
again empty under it.
"""

from __future__ import annotations

import asyncio
import fcntl
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.daemon.state import StateStore
from mapd.daemon.state_lock import lock_state_dir
from mapd.daemon.versions import label
from mapd.demo.ports import free_ports
from mapd.errors import StateError
from mapd.fusion.merge import NO_OWNER, Bounds, MergeResult
from mapd.fusion.store import FusionStore
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map
from mapd.mapping.synthetic import room_grid
from mapd.outputs import files as files_output
from mapd.outputs.base import GlobalUpdate, OutputContext
from mapd.outputs.files import FilesOptions, FilesOutput

ROOT = Path(__file__).resolve().parents[2]
LOST = "lost files under the running daemon"


def _empty(folder: Path) -> None:
    """``rm -rf folder/*`` (and its hidden files): the folder stays, empty."""
    for p in folder.iterdir():
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def _locked(path: Path) -> bool:
    """Whether some open file holds ``path``'s flock (another process's, or another descriptor's)."""
    fd = os.open(path, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


class _Maps:
    """A store with an own map, a base and a peer's map saved, as a running daemon has them."""

    def __init__(self, root: Path) -> None:
        self.lock = lock_state_dir(root)  # as the daemon takes it, before it opens the store
        self.store = StateStore(root)
        self.store.open()
        (root / "links" / "uwb").mkdir(parents=True)  # a transport's folder (counter, replay marks)
        self.own = room_grid(40, 50, seed=1).replace(robot="me", version=5)
        self.base = room_grid(40, 50, seed=2).replace(robot="me", version=4)
        self.peer = room_grid(30, 60, seed=3).replace(robot="beta", version=7)
        self.store.save_own(self.own)
        self.store.save_base(self.base)
        self.store.save_peer(self.peer, Pose2D(1.0, 2.0, 0.5), "key-of-beta")

    def close(self) -> None:
        os.close(self.lock)
        self.store.release()


def _restored(root: Path) -> tuple[OccupancyGrid | None, OccupancyGrid | None, Any, dict[str, Any]]:
    """What a restart reads: own map, base, beta's map (with what was saved beside it), state.json."""
    again = StateStore(root)
    again.open()
    return (
        again.own_map(),
        again.base_map(),
        again.saved_peer("beta"),
        json.loads((root / "state.json").read_text()),
    )


def test_an_emptied_state_directory_gets_its_maps_layout_and_lock_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Emptied under the daemon: its next save (here the shutdown's state.json) wrote state.json
    alone, naming maps that were gone, and a restart had none of them (nor the lock, so a second
    daemon could take the directory meanwhile)."""
    root = tmp_path / "state"
    m = _Maps(root)
    try:
        caplog.set_level(logging.INFO, logger="mapd.daemon.state")
        _empty(root)
        m.store.flush()  # what the daemon's stop writes
        own, base, peer, doc = _restored(root)
        assert own is not None and own.same_map(m.own) and own.version == 5
        assert base is not None and base.same_map(m.base) and base.version == 4
        assert peer is not None and peer.grid.same_map(m.peer) and peer.grid.version == 7
        assert peer.frame_pose == Pose2D(1.0, 2.0, 0.5) and peer.key == "key-of-beta"
        assert (
            doc["own"]["version"] == 5
            and doc["base"]["version"] == 4
            and doc["peers"]["beta"]["version"] == 7
        )
        assert all((root / d).is_dir() for d in ("own", "peers", "global", "links/uwb"))
        assert _locked(root / "lock"), "the lock file was made again, but not locked"
        said = [r.getMessage() for r in caplog.records if LOST in r.getMessage()]
        assert len(said) == 1 and "base" in said[0] and "beta" in said[0] and "state.json" in said[0], said
        m.store.check()  # (nothing lost since: nothing written, nothing said)
        m.store.flush()
        assert len([r for r in caplog.records if LOST in r.getMessage()]) == 1
        assert m.store.health()["writing"] is True
    finally:
        m.close()


def test_a_removed_state_directory_is_not_made_again_and_is_written_whole_once_it_is_back(
    tmp_path: Path,
) -> None:
    """Removed (or gone with a disk unmounted above it): a save made it again, on whatever disk
    was under it, with the one map saved and nothing else. It fails, saying why, until the
    directory is back; then everything is written."""
    root = tmp_path / "state"
    m = _Maps(root)
    try:
        shutil.rmtree(root)
        newer = room_grid(30, 60, seed=4).replace(robot="beta", version=8)
        with pytest.raises(
            StateError, match=r"state directory .* is gone \(removed, or its disk unmounted\?\)"
        ):
            m.store.save_peer(newer)
        with pytest.raises(StateError, match="is gone"):
            m.store.check()
        assert not root.exists()
        health = m.store.health()
        assert health["writing"] is False and "is gone" in health["error"]
        root.mkdir()  # an operator makes it again (or the disk is mounted again)
        m.store.save_peer(newer)
        assert m.store.health()["writing"] is True
        own, base, peer, doc = _restored(root)
        assert own is not None and own.same_map(m.own) and base is not None and base.same_map(m.base)
        assert peer is not None and peer.grid.same_map(newer) and doc["peers"]["beta"]["version"] == 8
        assert _locked(root / "lock")
    finally:
        m.close()


def test_a_look_at_the_directory_ends_no_outage_of_a_full_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The look every few seconds finds a full disk's directory there and writable: the own map
    the disk refused is still unsaved, so ``mapd status`` must go on saying so."""
    import mapd.daemon.state as state_mod

    root = tmp_path / "state"
    m = _Maps(root)
    try:

        def full(*args: Any, **kw: Any) -> str:
            raise StateError(f"{root}/own/map.yaml: cannot write map: No space left on device")

        monkeypatch.setattr(state_mod, "save_committed", full)
        with pytest.raises(StateError):
            m.store.save_own(m.own.replace(version=6))
        m.store.check()
        assert m.store.health()["writing"] is False and "No space left" in m.store.health()["error"]
        monkeypatch.undo()
        m.store.save_own(m.own.replace(version=6))
        assert m.store.health()["writing"] is True
    finally:
        m.close()


def _merge(version: int) -> MergeResult:
    grid = room_grid(30, 40, seed=version).replace(version=version)
    bounds = Bounds.of_grid(grid)
    assert bounds is not None
    return MergeResult(grid=grid, bounds=bounds, owner=np.full(grid.data.shape, NO_OWNER, np.uint8))


def test_the_global_map_is_written_again_but_never_into_a_state_directory_made_again(tmp_path: Path) -> None:
    """The fusion worker's files: ``save`` made the whole path again (parents too), so a state
    directory gone with its disk got a global map on the disk under it; and nothing wrote the last
    global map again once the directory was emptied (a fleet at rest merges nothing new)."""
    root = tmp_path / "state"
    root.mkdir()
    store = FusionStore(root / "global", robot="a")
    store.save(_merge(3), {}, stamp=1.0, fleet_frame=None, mode="logodds")
    shutil.rmtree(root)
    with pytest.raises(StateError, match="is gone"):
        store.save(_merge(4), {}, stamp=2.0, fleet_frame=None, mode="logodds")
    assert not root.exists() and store.health()["writing"] is False
    root.mkdir()  # back, empty: the last map saved (v3) is written again
    assert store.look() == ["the global map v3 and its placements"]
    back = FusionStore(root / "global", robot="a").load_global()
    assert back is not None and back.version == 3 and back.same_map(_merge(3).grid)
    assert json.loads((root / "global" / "transforms.json").read_text())["version"] == 3
    assert store.look() == []
    # The worker's save of v4 is still owed (it tries again): the look wrote an older map.
    assert store.health()["writing"] is False
    store.save(_merge(4), {}, stamp=2.0, fleet_frame=None, mode="logodds")
    assert store.health()["writing"] is True


def test_the_files_output_writes_its_map_again_when_its_folder_is_emptied(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A fleet at rest makes no new global map: the folder stayed empty until the next one. A
    folder gone with its parent (a disk unmounted above it) is not made again."""
    monkeypatch.setattr(files_output, "WRITE_RETRY_S", 0.05)
    caplog.set_level(logging.INFO, logger="mapd.outputs.files")
    mnt = tmp_path / "mnt"
    grid = room_grid(40, 50, seed=4)
    update = GlobalUpdate(grid=grid, frames={"a": Pose2D(1.0, 2.0, 0.0)}, stamp=5.0, versions={"a": 9})

    async def until(cond: Any, what: str) -> None:
        end = time.monotonic() + 10
        while not cond():
            assert time.monotonic() < end, what
            await asyncio.sleep(0.01)

    async def main() -> None:
        out = FilesOutput(FilesOptions(dir=mnt / "out", name="fleet"), OutputContext("base", "f"))
        await out.start()
        try:
            await asyncio.to_thread(out.publish, update)
            _empty(mnt / "out")
            await until(lambda: (mnt / "out" / "fleet.yaml").exists(), "the map was not written again")
            await until(lambda: out.stats()["written"] == 2, "not counted")
            shutil.rmtree(mnt)  # the disk above it unmounted: no folder to write in
            await asyncio.to_thread(out.publish, update)
            assert out.stats()["writing"] is False and not mnt.exists()
            mnt.mkdir()  # mounted again, without the output's folder
            await until(lambda: out.stats()["writing"] is True, "not written once the folder could be made")
        finally:
            await out.close()

    asyncio.run(main())
    assert load_map(mnt / "out" / "fleet.yaml").same_map(grid)
    assert json.loads((mnt / "out" / "transforms.json").read_text())["robots"]["a"]["version"] == 9
    said = [r.getMessage() for r in caplog.records]
    assert sum("was gone" in s and "written again" in s for s in said) == 1, said
    assert sum("cannot write the global map" in s for s in said) == 1, said


UNMOUNTED_ABOVE = """
import json, subprocess, sys
from pathlib import Path
import numpy as np
from mapd.daemon.state import StateStore
from mapd.fusion.merge import NO_OWNER, Bounds, MergeResult
from mapd.fusion.store import FusionStore
from mapd.mapping.synthetic import room_grid

disk = Path(sys.argv[1])  # a tmpfs, with the state directory in a folder on it
store = StateStore(disk / "robot" / "state")
store.open()
grid = room_grid(30, 40, seed=1).replace(robot="me", version=5)
store.save_own(grid)
fusion = FusionStore(disk / "robot" / "state" / "global", robot="me")
merged = MergeResult(grid=grid, bounds=Bounds.of_grid(grid), owner=np.full(grid.data.shape, NO_OWNER, np.uint8))
fusion.save(merged, {}, stamp=1.0, fleet_frame=None, mode="logodds")
subprocess.run(["umount", "-l", str(disk)], check=True)  # the disk goes: disk/ is the folder under it
said = []
for save in (lambda: store.save_own(grid.replace(version=6)), lambda: store.check(),
             lambda: fusion.save(merged, {}, stamp=2.0, fleet_frame=None, mode="logodds")):
    try:
        save()
        said.append(None)
    except Exception as exc:  # (StateError: said in one line)
        said.append(f"{type(exc).__name__}: {exc}")
print(json.dumps({"said": said, "left": sorted(p.name for p in disk.iterdir())}))
"""


def _unmounted_run(disk: Path, size: str, script: str) -> tuple[dict[str, Any], str]:
    """Python ``script`` run on a tmpfs of ``size`` mounted on ``disk`` in a namespace of its own
    (skipped where none can be made): its JSON report and its stderr, once checked that it ran and
    left nothing on the disk under the mount point (``left``)."""
    from tests.daemon.test_disk_full import _namespace_problem, in_tmpfs

    if problem := _namespace_problem(disk.parent / "probe"):
        pytest.skip(problem)
    disk.mkdir()
    done = in_tmpfs(disk, size, script)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["left"] == [], "written on the disk under the mount point"
    return out, done.stderr


def test_a_state_directory_on_a_disk_unmounted_above_it_is_not_made_again_on_the_disk_under_it(
    tmp_path: Path,
) -> None:
    """The state directory a folder on a disk mounted above it (``/mnt/usb`` holding ``robot/state``):
    unmounted, the saves made the whole path again on the disk under the mount point (the root
    file system), and wrote the maps there, where nobody would look for them."""
    disk = tmp_path / "disk"
    out, _ = _unmounted_run(disk, "4m", UNMOUNTED_ABOVE)
    assert all(
        s is not None and s.startswith("StateError: ") and f"(the disk mounted at {disk} unmounted?)" in s
        for s in out["said"]
    ), out


# ---------------------------------------------------------------------- real daemons, a real mount

#: Runs in the namespace: mounts the tmpfs, then takes one command a line on stdin and answers one
#: line when it is done. ``sh`` runs the rest of its line (mount, umount, rm) and answers its status.
#: ``snap`` copies the tmpfs while the daemon writes: a temporary file renamed away between cp's
#: listing and its copy fails that cp (seen once), so it tries again, and always answers.
CONTROL = r"""
disk=$1
mount -t tmpfs -o size=16m tmpfs "$disk" || exit 97
echo mounted
while IFS= read -r line; do
  set -f; set -- $line; set +f
  cmd=$1; a=$2; b=$3; c=$4
  case $cmd in
    start) "$PY" -m mapd run --config "$b" >>"$c" 2>&1 </dev/null & eval "pid_$a=\$!"; echo "pid $!";;
    stop) eval "p=\$pid_$a"; kill -TERM "$p"; wait "$p"; echo "rc $?";;
    snap) ok=; for try in 1 2 3 4 5; do rm -rf "$a"; cp -a "$disk/." "$a" 2>/dev/null && { ok=1; break; }; done
          [ -n "$ok" ] && echo snapped || echo "snap failed";;
    sh) shift; (eval "$*") >/dev/null 2>&1; echo "rc $?";;
  esac
done
"""


def _namespace(disk: Path) -> Any:
    """A tmpfs at ``disk`` in a user + mount namespace of its own (test_disk_full's, run by this
    module's CONTROL script), the daemons run inside it."""
    from tests.daemon import test_disk_full as on

    class Namespace(on.FullDisk):
        def sh(self, command: str) -> int:
            """Run ``command`` (one line of shell) in the namespace; its exit status."""
            return int(self.ask(f"sh {command}").split()[1])

    return Namespace(disk, None, CONTROL)


@pytest.mark.slow
def test_a_daemon_whose_state_directory_is_emptied_remounted_read_only_and_unmounted_runs_on_and_saves_again(
    tmp_path: Path,
) -> None:
    """robot1's state directory is a tmpfs mount point; robot0 (state on the ordinary disk) sends
    it maps over zenoh. Emptied at rest; remounted read-only while both robots make new maps, then
    read-write; unmounted while both make new maps, then a new empty tmpfs mounted there."""
    from tests.daemon import test_disk_full as on  # two robots taking maps from files the test writes
    from tests.daemon.test_disk_full import _count, _log_lines, _status, _wait

    if problem := on._namespace_problem(tmp_path / "probe"):
        pytest.skip(problem)
    roster = on._roster(tmp_path, ("robot0", "robot1"))
    p0, p1 = free_ports(2)
    disk = tmp_path / "disk"  # robot1's state directory, and the tmpfs mounted on it
    c0 = on._config(tmp_path, "robot0", (p0, p1), tmp_path / "robot0" / "state", roster)
    c1 = on._config(tmp_path, "robot1", (p1, p0), disk, roster)
    sock = tmp_path / "robot1" / "run" / "mapd.sock"
    log1 = tmp_path / "robot1.log"
    for robot in ("robot0", "robot1"):
        on._publish(tmp_path, robot, 1)
    ns = _namespace(disk)
    snaps = iter(range(100))

    def snap() -> Path:
        return ns.snapshot(tmp_path / f"snap{next(snaps)}")

    held: dict[str, int] = {"robot0": 0, "robot1": 0}  # the versions robot1 holds and fused

    def holds_newer() -> dict[str, Any] | None:
        """robot1's status once it holds and has fused a newer version of both maps than ``held``."""
        assert ns.alive("robot1"), log1.read_text()[-3000:]
        s = _status(sock)
        if s is None:
            return None
        now = {
            "robot1": s["source"]["version"] or 0,
            "robot0": (s["peers"].get("robot0") or {}).get("version") or 0,
        }
        merged = s["fusion"]["robots"]
        if any(v <= held[r] or (merged.get(r) or {}).get("version") != v for r, v in now.items()):
            return None
        held.update(now)
        return s

    global_version = [0]  # the newest global map robot1 made, as its status last said

    def saved(at: Path, n: int) -> bool:
        """Whether the copy ``at`` holds version ``n`` of both maps, each whole, with a state.json
        naming them, and the newest global map: what a restart reads."""
        if (s := _status(sock)) is not None and (made := s["fusion"]["global"]) is not None:
            global_version[0] = made["version"]  # (None while no global map is made yet: seen once)
        store = StateStore(at)
        try:
            store.open()
            own, peer = store.own_map(), store.peer_map("robot0")
            doc = json.loads((at / "state.json").read_text())
        except (OSError, ValueError, StateError):
            return False
        if own is None or peer is None or not own.same_map(on._room("robot1", n)):
            return False
        ok = peer.same_map(on._room("robot0", n)) and doc["own"]["version"] == own.version
        fused = FusionStore(at / "global", robot="robot1").load_global()
        ok = ok and fused is not None and fused.version == global_version[0]
        return ok and doc["peers"]["robot0"]["version"] == peer.version

    def publish(n: int) -> dict[str, Any]:
        for robot in ("robot0", "robot1"):
            on._publish(tmp_path, robot, n)
        return _wait(f"version {n} of both maps held and fused", holds_newer, 60)

    def state(writing: bool, error: str = "") -> dict[str, Any]:
        def now() -> dict[str, Any] | None:
            s = _status(sock)
            if s is None or s["state"]["writing"] is not writing or error not in (s["state"]["error"] or ""):
                return None
            return s

        return _wait(f"state.writing {writing} {error}", now, 20)

    try:
        ns.start("robot0", c0, tmp_path / "robot0.log")
        ns.start("robot1", c1, log1)
        _wait("both first maps held and fused", holds_newer, 60)
        _wait("the first maps saved", lambda: saved(snap(), 1))

        # ---- emptied at rest (rm -rf): everything written again within a look, the lock too
        assert ns.sh(f"rm -rf {disk}/*") == 0
        _wait("the emptied directory written again", lambda: _count(_log_lines(log1), LOST) == 1, 20)
        assert saved(snap(), 1)
        assert ns.sh(f"flock -n {disk}/lock true") != 0, "the lock was not taken again"

        # ---- remounted read-only: said at rest, new maps used and fused, saved once writable
        assert ns.sh(f"mount --bind {disk} {disk} && mount -o remount,bind,ro {disk}") == 0
        state(False, "read-only")
        publish(2)
        _wait(  # (the merge of version 2)
            "the global map's save failing",
            lambda: (s := _status(sock)) and s["state"]["global_map"]["writing"] is False,
        )
        state(False, "read-only")
        assert ns.sh(f"umount {disk}") == 0  # read-write again (the bind mount gone)
        state(True)
        _wait("version 2 saved once writable", lambda: saved(snap(), 2))

        # ---- unmounted (the disk gone), new maps, then a new empty disk mounted there
        assert ns.sh(f"umount -l {disk}") == 0
        state(False, "not mounted any more")
        publish(3)
        state(False, "not mounted any more")
        text = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--config", str(c1)],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=ROOT,
        )
        assert "state   FAULTS" in text.stdout and "is not mounted any more" in text.stdout, text
        assert ns.sh(f"mount -t tmpfs -o size=16m tmpfs {disk}") == 0
        state(True)
        _wait("version 3 written on the new disk", lambda: saved(snap(), 3))
        _wait("the global map written", lambda: (s := _status(sock)) and s["state"]["global_map"]["writing"])
        assert ns.sh(f"flock -n {disk}/lock true") != 0
        assert ns.stop("robot0") == 0  # out of reach: what robot1 restores is what it saved
        assert ns.stop("robot1") == 0
        final = snap()
        # ---- a restart restores what was saved after the recovery
        ns.start("robot1", c1, log1)
        back = _wait(
            "robot1 restarted, robot0's map restored",
            lambda: (s := _status(sock)) and (s["peers"].get("robot0") or {}).get("restored") and s,
            30,
        )
        assert back["peers"]["robot0"]["version"] == held["robot0"]
        assert ns.stop("robot1") == 0
    finally:
        ns.close()

    # Nothing of the state was written to the folder under the unmounted disk (seen from outside
    # the namespace, the mount point is that folder). (fused.csv, a log, is not the state's.)
    assert not any((disk / n).exists() for n in ("own", "peers", "global", "state.json", "lock")), list(
        disk.iterdir()
    )
    assert saved(final, 3)  # (and the global map robot1 last made)
    lines = _log_lines(log1)
    assert not any("Traceback" in line for line in lines), "\n".join(lines)
    resumed = [line for line in lines if "resumed from state" in line]
    # (as mapd status labels it: the raw number, incarnation and all, matched nothing it shows)
    assert len(resumed) == 1 and f"own_version={label(held['robot1'])} " in resumed[0], resumed
    assert "peers=robot0" in resumed[0], resumed
    assert _count(lines, LOST) == 2, lines  # emptied, and the new disk: once each
    for cause in ("read-only file system", "not mounted any more"):
        # said once each by what saves: peers' maps and acks, own maps, the global map; and by
        # each CSV log in the directory that wrote in the outage (at most once each)
        assert _count([ln for ln in lines if ".csv" not in ln], cause) == 3, (cause, lines)
        for csv in ("updates.csv", "fused.csv"):
            assert _count([ln for ln in lines if csv in ln], cause) <= 1, (cause, csv, lines)
    for said in (
        "saving peers' maps and acks again every",
        "new versions are not sent until one is saved",
        "fusion: global map not saved",
        "state saved again",
        "own map saved again",
        "fusion: global map saved again",
    ):
        assert _count(lines, said) == 2, (said, lines)  # once in each outage
    assert on._temps(final) == []


CSV_UNMOUNTED = """
import json, logging, subprocess, sys
from pathlib import Path
from mapd.daemon.coding import CsvLog

logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
disk = Path(sys.argv[1])  # a tmpfs; the log in it, as fused.csv is in the state directory
log = CsvLog(disk / "fused.csv")
log.write([{"time": 1.0, "robot": "beta", "version": 1}])
subprocess.run(["umount", "-l", str(disk)], check=True)  # the disk goes: disk/ is the folder under it
log.write([{"time": 2.0, "robot": "beta", "version": 2}])
log.write([{"time": 3.0, "robot": "beta", "version": 3}])
left = sorted(p.name for p in disk.iterdir())
subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)], check=True)  # back, empty
log.write([{"time": 4.0, "robot": "beta", "version": 4}])
print(json.dumps({"left": left, "after": (disk / "fused.csv").read_text().splitlines()}))
"""


def test_a_csv_log_writes_nothing_on_the_disk_under_its_unmounted_one(tmp_path: Path) -> None:
    """fused.csv and updates.csv were appended to in the folder left under an unmounted disk (on
    the root file system, where nobody looks); now that is a failed write, said once, and the log
    goes on in the disk mounted there again."""
    out, stderr = _unmounted_run(tmp_path / "disk", "1m", CSV_UNMOUNTED)
    assert out["after"] == ["time,robot,version", "4.0,beta,4"], out
    said = [ln for ln in stderr.splitlines() if "fused.csv" in ln]
    assert len(said) == 2 and "not mounted any more" in said[0] and "again" in said[1], said
