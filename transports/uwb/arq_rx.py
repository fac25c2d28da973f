"""The receiving half of :class:`~transports.uwb.arq.ArqEndpoint`: rules R10-R13 and the receiver's
part of R16 (in ``arq.py``'s docstring), as a mixin over the endpoint's state.

What a receiver does with DATA (reassembly, refusal, memory bounds), which ACK or DONE it owes and
when, and the frames that say them. The sender's half is in ``arq_tx.py`` and ``arq_acks.py``,
frame input in ``arq_input.py``, the timers in ``arq_timers.py`` and the rest of the API in
``arq.py``; all share one state, which :class:`~transports.uwb.arq.ArqEndpoint` sets up.
"""

from __future__ import annotations

import math
import random
from collections import OrderedDict, deque
from collections.abc import Callable

from transports.uwb import fec, wire
from transports.uwb.arq_types import ArqConfig, ArqCounters, Event, MessageReceived
from transports.uwb.framing import check_len, cobs_max_len
from transports.uwb.receiving import CHUNK_COST, Partial, PeerState

#: Chunks a message may have (the wire's u16 index; an ACK's base is clamped to it).
MAX_CHUNKS = 0xFFFF
#: COMPLETEs owed in DONE frames (R16), all peers together; past it the oldest goes unsaid (the
#: sender's probe asks again).
MAX_DONE_OWED = 64


def _no_ack(msg: int, when: float) -> None:
    """What a receiver owes for a DGRAM chunk: nothing."""


