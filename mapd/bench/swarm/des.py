"""The swarm's event loop: a heap of (time, seq, event) in virtual time; nothing reads a clock.

Events are plain tuples handed to one ``dispatch(now, event)`` callable. Ties run in the order they
were scheduled (``seq``), so a run is a pure function of its inputs and seed. Nodes whose next
deadline moves schedule a new wake-up and bump a generation number; stale wake-ups are skipped by
the dispatcher (lazy deletion), which keeps the heap small without a decrease-key.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable
from typing import Any

Event = tuple[Any, ...]


class EventLoop:
    """Virtual time, advanced only by popping the earliest scheduled event."""

    def __init__(self) -> None:
        self.now = 0.0
        self._heap: list[tuple[float, int, Event]] = []
        self._seq = 0
        self.dispatched = 0

    def schedule(self, t: float, event: Event) -> None:
        """Run ``event`` at ``t`` (never before now: a past time runs at once, in order)."""
        self._seq += 1
        heapq.heappush(self._heap, (max(t, self.now), self._seq, event))

    def peek(self) -> float | None:
        return self._heap[0][0] if self._heap else None

    def run(
        self, until: float, dispatch: Callable[[float, Event], None], stop: Callable[[], bool] | None = None
    ) -> float:
        """Dispatch events in time order up to ``until`` (or until ``stop()``); return the time reached."""
        heap = self._heap
        while heap and heap[0][0] <= until:
            t, _, ev = heapq.heappop(heap)
            self.now = t
            self.dispatched += 1
            dispatch(t, ev)
            if stop is not None and stop():
                return self.now
        self.now = max(self.now, until)
        return self.now
