"""What each peer takes: its announced ``limits.max_message_bytes``, and our maps over it.

A robot refuses a map over its own ``limits.max_message_bytes``, and between two hosts zenoh drops
one more than 64 KiB over it before mapd sees it (:mod:`transports.zenoh.session`), so the
receiver may say nothing at all; the sender heard only silence, waited for an ack on every offer
until its in-flight timeout, and said, at best, that the peer "takes none of our maps" 30 s later.
So each link declares a liveliness token ``mapd/<fleet>/<robot>/takes/<bytes>``
(:func:`~transports.zenoh.keys.takes_key`; inside the fleet's key space, so a router ACL that fences
``mapd/<fleet>/**`` passes it) and watches its fleet's. :class:`PeerLimits` keeps what each peer
announced, and when this robot offers a map larger than a peer takes (:meth:`PeerLimits.offered`):

* it is said once per peer (WARNING) with the peer, the map's size, the peer's limit and the fix,
  while our maps stay over that peer's limit: again only after a map fitted (or the peer announced
  another limit, a restart) and a later one is over;
* ``too_big_for`` in the link's stats shows each such peer (size and limit; at most
  :data:`MAX_SHOWN`), ``too_big_peers`` how many; ``mapd status`` shows them as a fault
  (:func:`mapd.daemon.headline.too_big_words`);
* the adapter emits ``Failed(again=False)`` for that peer and version, when it is one of the
  link's peers (those the publisher waits for), so the publisher does not wait for its ack (it
  still publishes: other peers take the map).

A peer that announces nothing (a robot from before the token) is taken as before: no line, no
``Failed``. A peer with two tokens at once (a restart whose old session has not timed out yet) is
held to the smaller limit.

**The tokens are unsigned**: a liveliness token carries no payload, so no signature. Anyone on the
network can declare one in a roster robot's name with any limit. What that can do is bounded to a
false warning, a false fault in ``mapd status`` and a skipped wait: the publisher stops waiting
for that peer's ack of that version (it goes on publishing, the peer still gets the map if it
takes it, and its ack still counts). Nothing is kept for a name the roster does not admit (the
adapter refuses those first, counted ``unadmitted``), for at most ``max_peers`` robots, with at
most :data:`MAX_VALUES` limits each; values outside
:data:`~transports.zenoh.keys.MIN_TAKES` .. :data:`~transports.zenoh.keys.MAX_TAKES` never parse.

Sans-I/O: no zenoh, clock or logging here (the caller says the lines). Fed on zenoh's threads
(:meth:`PeerLimits.announced`) and read on the loop's (:meth:`PeerLimits.offered`), hence the lock.
"""

from __future__ import annotations

import threading
from collections.abc import Collection
from dataclasses import dataclass, field
from typing import Any

#: Peers shown in ``too_big_for`` at once (all are counted in ``too_big_peers``).
MAX_SHOWN = 16
#: Limits kept per peer at once (one token per session: two only while a restart's old session
#: lingers); more under one name are ignored, so made-up tokens cannot grow what a name holds.
MAX_VALUES = 4


@dataclass(frozen=True)
class Over:
    """``peer`` takes messages up to ``limit`` bytes, and our map is ``size``."""

    peer: str
    size: int
    limit: int

    def reason(self) -> str:
        """Why the offer fails, for ``Failed.reason`` (said by the daemon once per peer)."""
        return (
            f"{self.size} bytes, over {self.peer}'s limits.max_message_bytes ({self.limit}): "
            f"raise it there to at least {self.size}"
        )


@dataclass
class Verdict:
    """What one offer meets: the peers that will refuse it, those of them to emit ``Failed`` for
    (the link's peers: the publisher waits for no other), and the lines to say now."""

    over: list[Over] = field(default_factory=list)
    failed: list[Over] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


@dataclass
class _Peer:
    #: The limits its tokens announce now (a set, in arrival order).
    limits: dict[int, None] = field(default_factory=dict)
    #: Our last map over its limit (None: the last one fitted, or none offered since it announced).
    over: Over | None = None
    said: bool = False

    def limit(self) -> int:
        return min(self.limits)


class PeerLimits:
    """The limits ``robot``'s peers announce, at most ``max_peers`` of them (see the module
    docstring); thread-safe."""

    def __init__(self, robot: str, max_peers: int) -> None:
        self.robot = robot
        self.max_peers = max_peers
        self._lock = threading.Lock()
        self._peers: dict[str, _Peer] = {}

    def announced(self, peer: str, limit: int, alive: bool) -> None:
        """``peer`` (admitted by the roster: the caller checks) declared (``alive``) or dropped a
        token saying it takes up to ``limit`` bytes. A new or lost limit is said anew."""
        if peer == self.robot:
            return  # our own token: we never send to ourselves
        with self._lock:
            st = self._peers.get(peer)
            if alive:
                if st is None:
                    if len(self._peers) >= self.max_peers:
                        return
                    st = self._peers[peer] = _Peer()
                if limit in st.limits or len(st.limits) >= MAX_VALUES:
                    return
                st.limits[limit] = None
            else:
                if st is None or limit not in st.limits:
                    return
                del st.limits[limit]
                if not st.limits:
                    del self._peers[peer]  # token gone: forgotten, as if it never announced
                    return
            # What it takes changed: the next offer is weighed against the new limit, and said.
            st.over, st.said = None, False

    def offered(self, size: int, peers: Collection[str] = ()) -> Verdict:
        """Our map of ``size`` bytes (within our own limit) is offered: the peers that take less,
        those of them among ``peers`` (the link's, whose acks the publisher waits for: ``Failed``
        goes only for them, so names that are no peer cannot fill the daemon's inbox), and the
        lines to say now (once per peer while our maps stay over its limit)."""
        out = Verdict()
        with self._lock:
            for peer, st in self._peers.items():
                limit = st.limit()
                if size <= limit:
                    st.over, st.said = None, False  # it fits: a later map over is said again
                    continue
                st.over = Over(peer, size, limit)
                out.over.append(st.over)
                if peer in peers:
                    out.failed.append(st.over)
                if not st.said:
                    st.said = True
                    out.warnings.append(self.line(st.over))
        return out

    def line(self, over: Over) -> str:
        """What a peer that refuses our map is said as: who, the sizes, the cost and the fix."""
        return (
            f"zenoh: {over.peer} takes messages up to {over.limit} bytes (its "
            f"limits.max_message_bytes), and {self.robot}'s map is {over.size} bytes: {over.peer} "
            f"gets none of this robot's maps while they are this large (its zenoh may drop them "
            f"unseen). Raise limits.max_message_bytes on {over.peer} to at least {over.size} (the "
            f"same on every robot), or make this robot's maps smaller"
        )

    def known(self) -> dict[str, int]:
        """Peer -> the limit it announced (the smaller of two), as kept now."""
        with self._lock:
            return {peer: st.limit() for peer, st in self._peers.items()}

    def stats(self) -> dict[str, Any]:
        """``too_big_for``: peer -> ``{"size", "limit"}`` of our last map over its limit (at most
        :data:`MAX_SHOWN`); ``too_big_peers``: how many peers that is in all."""
        with self._lock:
            over = [st.over for st in self._peers.values() if st.over is not None]
        return {
            "too_big_for": {o.peer: {"size": o.size, "limit": o.limit} for o in over[:MAX_SHOWN]},
            "too_big_peers": len(over),
        }
