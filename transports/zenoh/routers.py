"""Which zenoh routers the session is connected to, and the two lines worth saying about them.

zenoh reconnects a client to its router by itself (and a peer to the routers it connects to),
trying again every few seconds without a word. Meanwhile every robot reached only through that
router is gone (its liveliness token vanishes: ``PeerDown``) and maps, acks and keyframe queries go
nowhere; before this, ``mapd status`` listed the peers as gone and the log said nothing at all, not
when the router went and not when it came back. :class:`RouterLink` follows zenoh's transport
events (router transports opening and closing): it says the loss once, when the last router goes,
and the return once, when a router is there again, however many tries zenoh makes in between.
A router that comes back is another transport (a restarted router has a new zenoh id), so both
lines name the router by its id.

A loss within :data:`SAID_EVERY_S` of the last one said, and its return, go to DEBUG (counted in
``losses`` all the same): a router that flaps, or anyone who can open zenoh transports to a robot
that listens and calls itself a router, must not fill the journal with a pair of lines each time.

Sans-I/O: the adapter (:mod:`transports.zenoh.intake`) feeds it each event with ``now`` and logs
the line it returns at the level it says.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

#: Characters of a zenoh id shown in a line (enough to tell the routers of a mesh apart).
ZID_CHARS = 8
#: Seconds after a loss said within which another loss (and its return) is said at DEBUG only.
SAID_EVERY_S = 60.0


@dataclass
class RouterLink:
    """The routers this session is connected to now, and since when none is (see the module docstring)."""

    routers: set[str] = field(default_factory=set)
    #: Whether a router was ever connected (a peer fleet without one never says anything).
    seen: bool = False
    #: When the last router went (monotonic), while none is connected; None otherwise.
    lost_at: float | None = None
    #: How many times the session lost its last router.
    losses: int = 0
    #: When a loss was last said at WARNING, and whether the loss under way was (its return is then
    #: said at INFO).
    _said_at: float | None = None
    _loud: bool = False

    @property
    def connected(self) -> bool | None:
        """None while no router was ever connected, else whether one is now (``mapd status``)."""
        return bool(self.routers) if self.seen else None

    def opened(self, zid: str, now: float) -> tuple[int, str] | None:
        """A transport to router ``zid`` opened; the level and line to log when it ends a loss."""
        self.seen = True
        first = not self.routers
        self.routers.add(zid)
        if not first or self.lost_at is None:
            return None
        lost, self.lost_at = self.lost_at, None
        return (
            logging.INFO if self._loud else logging.DEBUG,
            f"zenoh: connected to a router again after {now - lost:.0f} s (router {zid[:ZID_CHARS]}); "
            "robots reached through it rejoin as their tokens arrive",
        )

    def closed(self, zid: str, now: float) -> tuple[int, str] | None:
        """The transport to router ``zid`` closed; the level and line to log when it was the last."""
        if zid not in self.routers:
            return None
        self.routers.discard(zid)
        if self.routers:
            return None
        self.lost_at = now
        self.losses += 1
        last = self._said_at
        # (a clock that went back counts as due, as the receiver's warnings do)
        self._loud = last is None or not 0 <= now - last < SAID_EVERY_S
        if self._loud:
            self._said_at = now
        again = "" if self._loud else f" (loss {self.losses}; said at most once a minute)"
        return (
            logging.WARNING if self._loud else logging.DEBUG,
            f"zenoh: lost the connection to router {zid[:ZID_CHARS]}; robots reached only through it "
            f"are out of reach until zenoh reconnects (it keeps trying by itself){again}",
        )
