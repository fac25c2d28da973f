"""``mapd run``: start-up, the running daemon, and graceful shutdown (as uvicorn's ``Server.serve``).

One update's way through the robot::

    source --grid--> save (worker) --> PublisherCore.poll: what to code, against which base, for
        which free links --> encode + sign (worker) --> offer to those transports (latest wins inside)
    transport --Received--> EventQueue --> verify (worker) --> Receiver.plan --> decode (worker)
        --> Receiver.accept --> save (worker), fusion worker, ack

The decisions live in sans-I/O cores (:mod:`~mapd.daemon.publisher`, :mod:`~mapd.daemon.receiver`);
their asyncio adapters are :mod:`~mapd.daemon.outbound` (own maps out) and
:mod:`~mapd.daemon.inbound` (transport events in), and this module starts them, with the
transports, fusion and outputs, and stops them. Around it: :mod:`~mapd.daemon.restore` reads what a
previous run left first, :mod:`~mapd.daemon.parts` makes the plugins the config names,
:mod:`~mapd.daemon.notifier` tells systemd, :mod:`~mapd.daemon.shutdown` closes everything in time,
and :mod:`~mapd.daemon.process` is the process around it: signals and the loop. The event loop only
moves bytes and decisions: encode, decode, verify, merge and file writes run in worker threads, so
a large map never stalls the links, timers or ``mapd status``. Every queue is bounded and
latest-wins where order does not matter.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from typing import TYPE_CHECKING, Any

from mapd import config as configmod
from mapd.codec import get_codec
from mapd.codec.base import CodecOptions
from mapd.daemon.coding import Coder, CsvLog
from mapd.daemon.events import EventQueue
from mapd.daemon.inbound import Inbound
from mapd.daemon.loop_lag import LagMeter, watch
from mapd.daemon.notifier import Notifier
from mapd.daemon.outbound import Outbound
from mapd.daemon.parts import make_output, make_source, make_transport, output_context
from mapd.daemon.poses import PoseRelay
from mapd.daemon.publisher import PublisherCore
from mapd.daemon.receiver import Receiver
from mapd.daemon.reload import Reloads
from mapd.daemon.reload import read as read_reload
from mapd.daemon.restore import SavedState, read_saved_state
from mapd.daemon.revocation import Revocation
from mapd.daemon.shutdown import close_all, log_stopped, unless_stopped
from mapd.daemon.sinks import Sinks, placed_frames
from mapd.daemon.snapshot import snapshot
from mapd.daemon.state import StateStore
from mapd.daemon.state_lock import lock_state_dir
from mapd.daemon.status_socket import StatusServer
from mapd.daemon.versions import VersionBounds, label
from mapd.errors import MapdError
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid
from mapd.outputs.base import Output, OutputContext
from mapd.record.writer import Recorder
from mapd.sources.base import MapSource, SourceOptions
from transports.base import Transport

if TYPE_CHECKING:
    from mapd.view.live import LiveView

log = logging.getLogger("mapd.daemon")
EVENT_QUEUE = 256


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
        # What systemd is told; the snapshot looked up at each line (a test replaces it).
        self.notifier = Notifier(lambda: self.snapshot())
        self.loop_lag = LagMeter()  # how late the event loop runs (mapd status: loop)
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
        self.notifier.reloading()
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
        self.notifier.ready()  # (ends RELOADING=1, with the Status line now)
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
            if not await unless_stopped(self._start(), self._stop):
                self._begin_stop("stopping during start-up")
                return
            self.notifier.ready()
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

    def _begin_stop(self, said: str) -> None:
        """A stop begins (the shutdown's timings count from here): systemd and the log are told."""
        self._stopping_at = time.monotonic()
        self.notifier.stopping()
        log.info(said)

    async def _start(self) -> None:
        """Make the source, transports and outputs and start them, and the control socket."""
        if self.source is None:
            self.source = make_source(self.cfg, self.options)
        # Where this robot's map frame lies in the fleet frame, when the source knows (a simulated
        # or logged robot's start, or start_pose in its config): fused as a known pose here, and
        # sent with every map so peers can too. Reading it may build a world or read a log.
        start = await asyncio.to_thread(self.source.start_pose)
        if start is not None:
            self.coder.frame_pose = start
            self.fusion.known_pose(self.me, start)
        for name in self.cfg.transports.use:
            latest = self.outbound.latest_keyframe
            t = make_transport(
                self.cfg, name, self.options, self.keys, emit=self.events.put, latest_keyframe=latest
            )
            self.transports.append(t)
            for robot, held in self.receiver.maps.items():
                t.restored(robot, held.version)  # (peers' maps from the state directory)
            if t.paced:
                self.publisher.paced.add(name)  # its offers are held until wholly on the air (P1)
        out_ctx = output_context(self.cfg, self.keys)
        for name in self.cfg.output.use:
            self.outputs.append(make_output(name, self.options, out_ctx))
        if self.view is not None:
            self.outputs.append(self.view)
        for t in self.transports:
            await t.start()
        for o in self.outputs:
            await o.start()
        # The maps the state directory held go to the outputs (and the recording) now, as every map
        # taken later does: a restarted base station's /<robot>/map waited for each robot's next map.
        for grid in [
            *([self.outbound.own] if self.outbound.own is not None else []),
            *self.receiver.maps.values(),
        ]:
            self.sinks.robot_map(grid)
        await self.status_server.start()
        if not self.keys.signed:
            log.warning(
                "fleet.allow_unsigned = true: unsigned messages are accepted, so anyone on the "
                "radio or the network can write as any robot"
            )

    async def _run_tasks(self) -> None:
        assert self.source is not None  # run() made it
        async with asyncio.TaskGroup() as tg:
            tasks = [
                tg.create_task(self.outbound.take_source(self.source), name="source"),
                tg.create_task(self.outbound.run(), name="publisher"),
                tg.create_task(self.inbound.run(), name="events"),
                tg.create_task(self.fusion.run(), name="fusion"),
                tg.create_task(self.notifier.watchdog(), name="watchdog"),
                tg.create_task(self._systemd_status(), name="systemd-status"),
                tg.create_task(self._record_links(), name="record"),
                tg.create_task(self.poses.run(self.source, self.transports), name="poses"),
                tg.create_task(self._reload_loop(), name="reload"),
                tg.create_task(watch(self.loop_lag), name="loop-lag"),
            ]
            # A link whose loop died raises here, which stops the daemon with its line: systemd
            # restarts it (Restart=on-failure) instead of a robot that looks alive and sends nothing.
            tasks += [tg.create_task(t.watch(), name=f"transport-{t.name}") for t in self.transports]
            await self._stop.wait()
            self._begin_stop("stopping")
            for task in tasks:
                task.cancel()

    async def _shutdown(self) -> None:
        t_tasks = time.monotonic()
        await close_all(self.transports, self.outputs, self.source, self.status_server, self.shutdown_timeout)
        t_closed = time.monotonic()
        await asyncio.to_thread(self.sinks.close)  # queued writes, then the recording's footer
        if self._state_read:
            with contextlib.suppress(MapdError, OSError):
                await asyncio.to_thread(self.store.flush)
        if self._state_lock is not None:  # state.json written: another daemon may take the directory
            os.close(self._state_lock)
            self._state_lock = None
        self.store.release()  # (a lock taken again after the directory was lost and came back)
        if self._stopping_at is not None:
            log_stopped(self._stopping_at, t_tasks, t_closed)

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
                        "own_version": label(self.store.data.own_version),
                        "peers": ",".join(self.receiver.maps) or "-",
                    }
                },
            )

    async def _systemd_status(self) -> None:
        """Keep the Status line of ``systemctl status mapd`` current (:meth:`Notifier.keep_status`)."""
        await self.notifier.keep_status()

    def _on_global(self, grid: OccupancyGrid) -> None:
        """The fusion worker made a new global map: outputs, recording and fused.csv take it."""
        self.sinks.global_map(grid, self.fusion.placements, self.fusion.status().get("robots", {}))

    async def _record_links(self) -> None:
        if self.sinks.recorder is None:
            return
        while True:
            await asyncio.sleep(self.cfg.record.stats_every_s)
            self.sinks.links(
                {t.name: {**t.stats(), "peers": t.peers()} for t in self.transports}, self.cfg.robot.name
            )

    # ------------------------------------------------------------------ status
    def snapshot(self) -> dict[str, Any]:
        """Everything ``mapd status`` shows, as JSON-able data (:mod:`~mapd.daemon.snapshot`)."""
        return snapshot(self)
