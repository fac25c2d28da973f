"""Own maps out: the source's maps numbered, saved, coded and offered to the transports.

:class:`Outbound` is the daemon's sending half, an asyncio adapter like :mod:`mapd.daemon.inbound`
around the sans-I/O core it drives: :class:`~mapd.daemon.publisher.PublisherCore` decides what to
code, against which base, for which free links. Two loops:

* :meth:`Outbound.take_source` numbers each map of the source (versions are the daemon's, so they
  keep increasing across restarts) and hands it to fusion and the outputs at once; only the newest
  waits to be saved and sent, so a fast source never queues.
* :meth:`Outbound.run` saves the newest version (worker thread), asks the core what to code, codes
  and signs it (worker), and offers it to the transports named (latest wins inside each).

A version is saved before it is sent: after a crash its number never comes again for another map.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mapd import wallclock
from mapd.codec.api import encode_problem
from mapd.daemon.coding import Coder
from mapd.daemon.publisher import PublisherCore
from mapd.daemon.sinks import Sinks
from mapd.daemon.state import StateStore
from mapd.envelope import Envelope
from mapd.errors import MapdError, StateError
from mapd.files.outage import WRITE_RETRY_S, WriteOutage
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid
from mapd.sources.base import MapSource
from transports.base import Transport

log = logging.getLogger("mapd.daemon")
#: A step of the wall clock ahead this large, after a new state's versions began from it, begins
#: them again (see Outbound._versions_to_begin_again): more than clocks that disagree a little, or a slew.
STEP_AHEAD_S = 60.0


@dataclass
class Outbound:
    """This robot's maps from the source to the transports (see the module docstring)."""

    me: str
    max_cells: int
    publisher: PublisherCore
    coder: Coder
    store: StateStore
    fusion: FusionWorker
    sinks: Sinks
    #: The transport of a name, once started; None for one that is gone.
    transport: Callable[[str], Transport | None]
    #: Each transport's peers now, by transport name (what the core offers to).
    peers: Callable[[], dict[str, list[str]]]
    #: Whether a name is a fleet robot's (on the roster, or heard from): not the source's to give.
    fleet_robot: Callable[[str], bool] = lambda robot: False
    #: ``[state] clock_wait_s``: how long a new state waits for a synchronized clock (see
    #: :meth:`_clock_for_a_new_state`), and how it asks the kernel.
    clock_wait_s: float = 0.0
    clock_synchronized: Callable[[], bool | None] = lambda: wallclock.synchronized()
    #: The wall clock versions are numbered by (a test steps its own).
    wall: Callable[[], float] = time.time
    #: (wall, monotonic) when this process began a new state's versions (see _versions_to_begin_again).
    _began: tuple[float, float] | None = None
    #: The newest own version (numbered), or None before the first.
    own: OccupancyGrid | None = None
    #: The newest own version saved: the only kind sent, and so the only one a late joiner's
    #: keyframe query is answered with (``own`` may be one a full disk kept from being saved, whose
    #: number a restart could give again).
    saved: OccupancyGrid | None = None
    #: The source has no more maps (a finished log); the daemon still serves its peers.
    source_finished: bool = False
    _pending: OccupancyGrid | None = None  # the newest own version, not yet saved
    _unsaved: OccupancyGrid | None = None  # the newest own version, whose save failed: tried again
    _retry_at: float = 0.0  # (monotonic) when _unsaved is tried again
    _wake: asyncio.Event = field(default_factory=asyncio.Event)
    _saves: WriteOutage = field(default_factory=lambda: WriteOutage(log))  # a full disk, said once
    _kf_lock: threading.Lock = field(default_factory=threading.Lock)
    _refused: set[str] = field(default_factory=set)  # fleet robots' names from the source, said once
    #: Why the source's newest maps are skipped (None: the newest was taken), and how many in a row.
    skipped: str | None = None
    skipped_maps: int = 0

    def __post_init__(self) -> None:
        # The fusion worker's files are in the state directory too: when it loses them under the
        # running daemon, they are written again with the rest (StateStore.check), as this robot's
        # own map is, also while no merge comes to save them (a fleet at rest).
        if self.fusion.store is not None:
            self.store.also_check(self.fusion.store.look)

    def wake(self) -> None:
        """The publisher has something to look at: a link became free, or a peer needs a keyframe."""
        self._wake.set()

    async def take_source(self, source: MapSource) -> None:
        """Take the source's maps until it ends; another robot's map (ros2 ``discover_robots``) is
        fused and recorded as a peer's is, never sent."""
        async for grid in source.maps():
            if grid.robot and grid.robot != self.me:
                self._local_peer_map(source, grid)
                continue
            if grid.cells > self.max_cells:
                self._skip(
                    f"the map of {grid.cells} cells is over limits.max_cells ({self.max_cells})",
                    "raise limits.max_cells on every robot (each refuses larger maps), or make the "
                    "source's map coarser",
                )
                continue
            problem = encode_problem(grid)
            if problem is not None:  # no codec could send it: skip it rather than fail on it later
                self._skip(problem, "no codec can send such a map")
                continue
            if self.skipped is not None:
                log.info("source maps fit again, after %d skipped: shared and fused again", self.skipped_maps)
                self.skipped, self.skipped_maps = None, 0
            new = self.store.new_state()
            if new or self._versions_to_begin_again():
                if new:
                    await self._clock_for_a_new_state()
                self._began = (self.wall(), time.monotonic())
                self.store.begin_again(self._began[0], synchronized=self.clock_synchronized() is not False)
            own = grid.replace(
                robot=self.me,
                version=self.store.next_own_version(self.wall()),
                stamp=grid.stamp or time.time(),
            )
            self.own = own
            self._pending = own  # latest wins: an unsaved older version is simply replaced
            self.sinks.robot_map(own)
            self._wake.set()
            self.fusion.submit(own)
        self.source_finished = True
        log.info("source finished; still serving peers")

    def _skip(self, why: str, fix: str) -> None:
        """The source's newest map cannot be taken: neither shared nor fused, so the robot's map
        as its peers and global map see it stops at the last one taken. Said once while its maps
        keep being skipped (one a period, all day, said nothing new), and shown in ``mapd status``."""
        if self.skipped is None:
            log.warning("source map skipped: %s; this robot's map is not shared until one fits: %s", why, fix)
        self.skipped = why
        self.skipped_maps += 1

    async def _clock_for_a_new_state(self) -> None:
        """Before the first own version of a new (or lost) state directory, whose versions start
        from the wall clock (:mod:`mapd.daemon.versions`): wait up to ``clock_wait_s`` for the
        kernel to say the clock is synchronized, and say it when it is not.

        A clock behind (a board without a battery-backed clock boots at its image's date, before
        NTP sets it) made every version of the robot older than those of its lost state, which its
        peers still hold: each of its maps was refused, for good. Once is enough: the state has an
        own version after this.
        """
        if self.clock_synchronized() is not False:
            return  # synchronized, or the kernel cannot be asked (not Linux)
        if self.clock_wait_s > 0:
            log.info(
                "the wall clock is not synchronized: waiting up to %g s for it before the first map "
                "of this new state (its versions start from the clock)",
                self.clock_wait_s,
            )
            end = time.monotonic() + self.clock_wait_s
            while time.monotonic() < end:
                await asyncio.sleep(min(1.0, max(0.0, end - time.monotonic())))
                if self.clock_synchronized() is not False:
                    log.info("the wall clock is synchronized: the first map goes out")
                    return
        log.warning(
            "the wall clock is not synchronized%s; this new state's versions start from it: if it is "
            "behind, peers holding maps of this robot from before refuse its new ones (they say so). "
            "Once a time service (chrony, NTP) synchronizes it or steps it ahead, the versions begin "
            "again from it by themselves: no restart, and keep the state directory",
            f" after {self.clock_wait_s:g} s" if self.clock_wait_s > 0 else "",
        )

    def _versions_to_begin_again(self) -> bool:
        """Whether this state's versions may have begun from a clock behind, which is right now:
        below those of the lost state its peers hold, every map would be refused. Said; they then
        begin again from the clock (a new incarnation, newer than anything before: versions only
        rise; it costs each peer a whole map). Two signs, as the kernel or this process can tell:

        * the wall clock stepped ahead (more than :data:`STEP_AHEAD_S`) since this process began
          the state's versions from it (NTP set it since);
        * they began from a clock the kernel did not say was synchronized (saved in the state, so
          a restart between the two still tells), and now it says it is.
        """
        if self._began is not None:
            wall0, mono0 = self._began
            ahead = (self.wall() - wall0) - (time.monotonic() - mono0)
            if ahead > STEP_AHEAD_S:
                log.warning(
                    "the wall clock stepped %.0f s ahead since this new state's versions began from it: "
                    "they begin again from the clock, so peers holding maps of this robot from before "
                    "take them",
                    ahead,
                )
                return True
        if self.store.began_unsynchronized() and self.clock_synchronized() is True:
            log.warning(
                "this state's versions began from a clock that was not synchronized, and now it is: "
                "they begin again from it, so peers holding maps of this robot from before take them"
            )
            return True
        return False

    def _local_peer_map(self, source: MapSource, grid: OccupancyGrid) -> None:
        """A map of another robot from this daemon's source (a map_merge drop-in): fused and
        recorded, placed by the source's known pose of that robot if any; neither sent nor kept."""
        if self.fleet_robot(grid.robot):
            # Fused under the fleet robot's name, its map and this one took turns in the global map.
            if grid.robot not in self._refused:
                self._refused.add(grid.robot)
                log.warning(
                    "map of %s from the source skipped: %s is a fleet robot's name, whose own maps count",
                    grid.robot,
                    grid.robot,
                )
            return
        if grid.cells > self.max_cells:
            log.warning(
                "map of %s from the source (%d cells) is over the limit; skipped", grid.robot, grid.cells
            )
            return
        problem = encode_problem(grid)
        if problem is not None:  # as for its own maps: a resolution of 1e-30 froze the global map
            log.warning("map of %s from the source skipped: %s", grid.robot, problem)
            return
        pose = source.robot_poses().get(grid.robot)
        if pose is not None:
            self.fusion.known_pose(grid.robot, pose)
        self.fusion.submit(grid)
        self.sinks.robot_map(grid)

    async def run(self) -> None:
        """The publisher core's adapter: save new versions, ask what to code, code it in a worker, offer it.

        A version is coded only when some transport can send it now (rule P1): a busy transport
        takes the newest version when its current one settles or times out, so the delta is taken
        against the base acked *by then* (on the 12.5 kb/s link the first keyframe takes seconds).
        """
        core = self.publisher
        while True:
            deadline = core.next_deadline()
            if self._unsaved is not None:
                deadline = self._retry_at if deadline is None else min(deadline, self._retry_at)
            timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), timeout)
            self._wake.clear()
            grid, self._pending = self._pending, None
            if grid is None and self._unsaved is not None and time.monotonic() >= self._retry_at:
                grid = self._unsaved  # no newer version came: the one that failed, again
            if grid is not None:
                try:
                    await asyncio.to_thread(self.store.save_own, grid)
                except StateError as exc:
                    # A full disk: the version is not sent unsaved (after a restart its number could
                    # come again), and the robot runs on; it is tried again every WRITE_RETRY_S, and
                    # a newer version replaces it.
                    self._saves.failed(f"{exc}; new versions are not sent until one is saved")
                    self._unsaved, self._retry_at = grid, time.monotonic() + WRITE_RETRY_S
                else:
                    self._saves.recovered("own map saved again")
                    self._unsaved = None
                    self.saved = grid
                    core.new_version(grid)
            job = core.poll(time.monotonic(), self.peers())
            if job is None:
                continue  # every transport is busy or has it: they take the newest when they settle
            try:
                env = await asyncio.to_thread(self.coder.envelope, job.grid, job.base)
            except MapdError as exc:  # one unsendable version must not stop the robot publishing
                log.error("cannot code v%d: %s", job.grid.version, exc)
                continue
            for name in core.encoded(job, env, time.monotonic(), self.peers()):
                transport = self.transport(name)
                if transport is not None:
                    transport.offer(env)
                    self._hold(name, transport, env)
            if self._pending is not None:
                self._wake.set()  # a newer version came while coding

    def _hold(self, name: str, transport: Transport, env: Envelope) -> None:
        """A link that says how long it may take over ``env`` before it gives it up (uwb: its
        deadline for a map of that size, ``offer_deadline_s``) keeps the offer that long (P1):
        a large map is not superseded half sent."""
        seconds = transport.offer_deadline_s(env)
        if seconds is not None:
            self.publisher.hold(name, env.version, time.monotonic() + seconds)

    def latest_keyframe(self) -> Envelope | None:
        """The newest own map saved, as a keyframe, for late joiners.

        Called by transports from worker threads (a zenoh query is answered on its job thread): it
        may encode, so it must never run on the event loop. One encode per version however many
        queries wait; the publisher's own keyframes are reused.
        """
        own = self.saved
        if own is None:
            return None
        with self._kf_lock:
            cached = self.publisher.cached_keyframe(own.version)
            if cached is not None:
                return cached
            env = self.coder.envelope(own, None)
            self.publisher.remember_keyframe(env)
            return env


__all__ = ["Outbound"]
