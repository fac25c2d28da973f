"""Transport events in: peers' maps verified, planned, decoded and kept; acks and presence to the publisher.

:class:`Inbound` is the daemon's receiving half, an asyncio adapter like :mod:`mapd.daemon.server`
around the sans-I/O cores it feeds: :class:`~mapd.daemon.receiver.Receiver` decides what to do with
a peer's map, :class:`~mapd.daemon.publisher.PublisherCore` learns what each peer acknowledged. For a
:class:`~transports.base.Received` map, in order: verify (worker thread), plan (loop), decode
(worker), accept (loop), then save (worker), fusion, outputs, ack, and each transport may relay
it. Nothing CPU-heavy runs on the loop, and one bad event costs one log line, never the daemon.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from mapd.daemon.events import EventQueue
from mapd.daemon.poses import PoseRelay
from mapd.daemon.publisher import PublisherCore
from mapd.daemon.receiver import AskKeyframe, Decode, Receiver, decode_envelope, open_envelope
from mapd.daemon.sinks import Sinks
from mapd.daemon.state import StateStore
from mapd.daemon.versions import label
from mapd.errors import CodecError, EnvelopeError, MapdError, StateError
from mapd.files import WriteOutage
from mapd.fusion.worker import FusionWorker
from mapd.identity import Roster
from transports.base import (
    Arrived,
    Delivered,
    Failed,
    KeyframeNeeded,
    OnAir,
    PeerDown,
    PeerRestarted,
    PeerUp,
    PoseReceived,
    Received,
    Transport,
    TransportEvent,
)

log = logging.getLogger("mapd.daemon")


@dataclass
class FailedOffers:
    """Failed offers of this robot's maps, said without repeating.

    Each new version of a map over a peer's message limit is refused again, and a map a one-way
    link never gets acknowledged fails again at every in-flight timeout while that peer stays
    known (P7): a line each time said the same words all day. The first failure to a peer is said, and a new reason for it; repeats go to DEBUG, and
    the next delivery to that peer says how many offers failed before it.
    """

    logger: logging.Logger
    #: (transport, peer) -> the reason last said at INFO, and failures since the last delivery.
    _failing: dict[tuple[str, str], tuple[str, int]] = field(default_factory=dict)

    def failed(self, ev: Failed) -> None:
        key = (ev.transport, ev.peer)
        said, count = self._failing.get(key, ("", 0))
        level = logging.DEBUG if _reason(ev.reason) == _reason(said) else logging.INFO
        self.logger.log(level, "update %s to %s failed: %s", label(ev.version), ev.peer, ev.reason)
        self._failing[key] = (ev.reason if level == logging.INFO else said, count + 1)

    def delivered(self, ev: Delivered) -> None:
        _, count = self._failing.pop((ev.transport, ev.peer), ("", 0))
        if count:
            self.logger.info(
                "update %s to %s delivered after %d failed offer%s",
                label(ev.version),
                ev.peer,
                count,
                "s" if count > 1 else "",
            )


def _reason(text: str) -> str:
    """A failure's reason without its numbers (sizes and times differ from version to version)."""
    return re.sub(r"\d[\d,.]*", "#", text)


