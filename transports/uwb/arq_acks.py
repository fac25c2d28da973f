"""The sender's ack handling of :class:`~transports.uwb.arq.ArqEndpoint`: what it does with the ACKs,
COMPLETEs and DONE entries it hears (R5's late COMPLETEs, R6, R8, R9, and the sender's part of R16
in ``arq.py``'s docstring), as a mixin over the endpoint's state.

A COMPLETE delivers a message to a peer; a selective ACK advances what the peer holds and detects
losses; a gap report (NACK mode) queues each asked chunk once for all; another receiver's ACK,
overheard, may make a gap report of ours redundant. Sending frames is in ``arq_tx.py``, the timers
in ``arq_timers.py``, the rest of the API in ``arq.py``; :class:`~transports.uwb.arq.ArqEndpoint`
sets up the state declared here.
"""

from __future__ import annotations

from collections import OrderedDict, deque

from transports.rtt import RttEstimator
from transports.uwb import fec, wire
from transports.uwb.arq_types import (
    ArqConfig,
    ArqCounters,
    Event,
    MessageClosed,
    MessageDelivered,
    MessageFailed,
)
from transports.uwb.receiving import PeerState, asked_by
from transports.uwb.sending import Outgoing

#: ``goodput_bps`` is what was delivered over this many seconds before ``now``: long enough to hold
#: a few maps (one every few seconds), short enough that an outage shows as 0 within half a minute.
GOODPUT_WINDOW_S = 30.0

#: Proactive parity (R16, fec): its share of each block's chunks at most, and its steps.
PROACTIVE_MAX = 0.5
PROACTIVE_UP = 0.05
PROACTIVE_DOWN = 0.01


class GoodputWindow:
    """Bytes delivered per second over the last ``window_s`` seconds, as bits/s. Sans-I/O: times
    are passed in.

    Each message's bytes are spread evenly over its life, from queued to delivered, and only the
    part of that life inside the window counts: a small message that left in the pacer's first
    burst counts as its bytes over the window (not as that burst's rate, many times the link's),
    a long one delivered at once does not count as all of it in the last few seconds, and with
    nothing delivered for ``window_s`` the rate is 0 (not the last message's, for ever). Bounded:
    at most ``max_items`` messages are kept (the oldest dropped first).
    """

    def __init__(self, window_s: float = GOODPUT_WINDOW_S, max_items: int = 1024) -> None:
        self.window_s = window_s
        self.max_items = max_items
        self._items: deque[tuple[float, float, int]] = deque(maxlen=max_items)  # (start, end, bytes)

    def __len__(self) -> int:
        return len(self._items)

    def add(self, nbytes: int, start: float, end: float) -> None:
        """A message of ``nbytes`` queued at ``start`` was delivered at ``end``."""
        self._items.append((start, max(start, end), nbytes))
        while self._items and self._items[0][1] <= end - self.window_s:
            self._items.popleft()  # ended before the window: counts for nothing any more

    def rate_bps(self, now: float) -> float:
        """Bits per second delivered over ``[now - window_s, now]``."""
        lo = now - self.window_s
        total = 0.0
        for start, end, n in self._items:
            if end <= lo or start > now:
                continue
            if end <= start:  # delivered the moment it was queued
                total += n
            else:
                total += n * (min(end, now) - max(start, lo)) / (end - start)
        return 8 * total / self.window_s