class ReceiverSide:
    """Receiving rules of the ARQ endpoint (a mixin: :class:`~transports.uwb.arq.ArqEndpoint` owns
    the state declared here)."""

    cfg: ArqConfig
    counters: ArqCounters
    node: int
    session: int
    _rng: random.Random
    _crc: bool
    _trailer: int
    _max_total: int
    _rx_budget: int
    _rx_held: int
    _ack_delay: float
    _nack_backoff: float
    _peers: dict[int, PeerState]
    #: (peer, msg) -> (due, the peer's session then): COMPLETEs to go in the next DONE frame.
    _done_owed: OrderedDict[tuple[int, int], tuple[float, int]]
    _done_max: int
    _events: deque[Event]

    def _nack_mode(self, dst: int) -> bool:
        """Whether a reliable message to ``dst`` (a link id, or BROADCAST) is acked in NACK mode."""
        return self.cfg.acks == "nack" or (self.cfg.acks == "auto" and dst == wire.BROADCAST)

    def _understands(self, node: int, feature: int) -> bool:
        """Whether peer ``node`` takes ``feature`` (a ``wire.F_*`` bit) by its last HELLO; yes for a
        node not heard announcing (``PeerState.understands``)."""
        peer = self._peers.get(node)
        return peer is None or peer.understands(feature)

    def _nack_due(self, now: float) -> float:
        """When a gap report is due: after a random backoff, skewed late the more receivers may
        share the gap, so that the first report is usually alone and overheard by the others in time
        (R16). The truncated exponential of NORM's RandomBackoff (RFC 5740; Nonnenmacher and Biersack):
        over ``[0, T]`` with lambda = ln(group) + 1, the group estimated by the peers heard."""
        t_max = self._nack_backoff
        lam = math.log(max(2, sum(1 for p in self._peers.values() if p.up))) + 1
        x = self._rng.uniform(0, lam / t_max) + lam / (t_max * (math.exp(lam) - 1))
        return now + max(0.0, (t_max / lam) * math.log(x * (math.exp(lam) - 1) * (t_max / lam)))

    def _on_data(self, peer: PeerState, d: wire.Data, now: float) -> None:
        cfg = self.cfg
        # A DGRAM's sender waits for no ack: owe none (a lost one is replaced by the next).
        owe = peer.owe_ack if d.reliable else _no_ack
        # A sender that says it lacks DONE would never hear our COMPLETE: ack it each, as it acks.
        nack = d.reliable and self._nack_mode(d.dst) and self._understands(peer.id, wire.F_DONE)
        if d.dst not in (self.node, wire.BROADCAST):
            self.counters.not_for_me += 1
            return
        if d.total > self._max_total:
            if d.msg not in peer.rejected:
                self.counters.rejected += 1
            peer.remember_rejected(d.msg)
            owe(d.msg, now)
            return
        if d.msg in peer.completed or d.msg in peer.rejected:
            self.counters.duplicates += 1
            if nack and d.msg in peer.completed:
                last = peer.complete_sent.get(d.msg)
                # Answered within the shortest probe interval: a burst of repairs for other peers,
                # not a probe (every probe still gets an answer: it may be our COMPLETE it lacks).
                if last is None or now - last >= cfg.min_rto_s:
                    self._owe_done(peer, d.msg, now + cfg.ack_min_gap_s)
                return
            owe(d.msg, now + cfg.ack_min_gap_s)
            return
        part = peer.partials.get(d.msg)
        if part is None:
            top = peer.stream_top.get(d.stream)
            if top is not None and wire.msg_before(d.msg, top):
                self.counters.stale += 1
                return
            for old in [p for p in peer.partials.values() if p.stream == d.stream]:
                self._rx_held -= peer.drop_partial(old.msg)
                self.counters.superseded_rx += 1
            if len(peer.partials) >= peer.max_partials:
                victim = peer.oldest_partial()
                if victim is not None:
                    self._rx_held -= peer.drop_partial(victim.msg)
                    self.counters.evicted += 1
            part = Partial(d.msg, d.stream, d.count, d.total, peer.next_gen(), now, nack=nack)
            peer.partials[d.msg] = part
            peer.stream_top[d.stream] = d.msg
        elif part.count != d.count or part.total != d.total:
            self.counters.bad_frames += 1
            return
        if d.index >= d.count:
            self._on_parity(peer, part, d, now)
            return
        if d.index in part.chunks:
            self.counters.duplicates += 1
            if not part.nack:
                owe(d.msg, now + cfg.ack_min_gap_s)
            elif part.gaps():
                owe(d.msg, self._nack_due(now))  # a probe or a repair for others, and we lack some
            return
        if part.held - part.parity_held + len(d.payload) > part.total:
            self.counters.bad_frames += 1
            return
        if not self._make_room(len(d.payload) + CHUNK_COST, keep=part):
            self.counters.evicted += 1
            return
        gap = d.index != part.top + 1
        new_hole = d.index > part.top + 1
        part.add(d.index, d.payload, now)
        self._rx_held += len(d.payload) + CHUNK_COST
        if part.parity:  # a chunk that arrives late may be the one a block's parity lacked
            self._recover(part, fec.block_of(part.count, d.index))
        if part.complete():
            self._complete(peer, part, now, owe)
            return
        if part.nack:
            # R16: report only new evidence of loss: a chunk past the next expected (a new hole), or
            # a resend arriving while a hole is left below it (that hole's repair was lost).
            if new_hole or (gap and part.base < d.index):
                owe(d.msg, self._nack_due(now))
            return
        urgent = gap or part.fresh >= cfg.ack_every
        owe(d.msg, now if urgent else now + self._ack_delay)

    def _on_parity(self, peer: PeerState, part: Partial, d: wire.Data, now: float) -> None:
        """A parity chunk (fec.py; only broadcast maps in NACK mode have them): held until its block
        can be rebuilt, and a gap report owed while chunks are still missing after it."""
        if not part.nack:
            if d.dst != wire.BROADCAST:
                self.counters.bad_frames += 1  # a unicast message is repaired chunk by chunk
                return
            # Acked each because of what its sender announced, but it repairs with parity, so it
            # runs NACK mode (a stale or false word): take the parity and ack as it expects, this
            # map and its next ones (else every repair it sends others gets an ACK of ours).
            part.nack = True
            if peer.features is not None:
                peer.features |= wire.F_DONE | wire.F_PARITY
        if len(d.payload) > part.total or not part.wants_parity(d.index):
            self.counters.duplicates += 1
            if part.gaps():
                peer.owe_ack(d.msg, self._nack_due(now))
            return
        if not self._make_room(len(d.payload) + CHUNK_COST, keep=part):
            self.counters.evicted += 1
            return
        part.add_parity(d.index, d.payload, now)
        self.counters.parity_rx += 1
        self._rx_held += len(d.payload) + CHUNK_COST
        self._recover(part, fec.parity_of(part.count, d.index)[0])
        if part.complete():
            self._complete(peer, part, now, peer.owe_ack)
        elif part.gaps():
            peer.owe_ack(d.msg, self._nack_due(now))

    def _recover(self, part: Partial, block: int) -> None:
        before = part.cost
        try:
            self.counters.recovered += part.recover(block)
        except ValueError:
            self.counters.bad_frames += 1  # parity of the wrong length: dropped with its block's
        self._rx_held += part.cost - before

    def _complete(
        self, peer: PeerState, part: Partial, now: float, owe: Callable[[int, float], None]
    ) -> None:
        """Every chunk of ``part`` is held: deliver it if its hash holds, else start it again."""
        self._rx_held -= peer.drop_partial(part.msg)
        data = part.verified()
        if data is None:
            self.counters.hash_errors += 1
            peer.partials[part.msg] = Partial(
                part.msg, part.stream, part.count, part.total, peer.next_gen(), now, nack=part.nack
            )
        else:
            peer.remember_completed(part.msg, part.gen)
            self.counters.messages_rx += 1
            self._events.append(MessageReceived(peer.id, part.stream, part.msg, data))
            if part.nack:
                # R16: said in a DONE frame with the other COMPLETEs owed by then (a frame
                # each would cost N (N - 1) frames a round of broadcast maps)
                self._owe_done(peer, part.msg, now + self._ack_delay)
                return
        owe(part.msg, now)

    def _make_room(self, n: int, keep: Partial) -> bool:
        """Drop the least recently active partials (not ``keep``) until ``n`` more fit (a chunk's
        bytes and its :data:`~transports.uwb.receiving.CHUNK_COST`)."""
        while self._rx_held + n > self._rx_budget:
            victims = [(p.last, peer, p) for peer in self._peers.values() for p in peer.partials.values()]
            victims = [v for v in victims if v[2] is not keep]
            if not victims:
                return False
            _, peer, p = min(victims, key=lambda v: v[0])
            self._rx_held -= peer.drop_partial(p.msg)
            self.counters.evicted += 1
        return True

    def _est(self, body_len: int) -> int:
        return cobs_max_len(body_len + self._trailer + check_len(self._crc)) + 1

    def _owe_done(self, peer: PeerState, msg: int, due: float) -> None:
        key = (peer.id, msg)
        old = self._done_owed.get(key)
        self._done_owed[key] = (min(due, old[0]) if old else due, peer.session)
        while len(self._done_owed) > MAX_DONE_OWED:
            self._done_owed.popitem(last=False)

    def _done_due(self) -> float | None:
        return min((due for due, _ in self._done_owed.values()), default=None)

    def _done_est(self) -> int:
        n = min(len(self._done_owed), self._done_max)
        return self._est(wire.HEADER_LEN + n * wire.DONE_ENTRY_LEN)

    def _owed_ack(self) -> tuple[float, PeerState, int] | None:
        best: tuple[float, PeerState, int] | None = None
        for peer in self._peers.values():
            for msg, due in peer.acks_due.items():
                if best is None or due < best[0]:
                    best = (due, peer, msg)
        return best

    def _build_ack(self, peer: PeerState, msg: int, now: float) -> wire.Ack | None:
        del peer.acks_due[msg]
        base, bitmap, flags = 0, b"", 0
        part = peer.partials.get(msg)
        if part is not None:
            if part.nack:
                if not part.gaps():
                    return None  # the holes were filled meanwhile: nothing to ask for
                self.counters.nacks_tx += 1
            base, bitmap = part.report()
            gen, base = part.gen, min(base, MAX_CHUNKS)
            part.fresh = 0
        elif msg in peer.completed:
            gen, flags = peer.completed[msg], wire.COMPLETE
            peer.sent_complete(msg, now)
        elif msg in peer.rejected:
            gen, flags = 0, wire.REJECT
        else:
            return None  # forgotten since (evicted): nothing true to say
        self.counters.acks_tx += 1
        return wire.Ack(self.node, peer.id, self.session, peer.session, msg, gen, flags, base, bitmap)

    def _build_done(self, now: float) -> wire.Done | None:
        """One DONE frame with every COMPLETE owed, due or not (earliest first, as many as fit)."""
        entries: list[tuple[int, int, int]] = []
        for key in sorted(self._done_owed, key=lambda k: self._done_owed[k][0]):
            if len(entries) >= self._done_max:
                break
            _, session = self._done_owed.pop(key)
            peer = self._peers.get(key[0])
            if peer is None or peer.session != session or key[1] not in peer.completed:
                continue  # it restarted, or we forgot: nothing true to say
            entries.append((peer.id, peer.session, key[1]))
            peer.sent_complete(key[1], now)
        if not entries:
            return None
        self.counters.acks_tx += 1
        self.counters.completes_tx += len(entries)
        return wire.Done(self.node, wire.BROADCAST, self.session, tuple(entries))
