"""The sender's view of one message in flight: its chunks, what each intended peer holds, what to resend.

Pure bookkeeping used by :mod:`transports.uwb.arq`; the rules that drive it are written there.
"""

from __future__ import annotations

import hashlib
import heapq
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from transports.uwb import fec
from transports.uwb.wire import bitmap_indices

HASH_LEN = 16


def message_hash(data: bytes) -> bytes:
    """The hash that travels after a message and is checked before delivery (SHA-256, 16 bytes)."""
    return hashlib.sha256(data).digest()[:HASH_LEN]


@dataclass
class PeerProgress:
    """What one intended receiver holds of a message, as its acks tell."""

    peer: int
    count: int
    acked: bytearray = field(init=False)
    n_acked: int = 0
    low: int = 0  # every chunk below is acked
    gen: int | None = None  # the receiver's reassembly buffer the acks describe
    done: bool = False
    failed: bool = False
    max_acked_seq: int = 0  # newest transmission (by send order) this peer acked
    rto_at: float | None = None

    def __post_init__(self) -> None:
        self.acked = bytearray(self.count)

    @property
    def pending(self) -> bool:
        return not self.done and not self.failed

    def reset(self) -> None:
        """The receiver lost what it held (restart, new buffer): nothing counts as acked."""
        self.acked = bytearray(self.count)
        self.n_acked = 0
        self.low = 0
        self.gen = None
        self.max_acked_seq = 0


