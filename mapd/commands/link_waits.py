"""When ``mapd link`` stops waiting: ``recv`` for a sender gone quiet, ``send`` for receivers gone
silent. Sans-I/O: the command passes what it saw and ``now``; no clock or link here.
"""

from __future__ import annotations

from typing import Any

#: ``recv``'s default ``--linger``: three of the sender's longest retransmission waits (the core's
#: ``max_rto_s``, 4 s). Its probes back off to one such wait, so a line quiet for three of them means
#: it heard our COMPLETE (or gave up), or that three probes in a row were lost (at 20 % loss, 1 in
#: 125; two would be 1 in 25). A fixed 3 s was shorter than one wait: a sender whose last COMPLETEs
#: were lost probed a receiver that had left, and reported a delivered file as not delivered.
LINGER_S = 12.0
#: ``send`` gives up on a receiver silent for this many of its peer timeouts (``--peer-timeout``,
#: 20 s by default) after the whole file was on the air: see :class:`Silence`.
SILENT_TIMEOUTS = 2.0
#: ``send --peer-timeout``'s default: the daemon's ``[transports.uwb] peer_timeout_s``.
PEER_TIMEOUT_S = 20.0
#: ``recv`` lingers at most this long in all: a sender that never hears it probes until its own limit.
LINGER_MAX_S = 60.0


class Quiet:
    """When ``recv`` may leave: once the line has been quiet for ``quiet_s`` (the sender heard our
    COMPLETE, or gave up), or ``max_s`` after it started lingering. Sans-I/O: the caller passes the
    bytes received so far and ``now``."""

    def __init__(self, quiet_s: float, max_s: float, now: float) -> None:
        self.quiet_s = quiet_s
        self.until = now + max_s
        self._count: int | None = None
        self._last = now

    def heard(self, count: int, now: float) -> None:
        """The link's received byte count at ``now``: a change means the sender still talks."""
        if count != self._count:
            self._count, self._last = count, now

    def over(self, now: float) -> bool:
        return now - self._last >= self.quiet_s or now >= self.until


class Silence:
    """When ``send`` stops waiting for peers that fell silent. Sans-I/O: the caller passes the core's
    events and ``now``.

    A peer still to acknowledge that was heard, and then not for ``silent_s`` since the whole file
    was on the air (or since it was last heard, if later): it got the file and left with its last
    acks lost, or it is gone, and waiting for ``--deadline`` only repeats probes to nobody. The
    core says a peer is down after ``timeout_s`` of silence (PeerDown), so it was last heard about
    ``timeout_s`` before that. ``silent_s`` is longer than ``timeout_s``: a receiver still taking
    the file answers each probe and says HELLO every few seconds, but at 50 % loss each way 20 s
    without one of its frames happens now and then, and giving up on a transfer that goes on would
    be the false failure this replaces. A peer never heard is waited for until the deadline (its
    ``recv`` may not have started yet).
    """

    def __init__(self, peers: list[int], timeout_s: float, silent_s: float) -> None:
        self.timeout_s = timeout_s
        self.silent_s = silent_s
        self.pending = set(peers)
        self.heard: set[int] = set()
        self._down_at: dict[int, float] = {}
        self.flushed_at: float | None = None

    def event(self, e: Any, now: float) -> None:
        from transports.uwb import arq

        if isinstance(e, arq.MessageFlushed) and self.flushed_at is None:
            self.flushed_at = now
        elif isinstance(e, arq.PeerUp):
            self.heard.add(e.peer)
            self._down_at.pop(e.peer, None)
        elif isinstance(e, arq.PeerDown):
            self._down_at[e.peer] = now
        elif isinstance(e, arq.MessageDelivered | arq.MessageFailed):
            self.pending.discard(e.peer)

    def gave_up(self, now: float) -> bool:
        """True once every peer still pending was heard, and has been silent for ``silent_s``
        since the file was wholly on the air."""
        flushed = self.flushed_at
        if not self.pending or flushed is None:
            return False
        for p in self.pending:
            down = self._down_at.get(p)
            if (
                p not in self.heard
                or down is None
                or now - max(down - self.timeout_s, flushed) < self.silent_s
            ):
                return False
        return True
