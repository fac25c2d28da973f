"""``mapd run``: start-up, the running daemon, and graceful shutdown, in one place.

One update's way through the robot::

    source --grid--> publish slot --encode(base = newest version every peer acked)--> Envelope
                                       --offer--> every transport (latest wins inside each)
    transport --Received--> events queue --verify, decode against the held base--> fusion worker

Every queue is bounded and latest-wins where order does not matter: a new own version replaces
an unsent older one, a full event queue drops (and counts) rather than grow. Blocking work
(encode, decode, state writes) runs in threads so the loop keeps serving status and timers.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import logging
import os
import signal
import threading
import time
from typing import Any

from mapd import config as configmod
from mapd import plugins
from mapd.codec import decode, encode, get_codec, read_header
from mapd.codec.base import CodecOptions
from mapd.codec.metrics import psnr, ssim
from mapd.daemon.events import EventQueue
from mapd.daemon.state import StateStore
from mapd.daemon.status_socket import StatusServer
from mapd.daemon.systemd import notify, watchdog_interval
from mapd.envelope import Envelope, unpack
from mapd.errors import CodecError, EnvelopeError, MapdError, StateError
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid
from mapd.sources.base import MapSource, SourceContext
from transports.base import (
    Delivered,
    Failed,
    KeyframeNeeded,
    PeerDown,
    PeerRestarted,
    PeerUp,
    Received,
    Transport,
    TransportContext,
    TransportEvent,
)

log = logging.getLogger("mapd.daemon.server")
EVENT_QUEUE = 256
KEEP_VERSIONS = 16
#: Recent versions of each peer's map kept in memory: a delta may be coded against a version the
#: sender saw acked while newer ones were still in flight.
KEEP_PEER_VERSIONS = 8
#: A transport gets the next version only when the previous one is acked by every peer, failed,
#: or older than this. Superseding a half-sent map with every new version starves a slow link.
INFLIGHT_TIMEOUT_S = 30.0


class Daemon:
    """One robot's mapd. Construct with a validated config, then ``await run()``."""

    def __init__(self, cfg: configmod.MapdConfig, *, shutdown_timeout: float = 5.0) -> None:
        self.cfg = cfg
        self.me = cfg.robot.name
        self.shutdown_timeout = shutdown_timeout
        self.options = configmod.check_plugins(cfg, all_tables=False)
        self.key = configmod.read_key(cfg)
        self.store = StateStore(cfg.state.dir, max_cells=cfg.limits.max_cells)
        self.started = time.time()
        self._stop = asyncio.Event()
        self._stopping_at: float | None = None
        self._publish = asyncio.Event()
        self._pending: OccupancyGrid | None = None
        self._events = EventQueue(EVENT_QUEUE, max_peers=EVENT_QUEUE)
        self._sent: dict[int, OccupancyGrid] = {}  # recent own versions, for delta bases
        self._kf_lock = threading.Lock()
        self._kf_cache: Envelope | None = None
        self.own: OccupancyGrid | None = None
        self.source_finished = False
        self.peer_maps: dict[str, OccupancyGrid] = {}
        self.peer_history: dict[str, dict[int, OccupancyGrid]] = {}
        self.peer_info: dict[str, dict[str, Any]] = {}
        self.since_keyframe = 0
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "bad_envelopes",
                "foreign_fleet",
                "bad_signature",
                "duplicates",
                "decode_errors",
                "keyframe_requests",
                "keyframes_sent",
                "deltas_sent",
                "updates_received",
            ),
            0,
        )
        self.codec_stats: dict[str, Any] = {"name": cfg.codec.use}
        self.transports: list[Transport] = []
        self._inflight: dict[str, tuple[int, float, set[str]]] = {}  # transport -> (version, since, unacked)
        self._offered: dict[str, int] = {}  # transport -> newest own version it was given
        self._latest: OccupancyGrid | None = None  # newest own version saved, coded or not
        self.source: MapSource | None = None
        codec_opts = self.options["codec"].get(cfg.codec.use)
        self.codec_options = codec_opts if isinstance(codec_opts, CodecOptions) else None
        self.codec = get_codec(cfg.codec.use, self.codec_options)
        self.fusion = FusionWorker(
            self.me,
            cfg.fusion,
            cfg.state.dir / "global",
            on_global=[self._on_global],
            max_cells=cfg.limits.max_cells,
        )
        self._fused_csv = cfg.state.dir / "fused.csv"
        self.control = StatusServer(cfg.control_socket(), self.snapshot)
        self._updates_csv = cfg.state.dir / "updates.csv"

    # ------------------------------------------------------------------ lifecycle
    def request_stop(self) -> None:
        self._stop.set()

    async def run(self) -> None:
        """Start everything, run until asked to stop, then shut down within the timeout."""
        await asyncio.to_thread(self.store.open)
        self._restore()
        source_cls = plugins.load("source", self.cfg.source.use)
        self.source = source_cls(
            self.options["source"].get(self.cfg.source.use),
            SourceContext(robot=self.me, max_cells=self.cfg.limits.max_cells),
        )
        for name in self.cfg.transports.use:
            cls = plugins.load("transport", name)
            ctx = TransportContext(
                robot=self.me,
                fleet=self.cfg.robot.fleet,
                key=self.key,
                max_message_bytes=self.cfg.limits.max_message_bytes,
                emit=self._emit,
                state_dir=self.cfg.state.dir / "links" / name,
                latest_keyframe=self.latest_keyframe,
            )
            (self.cfg.state.dir / "links" / name).mkdir(parents=True, exist_ok=True)
            self.transports.append(cls(self.options["transports"].get(name), ctx))
        try:
            for t in self.transports:
                await t.start()
            await self.control.start()
            notify("READY=1\nSTATUS=running")
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

    async def _run_tasks(self) -> None:
        async with asyncio.TaskGroup() as tg:
            tasks = [
                tg.create_task(self._source_loop(), name="source"),
                tg.create_task(self._publisher(), name="publisher"),
                tg.create_task(self._event_loop(), name="events"),
                tg.create_task(self.fusion.run(), name="fusion"),
                tg.create_task(self._watchdog(), name="watchdog"),
            ]
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
            if self.source is not None:
                with contextlib.suppress(Exception):
                    await self.source.close()
            await self.control.close()

        t_tasks = time.monotonic()
        try:
            await asyncio.wait_for(close_all(), self.shutdown_timeout)
        except TimeoutError:
            log.warning("shutdown timed out after %.1f s", self.shutdown_timeout)
        t_closed = time.monotonic()
        with contextlib.suppress(MapdError, OSError):
            await asyncio.to_thread(self.store.flush)
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

    def _restore(self) -> None:
        """Resume from the state directory: own version, bases, and every peer's last map."""
        data = self.store.data
        base = self.store.base_map()
        if base is not None:
            self._sent[base.version] = base
        own = self.store.own_map()
        if own is not None:
            self.own = own.replace(robot=self.me)
            self._sent[own.version] = self.own
            self.fusion.submit(self.own)
        for robot in list(data.peers):
            grid = self.store.peer_map(robot)
            if grid is None:
                data.peers.pop(robot, None)
                continue
            self.peer_maps[robot] = grid
            self.peer_history[robot] = {grid.version: grid}
            self.fusion.submit(grid)
        if data.own_version:
            log.info(
                "resumed from state",
                extra={"fields": {"own_version": data.own_version, "peers": ",".join(self.peer_maps) or "-"}},
            )

    async def _watchdog(self) -> None:
        interval = watchdog_interval()
        if interval is None:
            return
        while True:
            notify("WATCHDOG=1")
            await asyncio.sleep(interval)

    # ------------------------------------------------------------------ own maps out
    async def _source_loop(self) -> None:
        assert self.source is not None
        async for grid in self.source.maps():
            if grid.cells > self.cfg.limits.max_cells:
                log.warning("source map of %d cells is over the limit; skipped", grid.cells)
                continue
            # Versions are the daemon's, so they keep increasing across restarts.
            self.store.data.own_version += 1
            own = grid.replace(
                robot=self.me, version=self.store.data.own_version, stamp=grid.stamp or time.time()
            )
            self.own = own
            self._pending = own  # latest wins: an unencoded older version is simply replaced
            self._publish.set()
            self.fusion.submit(own)
        self.source_finished = True
        log.info("source finished; still serving peers")

    def _target_peers(self) -> set[str]:
        peers: set[str] = set()
        for t in self.transports:
            peers.update(t.peers())
        return peers

    def _choose_base(self) -> OccupancyGrid | None:
        if not self.codec.uses_base or self.since_keyframe + 1 >= self.cfg.codec.keyframe_every:
            return None
        peers = self._target_peers()
        if not peers:
            return None
        acked = {self.store.data.acked.get(p, 0) for p in peers}
        if len(acked) != 1:
            return None  # peers hold different versions: only a keyframe suits them all
        return self._sent.get(acked.pop())

    async def _publisher(self) -> None:
        """Code the newest own version for every transport that is free to take it.

        A version is coded only when some transport can send it now: a busy transport takes the
        newest version when its current one settles (:meth:`_settled` wakes this loop). So a slow
        link neither queues stale maps nor makes the robot code versions that would be replaced
        unsent, and the delta is taken against the base acked *by then*, not the older one acked
        when the version was made (on the 12.5 kb/s link the first keyframe takes seconds).
        """
        while True:
            await self._publish.wait()
            self._publish.clear()
            grid, self._pending = self._pending, None
            if grid is not None:
                await asyncio.to_thread(self.store.save_own, grid)
                self._sent[grid.version] = grid
                for v in sorted(self._sent)[:-KEEP_VERSIONS]:
                    if self.store.data.base is None or v != self.store.data.base.version:
                        del self._sent[v]
                self._latest = grid
            latest = self._latest
            if latest is None:
                continue
            free = [
                t
                for t in self.transports
                if self._offered.get(t.name, 0) < latest.version and not self._busy(t.name)
            ]
            if not free:
                continue  # every transport is busy or has it: they take the newest when they settle
            base = self._choose_base()
            env = await asyncio.to_thread(self._make_envelope, latest, base)
            if env.is_keyframe:
                self.since_keyframe = 0
                self.counters["keyframes_sent"] += 1
                with self._kf_lock:
                    self._kf_cache = env
            else:
                self.since_keyframe += 1
                self.counters["deltas_sent"] += 1
            for t in free:
                self._offered[t.name] = env.version
                self._inflight[t.name] = (env.version, time.monotonic(), set(t.peers()))
                t.offer(env)
            if self._pending is not None:
                self._publish.set()  # a newer version came while coding

    def _busy(self, transport: str) -> bool:
        """An earlier version is still on its way on ``transport`` (and not yet given up on)."""
        busy = self._inflight.get(transport)
        return busy is not None and bool(busy[2]) and time.monotonic() - busy[1] < INFLIGHT_TIMEOUT_S

    def _settled(self, transport: str, peer: str, version: int) -> None:
        busy = self._inflight.get(transport)
        if busy is None or version < busy[0]:
            return
        busy[2].discard(peer)
        if not busy[2]:
            self._publish.set()  # the link is free: the publisher sends it the newest version

    def _make_envelope(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Envelope:
        t0 = time.perf_counter()
        payload = encode(grid, self.cfg.codec.use, base, options=self.codec_options)
        enc_ms = 1000 * (time.perf_counter() - t0)
        head = read_header(payload, max_cells=self.cfg.limits.max_cells)
        base_version = head.base_version if head.delta else 0
        self.store.data.seq += 1
        env = Envelope(
            fleet=self.cfg.robot.fleet,
            robot=self.me,
            version=grid.version,
            base_version=base_version,
            codec=self.cfg.codec.use,
            variant=head.variant,
            width=grid.width,
            height=grid.height,
            resolution=grid.resolution,
            origin=grid.origin,
            frame_id=grid.frame_id,
            stamp=grid.stamp,
            seq=self.store.data.seq,
            payload=payload,
        )
        if self.key is not None:
            env = env.signed(self.key)
        row: dict[str, Any] = {
            "time": round(time.time(), 3),
            "version": grid.version,
            "kind": "delta" if head.delta else "keyframe",
            "cells": grid.cells,
            "bytes": len(payload),
            "ratio": round(grid.cells / len(payload), 2),
            "encode_ms": round(enc_ms, 2),
            "psnr": "",
            "ssim": "",
        }
        if self.cfg.codec.measure_quality and not self.codec.lossless:
            back = decode(payload, base, max_cells=self.cfg.limits.max_cells, options=self.codec_options)
            row["psnr"], row["ssim"] = (
                round(psnr(grid.data, back.data), 3),
                round(ssim(grid.data, back.data), 5),
            )
        self.codec_stats.update(
            last_version=grid.version,
            last_bytes=len(payload),
            last_ratio=row["ratio"],
            last_encode_ms=row["encode_ms"],
            last_kind=row["kind"],
        )
        self._log_update(row)
        return env

    def _log_update(self, row: dict[str, Any]) -> None:
        new = not self._updates_csv.exists()
        with open(self._updates_csv, "a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(row))
            if new:
                w.writeheader()
            w.writerow(row)

    def _on_global(self, grid: OccupancyGrid) -> None:
        """Log which version of each robot's map the new global map holds (for latency benches)."""
        now = round(time.time(), 3)
        robots = self.fusion.status().get("robots", {})
        new = not self._fused_csv.exists()
        with open(self._fused_csv, "a", newline="") as fh:
            w = csv.writer(fh)
            if new:
                w.writerow(["time", "robot", "version"])
            for robot, info in robots.items():
                if isinstance(info, dict) and info.get("accepted") and info.get("version"):
                    w.writerow([now, robot, info["version"]])

    def latest_keyframe(self) -> Envelope | None:
        """The newest own map as a keyframe, for late joiners (thread-safe; encodes at most once)."""
        own = self.own
        if own is None:
            return None
        with self._kf_lock:
            if self._kf_cache is not None and self._kf_cache.version == own.version:
                return self._kf_cache
        env = self._make_envelope(own, None)
        with self._kf_lock:
            self._kf_cache = env
        return env

    # ------------------------------------------------------------------ events in
    def _emit(self, event: TransportEvent) -> None:
        self._events.put(event)

    async def _event_loop(self) -> None:
        while True:
            ev = await self._events.get()
            try:
                await self._handle(ev)
            except MapdError as exc:
                log.warning("event from %s dropped: %s", getattr(ev, "peer", "?"), exc)

    def _transport(self, name: str) -> Transport | None:
        return next((t for t in self.transports if t.name == name), None)

    async def _handle(self, ev: TransportEvent) -> None:
        if isinstance(ev, Received):
            await self._on_received(ev)
        elif isinstance(ev, Delivered):
            if ev.robot != self.me:
                return
            self._settled(ev.transport, ev.peer, ev.version)
            prev = self.store.data.acked.get(ev.peer, 0)
            if ev.version > prev:
                self.store.data.acked[ev.peer] = ev.version
                await self._maybe_save_base()
        elif isinstance(ev, KeyframeNeeded | PeerRestarted):
            # The peer may not hold our base any more: the next update goes out whole.
            self.since_keyframe = self.cfg.codec.keyframe_every
            self.store.data.acked.pop(ev.peer, None)
            if self.own is not None:
                self._pending = self._pending or self.own
                self._offered.clear()  # even a transport that had the newest version gets it whole
                self._publish.set()
        elif isinstance(ev, PeerUp | PeerDown):
            info = self.peer_info.setdefault(ev.peer, {})
            info["present"] = isinstance(ev, PeerUp)
            info["link"] = ev.transport
        elif isinstance(ev, Failed):
            self._settled(ev.transport, ev.peer, ev.version)
            log.info("update v%d to %s failed: %s", ev.version, ev.peer, ev.reason)

    async def _maybe_save_base(self) -> None:
        peers = self._target_peers() or set(self.store.data.acked)
        versions = {self.store.data.acked.get(p, 0) for p in peers}
        if len(versions) == 1:
            v = versions.pop()
            grid = self._sent.get(v)
            if grid is not None and (self.store.data.base is None or self.store.data.base.version != v):
                await asyncio.to_thread(self.store.save_base, grid)
                return
        await asyncio.to_thread(self.store.flush)

    async def _on_received(self, ev: Received) -> None:
        try:
            env = unpack(ev.data, max_bytes=self.cfg.limits.max_message_bytes, key=self.key)
        except EnvelopeError as exc:
            msg = str(exc)
            key = "bad_signature" if "signature" in msg or "unsigned" in msg else "bad_envelopes"
            self.counters[key] += 1
            log.info("dropped envelope from %s: %s", ev.peer, msg)
            return
        if env.fleet != self.cfg.robot.fleet:
            self.counters["foreign_fleet"] += 1
            return
        if env.robot == self.me:
            return
        held = self.peer_maps.get(env.robot)
        if held is not None and env.version <= held.version:
            self.counters["duplicates"] += 1
            return
        base = None
        transport = self._transport(ev.transport)
        if not env.is_keyframe:
            base = self.peer_history.get(env.robot, {}).get(env.base_version)
            if base is None:
                self.counters["keyframe_requests"] += 1
                if transport is not None:
                    await transport.request_keyframe(env.robot)
                return
        try:
            grid = await asyncio.to_thread(decode, env.payload, base, max_cells=self.cfg.limits.max_cells)
        except CodecError as exc:
            self.counters["decode_errors"] += 1
            log.info("cannot decode v%d from %s: %s", env.version, env.robot, exc)
            if transport is not None and base is not None:
                self.counters["keyframe_requests"] += 1
                await transport.request_keyframe(env.robot)
            return
        if (grid.width, grid.height) != (env.width, env.height):
            self.counters["decode_errors"] += 1
            return
        grid = grid.replace(robot=env.robot, version=env.version, stamp=env.stamp, frame_id=env.frame_id)
        self.peer_maps[env.robot] = grid
        history = self.peer_history.setdefault(env.robot, {})
        history[env.version] = grid
        for v in sorted(history)[:-KEEP_PEER_VERSIONS]:
            del history[v]
        self.counters["updates_received"] += 1
        info = self.peer_info.setdefault(env.robot, {})
        info.update(
            version=env.version,
            received_at=time.time(),
            link=ev.transport,
            present=True,
            bytes=info.get("bytes", 0) + len(ev.data),
            updates=info.get("updates", 0) + 1,
            last_kind="keyframe" if env.is_keyframe else "delta",
        )
        try:
            await asyncio.to_thread(self.store.save_peer, grid)
        except StateError as exc:
            log.error("%s", exc)
        self.fusion.submit(grid)
        ack = getattr(transport, "ack", None)
        if callable(ack):
            ack(env.robot, env.version)

    # ------------------------------------------------------------------ status
    def snapshot(self) -> dict[str, Any]:
        """Everything ``mapd status`` shows, as JSON-able data."""
        now = time.time()
        peers = {}
        for robot in sorted(set(self.peer_info) | set(self.peer_maps)):
            info = dict(self.peer_info.get(robot, {}))
            if "received_at" in info:
                info["age_s"] = round(now - info.pop("received_at"), 1)
            held = self.peer_maps.get(robot)
            if held is not None:
                # The version we hold, also for a peer restored from the state directory that has
                # sent nothing since this start (its counters are then empty, its map is not).
                info["version"] = held.version
                info["restored"] = "age_s" not in info  # nothing received from it since this start
            info["acked_our_version"] = self.store.data.acked.get(robot, 0)
            peers[robot] = info
        return {
            "robot": self.me,
            "fleet": self.cfg.robot.fleet,
            "pid": os.getpid(),
            "uptime_s": round(now - self.started, 1),
            "source": {
                "name": self.cfg.source.use,
                "version": self.own.version if self.own else 0,
                "size": [self.own.width, self.own.height] if self.own else None,
                "finished": self.source_finished,
                "stats": self.source.stats() if self.source else {},
            },
            "codec": {
                **self.codec_stats,
                "keyframes": self.counters["keyframes_sent"],
                "deltas": self.counters["deltas_sent"],
            },
            "peers": peers,
            "links": {t.name: {**t.stats(), "peers": t.peers()} for t in self.transports},
            "fusion": self.fusion.status(),
            "counters": {
                **self.counters,
                # a flood: older updates replaced by newer ones before decoding, or events dropped
                "superseded_updates": self._events.counters["superseded"],
                "dropped_events": self._events.counters["dropped"],
            },
            "state_dir": str(self.cfg.state.dir),
        }


def run_daemon(cfg: configmod.MapdConfig) -> int:
    """Run the daemon with signal handling: SIGTERM/SIGINT drain, a second SIGINT forces exit."""

    async def main() -> None:
        daemon = Daemon(cfg)
        loop = asyncio.get_running_loop()
        hits = {"int": 0}

        def on_sigint() -> None:
            hits["int"] += 1
            if hits["int"] > 1:
                log.warning("second SIGINT: exiting now")
                os._exit(130)
            daemon.request_stop()

        loop.add_signal_handler(signal.SIGTERM, daemon.request_stop)
        loop.add_signal_handler(signal.SIGINT, on_sigint)
        await daemon.run()

    asyncio.run(main())
    return 0