class AckSide:
    """The sender's ack rules (a mixin: :class:`~transports.uwb.arq.ArqEndpoint` owns the state
    declared here)."""

    cfg: ArqConfig
    counters: ArqCounters
    node: int
    session: int
    _peers: dict[int, PeerState]
    _out: OrderedDict[int, Outgoing]
    #: Superseded message -> the peers whose late COMPLETE still counts (R5).
    _late: OrderedDict[int, set[int]]
    _rtt: dict[int, RttEstimator]
    _events: deque[Event]
    _now: float
    #: Messages delivered lately, for ``goodput_bps`` in ``stats()``.
    _delivered: GoodputWindow
    _proactive: float

    def _on_done_entry(self, peer: PeerState, target: int, low: int, now: float) -> None:
        """A DONE entry for us: the COMPLETE ack it stands for, with the message's full id and the
        peer's buffer generation filled in from what we track (wire.py: entries carry low bits)."""
        if target != self.session & 0xFF:
            self.counters.stale_acks += 1
            return
        msg = next((m for m in (*self._out, *self._late) if m & 0xFFFF == low), None)
        if msg is None:
            self.counters.unknown_acks += 1
            return
        out = self._out.get(msg)
        prog = out.peers.get(peer.id) if out is not None else None
        gen = prog.gen if prog is not None and prog.gen is not None else 0
        self._on_ack(
            peer,
            wire.Ack(peer.id, self.node, peer.session, self.session, msg, gen, wire.COMPLETE, 0, b""),
            now,
        )

    def _on_ack(self, peer: PeerState, a: wire.Ack, now: float) -> None:
        self.counters.acks_rx += 1
        if a.dst != self.node:
            self.counters.not_for_me += 1
            self._overheard(a)
            return
        if a.target_session != self.session:
            self.counters.stale_acks += 1
            return
        m = self._out.get(a.msg)
        prog = m.peers.get(peer.id) if m is not None else None
        if m is None and a.flags & wire.COMPLETE and peer.id in self._late.get(a.msg, ()):
            self._late[a.msg].discard(peer.id)
            self.counters.late_completes += 1
            self._events.append(MessageDelivered(a.msg, peer.id))
            return
        if m is None or prog is None or not prog.pending:
            self.counters.unknown_acks += 1
            return
        if a.flags & wire.REJECT:
            prog.failed = True
            self.counters.messages_failed += 1
            self._events.append(
                MessageFailed(m.msg, peer.id, "refused by peer (over its message limit)", final=True)
            )
            self._maybe_close(m, now)
            return
        if prog.gen is not None and a.gen != prog.gen:
            prog.reset()
            self.counters.gen_resets += 1
            for i in range(m.next_new):
                m.queue_resend(i)
        prog.gen = a.gen
        if a.flags & wire.COMPLETE:
            newly = [i for i in range(m.count) if not prog.acked[i]]
            m.mark_all_acked(prog)
        else:
            newly = m.apply_ack(prog, a.base, a.bitmap)
        rtt = self._rtt_of(peer.id)
        once = [i for i in newly if m.sends[i] == 1]
        if once:
            # NACK mode acks whole runs of chunks at once, long after the first was sent: time the
            # round trip from the newest (a sample that includes the receiver's backoff, as the
            # probe timer should; RFC 5740's GRTT does the same).
            sent = max if m.nack else min
            rtt.sample(now - sent(m.sent_at[i] for i in once))
        if a.flags & wire.COMPLETE:
            prog.done = True
            prog.rto_at = None
            self._events.append(MessageDelivered(m.msg, peer.id))
            self._maybe_close(m, now)
            return
        if m.nack:
            # A gap report: every chunk it asks for is queued once, whoever else asked for it too;
            # the probe timer restarts when the sender runs out of chunks to send (see _build).
            # With parity, a report asks for so many chunks of each block, and the parity queued
            # for the others' reports serves it too (the report leaves out what parity it holds).
            if m.fec:
                asked = [i for i in asked_by(a.base, a.bitmap) if i < m.next_new and m.sends[i]]
                self.counters.repairs_queued += m.queue_parity(asked)
                return
            for i in m.requested(prog, a.base, a.bitmap):
                self.counters.repairs_queued += m.queue_resend(i)
            return
        m.detect_losses(prog, self.cfg.reorder_tolerance)
        if newly:
            waiting = bool(m.outstanding(prog)) or prog.n_acked == m.count
            prog.rto_at = now + rtt.rto if waiting else None

    def _overheard(self, a: wire.Ack) -> None:
        """Another receiver's ACK to a data sender (a shared channel carries every frame to all): in
        NACK mode, a gap report of ours that it makes redundant is dropped (R16, suppression): one
        that asks for every chunk we lack or, once the sender is known to repair with parity, for
        as many chunks of each block."""
        if a.flags:
            return  # COMPLETE and REJECT ask for nothing
        sender = self._peers.get(a.dst)
        if sender is None or a.target_session != sender.session or a.msg not in sender.acks_due:
            return
        part = sender.partials.get(a.msg)
        if part is None or not part.nack:
            return
        mine = part.gaps()
        theirs = asked_by(a.base, a.bitmap)
        if part.parity:
            # The sender repairs with parity (we hold some): its answer to their report is so many
            # parity chunks of each block, which serve us as well as them if we need no more.
            want, asked = fec.per_block(part.count, mine), fec.per_block(part.count, theirs)
            covered = all(n <= asked.get(b, 0) for b, n in want.items())
        else:
            covered = set(mine) <= theirs
        if mine and covered:
            del sender.acks_due[a.msg]
            self.counters.nacks_suppressed += 1

    def _rtt_of(self, peer: int) -> RttEstimator:
        rtt = self._rtt.get(peer)
        if rtt is None:
            rtt = RttEstimator(
                initial_rto=self.cfg.initial_rto_s, min_rto=self.cfg.min_rto_s, max_rto=self.cfg.max_rto_s
            )
            self._rtt[peer] = rtt
        return rtt

    def _maybe_close(self, m: Outgoing, now: float) -> None:
        if not m.finished():
            return
        if all(p.done for p in m.peers.values()):
            self.counters.messages_delivered += 1
            self.counters.bytes_delivered += m.size
            self._delivered.add(m.size, m.created, now)
        self._close(m)

    def _close(self, m: Outgoing, outcome: str | None = None) -> None:
        if m.fec and m.flushed:
            # R16 with fec: parity sent behind the first pass follows the worst receiver's loss. A
            # gap report after the pass (a repair round: a TDMA cycle or two of waiting) raises it
            # by what that round sent, a message without one lowers it a little, and a clean
            # channel never carries parity. A message whose receivers all completed before its
            # pass ended (parity asked for during it went instead of the rest) says nothing.
            step = max(PROACTIVE_UP, m.late_parity / m.count) if m.repaired else -PROACTIVE_DOWN
            self._proactive = min(PROACTIVE_MAX, max(0.0, self._proactive + step))
        self._out.pop(m.msg, None)
        if outcome is None:
            outcome = "delivered" if all(p.done for p in m.peers.values()) else "failed"
        self._events.append(MessageClosed(m.msg, outcome))
