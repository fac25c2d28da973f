"""Transport events in: peers' maps verified, planned, decoded and kept; acks and presence to the publisher.

:class:`Inbound` is the daemon's receiving half, an asyncio adapter like :mod:`mapd.daemon.server`
around the sans-I/O cores it feeds: :class:`~mapd.daemon.receiver.Receiver` decides what to do with
a peer's map, :class:`~mapd.daemon.publisher.PublisherCore` learns what each peer acknowledged. For a
:class:`~transports.base.Received` map, in order: verify (worker thread), plan (loop), decode
(worker), accept (loop), then save (worker), fusion, outputs, ack, and each transport may relay
it. Nothing CPU-heavy runs on the loop, and one bad event costs one log line, never the daemon.

Refusals that a config fixes (a robot missing from the roster, an old key, another fleet, limits
smaller than a peer's maps, ``nodes`` lists that differ, a codec model this robot lacks) come with
every map the peer sends: each is said once per robot and cause with the fix, as a warning
(:class:`~mapd.daemon.refusals.Refusal`), and again only after that robot's maps were taken in
between. What a link refuses before the daemon sees it (zenoh: robots off the roster, signatures
the roster's keys refuse) is said once per link and cause, from its counters (:class:`LinkRefusals`).

A peer's map whose save fails (a full disk) is used and acked all the same; it is saved again
until it goes through, as the base and ``state.json`` (acks) are (:mod:`~mapd.daemon.peer_saves`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from mapd.codec.base import CodecOptions
from mapd.daemon.events import EventQueue
from mapd.daemon.headline import roster_refusals
from mapd.daemon.intake import AskKeyframe, Decode, decode_envelope, open_envelope
from mapd.daemon.peer_saves import PeerSaves, UnsavedPeer
from mapd.daemon.poses import PoseRelay
from mapd.daemon.presence_log import PresenceLog
from mapd.daemon.publisher import PublisherCore
from mapd.daemon.receiver import Receiver
from mapd.daemon.refusals import decode_cause, shown
from mapd.daemon.sinks import Sinks
from mapd.daemon.state import StateStore
from mapd.daemon.versions import label
from mapd.envelope import peek_robot
from mapd.errors import CodecError, EnvelopeError, MapdError
from mapd.files.outage import WriteOutage
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


#: A link's refusals for the roster that have not risen for this long are over: the next are said anew.
LINK_QUIET_S = 600.0


@dataclass
class LinkRefusals:
    """What links refuse for the roster before the daemon sees it (zenoh checks updates, acks and
    queries itself: robots off the roster, signatures its keys refuse), said once per link while
    it goes on (:func:`~mapd.daemon.headline.roster_refusals`); names are not known here.

    Pure bookkeeping: :meth:`look` takes each link's stats and ``now`` and gives the lines to say.
    """

    #: link -> its count at the last look, and when it last rose
    _seen: dict[str, tuple[int, float]] = field(default_factory=dict)

    def look(self, stats: dict[str, dict[str, object]], now: float) -> list[str]:
        lines = []
        for link, st in stats.items():
            n = roster_refusals(st)
            last, rose = self._seen.get(link, (0, -LINK_QUIET_S))
            if n > last:
                if now - rose >= LINK_QUIET_S:
                    lines.append(
                        f"{link}: messages refused for this robot's [fleet.roster] ({n} so far): a robot "
                        f"of this fleet missing there, or its key there old (it was re-keyed)? put the "
                        f"line 'mapd keygen <robot> --public <its key file>' prints on it in "
                        f"[fleet.roster], then 'systemctl reload mapd' (a robot removed on purpose that "
                        f"still runs, an outsider or a forgery look the same)"
                    )
                self._seen[link] = (n, now)
            elif n < last:  # the link started again: count from there
                self._seen[link] = (n, rose)
        return lines


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
    #: This robot's codec and its options (``[codec] use`` and ``[codec.<use>]``): maps in that
    #: codec are decoded with them (a paper model other than the default one), others with defaults.
    codec_options: tuple[str, CodecOptions | None] | None = None
    #: Offers failing again and again for one reason (each version over a peer's limit) said once.
    _failures: FailedOffers = field(default_factory=lambda: FailedOffers(log))
    #: Revocations so far, and robot -> the number of its last (see :meth:`revoked`).
    _revocations: int = 0
    _revoked_at: dict[str, int] = field(default_factory=dict)
    #: What the links refuse before the daemon sees it (zenoh), said once per link and cause.
    _link_refusals: LinkRefusals = field(default_factory=LinkRefusals)
    #: How often to look at the links' counters while no event comes (a robot off the roster
    #: sends nothing the daemon sees: only the link counts it).
    look_every_s: float = 2.0
    _looked_at: float = 0.0
    #: The state's saves that failed (a full disk), tried again (:class:`PeerSaves`).
    saves: PeerSaves = field(init=False)
    #: Robots coming, going and restarting, said in the log (:mod:`mapd.daemon.presence_log`).
    _presence: PresenceLog = field(default_factory=PresenceLog)

    def __post_init__(self) -> None:
        self.saves = PeerSaves(self.store, self._trusted, self._save_base, WriteOutage(log))

    async def run(self) -> None:
        """Take events off the queue until cancelled; between them, look at the links every
        ``look_every_s`` and save again what a full disk kept from being saved."""
        while True:
            now = time.monotonic()
            wait = self._looked_at + self.look_every_s - now
            if (retry_at := self.saves.retry_at()) is not None:
                wait = min(wait, retry_at - now)
            ev: TransportEvent | None = None
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(max(0.0, wait)):  # get() is cancel-safe
                    ev = await self.events.get()
            if time.monotonic() - self._looked_at >= self.look_every_s:
                self.look_at_links()
            if (retry_at := self.saves.retry_at()) is not None and time.monotonic() >= retry_at:
                try:
                    await self.saves.save_again()
                except Exception:  # a bug must cost this try, not the daemon: the next comes
                    log.exception("saving again: internal error")
            if ev is None:
                continue
            try:
                await self.handle(ev)
            except MapdError as exc:
                log.warning("event from %s dropped: %s", _source(ev), exc)
            except Exception:
                # A bug (or an error a save let out) must cost this event, not the daemon: the
                # peer sends again, and a daemon ended by it would be restarted into the same.
                log.exception("event from %s dropped: internal error", _source(ev))

    def look_at_links(self) -> None:
        """Say what the links refused on their own since the last look (:class:`LinkRefusals`)."""
        self._looked_at = time.monotonic()
        try:
            stats = {t.name: t.stats() for t in self.transports}
        except Exception:  # a link's stats must not stop its events (status shows the error)
            return
        for line in self._link_refusals.look(stats, time.monotonic()):
            log.warning("%s", line)

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
            if (line := self.receiver.acked(ev.transport, ev.peer)) is not None:
                log.info("%s", line)
            free, newer = core.acked(ev.transport, ev.peer, ev.version)
            if free:
                self.wake()  # the link is free: the publisher sends it the newest version
            if newer and self.store.set_acked(ev.peer, ev.version):
                await self.saves.save_state()
        elif isinstance(ev, OnAir):
            if ev.robot == self.me and core.on_air(ev.transport, ev.version, time.monotonic()):
                self.wake()  # the offer now times out: the publisher waits for that, not for ever
        elif isinstance(ev, KeyframeNeeded | PeerRestarted):
            self._lost_our_base(ev.peer)
            if (
                isinstance(ev, PeerRestarted)
                and ev.peer in self.receiver.info
                and (line := self._presence.restarted(ev.peer, ev.transport, time.monotonic())) is not None
            ):
                log.info("%s", line)
        elif isinstance(ev, PeerUp | PeerDown):
            self.receiver.presence(ev.peer, ev.transport, isinstance(ev, PeerUp))
            if ev.peer in self.receiver.info:  # (robots the roster admits, and not too many)
                line = self._presence.change(ev.peer, ev.transport, isinstance(ev, PeerUp), time.monotonic())
                if line is not None:
                    log.info("%s", line)
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
        wherever on its way in it is (a new key still admits the robot, so the roster cannot say),
        held unsaved too."""
        self._revocations += 1
        self._revoked_at[robot] = self._revocations
        self.saves.revoked(robot)
        self._presence.forget(robot)

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
            # Said once per robot and cause with the fix, not once per map it sends (the name is
            # read unverified from the bytes, only to say whose they claim to be).
            peeked = peek_robot(ev.data)
            robot = peeked if peeked and shown(peeked) == peeked else ev.peer
            line = rx.refused_bytes(exc, robot, time.time())
            if line is not None:
                log.warning("%s (from %s on %s)", line, ev.peer, ev.transport)
            else:
                log.debug("dropped envelope from %s: %s", ev.peer, exc)
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
                if plan.refusal:  # names the robot and the fix already
                    say("%s (%s from %s on %s)", plan.reason, label(env.version), ev.peer, ev.transport)
                else:
                    say("dropped %s of %s from %s: %s", label(env.version), env.robot, ev.peer, plan.reason)
            else:
                log.debug("dropped %s of %s from %s: %s", label(env.version), env.robot, ev.peer, plan.reason)
            if plan.forget and transport is not None:
                await transport.request_keyframe(env.robot)
            if plan.held and transport is not None and env.robot == ev.peer:
                transport.ack(env.robot, env.version)  # (from its robot: not for each relay's copy)
            if plan.held and env.base_version == 0 and env.sig:
                # A whole map of the version held, which came as a delta: what a relay asked its
                # robot for on a neighbour's behalf, that neighbour lacking the delta's base. Kept
                # for forwarding; dropped here, the relay asked again each retry, in vain, until
                # the robot made another version (never, for a map that no longer changes).
                for t in self.transports:
                    t.held(env, ev.data)
            return
        try:
            own_codec = self.codec_options is not None and env.codec == self.codec_options[0]
            grid = await asyncio.to_thread(
                decode_envelope,
                env,
                plan.base,
                max_cells=self.max_cells,
                options=self.codec_options[1] if own_codec and self.codec_options is not None else None,
            )
        except CodecError as exc:
            # A codec (or model) this robot lacks fails every map of that robot: said once, with
            # the fix. Damage or a base that differs (healed by the keyframe asked for) as before.
            line = f"cannot decode {label(env.version)} from {env.robot}: {exc}"
            cause = decode_cause(str(exc))
            if cause is None:
                log.info("%s", line)
            elif rx.refuse(env.robot, cause[0], f"{line}{cause[1]}", time.time()):
                log.warning("%s%s", line, cause[1])
            else:
                log.debug("%s", line)
            ask = rx.undecodable(env, plan.base)
            if ask is not None and transport is not None:
                await transport.request_keyframe(ask.robot)
            return
        if not self._trusted(env.robot, mark):
            log.info("dropped %s of %s: revoked while it was decoded", label(env.version), env.robot)
            return
        now = time.time()
        if (line := rx.stranger_link(env, ev.peer)) is not None:
            log.warning("%s", line)
        ended = rx.accept(grid, env, ev.transport, len(ev.data), now, link_peer=ev.peer)
        if ended is not None:
            log.info("maps of %s taken again, after %d refused (%s)", env.robot, ended.maps, ended.why)
        if env.robot == ev.peer and ev.transport not in self.publisher.paced:
            # A link whose acks say the peer took the map (not a radio's frame acks): a peer whose
            # maps come while it acks none of ours refuses them, and only this side can tell.
            offer = self.publisher.offers(time.monotonic()).get(ev.transport) or {}
            waiting = env.robot in (offer.get("waiting") or ())
            if (line := rx.unacked(ev.transport, env.robot, waiting, now)) is not None:
                log.warning("%s", line)
            if (ev.transport, env.robot) in rx.deaf and self.publisher.peer_gone(ev.transport, env.robot):
                # Waiting for it would hold our maps back from every other peer on this link for
                # the whole in-flight timeout, each version: stop at each map it sends instead.
                self.wake()
        # The key it was verified with (none was revoked since: _trusted), saved with it. A save
        # that fails (a full disk) keeps the map to save again: it is used and acked all the same.
        key = self.key_of(env.robot) if env.sig else None
        if not await self.saves.save_peer(UnsavedPeer(grid, env.frame_pose, key, mark)):
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
