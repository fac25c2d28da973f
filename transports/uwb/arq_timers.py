"""When :class:`~transports.uwb.arq.ArqEndpoint` wants to be called back, and what fires then: a
message's deadline (R6), a peer's retransmission timer (R8; the flush probe of R16), a peer gone
silent (R3) and partial messages left idle (R11) (rules in ``arq.py``'s docstring), as a mixin over
the endpoint's state.

One timer for everything: :meth:`~TimerSide.get_timer` is the earliest of the frames waiting for
the pacer or the medium, the deadlines, the retransmission timers, the peers' timeouts and the
housekeeping of partials; :meth:`~TimerSide.handle_timer` fires whatever is due at ``now``.
"""

from __future__ import annotations

from transports.uwb import wire
from transports.uwb.arq_tx import SenderSide
from transports.uwb.arq_types import MessageFailed, PeerDown


class TimerSide(SenderSide):
    """The timers (a mixin: :class:`~transports.uwb.arq.ArqEndpoint` owns the state declared here
    and in the sides it builds on)."""

    _now: float
    #: R3: how long a peer may stay silent before it is down (with TDMA, at least two cycles more).
    _presence_s: float
    #: R11: how long a partial message may stay idle, and when idle ones are looked for next.
    _partial_ttl: float
    _housekeeping_at: float

    def get_timer(self) -> float | None:
        """When to call :meth:`handle_timer` (and :meth:`data_to_send`) next; None: only on input."""
        now = self._now
        times: list[float] = []
        can_sign = self._signer is None or self._signer.can_sign()
        if can_sign:
            for due, est in self._send_dues(now):
                t = max(due, now)
                times.append(max(t, self._pacer.ready_at(est, t), self._mac.ready_at(est, t)))
            lend = self._lend_to(now)
            if lend is not None:
                t, est = lend[0], self._est(wire.LEND_LEN)
                times.append(max(t, self._pacer.ready_at(est, t), self._mac.ready_at(est, t)))
        for m in self._out.values():
            times.append(m.deadline)
            times.extend(p.rto_at for p in m.peers.values() if p.pending and p.rto_at is not None)
        times.extend(p.last_heard + self._presence_s for p in self._peers.values() if p.up)
        if any(p.partials for p in self._peers.values()):
            times.append(self._housekeeping_at)
        return min(times) if times else None

    def handle_timer(self, now: float) -> None:
        """Fire whatever is due at ``now``: deadlines, retransmission timers, peer timeouts."""
        self._now = now
        for m in list(self._out.values()):
            if now >= m.deadline:
                for p in m.pending():
                    p.failed = True
                    self.counters.messages_failed += 1
                    self._events.append(MessageFailed(m.msg, p.peer, "deadline"))
                self._close(m)
                continue
            for p in m.pending():
                if p.rto_at is None or now < p.rto_at:
                    continue
                missing = m.outstanding(p)
                if m.nack:
                    # R16: probe with the last chunk (a receiver lacking it sees a gap, one holding
                    # it a duplicate: either answers with its gaps, or COMPLETE); once the peer is
                    # known to hold it, with the lowest chunk it is known to lack.
                    last = m.count - 1
                    m.queue_probe(missing[0] if p.acked[last] and missing else last)
                    rtt = self._rtt_of(p.peer)
                    rtt.backoff()
                    self.counters.timeouts += 1
                    p.rto_at = now + max(rtt.rto, self._cycle)
                    continue
                if missing:
                    m.queue_resend(missing[0])
                elif p.n_acked == m.count:
                    m.queue_resend(m.count - 1)  # all acked but COMPLETE not heard: ask again
                rtt = self._rtt_of(p.peer)
                rtt.backoff()
                self.counters.timeouts += 1
                p.rto_at = now + rtt.rto if (missing or p.n_acked == m.count) else None
        for peer in self._peers.values():
            if peer.up and now >= peer.last_heard + self._presence_s:
                peer.up = False
                self._events.append(PeerDown(peer.id))
        if now >= self._housekeeping_at:
            self._housekeeping_at = now + 1.0
            for peer in self._peers.values():
                for part in [p for p in peer.partials.values() if now - p.last > self._partial_ttl]:
                    self._rx_held -= peer.drop_partial(part.msg)
                    self.counters.evicted += 1