class Outgoing:
    """One message being sent to a set of peers, chunked, with per-chunk send history."""

    def __init__(
        self,
        msg: int,
        stream: int,
        data: bytes,
        chunk_size: int,
        dests: list[int],
        dst: int,
        now: float,
        deadline: float,
    ) -> None:
        self.msg = msg
        self.stream = stream
        self.size = len(data)
        self.body = data + message_hash(data)
        self.total = len(self.body)
        self.chunk_size = chunk_size
        self.count = -(-self.total // chunk_size)
        self.dst = dst
        self.created = now
        self.deadline = deadline
        self.peers = {p: PeerProgress(p, self.count) for p in dests}
        self.next_new = 0
        self.seq = [0] * self.count  # send order of each chunk's latest transmission (0: never)
        self.sent_at = [0.0] * self.count
        self.sends = [0] * self.count
        self.xmit = 0
        self._resend: list[int] = []
        self._resend_set: set[int] = set()
        #: Probes (NACK mode) go even when no pending peer is known to lack the chunk: the point is
        #: to make a silent receiver answer.
        self._probes: set[int] = set()
        #: NACK mode (R16): receivers report only gaps, so the send window is not held to acks.
        self.nack = False
        #: Sent only when no other message has a chunk to send (poses yield to maps).
        self.background = False
        #: False: each chunk goes once, as DGRAM frames, and nobody acks (poses).
        self.reliable = True
        #: Every chunk went once: receivers may complete it, even after it is superseded.
        self.flushed = False
        #: NACK mode: repairs go as parity chunks (fec.py), each of which any receiver missing any
        #: chunk of its block can use, rather than as the chunks asked for.
        self.fec = False
        #: Parity to send behind the first pass unasked, as a share of each block (the sender's
        #: running guess of the worst receiver's loss), so most messages need no repair round.
        self.proactive = 0.0
        #: A gap report asked for parity after the first pass (the guess was short), and how much.
        self.repaired = False
        self.late_parity = 0
        self.parity_sent = 0
        self._parity_next: dict[int, int] = {}  # block -> next parity share (j) not yet queued
        self._parity_unsent: dict[int, int] = {}  # block -> parity chunks queued, not yet sent
        self._parity: OrderedDict[int, bytes] = OrderedDict()  # a few made, by chunk index
        self._blocks: dict[int, tuple[bytes, ...]] = {}  # block -> its padded chunks, once parity goes

    def chunk(self, i: int) -> bytes:
        """Chunk ``i``'s bytes: data below ``count``, parity (made when first asked for) past it."""
        if i < self.count:
            return self.body[i * self.chunk_size : (i + 1) * self.chunk_size]
        made = self._parity.get(i)
        if made is None:
            b, share = fec.parity_of(self.count, i)
            block = self._blocks.get(b)
            if block is None:
                data = [self.chunk(c) for c in range(self.count)]
                block = self._blocks[b] = fec.pad_block(data, self.count, b)
            made = self._parity[i] = fec.encode_parity(block, [share])[0]
            while len(self._parity) > 4:  # a parity chunk goes once: keep the few about to go
                self._parity.popitem(last=False)
        return made

    def queue_parity(self, asked: Iterable[int]) -> int:
        """A gap report (NACK mode) asks for ``asked`` (data chunks): queue fresh parity chunks until
        as many of each block are queued and unsent as it asks of that block. Another receiver's
        report may have queued them already, as one parity chunk serves every receiver that lacks
        any chunk of its block. Past the code's parity, the chunks asked go again themselves.
        Returns how many were queued."""
        asked = list(asked)
        nb = fec.blocks(self.count)
        queued = self._queue_parity(
            fec.per_block(self.count, asked), lambda b: [i for i in asked if i % nb == b]
        )
        if self.flushed:
            self.repaired = True
            self.late_parity += queued
        return queued

    def _queue_parity(self, need: dict[int, int], fallback: Callable[[int], list[int]]) -> int:
        queued = 0
        limit = fec.max_parity(self.count)
        for b, n in need.items():
            while self._parity_unsent.get(b, 0) < n:
                j = self._parity_next.get(b, 0)
                if j >= limit:
                    queued += sum(self.queue_resend(i) for i in fallback(b))
                    break
                self._parity_next[b] = j + 1
                self._parity_unsent[b] = self._parity_unsent.get(b, 0) + 1
                queued += self.queue_resend(fec.parity_index(self.count, b, j))
        return queued

    def _queue_proactive(self) -> None:
        """The first pass is out: send ``proactive`` of each block as parity behind it."""
        nb = fec.blocks(self.count)
        need = {b: int(fec.block_size(self.count, b) * self.proactive + 0.5) for b in range(nb)}
        self._queue_parity({b: n for b, n in need.items() if n}, lambda b: [])

    def pending(self) -> list[PeerProgress]:
        return [p for p in self.peers.values() if p.pending]

    def finished(self) -> bool:
        return not any(p.pending for p in self.peers.values())

    def needed(self, i: int) -> bool:
        if i >= self.count:  # parity: asked for by a gap report, of use to whoever still lacks some
            return any(p.pending for p in self.peers.values())
        return any(p.pending and not p.acked[i] for p in self.peers.values())

    def window_base(self) -> int:
        """New chunks may go up to this plus the window: the most advanced pending peer sets it, so a
        silent peer never holds the others back (it gets probes, and resends once it answers)."""
        lows = [p.low for p in self.peers.values() if p.pending]
        return max(lows) if lows else self.count

    def queue_resend(self, i: int) -> bool:
        """Queue chunk ``i`` to go again; False when it already was."""
        if i in self._resend_set:
            return False
        self._resend_set.add(i)
        heapq.heappush(self._resend, i)
        return True

    def queue_probe(self, i: int) -> None:
        """Queue chunk ``i`` to go again whether or not a peer is known to lack it (NACK mode)."""
        self._probes.add(i)
        self.queue_resend(i)

    def next_index(self, window: int) -> int | None:
        """The chunk to send next: the lowest queued resend still needed, else a new chunk in the window."""
        if self.nack:
            window = self.count  # no flow control by acks: the receivers buffer a whole message
        while self._resend:
            i = self._resend[0]
            if self.needed(i) or i in self._probes:
                return i
            heapq.heappop(self._resend)
            self._resend_set.discard(i)
        if self.next_new < self.count and self.next_new < self.window_base() + window:
            return self.next_new
        return None

    def has_work(self, window: int) -> bool:
        return self.next_index(window) is not None

    def mark_sent(self, i: int, now: float) -> bool:
        """Record a transmission of chunk ``i``; True when it was a resend."""
        if self._resend and self._resend[0] == i:
            heapq.heappop(self._resend)
            self._resend_set.discard(i)
        if i >= self.count:  # parity: each goes once, and is a repair
            b, _ = fec.parity_of(self.count, i)
            self._parity_unsent[b] = max(0, self._parity_unsent.get(b, 0) - 1)
            self.parity_sent += 1
            self.xmit += 1
            return True
        self._probes.discard(i)
        if i == self.next_new:
            self.next_new += 1
            if self.next_new == self.count and self.fec and self.proactive > 0:
                self._queue_proactive()
        self.xmit += 1
        self.seq[i] = self.xmit
        self.sent_at[i] = now
        self.sends[i] += 1
        return self.sends[i] > 1

    def apply_ack(self, p: PeerProgress, base: int, bitmap: bytes) -> list[int]:
        """Mark what an ACK says ``p`` holds; return the chunks newly acked."""
        newly: list[int] = []
        top = min(base, self.count)
        for i in range(p.low, top):
            if not p.acked[i]:
                newly.append(i)
        for i in bitmap_indices(base, bitmap):
            if i < self.count and not p.acked[i] and i >= top:
                newly.append(i)
        for i in newly:
            p.acked[i] = 1
            p.max_acked_seq = max(p.max_acked_seq, self.seq[i])
        p.n_acked += len(newly)
        while p.low < self.count and p.acked[p.low]:
            p.low += 1
        return newly

    def requested(self, p: PeerProgress, base: int, bitmap: bytes) -> list[int]:
        """NACK mode: the chunks an ACK asks for, those it shows ``p`` lacking below the highest one
        it holds (chunks past that may still be on their way; the sender's probe covers them)."""
        held = bitmap_indices(base, bitmap)
        top = min(max(held, default=base - 1), self.count)
        return [i for i in range(p.low, min(top, self.next_new)) if not p.acked[i] and self.sends[i]]

    def mark_all_acked(self, p: PeerProgress) -> None:
        p.acked = bytearray(b"\x01" * self.count)
        p.n_acked = p.low = self.count

    def outstanding(self, p: PeerProgress) -> list[int]:
        """Chunks sent at least once that ``p`` has not acked."""
        return [i for i in range(p.low, self.next_new) if not p.acked[i] and self.sends[i]]

    def detect_losses(self, p: PeerProgress, tolerance: int) -> int:
        """Queue for resend every chunk ``p`` lacks that was sent well before one it acked (RACK-like)."""
        lost = 0
        for i in self.outstanding(p):
            if self.seq[i] + tolerance <= p.max_acked_seq and i not in self._resend_set:
                self.queue_resend(i)
                lost += 1
        return lost
