"""Peers' maps and acks that a full disk kept from being saved, saved again until they are.

A peer's map whose save fails is used and acked all the same, so its robot does not send that
version again: the newest unsaved map of each robot is kept and saved again every
:data:`~mapd.files.outage.WRITE_RETRY_S` until it goes through, as the base and ``state.json`` (acks) are,
as the own map, the global map and the files output are elsewhere. Waiting for the robot's next map
instead lost it to a restart whenever that robot had gone out of reach or stopped first, long
after the disk had room again. The outage is said once (the first failure, with what it costs) and
once when nothing is left unsaved; ``mapd status`` shows the state directory failing until then
(:meth:`~mapd.daemon.state.StateStore.set_unsaved_peers`).

While nothing is unsaved, the state directory is looked at every :data:`~mapd.files.outage.WRITE_RETRY_S`
all the same (:meth:`~mapd.daemon.state.StateStore.check`): a fleet at rest saves nothing, and a
directory emptied, unmounted or remounted read-only under it would go unseen until a restart found
it empty. One that lost files gets them again from memory; one that cannot be written is a failed
save of the state like any other (said once, tried again until it goes through).

:class:`PeerSaves` runs on the event loop's thread (one caller at a time: the inbound loop) and
saves on worker threads.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from mapd.daemon.state import StateStore
from mapd.errors import StateError
from mapd.files.outage import WRITE_RETRY_S, WriteOutage
from mapd.grid import OccupancyGrid, Pose2D

log = logging.getLogger("mapd.daemon")

#: What a failed save of a peer map, the base or ``state.json`` costs, after the error (said once
#: per outage): nothing is lost while the daemon runs.
RETRY_SAID = "saving peers' maps and acks again every {:g} s (the maps are used meanwhile)"


@dataclass(frozen=True)
class UnsavedPeer:
    """A peer's map in use, to be saved, with what is saved beside it."""

    grid: OccupancyGrid
    #: The pose of its map frame its envelope reported, and the roster key it was verified with.
    frame_pose: Pose2D | None
    key: str | None
    #: The revocations counted when it was verified (``trusted``): one since voids it.
    mark: int


@dataclass
class PeerSaves:
    """The saves of peers' maps and of the state (see the module docstring)."""

    store: StateStore
    #: Whether a robot's map, verified after revocation number ``mark``, may still be used.
    trusted: Callable[[str, int], bool]
    #: Saves the base and ``state.json`` (the acks); StateError on a full disk.
    save_base: Callable[[], Awaitable[None]]
    #: Said once per outage, and once when nothing is left unsaved.
    outage: WriteOutage
    #: robot -> its newest map whose save failed. A newer map of the robot replaces it, its save
    #: going through ends it, a revocation drops it (never written back).
    unsaved: dict[str, UnsavedPeer] = field(default_factory=dict)
    #: The base or ``state.json`` (acks) failed to save: saved again with the peers' maps.
    state_unsaved: bool = False
    #: (monotonic) When what failed to save is tried again, or the state directory looked at.
    _retry_at: float = 0.0

    def retry_at(self) -> float | None:
        """(monotonic) When :meth:`save_again` is due: to save again what failed to save, or, while
        nothing did, to look at the state directory."""
        return self._retry_at

    async def save_peer(self, held: UnsavedPeer) -> bool:
        """Save a peer's map (a worker thread); on a full disk it is held, saved again every
        WRITE_RETRY_S. False when its robot was revoked meanwhile (then its files go again)."""
        robot = held.grid.robot
        try:
            await asyncio.to_thread(self.store.save_peer, held.grid, held.frame_pose, held.key)
        except StateError as exc:
            self._failed(exc)
            if not self.trusted(robot, held.mark):
                # Revoked meanwhile: nothing to hold, but state.json names it, and a write that
                # goes through ends the outage its failure shows in `mapd status`.
                self._retry_soon()
                self.state_unsaved = True
            elif self.store.savable(robot):  # (a name no folder may have fails every try alike)
                self._hold(held)
        else:
            old = self.unsaved.get(robot)
            if old is not None and old.grid.version <= held.grid.version:
                del self.unsaved[robot]
                self.store.set_unsaved_peers(self.unsaved)
            self._saved()
        if self.trusted(robot, held.mark):
            return True
        # Revoked while it was saved: the revocation took the map out of the receiver and the
        # state directory, but the save has put it back in since.
        try:
            await asyncio.to_thread(self.store.remove_peer, robot)
        except StateError as exc:
            log.warning("revoked %s: %s", robot, exc)
        return False

    async def save_state(self) -> None:
        """Save the base and ``state.json`` (acks); on a full disk, again every WRITE_RETRY_S."""
        try:
            await self.save_base()
        except StateError as exc:
            self._failed(exc)
            self._retry_soon()
            self.state_unsaved = True
        else:
            self.state_unsaved = False
            self._saved()

    async def save_again(self) -> None:
        """Save what failed to save: each robot's newest unsaved map, then the base and
        ``state.json``. One failure does not stop the rest (a folder of one robot that cannot be
        made fails it alone)."""
        self._retry_at = time.monotonic() + WRITE_RETRY_S  # (first: an error out of here waits too)
        if not self.unsaved and not self.state_unsaved:
            await self._look()
            return
        for robot, held in list(self.unsaved.items()):
            if self.unsaved.get(robot) is held:  # (not revoked while the one before was saved)
                await self.save_peer(held)
        if self.state_unsaved:
            await self.save_state()

    async def _look(self) -> None:
        """Look at the state directory (nothing to save again): what it lost is written again from
        memory; one that cannot be written is a failed save of the state, tried again."""
        try:
            await asyncio.to_thread(self.store.check)
        except StateError as exc:
            self._failed(exc)
            self.state_unsaved = True  # (state.json, with the maps it lost: when it can be)

    def revoked(self, robot: str) -> None:
        """``robot``'s key was revoked: its unsaved map is dropped, never written back."""
        if self.unsaved.pop(robot, None) is not None:
            self.store.set_unsaved_peers(self.unsaved)
            # state.json still names it (the revocation writes none): and a write that goes
            # through ends the outage that map alone may have kept in `mapd status`
            self.state_unsaved = True

    def _hold(self, held: UnsavedPeer) -> None:
        """Keep ``held`` to save again: its robot's newest unsaved map from now."""
        old = self.unsaved.get(held.grid.robot)
        if old is not None and old.grid.version > held.grid.version:
            return  # (not in this order: the receiver takes only newer maps)
        self._retry_soon()
        self.unsaved[held.grid.robot] = held
        self.store.set_unsaved_peers(self.unsaved)

    def _retry_soon(self) -> None:
        """Something is to be held unsaved: the first is tried again WRITE_RETRY_S from now, and
        what fails while it is held joins its tries."""
        if not self.unsaved and not self.state_unsaved:
            self._retry_at = time.monotonic() + WRITE_RETRY_S

    def _failed(self, exc: StateError) -> None:
        """A save of the state failed: said once per outage, with what it costs."""
        self.outage.failed(f"{exc}; {RETRY_SAID.format(WRITE_RETRY_S)}")

    def _saved(self) -> None:
        """A save of the state went through: the outage is over once nothing is left unsaved."""
        if not self.unsaved and not self.state_unsaved:
            self.outage.recovered("state saved again")
