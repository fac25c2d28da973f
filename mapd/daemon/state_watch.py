"""A state directory lost under the running daemon: seen before each save, and made whole again.

The directory may go while the daemon runs: emptied (``rm -rf /var/lib/mapd/*``, a tmpfs cleared),
removed, its disk unmounted (and mounted again, empty or not), or remounted read-only after an I/O
error. The daemon keeps every map in memory and runs on. Before each save, and every
:data:`~mapd.files.outage.WRITE_RETRY_S` while nothing is saved (:meth:`StateDirWatch.check`), the
store looks (without writing) whether the directory can be written: while it is gone, not mounted
any more, or read-only, saves fail with one line saying so (counted in ``mapd status``), and
nothing is written to the folder under an unmounted disk nor to a state directory made again in its
place by the daemon (only an operator, or the mount, brings it back). Once it can be written, the
layout is made again (``own``, ``peers``, ``global``, ``links/<transport>``), the lock taken again,
and every file the store wrote that is gone or not the one it wrote (another disk mounted there) is
written again from memory, then ``state.json``, which then names only maps that are there: one
warning says what was written again. The fusion worker's files are looked at the same way
(:meth:`StateDirWatch.also_check`).

:class:`StateDirWatch` is that part of :class:`~mapd.daemon.state.StateStore`: what it keeps to
tell a file lost (the ids of the files written, the maps as last saved) and what it does then.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mapd.daemon.state_lock import _flock
from mapd.daemon.state_records import StateData, _Held
from mapd.daemon.versions import label
from mapd.errors import MapdError, StateError
from mapd.files import make_dir
from mapd.files.folders import file_id, file_ids, folder_unusable
from mapd.files.outage import WriteOutage
from mapd.grid import OccupancyGrid
from mapd.imaging.pixels import one_line

# Said as the store's lines are: one logger for everything the state directory says.
log = logging.getLogger("mapd.daemon.state")
#: The folders of the state directory, made at start and made again where they went.
LAYOUT = ("own", "peers", "global")
#: A file's device and inode (:func:`~mapd.files.folders.file_id`).
_FileId = tuple[int, int]


class StateDirWatch:
    """The part of :class:`~mapd.daemon.state.StateStore` that sees the directory lost under it
    and makes it whole again (see the module docstring); it writes with the store's own saves."""

    # The store's (StateStore), used here: its folder, its records and its two locks.
    root: Path
    data: StateData
    _lock: threading.Lock
    _io: threading.Lock

    def __init__(self) -> None:
        #: Set by :meth:`~mapd.daemon.state.StateStore.open`: from then on the directory is looked
        #: at before each save.
        self._opened = False
        #: The mount point the directory was on when opened (itself, or one above it; None: the
        #: root file system): one that is not any more had its disk unmounted, and what is left
        #: there (a folder of another disk) is not written to.
        self._mount: Path | None = None
        #: The maps as last saved (or restored at start): what a directory that lost them gets again.
        self._own_held: OccupancyGrid | None = None
        self._base_held: OccupancyGrid | None = None
        self._peers_held: dict[str, _Held] = {}
        #: What was written (or read), by what it holds ("state.json", "own", "base",
        #: "peers/<robot>"): each file's path and id then. One gone or replaced is written again.
        self._ids: dict[str, list[tuple[Path, _FileId]]] = {}
        #: The folders to make again where they went: the layout, and ``links/<transport>`` as seen.
        self._dirs: set[str] = set(LAYOUT)
        #: The lock file's id as the daemon holds it (taken by
        #: :func:`~mapd.daemon.state_lock.lock_state_dir`, or again here after the directory lost
        #: it: then also its descriptor, closed with the store).
        self._lock_id: _FileId | None = None
        self._lock_fd: weakref.finalize[Any, Any] | None = None
        #: Looks at other files of the directory (the fusion worker's), run by :meth:`check`.
        self._others: list[Callable[[], list[str]]] = []
        self._others_outage = WriteOutage(log)

    # The store's saves (StateStore has them), with which what was lost is written again.
    def _counted(
        self, peer: str | None = None, *, ends: bool = True
    ) -> contextlib.AbstractContextManager[None]:
        raise NotImplementedError

    def _remove_stale_temps(self) -> None:
        raise NotImplementedError

    def _save_own(self, grid: OccupancyGrid) -> None:
        raise NotImplementedError

    def _save_base(self, grid: OccupancyGrid) -> None:
        raise NotImplementedError

    def _save_peer(self, held: _Held) -> None:
        raise NotImplementedError

    def _write_state(self) -> None:
        raise NotImplementedError

    def release(self) -> None:
        """Close the lock this store took again (see :meth:`_relock`), if any. The daemon's first
        lock is its own (:func:`~mapd.daemon.state_lock.lock_state_dir`); this one also goes with
        the store."""
        if self._lock_fd is not None:
            self._lock_fd()
            self._lock_fd = None

    def also_check(self, look: Callable[[], list[str]]) -> None:
        """Have :meth:`check` run ``look`` too: it writes again what another part saved in the
        directory and lost (the fusion worker's files), and returns what it wrote (words, for the
        line that says so) or raises :class:`StateError`."""
        self._others.append(look)

    def check(self) -> None:
        """Look at the directory while nothing is saved (a fleet at rest: called every
        :data:`~mapd.files.outage.WRITE_RETRY_S`), as each save does first (:meth:`_ready`): write again
        what it lost. :class:`StateError` while it cannot be written (gone, not mounted any more,
        read-only), counted as a failed save."""
        with self._io, self._counted(ends=False):
            self._ready(others=True)

    def _ready(self, *, others: bool = False) -> None:
        """Before a save (under ``_io``): :class:`StateError` when the directory cannot be written
        now; and once it can, after it lost files, its layout, lock and files made again, and the
        others' (:meth:`also_check`) looked at too (``others``: looked at in any case). What was
        written again is said in one line."""
        if not self._opened:
            return  # (a store used without open(): its maker's folder, as it is)
        why = folder_unusable(self.root, mount=self._mount)
        if why is not None:
            # Not made again here: a folder made where a disk was unmounted, or where an operator
            # removed it, is on the wrong disk (only the mount, or the operator, brings it back).
            raise StateError(f"state directory {self.root} {why}")
        self._relock()
        lost = self._lost()
        for sub in sorted(self._dirs):
            d = self.root / sub
            if not os.path.lexists(d):  # (a symlink to a folder elsewhere is its owner's to fix)
                try:
                    make_dir(d)
                except OSError as exc:
                    raise StateError(
                        f"{d}: cannot create the folder: {exc.strerror or one_line(exc)}"
                    ) from None
        with contextlib.suppress(OSError):  # each transport's folder, to make again if it goes
            self._dirs.update(f"links/{p.name}" for p in (self.root / "links").iterdir() if p.is_dir())
        written = self._write_again(lost) if lost else []
        if lost or others:
            written += self._look_at_others()
        if written:
            log.warning(
                "state directory %s lost files under the running daemon (emptied, or another disk "
                "mounted there?): written again from memory: %s",
                self.root,
                ", ".join(written),
            )

    def _look_at_others(self) -> list[str]:
        """Run the others' looks (:meth:`also_check`); what they wrote again. One that fails is
        counted where it failed (the global map's status) and said here once, not raised: this
        store's own saves went through."""
        written: list[str] = []
        try:
            for look in self._others:
                written += look()
        except MapdError as exc:
            self._others_outage.failed(f"{exc}; written again at the next look")
        else:
            self._others_outage.recovered(f"state directory {self.root}: written again")
        return written

    def _lost(self) -> set[str]:
        """What was written (:attr:`_ids`) whose files are gone or are not the ones written."""
        with self._lock:
            ids = dict(self._ids)
        lost = set()
        for what, files in ids.items():
            for path, known in files:
                try:
                    now = file_id(path)
                except OSError as exc:
                    raise StateError(f"{path}: cannot look at it: {exc.strerror or one_line(exc)}") from None
                if now != known:
                    lost.add(what)
        return lost

    def _write_again(self, lost: set[str]) -> list[str]:
        """Write again, from memory, the maps whose files the directory lost (``lost``, as
        :meth:`_lost` names them), then ``state.json``, naming only the maps that are there; what
        was written, in words. A failure half-way leaves the rest lost: the next look writes them."""
        self._remove_stale_temps()  # (a disk mounted there again may hold an old run's)
        with self._lock:
            own, base, peers = self._own_held, self._base_held, dict(self._peers_held)
            # Records of maps no longer held name files that are not there: left out.
            self.data.peers = {r: rec for r, rec in self.data.peers.items() if r in peers}
            if own is None:
                self.data.own = None
            if base is None:
                self.data.base = None
        written = []
        if own is not None and "own" in lost:
            self._save_own(own)
            written.append(f"own map {label(own.version)}")
        if base is not None and "base" in lost:
            self._save_base(base)
            written.append("base")
        again = sorted(r for r in peers if f"peers/{r}" in lost)
        for robot in again:
            self._save_peer(peers[robot])
        if again:
            written.append(f"the map{'s' if len(again) > 1 else ''} of {', '.join(again)}")
        self._write_state()
        return [*written, "state.json"]

    def _relock(self) -> None:
        """Take the lock again when the directory lost its lock file (emptied, another disk
        mounted there): a second daemon could have taken the directory while this one wrote it."""
        if self._lock_id is None:
            return  # (no lock was taken: a store used without a daemon)
        path = self.root / "lock"
        try:
            if file_id(path) == self._lock_id:
                return
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise StateError(
                f"state directory {self.root}: cannot lock it again: {exc.strerror or one_line(exc)}"
            ) from None
        _flock(self.root, fd, "was taken by another mapd{} while its lock file was gone: not written to")
        st = os.fstat(fd)
        self.release()
        self._lock_fd = weakref.finalize(self, os.close, fd)
        self._lock_id = (st.st_dev, st.st_ino)

    def _remember(self, what: str, *paths: Path) -> None:
        """Keep the ids of the files just written (or read) for ``what``: see :meth:`_lost`."""
        ids = file_ids(*paths)
        with self._lock:
            self._ids[what] = ids

    def _remember_map(self, what: str, yaml_path: Path, grid: OccupancyGrid) -> None:
        """:meth:`_remember` a map saved by :func:`~mapd.grid.save_committed`: its YAML and image."""
        self._remember(what, yaml_path, yaml_path.with_name(f"{yaml_path.stem}-{grid.version}.pgm"))
