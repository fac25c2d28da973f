"""The receiver's view of a peer: its session, the messages being reassembled, what was delivered.

Pure, bounded bookkeeping used by :mod:`transports.uwb.arq` (the rules are written there). Every
table here has a fixed cap, so a peer (or a forger with a valid CRC) cannot grow memory without
bound: a few partial messages per peer, a short memory of completed and rejected message ids, and a
short list of acks owed.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field

from transports.uwb import fec
from transports.uwb.sending import HASH_LEN, message_hash
from transports.uwb.wire import MAX_BITMAP, bitmap_indices

MAX_ACKS_OWED = 16
REMEMBER_COMPLETED = 64
REMEMBER_REJECTED = 16
#: What a held chunk costs beyond its bytes: its dict entry, int key and bytes object (106 B
#: measured for a 1-byte chunk). Counted against the receive budget, so that a forger's 1-byte
#: chunks cannot hold a hundred times the budget in memory (a 16 MiB budget held 1.2 GB).
CHUNK_COST = 112


@dataclass
class Partial:
    """A message being reassembled from chunks addressed by index."""

    msg: int
    stream: int
    count: int
    total: int
    gen: int
    last: float
    chunks: dict[int, bytes] = field(default_factory=dict)
    held: int = 0
    base: int = 0  # lowest index not held
    top: int = -1  # highest index held
    fresh: int = 0  # chunks added since the last ack
    nack: bool = False  # acked in NACK mode (R16): only gaps and completion
    #: block -> zfec share number -> parity chunk held (fec.py), until the block is whole
    parity: dict[int, dict[int, bytes]] = field(default_factory=dict)
    parity_held: int = 0  # bytes of it (in ``held`` too)
    entries: int = 0  # chunks and parity chunks held, each costing CHUNK_COST beyond its bytes
    #: block -> the missing chunks its parity stands for (see :meth:`_covered`), kept up to date
    #: block by block as chunks and parity arrive: rebuilt for every block on every frame, a sender
    #: with parity held in each of a 65,000-chunk message's 500 blocks cost 5 ms a 25-byte frame.
    _cover: dict[int, frozenset[int]] = field(default_factory=dict, init=False, repr=False)

    def add(self, index: int, payload: bytes, now: float) -> bool:
        """Store a chunk; False when it was already held (a duplicate)."""
        if index in self.chunks:
            return False
        self.chunks[index] = payload
        self.held += len(payload)
        self.entries += 1
        self.top = max(self.top, index)
        self.fresh += 1
        self.last = now
        while self.base in self.chunks:
            self.base += 1
        b = fec.block_of(self.count, index)
        if b in self.parity:
            self._update_cover(b)
        return True

    def complete(self) -> bool:
        return len(self.chunks) == self.count

    def verified(self) -> bytes | None:
        """The message without its hash trailer when lengths and hash agree; else None."""
        body = b"".join(self.chunks[i] for i in range(self.count))
        if len(body) != self.total or len(body) < HASH_LEN:
            return None
        data, digest = body[:-HASH_LEN], body[-HASH_LEN:]
        return data if message_hash(data) == digest else None

    def wants_parity(self, index: int) -> bool:
        """Whether parity chunk ``index`` is of use: not held yet, and its block lacks more chunks
        than parity is held for it (more would be of no use, which bounds what parity may take)."""
        b, share = fec.parity_of(self.count, index)
        shares = self.parity.get(b, {})
        return share not in shares and len(shares) < len(self._missing(b))

    def add_parity(self, index: int, payload: bytes, now: float) -> None:
        """Store parity chunk ``index`` (one :meth:`wants_parity` said is of use)."""
        b, share = fec.parity_of(self.count, index)
        self.parity.setdefault(b, {})[share] = payload
        self._update_cover(b)
        self.held += len(payload)
        self.entries += 1
        self.parity_held += len(payload)
        self.fresh += 1
        self.last = now
        self.top = self.count - 1  # parity follows the chunks it repairs: what is missing is lost

    def recover(self, b: int) -> int:
        """Rebuild block ``b``'s missing chunks when enough parity is held; returns how many were
        rebuilt (``held`` follows). ValueError when the parity cannot be this message's (its
        block's parity is then dropped)."""
        nb = fec.blocks(self.count)
        have = {i: self.chunks[i] for i in range(b, self.count, nb) if i in self.chunks}
        try:
            got = fec.recover(self.count, b, have, self.parity.get(b, {}))
        except ValueError:
            self._drop_parity(b)
            raise
        if not got:
            return 0
        width = len(next(iter(self.parity[b].values())))
        self._drop_parity(b)
        for i, data in got.items():
            if i == self.count - 1:  # the message's last chunk is the only short one
                data = data[: self.total - (self.count - 1) * width]
            self.chunks[i] = data
            self.held += len(data)
            self.entries += 1
            self.top = max(self.top, i)
        while self.base in self.chunks:
            self.base += 1
        return len(got)

    def _drop_parity(self, b: int) -> None:
        self._cover.pop(b, None)
        shares = self.parity.pop(b, {})
        n = sum(len(p) for p in shares.values())
        self.held -= n
        self.parity_held -= n
        self.entries -= len(shares)

    @property
    def cost(self) -> int:
        """What holding this partial costs against the receive budget: bytes and entries."""
        return self.held + CHUNK_COST * self.entries

    def _missing(self, b: int) -> list[int]:
        """Block ``b``'s data chunks not held, lowest first."""
        return [i for i in range(b, self.count, fec.blocks(self.count)) if i not in self.chunks]

    def _update_cover(self, b: int) -> None:
        """Work out again which of block ``b``'s missing chunks its parity stands for: as many as
        parity chunks held, the highest first (those a report would otherwise ask for while they may
        still be coming)."""
        shares = self.parity.get(b)
        if not shares:
            self._cover.pop(b, None)
            return
        missing = self._missing(b)
        self._cover[b] = frozenset(missing[len(missing) - min(len(shares), len(missing)) :])

    def _covered(self, i: int) -> bool:
        """Whether missing chunk ``i`` is one the parity held stands for (O(1): per frame, a report
        or a gap check looks at up to 256 chunks, never at every block of the message)."""
        return i in self._cover.get(fec.block_of(self.count, i), ())

    def report(self) -> tuple[int, bytes]:
        """(base, bitmap) of an ACK: chunks held, with those the parity held stands for counted as
        held, so a gap report asks, block by block, for just what this receiver still needs."""
        covered = self._covered
        base = self.base
        while base in self.chunks or covered(base):
            base += 1
        out = bytearray(MAX_BITMAP)
        for i in range(base + 1, min(self.count, base + 1 + 8 * MAX_BITMAP)):
            if i in self.chunks or covered(i):
                k = i - base - 1
                out[k >> 3] |= 1 << (k & 7)
        return base, bytes(out.rstrip(b"\x00"))

    def gaps(self) -> list[int]:
        """Chunks missing below the highest one held, as far as an ACK can describe them (NACK mode:
        what a gap report asks for), less those the parity held stands for."""
        top = min(self.top, self.base + 8 * MAX_BITMAP)
        return [i for i in range(self.base, top) if i not in self.chunks and not self._covered(i)]


