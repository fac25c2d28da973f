"""``mapd run``: start-up, the running daemon, and graceful shutdown (as uvicorn's ``Server.serve``).

One update's way through the robot::

    source --grid--> save (worker) --> PublisherCore.poll: what to code, against which base, for
        which free links --> encode + sign (worker) --> offer to those transports (latest wins inside)
    transport --Received--> EventQueue --> verify (worker) --> Receiver.plan --> decode (worker)
        --> Receiver.accept --> save (worker), fusion worker, ack

The decisions live in sans-I/O cores (:mod:`~mapd.daemon.publisher`, :mod:`~mapd.daemon.receiver`);
their asyncio adapters are :mod:`~mapd.daemon.outbound` (own maps out) and
:mod:`~mapd.daemon.inbound` (transport events in), and this module starts them, with the
transports, fusion and outputs, and stops them (:mod:`~mapd.daemon.restore` reads what a previous
run left first; :mod:`~mapd.daemon.process` is the process around it: signals and the loop). The event loop only moves bytes and decisions:
encode, decode, verify, merge and file writes run in worker threads, so a large map never stalls
the links, timers or ``mapd status``. Every queue is bounded and latest-wins where order does not
matter.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Coroutine
from typing import TYPE_CHECKING, Any, TypeVar

from pydantic import BaseModel

from mapd import config as configmod
from mapd import plugins
from mapd.codec import get_codec
from mapd.codec.base import CodecOptions
from mapd.daemon.coding import Coder, CsvLog
from mapd.daemon.events import EventQueue
from mapd.daemon.headline import status_line
from mapd.daemon.inbound import Inbound
from mapd.daemon.outbound import Outbound
from mapd.daemon.poses import PoseRelay
from mapd.daemon.publisher import PublisherCore
from mapd.daemon.receiver import Receiver
from mapd.daemon.reload import Reloads
from mapd.daemon.reload import read as read_reload
from mapd.daemon.restore import SavedState, read_saved_state
from mapd.daemon.revocation import Revocation
from mapd.daemon.sinks import Sinks, placed_frames
from mapd.daemon.snapshot import snapshot
from mapd.daemon.state import StateStore, lock_state_dir
from mapd.daemon.status_socket import StatusServer
from mapd.daemon.systemd import notify, watchdog_interval
from mapd.daemon.versions import VersionBounds
from mapd.errors import MapdError, StateError
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid
from mapd.outputs.base import Output, OutputContext
from mapd.record.writer import Recorder
from mapd.sources.base import MapSource, SourceContext, SourceOptions
from transports.base import (
    Transport,
    TransportContext,
)

if TYPE_CHECKING:
    from mapd.view.live import LiveView

log = logging.getLogger("mapd.daemon")
EVENT_QUEUE = 256
#: seconds between looks at whether the systemd Status line changed
STATUS_PERIOD_S = 2.0
M = TypeVar("M", bound=BaseModel)


class Daemon:
    """One robot's mapd. Construct with a validated config, then ``await run()``.

    ``source`` replaces the configured source plugin (tests and embedding).
    """

    def __init__(
        self, cfg: configmod.MapdConfig, *, shutdown_timeout: float = 5.0, source: MapSource | None = None
    ) -> None:
        self.cfg = cfg
        self.me = cfg.robot.name
        self.shutdown_timeout = shutdown_timeout
        checked = configmod.check(cfg)  # what check-config checks, no more and no less
        self.options = checked.options
        self.keys = checked.keys
        self.store = StateStore(cfg.state.dir, max_cells=cfg.limits.max_cells)
        self.started = time.time()
        self.source = source
        self.transports: list[Transport] = []
        self._stop = asyncio.Event()
        self._status_said = "running"  # the Status line systemd was last told
        self._reload = asyncio.Event()  # SIGHUP: read the config again (systemctl reload)
        self.reloads = Reloads(cfg)
        self._stopping_at: float | None = None
        self.events = EventQueue(EVENT_QUEUE, max_peers=EVENT_QUEUE)
        codec_opts = self.options["codec"].get(cfg.codec.use)
        options = codec_opts if isinstance(codec_opts, CodecOptions) else None
        codec = get_codec(cfg.codec.use, options)
        self.publisher = PublisherCore(uses_base=codec.uses_base, keyframe_every=cfg.codec.keyframe_every)
        lim = cfg.limits
        self.receiver = Receiver(
            self.me,
            cfg.robot.fleet,
            roster=self.keys.roster,
            bounds=VersionBounds(max_jump=lim.max_version_jump, max_rate=lim.max_version_rate),
            max_peers=lim.max_peers,
            max_cells=lim.max_cells,
            max_growth=lim.max_growth,
        )
        self.coder = Coder(
            robot=self.me,
            fleet=cfg.robot.fleet,
            codec=cfg.codec.use,
            options=options,
            lossless=codec.lossless,
            measure_quality=cfg.codec.measure_quality,
            identity=self.keys.identity,
            max_cells=cfg.limits.max_cells,
            store=self.store,
            log=CsvLog(cfg.state.dir / "updates.csv"),
        )
        self.fusion = FusionWorker(
            self.me,
            cfg.fusion,
            cfg.state.dir / "global",
            on_global=[self._on_global],
            max_cells=cfg.limits.max_cells,
            max_robots=cfg.limits.max_peers + 1,  # the peers and this robot
            # a base station has no map frame of its own: the anchor, or the first robot heard
            anchor=cfg.fusion.anchor or (self.me if self._own_map_source() else None),
            admits=self.keys.roster.admits,
            key_of=self._key_of,
        )
        self.status_server = StatusServer(cfg.control_socket(), self.snapshot)
        #: The state directory's lock (lock_state_dir), taken as the state is loaded.
        self._state_lock: int | None = None
        #: Whether the state directory was read whole: only then does the shutdown write state.json
        #: (a restore that failed has nothing to save, and must not write an empty state over one).
        self._state_read = False
        self.outputs: list[Output] = []
        # Outputs, the MCAP recording and fused.csv, each on a worker thread, never on the loop.
        rec = cfg.record
        recorder = (
            Recorder(
                rec.path,
                max_bytes=rec.max_bytes,
                max_total_bytes=rec.max_total_bytes,
                min_free_bytes=rec.min_free_bytes,
            )
            if rec.path
            else None
        )
        self.sinks = Sinks(self.outputs, recorder, CsvLog(cfg.state.dir / "fused.csv"))
        self.poses = PoseRelay(
            self.me,
            cfg.robot.fleet,
            identity=self.keys.identity,
            roster=self.keys.roster,
            max_robots=cfg.limits.max_peers + 1,
            frames=lambda: placed_frames(self.fusion.placements),
            publish=self.sinks.poses,
        )
        self.outbound = Outbound(
            me=self.me,
            max_cells=lim.max_cells,
            publisher=self.publisher,
            coder=self.coder,
            store=self.store,
            fusion=self.fusion,
            sinks=self.sinks,
            transport=lambda name: self.inbound.transport(name),
            peers=lambda: {t.name: t.peers() for t in self.transports},
            fleet_robot=lambda r: r in self.keys.roster.robots or r in self.receiver.maps,
            clock_wait_s=cfg.state.clock_wait_s,
        )
        self.inbound = Inbound(
            me=self.me,
            events=self.events,
            transports=self.transports,  # the same list: filled once the transports start
            publisher=self.publisher,
            receiver=self.receiver,
            store=self.store,
            fusion=self.fusion,
            sinks=self.sinks,
            poses=self.poses,
            roster=self.keys.roster,
            max_message_bytes=lim.max_message_bytes,
            max_cells=lim.max_cells,
            wake=self.outbound.wake,
            key_of=self._key_of,
            codec_options=(cfg.codec.use, self.coder.options),
        )
        self.revocation = Revocation(
            self.receiver, self.fusion, self.poses, self.inbound, self.transports, self.store
        )
        # The live web view ([view] listen): an output like the others, plus the status dict.
        self.view: LiveView | None = None
        if cfg.view.listen is not None:
            from mapd.view.live import LiveView  # aiohttp is imported only when the view is on

            ctx = OutputContext(robot=self.me, fleet=cfg.robot.fleet, state_dir=cfg.state.dir)
            self.view = LiveView(cfg.view, ctx, token=checked.view_token, snapshot=self.snapshot)
            self.sinks.map_watchers.append(self.view.robot_map)

    def _key_of(self, robot: str) -> str | None:
        """``robot``'s public key in the roster now (as the config gives it), or None."""
        return self.reloads.config.fleet.roster.get(robot)

    @property
    def own(self) -> OccupancyGrid | None:
        """This robot's newest map version, or None before the first."""
        return self.outbound.own

    def _own_map_source(self) -> bool:
        """Whether the source yields this robot's own map (not ``none``, nor only other robots' maps)."""
        if self.cfg.source.use == "none":
            return False
        opts = self.options["source"].get(self.cfg.source.use)
        return not isinstance(opts, SourceOptions) or opts.yields_own_map

    # ------------------------------------------------------------------ lifecycle
    def request_stop(self) -> None:
        self._stop.set()

    def request_reload(self) -> None:
        """SIGHUP: read the config again and take its roster (:mod:`mapd.daemon.reload`)."""
        self._reload.set()

    async def reload(self) -> bool:
        """Read the config file again (on a worker) and apply its roster; False when refused."""
        notify(f"RELOADING=1\nMONOTONIC_USEC={time.monotonic_ns() // 1000}")
        try:
            token = self.view.token if self.view is not None else None
            new, keys, plan = await asyncio.to_thread(read_reload, self.reloads.config, self.keys, token)
        except MapdError as exc:
            log.error("reload %s", self.reloads.failed(str(exc)))
            ok = False
        except Exception as exc:  # a bug in reading it must not take the running daemon down
            log.error("reload %s", self.reloads.failed(f"{type(exc).__name__}: {exc}"))
            ok = False
        else:
            self.keys.roster.adopt(keys.roster)
            if self.view is not None:  # checked per request: a rotated token is in force at once
                self.view.set_token(plan.view_token)
            # A robot given a new key is revoked as one removed is: what its old key signed goes
            # (a key is replaced because it leaked), with a version from the future it may have
            # signed to lock the real robot out. Its new key's maps are taken from the next on.
            revoked = [r for r in plan.removed if not self.keys.roster.admits(r)] + plan.rekeyed
            revoked = [r for r in revoked if r != self.me]
            for robot in revoked:
                self.revocation.revoke(robot, rekeyed=robot in plan.rekeyed)
            said = self.reloads.applied(new, plan)
            (log.warning if plan.restart else log.info)("reloaded: %s", said)
            for robot in revoked:  # its files too (a worker: the disk may be slow)
                await self.revocation.remove_saved(robot)
            # A robot just admitted (or re-keyed) had its maps refused so far: ask for its newest
            # now rather than wait for its next offer to time out.
            for robot in plan.added + plan.rekeyed:
                for t in self.transports:
                    await t.request_keyframe(robot)
            ok = True
        # READY=1 ends RELOADING=1; the Status line goes with it (not "running": the loop below
        # says a line again only when it changes, so a steady robot's FAULTS would vanish)
        notify(f"READY=1\nSTATUS={self._status_now()}")
        return ok

    async def _reload_loop(self) -> None:
        while True:
            await self._reload.wait()
            self._reload.clear()  # signals during a reload fold into one more
            await self.reload()

    async def run(self) -> None:
        """Start everything, run until asked to stop, then shut down within the timeout.

        A stop asked for during start-up (``systemctl stop`` of a start that takes long: a source
        building its world, a transport opening) ends the start-up there, without READY=1.
        """
        try:
            # In the try: a restore that fails after taking the state directory's lock (a file
            # where a folder goes) held it for the rest of the process, so a daemon started again
            # in it (an embedding, a test) found the directory "in use" by itself.
            await self._restore()
            if not await self._unless_stopped(self._start()):
                return
            notify(f"READY=1\nSTATUS={self._status_now()}")
            log.info(
                "mapd started",
                extra={"fields": {"robot": self.me, "transports": ",".join(self.cfg.transports.use)}},
            )
            try:
                await self._run_tasks()
            except* MapdError as group:
                raise group.exceptions[0] from None
        finally:
            await self._shutdown()

    async def _unless_stopped(self, job: Coroutine[Any, Any, None]) -> bool:
        """Run ``job`` unless a stop comes first, which cancels it: True when it finished."""
        task = asyncio.ensure_future(job)
        stop = asyncio.ensure_future(self._stop.wait())
        cut = True
        try:
            await asyncio.wait({task, stop}, return_when=asyncio.FIRST_COMPLETED)
            cut = not task.done()
        finally:
            stop.cancel()
            if not task.done():
                # A stop came first, or run() itself was cancelled: either way the start-up must
                # not go on starting transports and the control socket after the shutdown that
                # follows has closed them.
                task.cancel()
                await asyncio.wait({task})
        if not cut:
            task.result()  # its error, if it failed
            return True
        if not task.cancelled():
            task.exception()  # (retrieved: what its cancellation raised is not news now)
        self._stopping_at = time.monotonic()
        notify("STOPPING=1")
        log.info("stopping during start-up")
        return False

    async def _start(self) -> None:
        """Make the source, transports and outputs and start them, and the control socket."""
        if self.source is None:
            source_cls = plugins.load("source", self.cfg.source.use)
            self.source = source_cls(
                self._options("source", self.cfg.source.use, source_cls.Options),
                SourceContext.of(self.cfg),  # as check-config's check_with_config finds its files
            )
        # Where this robot's map frame lies in the fleet frame, when the source knows (a simulated
        # or logged robot's start, or start_pose in its config): fused as a known pose here, and
        # sent with every map so peers can too. Reading it may build a world or read a log.
        start = await asyncio.to_thread(self.source.start_pose)
        if start is not None:
            self.coder.frame_pose = start
            self.fusion.known_pose(self.me, start)
        for name in self.cfg.transports.use:
            cls = plugins.load("transport", name)
            state_dir = self.cfg.state.dir / "links" / name
            try:  # (check-config refuses a file in the way; this is for one put there since)
                state_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise StateError(
                    f"state directory {self.cfg.state.dir} is not writable: {exc.strerror or exc}"
                ) from None
            ctx = TransportContext(
                robot=self.me,
                fleet=self.cfg.robot.fleet,
                identity=self.keys.identity,
                roster=self.keys.roster,
                link_key=self.keys.link_key,
                max_message_bytes=self.cfg.limits.max_message_bytes,
                emit=self.events.put,
                state_dir=state_dir,
                latest_keyframe=self.outbound.latest_keyframe,
            )
            self.transports.append(cls(self._options("transports", name, cls.Options), ctx))
            if cls.paced:
                self.publisher.paced.add(name)  # its offers are held until wholly on the air (P1)
        out_ctx = OutputContext(
            robot=self.me,
            fleet=self.cfg.robot.fleet,
            state_dir=self.cfg.state.dir,
            identity=self.keys.identity,
        )
        for name in self.cfg.output.use:
            out_cls = plugins.load("output", name)
            self.outputs.append(out_cls(self._options("output", name, out_cls.Options), out_ctx))
        if self.view is not None:
            self.outputs.append(self.view)
        for t in self.transports:
            await t.start()
        for o in self.outputs:
            await o.start()
        await self.status_server.start()
        if not self.keys.signed:
            log.warning(
                "fleet.allow_unsigned = true: unsigned messages are accepted, so anyone on the "
                "radio or the network can write as any robot"
            )

    def _options(self, section: str, name: str, model: type[M]) -> M | None:
        """A plugin's validated options (``check_plugins`` built them with ``model``)."""
        opts = self.options[section].get(name)
        return opts if isinstance(opts, model) else None

    async def _run_tasks(self) -> None:
        assert self.source is not None  # run() made it
        async with asyncio.TaskGroup() as tg:
            tasks = [
                tg.create_task(self.outbound.take_source(self.source), name="source"),
                tg.create_task(self.outbound.run(), name="publisher"),
                tg.create_task(self.inbound.run(), name="events"),
                tg.create_task(self.fusion.run(), name="fusion"),
                tg.create_task(self._watchdog(), name="watchdog"),
                tg.create_task(self._systemd_status(), name="systemd-status"),
                tg.create_task(self._record_links(), name="record"),
                tg.create_task(self.poses.run(self.source, self.transports), name="poses"),
                tg.create_task(self._reload_loop(), name="reload"),
            ]
            # A link whose loop died raises here, which stops the daemon with its line: systemd
            # restarts it (Restart=on-failure) instead of a robot that looks alive and sends nothing.
            tasks += [tg.create_task(t.watch(), name=f"transport-{t.name}") for t in self.transports]
            await self._stop.wait()
            self._stopping_at = time.monotonic()
            notify("STOPPING=1")
            log.info("stopping")
            for task in tasks:
                task.cancel()

    async def _shutdown(self) -> None:
        async def close_all() -> None:
            for t in self.transports:
                with contextlib.suppress(Exception):
                    await t.close()
            for o in self.outputs:
                with contextlib.suppress(Exception):
                    await o.close()
            if self.source is not None:
                with contextlib.suppress(Exception):
                    await self.source.close()
            await self.status_server.close()

        t_tasks = time.monotonic()
        try:
            await asyncio.wait_for(close_all(), self.shutdown_timeout)
        except TimeoutError:
            log.warning("shutdown timed out after %.1f s", self.shutdown_timeout)
        t_closed = time.monotonic()
        await asyncio.to_thread(self.sinks.close)  # queued writes, then the recording's footer
        if self._state_read:
            with contextlib.suppress(MapdError, OSError):
                await asyncio.to_thread(self.store.flush)
        if self._state_lock is not None:  # state.json written: another daemon may take the directory
            os.close(self._state_lock)
            self._state_lock = None
        if self._stopping_at is not None:
            # How long a stop takes, and where: systemd's TimeoutStopSec must cover it.
            done = time.monotonic()
            log.info(
                "stopped",
                extra={
                    "fields": {
                        "seconds": round(done - self._stopping_at, 2),
                        "tasks_s": round(t_tasks - self._stopping_at, 2),
                        "transports_s": round(t_closed - t_tasks, 2),
                        "flush_s": round(done - t_closed, 2),
                    }
                },
            )

    def _load_state(self) -> SavedState:
        """Take the state directory and read what a previous run left (blocking: a worker thread)."""
        self._state_lock = lock_state_dir(self.cfg.state.dir)  # (held until the process exits)
        saved = read_saved_state(self.store, self.me, self.keys.roster, self._key_of)
        self._state_read = True
        return saved

    async def _restore(self) -> None:
        """Resume from the state directory: own version, bases, and every peer's last map."""
        saved_state = await asyncio.to_thread(self._load_state)
        own, base = saved_state.own, saved_state.base
        if own is not None:
            own = self.outbound.own = self.outbound.saved = own.replace(robot=self.me)
            self.fusion.submit(own)
        self.publisher.restore(own, base, self.store.acked())
        now = time.time()
        for saved in saved_state.peers:
            self.receiver.restore(saved.grid, held_at=saved.saved_at, now=now)
            # As a live map with a pose goes (Inbound): else a peer placed by the start pose it
            # reported was searched for after a restart, and left out if its map overlaps none.
            if saved.frame_pose is not None:
                self.fusion.known_pose(saved.grid.robot, saved.frame_pose)
            self.fusion.submit(saved.grid)
        if self.store.data.own_version:
            log.info(
                "resumed from state",
                extra={
                    "fields": {
                        "own_version": self.store.data.own_version,
                        "peers": ",".join(self.receiver.maps) or "-",
                    }
                },
            )

    async def _watchdog(self) -> None:
        interval = watchdog_interval()
        if interval is None:
            return
        while True:
            notify("WATCHDOG=1")
            await asyncio.sleep(interval)

    async def _systemd_status(self) -> None:
        """Keep the Status line of ``systemctl status mapd`` current (sd_notify STATUS=): the map,
        the peers', the global map and any fault, said again only when it changes."""
        if not os.environ.get("NOTIFY_SOCKET"):
            return
        while True:
            await asyncio.sleep(STATUS_PERIOD_S)
            said = self._status_said
            line = self._status_now()
            if line != said:
                notify(f"STATUS={line}")

    def _status_now(self) -> str:
        """The Status line for systemd now (remembered as said: every caller sends it)."""
        try:
            line = status_line(self.snapshot())
        except Exception:  # a status bug must never take the daemon down (as on the socket)
            log.exception("status line failed")
            line = self._status_said
        self._status_said = line
        return line

    def _on_global(self, grid: OccupancyGrid) -> None:
        """The fusion worker made a new global map: outputs, recording and fused.csv take it."""
        self.sinks.global_map(grid, self.fusion.placements, self.fusion.status().get("robots", {}))

    async def _record_links(self) -> None:
        if self.sinks.recorder is None:
            return
        while True:
            await asyncio.sleep(self.cfg.record.stats_every_s)
            self.sinks.links({t.name: {**t.stats(), "peers": t.peers()} for t in self.transports})

    # ------------------------------------------------------------------ status
    def snapshot(self) -> dict[str, Any]:
        """Everything ``mapd status`` shows, as JSON-able data (:mod:`~mapd.daemon.snapshot`)."""
        return snapshot(self)
