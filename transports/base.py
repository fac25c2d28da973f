"""The transport interface: how envelopes leave and reach a robot.

A transport is an asyncio adapter around a wire protocol. The daemon gives it envelopes with
:meth:`Transport.offer` (latest wins: a newer version of the same robot's map replaces one not yet
sent) and hears back through the ``emit`` callback of its :class:`TransportContext`, on the event
loop's thread, with the events below.
"""

from __future__ import annotations

import asyncio
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict

from mapd.envelope import Envelope
from mapd.identity import Identity, Roster


class TransportOptions(BaseModel):
    """Options a transport reads from its ``[transports.<name>]`` table. Subclass to add fields."""

    model_config = ConfigDict(extra="forbid")


@dataclass(frozen=True)
class Received:
    """Envelope bytes arrived from ``peer`` (unverified: the daemon unpacks and checks them)."""

    transport: str
    peer: str
    data: bytes


@dataclass(frozen=True)
class Delivered:
    """``peer`` has acknowledged ``robot``'s map ``version`` (so it can serve as a delta base)."""

    transport: str
    peer: str
    robot: str
    version: int


@dataclass(frozen=True)
class Failed:
    """An offered version could not be delivered to ``peer`` by its deadline. ``again``: whether
    offering that same version again may succeed (False: it was refused for its size, by the peer
    or by this link's own limit, and would be every time)."""

    transport: str
    peer: str
    robot: str
    version: int
    reason: str
    again: bool = True


@dataclass(frozen=True)
class OnAir:
    """Every byte of ``robot``'s map ``version`` has been on the air once, so what is left is repair
    (sent only by links that pace: see :attr:`Transport.paced`)."""

    transport: str
    robot: str
    version: int


@dataclass(frozen=True)
class PeerUp:
    """A peer appeared (liveliness token, first valid frame)."""

    transport: str
    peer: str


@dataclass(frozen=True)
class Arrived:
    """``peer`` came into reach and no map of ours on its way over this link will reach it (sent by
    links where robots pass in and out of range and nobody asks for the newest map: uwb). The
    publisher offers it the newest own version once the link is free (P6)."""

    transport: str
    peer: str


@dataclass(frozen=True)
class PeerDown:
    """A peer vanished (token dropped, silent past its timeout)."""

    transport: str
    peer: str


@dataclass(frozen=True)
class PeerRestarted:
    """A peer restarted (new session id): it may have lost what it held."""

    transport: str
    peer: str


@dataclass(frozen=True)
class KeyframeNeeded:
    """A peer asked for a whole map of ``robot`` (late join, gap, unknown base)."""

    transport: str
    peer: str
    robot: str


@dataclass(frozen=True)
class PoseReceived:
    """Pose message bytes arrived from ``peer`` (unverified: the daemon unpacks and checks them)."""

    transport: str
    peer: str
    data: bytes


TransportEvent = (
    Received
    | Delivered
    | Failed
    | OnAir
    | PeerUp
    | Arrived
    | PeerDown
    | PeerRestarted
    | KeyframeNeeded
    | PoseReceived
)


@dataclass
class PoseThrottle:
    """At most one pose per ``period_s`` on a link (0 turns poses off); ``now`` is passed in."""

    period_s: float
    sent: int = 0
    _next: float = float("-inf")

    def due(self, now: float) -> bool:
        """Whether a pose may go at ``now``; if so, the next may go one period later."""
        if self.period_s <= 0 or now < self._next:
            return False
        self._next = now + self.period_s
        self.sent += 1
        return True


@dataclass
class TransportContext:
    """What the daemon hands every transport."""

    robot: str
    fleet: str
    max_message_bytes: int
    emit: Callable[[TransportEvent], None]
    #: This robot's signing key (None in a fleet that allows unsigned messages and has none).
    identity: Identity | None = None
    #: Whose signatures to accept; the default accepts anything (tools and tests, never the daemon).
    roster: Roster = field(default_factory=Roster.open)
    #: The fleet's shared secret authenticating link frames (uwb), or None.
    link_key: bytes | None = None
    state_dir: Path | None = None
    #: Returns the robot's latest keyframe envelope (for late joiners), or None before the first map.
    #: It may encode the map first (seconds for a large one): call it from a worker thread, never on
    #: the event loop's thread.
    latest_keyframe: Callable[[], Envelope | None] = field(default=lambda: None)


