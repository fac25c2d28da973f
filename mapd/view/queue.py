"""One viewer's bounded queue of server-sent events: latest wins, memory never grows.

Every message is encoded once (an SSE frame as bytes) and shared by all viewers, so a queue holds
references, not copies. Three kinds of message travel:

* ``map`` deltas must arrive in order (each draws only the tiles that changed since the one before);
* ``robots`` and ``status`` replace the whole previous one, so a queued older one is simply dropped
  when a newer one comes (latest wins);
* when a viewer falls ``limit`` messages behind (a phone on a bad link), its queue is emptied and it
  is marked to *resync*: the next time it is written to, it gets the current full state (the whole
  map, the robots, the status) instead of the deltas it missed.

So a slow viewer skips intermediate map versions and still ends on the newest one, and each queue
holds at most ``limit`` references however slow its reader. Sans-I/O: no asyncio, no clock.
"""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

#: Kinds whose newer message makes an older queued one worthless.
REPLACEABLE = frozenset({"robots", "status"})


@dataclass(frozen=True)
class Message:
    """One server-sent event, encoded once for every viewer."""

    kind: str
    frame: bytes
    #: For ``map``: the map version it brings the viewer to (0 for others).
    seq: int = 0

    @property
    def replaceable(self) -> bool:
        return self.kind in REPLACEABLE


def sse(kind: str, body: dict[str, Any], seq: int = 0) -> Message:
    """Encode ``body`` as one SSE frame (``event:`` + one ``data:`` line of compact JSON)."""
    data = json.dumps(body, separators=(",", ":"), default=str)
    # JSON never holds a raw newline, so the frame is exactly one data line.
    return Message(kind, f"event: {kind}\ndata: {data}\n\n".encode(), seq)


class ClientQueue:
    """The messages waiting for one viewer (at most ``limit``)."""

    def __init__(self, limit: int = 8) -> None:
        if limit < 2:
            raise ValueError("limit must be at least 2")
        self.limit = limit
        self._items: deque[Message] = deque()
        #: True when the viewer missed map deltas: its next batch starts with the full state.
        self.resync = True  # a new viewer starts with the full state, too
        #: Messages this viewer never got (dropped as stale or on overflow).
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._items)

    def put(self, msg: Message) -> None:
        """Queue ``msg``; a replaceable one drops its queued predecessor; overflow means resync."""
        if self.resync:
            # The full state it will get is newer than anything queued so far: nothing to keep.
            self.dropped += 1
            return
        if msg.replaceable:
            for old in self._items:
                if old.kind == msg.kind:
                    self._items.remove(old)
                    self.dropped += 1
                    break
        if len(self._items) >= self.limit:
            self.dropped += len(self._items) + 1
            self._items.clear()
            self.resync = True
            return
        self._items.append(msg)

    def take(self, current: Callable[[], list[Message]]) -> list[Message]:
        """Everything to write now, oldest first; ``current()`` gives the full state on resync."""
        if self.resync:
            self.resync = False
            self._items.clear()
            return list(current())
        out = list(self._items)
        self._items.clear()
        return out
