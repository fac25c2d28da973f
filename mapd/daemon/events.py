"""The daemon's event inbox: transport events wait here for the event loop, bounded and latest-wins.

A peer may send faster than the daemon can verify and decode (a flood, or a fast link and a slow
robot). A plain bounded queue would then drop the *newest* update, which is the one that matters.
Here each ``(transport, peer)`` holds at most one waiting :class:`~transports.base.Received`: a newer
one replaces it (counted as ``superseded``), so the daemon always ends on the peer's latest map and
memory stays bounded by the number of peers. Pose messages are latest-wins too, one waiting per
peer beside its map. Other events (acks, presence, keyframe needs) are small and must not be lost
to a flood of maps or poses, so they wait in their own bounded FIFO and go first.

Transports report updates under the peer that handed them over (zenoh: the robot; UWB: the sending
node), and a UWB node also forwards other robots' maps (the multi-hop relay). So a map waits in the
slot of its sender *and* of the robot it names (read from the envelope's first fields, unverified:
only to pick the slot), and "latest per slot" is "latest per robot": a relayed map never replaces
the relayer's own map, nor one of another robot, before the daemon has checked either. A sender
gets at most :data:`MAX_RELAYED` slots for robots other than itself, so one that names invented
robots (a forger, before any signature is checked) cannot take the inbox from the others.
"""

from __future__ import annotations

import asyncio
from collections import deque
from dataclasses import dataclass

from mapd.envelope import peek_robot
from transports.base import PoseReceived, Received, TransportEvent

#: Maps of robots other than the sender that may wait from one sender, each in a slot of its own. A
#: UWB robot relays one map at a time, so a few are plenty; more from one sender are dropped.
MAX_RELAYED = 8


@dataclass
class EventQueueCounters:
    """Updates replaced by a newer one of the same robot from the same peer before the daemon took
    them, and events dropped."""

    superseded: int = 0
    dropped: int = 0


class EventQueue:
    """Bounded inbox: one waiting update per (transport, peer, robot), and a FIFO of other events."""

    def __init__(self, max_events: int = 256, max_peers: int = 256) -> None:
        self.max_events = max_events
        self.max_peers = max_peers
        self._control: deque[TransportEvent] = deque()
        # (is a pose, transport, peer, robot) -> the update waiting in that slot
        self._updates: dict[tuple[bool, str, str, str], Received | PoseReceived] = {}
        # (transport, peer) -> how many of its slots hold maps of other robots (relayed)
        self._relayed: dict[tuple[str, str], int] = {}
        self._wake = asyncio.Event()
        self.counters = EventQueueCounters()

    def __len__(self) -> int:
        return len(self._control) + len(self._updates)

    def put(self, event: TransportEvent) -> None:
        """Add an event (event-loop thread only); never blocks."""
        if isinstance(event, Received | PoseReceived):
            # Poses are bound to their link; a map may be another robot's, which the peer relays.
            robot = (peek_robot(event.data) if isinstance(event, Received) else None) or event.peer
            key = (isinstance(event, PoseReceived), event.transport, event.peer, robot)
            sender = (event.transport, event.peer)
            if key in self._updates:
                del self._updates[key]  # re-insert at the end: peers take turns in arrival order
                self.counters.superseded += 1
            elif len(self._updates) >= self.max_peers or (
                robot != event.peer and self._relayed.get(sender, 0) >= MAX_RELAYED
            ):
                self.counters.dropped += 1
                return
            elif robot != event.peer:
                self._relayed[sender] = self._relayed.get(sender, 0) + 1
            self._updates[key] = event
        else:
            if len(self._control) >= self.max_events:
                self.counters.dropped += 1
                return
            self._control.append(event)
        self._wake.set()

    def get_nowait(self) -> TransportEvent | None:
        """The next event (control events first), or None when empty."""
        if self._control:
            return self._control.popleft()
        if self._updates:
            key = next(iter(self._updates))
            _, transport, peer, robot = key
            if robot != peer:
                sender = (transport, peer)
                if self._relayed[sender] > 1:
                    self._relayed[sender] -= 1
                else:
                    del self._relayed[sender]  # no entry kept per sender ever heard
            return self._updates.pop(key)
        return None

    async def get(self) -> TransportEvent:
        """Wait for the next event."""
        while True:
            event = self.get_nowait()
            if event is not None:
                return event
            self._wake.clear()
            await self._wake.wait()
