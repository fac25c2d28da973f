"""An in-process transport for tests and examples, as python-can's ``VirtualBus`` is for CAN.

Every :class:`VirtualTransport` joins a named :class:`VirtualChannel` in this process; what one
offers reaches every other member of the channel as the packed envelope bytes a real link would
carry. It behaves like the ``zenoh`` transport, minus the network:

* ``offer`` delivers at once to every other member;
* ``ack`` reaches the map's robot as :class:`~transports.base.Delivered` (peer = the acker);
* ``request_keyframe`` reaches the map's robot as :class:`~transports.base.KeyframeNeeded`;
* :meth:`VirtualTransport.query_keyframe` asks a member for its latest keyframe the way a zenoh
  query does: answered in a worker thread, never on the asker's event loop;
* joining and leaving emit :class:`~transports.base.PeerUp` / :class:`~transports.base.PeerDown`.

Events are emitted with ``loop.call_soon``, never from inside the caller, so a daemon sees them
in the order a real link would. All members must run on one event loop.

Config: ``[transports] use = ["virtual"]`` with ``[transports.virtual] channel = "NAME"``.
"""

from __future__ import annotations

import asyncio
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

from pydantic import Field

from mapd.envelope import Envelope
from mapd.errors import TransportError
from transports.base import (
    Delivered,
    KeyframeNeeded,
    PeerDown,
    PeerUp,
    PoseReceived,
    PoseThrottle,
    Received,
    Transport,
    TransportContext,
    TransportEvent,
    TransportOptions,
)

NAME = "virtual"


class VirtualOptions(TransportOptions):
    """``[transports.virtual]``: which channel to join."""

    channel: str = "default"
    pose_period_s: float = Field(default=0.5, ge=0, description="seconds between pose messages (0: none)")


@dataclass
class VirtualStats:
    """Counters for ``mapd status``."""

    offers: int = 0
    bytes_out: int = 0
    updates_in: int = 0
    acks_out: int = 0
    keyframe_requests_out: int = 0
    poses_out: int = 0
    poses_in: int = 0


@dataclass
class VirtualChannel:
    """The members of one channel, by robot."""

    name: str
    members: dict[str, VirtualTransport] = field(default_factory=dict)

    _all: ClassVar[dict[str, VirtualChannel]] = {}

    @classmethod
    def get(cls, name: str) -> VirtualChannel:
        """The channel called ``name`` in this process (created on first use)."""
        return cls._all.setdefault(name, cls(name))

    def deliver(self, sender: str, env: Envelope) -> None:
        data = env.pack()
        for robot, member in self.members.items():
            if robot != sender:
                member.stats_.updates_in += 1
                member.post(Received(NAME, sender, data))


class VirtualTransport(Transport):
    """One robot's end of a :class:`VirtualChannel`."""

    name = NAME
    Options = VirtualOptions

    def __init__(self, options: TransportOptions | None, ctx: TransportContext) -> None:
        super().__init__(options, ctx)
        assert isinstance(self.options, VirtualOptions)
        self.opts: VirtualOptions = self.options
        self.channel = VirtualChannel.get(self.opts.channel)
        self.stats_ = VirtualStats()
        self.offers: list[Envelope] = []  # everything offered, for tests to read
        self._loop: asyncio.AbstractEventLoop | None = None
        self._poses = PoseThrottle(self.opts.pose_period_s)

    def post(self, event: TransportEvent) -> None:
        """Emit ``event`` on this member's loop, after the caller returns."""
        if self._loop is not None:
            self._loop.call_soon(self.ctx.emit, event)

    async def start(self) -> None:
        me = self.ctx.robot
        if me in self.channel.members:
            raise TransportError(f"virtual: robot '{me}' is already on channel '{self.channel.name}'")
        self._loop = asyncio.get_running_loop()
        for robot, other in self.channel.members.items():
            other.post(PeerUp(NAME, me))
            self.post(PeerUp(NAME, robot))
        self.channel.members[me] = self

    async def close(self) -> None:
        me = self.ctx.robot
        if self.channel.members.get(me) is self:
            del self.channel.members[me]
            for other in self.channel.members.values():
                other.post(PeerDown(NAME, me))
        self._loop = None

    def offer(self, envelope: Envelope) -> None:
        self.offers.append(envelope)
        self.stats_.offers += 1
        self.stats_.bytes_out += len(envelope.pack())
        self.channel.deliver(self.ctx.robot, envelope)

    def send_pose(self, data: bytes, now: float) -> bool:
        if not self._poses.due(now):
            return False
        self.stats_.poses_out += 1
        for robot, member in self.channel.members.items():
            if robot != self.ctx.robot:
                member.stats_.poses_in += 1
                member.post(PoseReceived(NAME, self.ctx.robot, data))
        return True

    def ack(self, robot: str, version: int) -> None:
        owner = self.channel.members.get(robot)
        if owner is not None:
            self.stats_.acks_out += 1
            owner.post(Delivered(NAME, self.ctx.robot, robot, version))

    async def request_keyframe(self, robot: str) -> None:
        owner = self.channel.members.get(robot)
        if owner is not None:
            self.stats_.keyframe_requests_out += 1
            owner.post(KeyframeNeeded(NAME, self.ctx.robot, robot))

    async def query_keyframe(self, robot: str) -> Envelope | None:
        """``robot``'s latest keyframe, answered in a worker thread as a zenoh queryable is."""
        owner = self.channel.members.get(robot)
        if owner is None:
            return None
        return await asyncio.to_thread(owner.ctx.latest_keyframe)

    def peers(self) -> list[str]:
        return sorted(r for r in self.channel.members if r != self.ctx.robot)

    def stats(self) -> dict[str, Any]:
        return asdict(self.stats_)