@dataclass
class Inbound:
    """Handles every event the transports put on the daemon's queue (see the module docstring)."""

    me: str
    events: EventQueue
    transports: Sequence[Transport]
    publisher: PublisherCore
    receiver: Receiver
    store: StateStore
    fusion: FusionWorker
    sinks: Sinks
    poses: PoseRelay
    roster: Roster
    max_message_bytes: int
    max_cells: int
    #: Called when a link became free or a peer needs a keyframe: the publisher has work.
    wake: Callable[[], None]
    #: The roster's key of a robot now (its text), saved with each map of it the key signed: a map
    #: whose robot has another key by the next start is not restored (the key was replaced).
    key_of: Callable[[str], str | None] = lambda robot: None
    #: A full disk fails the save of every peer map and base (several a second in a large fleet):
    #: said once, and once when saving works again.
    _saves: WriteOutage = field(default_factory=lambda: WriteOutage(log))
    #: Offers failing again and again for one reason (each version over a peer's limit) said once.
    _failures: FailedOffers = field(default_factory=lambda: FailedOffers(log))
    #: Revocations so far, and robot -> the number of its last (see :meth:`revoked`).
    _revocations: int = 0
    _revoked_at: dict[str, int] = field(default_factory=dict)

    async def run(self) -> None:
        """Take events off the queue until cancelled."""
        while True:
            ev = await self.events.get()
            try:
                await self.handle(ev)
            except MapdError as exc:
                log.warning("event from %s dropped: %s", _source(ev), exc)
            except Exception:
                # A bug (or an error a save let out) must cost this event, not the daemon: the
                # peer sends again, and a daemon ended by it would be restarted into the same.
                log.exception("event from %s dropped: internal error", _source(ev))

    def transport(self, name: str) -> Transport | None:
        return next((t for t in self.transports if t.name == name), None)

    async def handle(self, ev: TransportEvent) -> None:
        core = self.publisher
        if isinstance(ev, Received):
            await self._on_received(ev)
        elif isinstance(ev, PoseReceived):
            await self.poses.received(ev)
        elif isinstance(ev, Delivered):
            if ev.robot != self.me:
                return
            self._failures.delivered(ev)
            free, newer = core.acked(ev.transport, ev.peer, ev.version)
            if free:
                self.wake()  # the link is free: the publisher sends it the newest version
            if newer and self.store.set_acked(ev.peer, ev.version):
                try:
                    await self._save_base()
                except StateError as exc:  # a full disk: the base is saved with a later ack
                    self._saves.failed(f"{exc}; trying again with each map or ack")
                else:
                    self._saves.recovered("state saved again")
        elif isinstance(ev, OnAir):
            if ev.robot == self.me and core.on_air(ev.transport, ev.version, time.monotonic()):
                self.wake()  # the offer now times out: the publisher waits for that, not for ever
        elif isinstance(ev, KeyframeNeeded | PeerRestarted):
            self._lost_our_base(ev.peer)
        elif isinstance(ev, PeerUp | PeerDown):
            self.receiver.presence(ev.peer, ev.transport, isinstance(ev, PeerUp))
            if isinstance(ev, PeerDown) and core.peer_gone(ev.transport, ev.peer):
                self.wake()  # the offer waited only for a robot that left: the link is free
        elif isinstance(ev, Arrived):
            if core.arrived(ev.transport, ev.peer):
                self.wake()  # back in reach and behind: the newest goes out again (P6)
        elif isinstance(ev, Failed):
            if core.failed(ev.transport, ev.peer, ev.version, again=ev.again):
                self.wake()
            self._failures.failed(ev)

    def _lost_our_base(self, peer: str) -> None:
        """``peer`` may not hold our base any more: the next update goes out whole (P4)."""
        self.store.forget_acked(peer)
        if self.publisher.keyframe_needed(peer):
            self.wake()

    async def _save_base(self) -> None:
        peers = {p for t in self.transports for p in t.peers()}
        grid = self.publisher.base_to_save(peers)
        if grid is None:
            await asyncio.to_thread(self.store.flush)
            return
        await asyncio.to_thread(self.store.save_base, grid)
        self.publisher.set_base(grid.version)

    def revoked(self, robot: str) -> None:
        """``robot``'s key was revoked (removed or replaced): a map of it verified before is dropped
        wherever on its way in it is (a new key still admits the robot, so the roster cannot say)."""
        self._revocations += 1
        self._revoked_at[robot] = self._revocations

    def _trusted(self, robot: str, mark: int) -> bool:
        """Whether ``robot``'s map, verified after revocation number ``mark``, may still be used."""
        return self.roster.admits(robot) and self._revoked_at.get(robot, 0) <= mark

    async def _on_received(self, ev: Received) -> None:
        rx = self.receiver
        mark = self._revocations  # the keys it is verified with: any revoked later voids it
        try:
            env = await asyncio.to_thread(
                open_envelope, ev.data, max_bytes=self.max_message_bytes, roster=self.roster
            )
        except EnvelopeError as exc:
            rx.refused(exc)
            log.info("dropped envelope from %s: %s", ev.peer, exc)
            return
        plan = rx.plan(env, ev.peer, time.time())
        if isinstance(plan, Decode | AskKeyframe) and plan.new_incarnation:
            # Its maps come from a new incarnation: it lost its state, so it lost ours too, also
            # where its link cannot tell a restart (zenoh within its lease time).
            self._lost_our_base(env.robot)
        transport = self.transport(ev.transport)
        if transport is not None and env.robot != ev.peer and env.sig:
            transport.relayed(env)  # another robot forwarded it: ours would repeat it
        if isinstance(plan, AskKeyframe):
            if transport is not None:
                await transport.request_keyframe(plan.robot)
            return
        if not isinstance(plan, Decode):
            if not plan.routine:  # duplicates and echoes are; refusals are worth a line
                say = log.warning if plan.warning else log.info
                say("dropped %s of %s from %s: %s", label(env.version), env.robot, ev.peer, plan.reason)
            if plan.forget and transport is not None:
                await transport.request_keyframe(env.robot)
            if plan.held and transport is not None and env.robot == ev.peer:
                transport.ack(env.robot, env.version)  # (from its robot: not for each relay's copy)
            return
        try:
            grid = await asyncio.to_thread(decode_envelope, env, plan.base, max_cells=self.max_cells)
        except CodecError as exc:
            log.info("cannot decode %s from %s: %s", label(env.version), env.robot, exc)
            ask = rx.undecodable(env, plan.base)
            if ask is not None and transport is not None:
                await transport.request_keyframe(ask.robot)
            return
        if not self._trusted(env.robot, mark):
            log.info("dropped %s of %s: revoked while it was decoded", label(env.version), env.robot)
            return
        rx.accept(grid, env, ev.transport, len(ev.data), time.time())
        # The key it was verified with (none was revoked since: _trusted), saved with it.
        key = self.key_of(env.robot) if env.sig else None
        try:
            await asyncio.to_thread(self.store.save_peer, grid, env.frame_pose, key)
        except StateError as exc:  # the map is still used; after a restart it comes again whole
            self._saves.failed(f"{exc}; trying again with each map or ack")
        else:
            self._saves.recovered("state saved again")
        if not self._trusted(env.robot, mark):
            # Revoked while it was saved: the revocation took the map out of the receiver and the
            # state directory, but the save has put it back in since.
            try:
                await asyncio.to_thread(self.store.remove_peer, env.robot)
            except StateError as exc:
                log.warning("revoked %s: %s", env.robot, exc)
            log.info("dropped %s of %s: revoked while it was saved", label(env.version), env.robot)
            return
        if env.frame_pose is not None:
            self.fusion.known_pose(env.robot, env.frame_pose)
        self.fusion.submit(grid)
        self.sinks.robot_map(grid)
        if transport is not None:
            transport.ack(env.robot, env.version)
        for t in self.transports:
            t.held(env, ev.data)  # a relaying link may forward it, still signed by its robot


def _source(ev: TransportEvent) -> str:
    """Who an event came from, for a log line (OnAir is about own maps: its transport)."""
    return ev.transport if isinstance(ev, OnAir) else ev.peer
