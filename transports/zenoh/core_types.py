"""What the zenoh core gives back: the :class:`Step` the adapter carries out, and the counters.

Shared by :class:`~transports.zenoh.core.ZenohCore` and the sides it is built from
(:mod:`~transports.zenoh.answers`), and by the adapter that applies each step
(:mod:`~transports.zenoh.link`, :mod:`~transports.zenoh.intake`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from transports.base import TransportEvent

#: The transport's name, as its events carry it.
NAME = "zenoh"


@dataclass
class Step:
    """What the adapter must do after feeding the core one input."""

    events: list[TransportEvent] = field(default_factory=list)
    #: Robots whose latest keyframe to query now.
    queries: list[str] = field(default_factory=list)
    #: Lines to log as warnings (each said once: see :meth:`ZenohCore.oversize`).
    warnings: list[str] = field(default_factory=list)


@dataclass
class CoreCounters:
    """What the core has counted; :meth:`ZenohCore.stats` reports each field under its name."""

    bytes_rx: int = 0
    updates_rx: int = 0
    gaps: int = 0
    keyframe_queries: int = 0
    #: Updates, replies and acks refused with a SignatureError (unsigned while the fleet has a key,
    #: badly signed, or a signature field of the wrong form).
    bad_signature: int = 0
    #: Anything else refused: malformed, on a key it does not belong to, an ack of a version never sent.
    dropped: int = 0
    stale: int = 0
    acks_rx: int = 0
    queries_served: int = 0
    #: Keyframe queries left unanswered because answers were coming faster than the budget allows
    #: (a burst of REPLY_BURST, then REPLY_RATE_HZ; at most MAX_REPLIES_PENDING waiting).
    queries_shed: int = 0
    #: Updates, replies and keyframe queries naming a robot the roster does not admit: refused
    #: unread (updates, replies) or answered without a ``KeyframeNeeded`` (queries).
    unadmitted: int = 0
    #: Keyframe queries answered without a ``KeyframeNeeded`` because their nonce was not above the
    #: last one heeded from their asker: a recorded query played back.
    replayed: int = 0
    #: Updates and query replies over ``max_message_bytes``, refused unread: a peer whose limits
    #: are larger than ours (its robots in ``oversize_from``, each said once).
    oversize_rx: int = 0