class Transport(ABC):
    """A pluggable link. Subclasses set ``name`` and ``Options`` and implement the methods.

    These are all the methods the daemon calls: start and close; offer (own maps out); send_pose
    (the robot's pose out, latest wins); ack and request_keyframe (answers to what was received);
    peers and stats (for the publisher's choice of base and for ``mapd status``).
    """

    name: ClassVar[str]
    Options: ClassVar[type[TransportOptions]] = TransportOptions
    #: The link puts an offer on the air at a share of a slow channel, and says when it is wholly
    #: there (:class:`OnAir`): the publisher then never replaces an offer half sent (P1).
    paced: ClassVar[bool] = False

    def __init__(self, options: TransportOptions | None, ctx: TransportContext) -> None:
        self.options = options if options is not None else self.Options()
        self.ctx = ctx

    @abstractmethod
    async def start(self) -> None:
        """Open the link; raise :class:`~mapd.errors.TransportError` with one clear line on failure."""

    @abstractmethod
    async def close(self) -> None:
        """Stop promptly and release everything (undeclare, close ports); never hang."""

    async def watch(self) -> None:
        """Wait while the link works; return once it is closed. Raise
        :class:`~mapd.errors.TransportError` (one line, the cause) if its background work stopped
        for good, so that the daemon stops with that line (and systemd restarts it) rather than run
        on as a robot that looks alive and sends nothing. The default, for a link whose work runs
        in its library's threads, waits for ever (the daemon cancels it on shutdown)."""
        await asyncio.Event().wait()

    @abstractmethod
    def offer(self, envelope: Envelope) -> None:
        """Queue ``envelope`` for every peer; replaces any unsent older version of the same robot."""

    def send_pose(self, data: bytes, now: float) -> bool:
        """Send this robot's packed, signed pose message if the link's pose period allows it now.

        Poses are latest wins and best effort: a link sends one only when ``now`` (loop seconds) is
        its pose period past the last, and drops it rather than let it delay a map. Returns whether
        it went out. The default carries no poses.
        """
        return False

    async def request_keyframe(self, robot: str) -> None:  # noqa: B027 - optional hook
        """Ask peers for a whole map of ``robot`` (after a gap or an unknown base)."""

    def ack(self, robot: str, version: int) -> None:  # noqa: B027 - optional hook
        """The daemon applied ``robot``'s map ``version``: tell its sender, if this link acks that way.

        A link that acknowledges below the daemon (the ``uwb`` ARQ acks every whole message) keeps
        this default, which does nothing.
        """

    def offer_deadline_s(self, envelope: Envelope) -> float | None:
        """How long after :meth:`offer` a paced link may still be sending ``envelope`` before it
        gives it up, or None (the default: the publisher's own hold applies). The publisher keeps
        the offer that long if longer (P1), so a large map is not superseded half sent."""
        return None

    def held(self, envelope: Envelope, data: bytes) -> None:  # noqa: B027 - optional hook
        """The daemon accepted ``envelope`` of another robot (``data``: its bytes as received, on
        any transport), or got a whole map of the version it holds, which came as a delta. A link
        that relays maps (``uwb``) may forward them unaltered; the default does nothing."""

    def restored(self, robot: str, version: int) -> None:  # noqa: B027 - optional hook
        """This robot holds ``robot``'s ``version`` from its state directory (at start, before
        :meth:`start`): a link that tells neighbours what it holds (``uwb``'s relay summaries) lists
        it, though it has no bytes of it to pass on; the default does nothing."""

    def relayed(self, envelope: Envelope) -> None:  # noqa: B027 - optional hook
        """``envelope`` of another robot came on this transport from a third robot (a relay), held
        already or not: a relaying link need not forward the same version for a while; the default
        does nothing."""

    def forget(self, robot: str) -> None:  # noqa: B027 - optional hook
        """``robot`` was revoked: drop what the link holds of it to pass on (a relaying link keeps
        other robots' maps to forward); the default holds nothing."""

    def peers(self) -> list[str]:
        """Peers this transport currently sees."""
        return []

    def stats(self) -> dict[str, Any]:
        """Counters for ``mapd status`` (bytes, goodput, resends, errors, RTT ...)."""
        return {}