def asked_by(base: int, bitmap: bytes) -> set[int]:
    """The chunks an ACK shows its sender lacking below the highest one it holds: in NACK mode, what
    it asks the data sender to resend (see :meth:`Partial.gaps`)."""
    held = set(bitmap_indices(base, bitmap))
    top = max(held, default=base - 1)
    return {i for i in range(base, top) if i not in held}


class PeerState:
    """Everything one node knows about one peer as a receiver: its session and its messages."""

    def __init__(self, peer: int, session: int, now: float, max_partials: int) -> None:
        self.id = peer
        self.session = session
        self.retired: deque[int] = deque(maxlen=4)
        self.last_heard = now
        self.up = True
        self.max_partials = max_partials
        self.partials: dict[int, Partial] = {}
        self.stream_top: dict[int, int] = {}
        self.completed: OrderedDict[int, int] = OrderedDict()
        self.rejected: OrderedDict[int, None] = OrderedDict()
        self.acks_due: OrderedDict[int, float] = OrderedDict()
        #: When a COMPLETE for a (broadcast) message was last sent: NACK mode answers a sender's
        #: probes with it again at most every so often (the probe is for the peers still pending).
        self.complete_sent: OrderedDict[int, float] = OrderedDict()
        #: What its last HELLO announced (wire.hello_features); None: nothing heard (yet) this session.
        self.features: int | None = None
        #: The last word heard whatever the session (to say an upgrade across a restart).
        self.announced: int | None = None
        self._gen = 0

    def understands(self, feature: int) -> bool:
        """Whether the peer takes ``feature`` (a ``wire.F_*`` bit): what its HELLO announced, or yes
        while it announced nothing yet (as every node did before the announcement)."""
        return self.features is None or bool(self.features & feature)

    def next_gen(self) -> int:
        self._gen = (self._gen + 1) & 0xFF
        return self._gen

    def cost(self) -> int:
        """What this peer's partial messages cost against the receive budget (:attr:`Partial.cost`)."""
        return sum(p.cost for p in self.partials.values())

    def restart(self, session: int) -> int:
        """The peer came back with a new session: forget everything; return the bytes released."""
        self.retired.append(self.session)
        self.session = session
        released = self.cost()
        self.partials.clear()
        self.stream_top.clear()
        self.completed.clear()
        self.rejected.clear()
        self.acks_due.clear()
        self.complete_sent.clear()
        self.features = None  # it may come back as another version: unknown until it says
        return released

    def owe_ack(self, msg: int, due: float) -> None:
        """Schedule an ack for ``msg`` no later than ``due``; the oldest owed ack goes when full."""
        if msg in self.acks_due:
            self.acks_due[msg] = min(self.acks_due[msg], due)
            return
        if len(self.acks_due) >= MAX_ACKS_OWED:
            self.acks_due.popitem(last=False)
        self.acks_due[msg] = due

    def remember_completed(self, msg: int, gen: int) -> None:
        self.completed[msg] = gen
        while len(self.completed) > REMEMBER_COMPLETED:
            self.completed.popitem(last=False)

    def sent_complete(self, msg: int, now: float) -> None:
        self.complete_sent[msg] = now
        self.complete_sent.move_to_end(msg)
        while len(self.complete_sent) > REMEMBER_COMPLETED:
            self.complete_sent.popitem(last=False)

    def remember_rejected(self, msg: int) -> None:
        self.rejected[msg] = None
        while len(self.rejected) > REMEMBER_REJECTED:
            self.rejected.popitem(last=False)

    def drop_partial(self, msg: int) -> int:
        """Forget a partial message; return the cost released (:attr:`Partial.cost`)."""
        p = self.partials.pop(msg, None)
        return p.cost if p else 0

    def oldest_partial(self, exclude: int | None = None) -> Partial | None:
        cands = [p for p in self.partials.values() if p.msg != exclude]
        return min(cands, key=lambda p: p.last) if cands else None
