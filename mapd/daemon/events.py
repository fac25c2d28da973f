"""The daemon's event inbox: transport events wait here for the event loop, bounded and latest-wins.

A peer may send faster than the daemon can verify and decode (a flood, or a fast link and a slow
robot). A plain bounded queue would then drop the *newest* update, which is the one that matters.
Here each ``(transport, peer)`` holds at most one waiting :class:`~transports.base.Received`: a newer
one replaces it (counted as ``superseded``), so the daemon always ends on the peer's latest map and
memory stays bounded by the number of peers. Pose messages are latest-wins too, one waiting per
peer beside its map. Other events (acks, presence, keyframe needs) are small and must not be lost
to a flood of maps or poses, so they wait in their own bounded FIFO and go first.

Transports report every robot's updates under that robot's peer name (zenoh: the robot; UWB: the
sending node, which only sends its own robot's map), so "latest per peer" is "latest per robot".
"""

from __future__ import annotations

import asyncio
from collections import deque
from dataclasses import dataclass

from transports.base import PoseReceived, Received, TransportEvent


@dataclass
class EventQueueCounters:
    """Updates replaced by a newer one from the same peer before the daemon took them, and events dropped."""

    superseded: int = 0
    dropped: int = 0


class EventQueue:
    """Bounded inbox: one waiting update per (transport, peer), and a FIFO of other events."""

    def __init__(self, max_events: int = 256, max_peers: int = 256) -> None:
        self.max_events = max_events
        self.max_peers = max_peers
        self._control: deque[TransportEvent] = deque()
        self._updates: dict[tuple[bool, str, str], Received | PoseReceived] = {}
        self._wake = asyncio.Event()
        self.counters = EventQueueCounters()

    def __len__(self) -> int:
        return len(self._control) + len(self._updates)

    def put(self, event: TransportEvent) -> None:
        """Add an event (event-loop thread only); never blocks."""
        if isinstance(event, Received | PoseReceived):
            key = (isinstance(event, PoseReceived), event.transport, event.peer)
            if key in self._updates:
                del self._updates[key]  # re-insert at the end: peers take turns in arrival order
                self.counters.superseded += 1
            elif len(self._updates) >= self.max_peers:
                self.counters.dropped += 1
                return
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
