"""Frame bodies of the UWB link protocol: fixed little-endian layouts, strictly parsed.

Every body starts with a 6-byte header::

    u8  kind      low 4 bits: frame type; bits 4-6: protocol version (2); bit 7: signed
    u8  src       sender's link id, 1..254
    u8  dst       receiver's link id, 1..254, or 255 for broadcast
    u24 session   sender's session id, new at every start (restart detection)

then, by type::

    DATA   u24 msg, u8 stream, u16 index, u16 count, u24 total, payload (1.. bytes)
    ACK    u24 target_session, u24 msg, u8 gen, u8 flags, u16 base, bitmap (0..32 bytes)
    HELLO  (nothing: presence and session announcement; dst carries the sender's features)
    DGRAM  as DATA, for a message that is sent once and never acknowledged (robot poses: the next
           one replaces a lost one, and an ack would cost a receiver a whole frame slot of its
           1 s pacing window)
    DONE   1.. entries of (u8 sender, u8 target_session & 0xFF, u16 msg & 0xFFFF), dst 255: COMPLETE
           for several messages, of several senders, in one frame (NACK mode, R16 in ``arq.py``)
    LEND   u16 slot: the rest of TDMA slot number ``slot`` (mod 2^16 on the shared clock), which is
           the sender's own, goes to ``dst`` (R17 in ``arq.py``)
    TIME   u8 root, u8 hops (bit 7: the root's clock is kept by a time service), u8 parent (0:
           none), u8 epoch (the root's clock steps), u16 seq, u64 stamp (us on the sender's link
           clock when the frame went on the air), u8 echo_id (0: none), u32 echo (low bits of the
           stamp of echo_id's last TIME frame), u32 hold (us since); dst 255: the fleet's TDMA
           clock kept over the radio (``radio_time.py``). One size, so that a round trip of two
           is twice the path delay of each, whatever the radio's real rate

A signed body ends with a 12-byte trailer (u48 counter, 6-byte truncated HMAC; see
:mod:`transports.uwb.signing`) that is checked and stripped before :func:`parse` sees the body.

Version 2 narrowed session, msg and total from 32 to 24 bits (and signing dropped the CRC and two
tag bytes) so a signed frame carries 192 data bytes of 223, not 183: at seven frames a second that
is what keeps goodput above 0.85 of a 12.5 kb/s link. 24 bits are enough: a session id is only
compared for equality (a restart draws a new one; one in 16 million repeats the old), message ids
are compared in serial-number arithmetic (:func:`msg_before`, RFC 1982), and a message is at most
:data:`MAX_TOTAL` bytes, three hours of the link.

DONE was added to version 2 without a version bump (issue #22, scalable acks): each entry says what
an ACK with the COMPLETE flag says, and a broadcast map would otherwise cost every receiver a frame
of its own per map, N (N - 1) frames a round for N robots. Nodes from before it drop DONE frames as
an unknown type (counted ``bad_frames``), so a fleet with such nodes runs ``acks = "each"`` (a
sender whose HELLO says it lacks DONE is acked with ACKs alone: *Features* below). Its entries
are 4 bytes, the low bits of what an ACK names in 7: at 32 robots a receiver's DONE carries some
twenty COMPLETEs a turn, and with 8-byte entries DONEs took 18 % of the channel (``mapd bench
swarm``). The sender resolves the low 16 bits of ``msg`` against the few messages it still tracks
(ids rise by one per message in a session, so those are unique), and a restarted sender, with a
new session, takes a stale entry only if the session's low byte matches too (1 in 2^24 a stale
entry).

LEND was added the same way (issue #22: a TDMA turn its owner leaves half empty goes to a robot
with chunks still to send). A node from before it drops a LEND as an unknown type and so never
borrows; lending to it wastes the rest of that one slot (none is lent to a node whose HELLO says
it lacks LEND).
The slot number makes a LEND that arrives late (a radio's buffer) useless rather than harmful: a
receiver borrows only the slot it names, never the next one, whose owner will be sending.

Parity chunks were added the same way (issue #22: a broadcast map's repair round costs what the
worst receiver lacks, not the union of everyone's losses; :mod:`transports.uwb.fec`). A parity
chunk is a DATA frame whose ``index`` is at or past ``count`` (below :func:`~transports.uwb.fec.
index_limit`), which says its block and share. A node from before it refuses such a frame as
malformed and so never completes a map whose repairs came as parity: a fleet with such nodes runs
``fec = false``, with which no parity is sent (a message goes without parity where any receiver
says it lacks it: *Features* below).

TIME was added the same way (a fleet without a time service: TDMA's turns need one clock). A node
from before it drops TIME frames as an unknown type and keeps its turns on its own clock, as
before; nothing else it hears changes.

Features (mixed versions). Nodes from before the announcement send HELLO to 255; later ones put
:data:`FEATURES_FLAG` ``|`` the features they understand (:data:`F_DONE`, :data:`F_PARITY`,
:data:`F_LEND`) in its ``dst``, which nodes from before never read: they take any HELLO as presence,
whatever its dst. A node holds each peer to what its last HELLO announced: a sender without DONE is
acked message by message with ACKs, as ``acks = "each"`` does; a message goes without parity if
any of its receivers lacks it (one on its way when the word comes is repaired without it from
then on); no LEND goes to a node without it. So once a feature is added after this one, a fleet
upgraded one robot at a time needs no setting for it: what the older nodes would refuse as
malformed or unknown goes only where it is understood (they still overhear, and drop, frames that
newer nodes send one another: harmless).

A peer that announced nothing (a HELLO to 255, or none heard yet) is taken to understand what this
node does, as every node did before the announcement: the nodes of the release before it
understand DONE, parity and LEND, and only send HELLO to 255, so a fleet of both needs no setting
either. Nodes from before DONE or parity announce nothing and understand neither: a fleet mixing
them still sets ``acks = "each"`` and ``fec = false`` (README, *Known gaps*). A receiver takes a
parity chunk whatever the sender announced: the chunk shows the sender repairs with parity, and
so runs gap reports and DONE, which it is given from then on. To be heard by a newcomer, a node
sends a HELLO soon after it first hears a peer or hears one restart (one for all heard within
:data:`~transports.uwb.arq_tx.HELLO_MIN_GAP_S`), and at least every
:data:`~transports.uwb.arq_tx.HELLO_REFRESH_S` however busy (else only at start and after
``beacon_s`` of its own silence, which a busy node never has). The dst of a signed HELLO is under
its signature like every field: only a holder of the link key can make a robot look older, which
costs the channel parity repair toward it, nothing more.

A chunk is addressed by (msg, index), so a resend is idempotent. ``total`` is the length of the
message plus its hash trailer; ``count`` the number of chunks. An ACK tells the data sender which
chunks the receiver holds: all below ``base``, and bit ``k`` of ``bitmap`` is chunk ``base + 1 + k``.
``gen`` names the receiver's reassembly buffer for that message: when it changes, the receiver has
thrown away what it held (hash mismatch, memory pressure) and earlier acks no longer count.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from mapd.errors import ProtocolError
from transports.uwb import fec

VERSION = 2
BROADCAST = 255
SIGNED = 0x80

DATA, ACK, HELLO, DGRAM, DONE, LEND, TIME = 1, 2, 3, 4, 5, 6, 7
KIND_NAMES = {
    DATA: "DATA",
    ACK: "ACK",
    HELLO: "HELLO",
    DGRAM: "DGRAM",
    DONE: "DONE",
    LEND: "LEND",
    TIME: "TIME",
}

#: A HELLO whose dst has this bit (and is not BROADCAST) announces the sender's features in the
#: bits below it; see the module docstring. Bit 6 stays clear (0xFF is BROADCAST): six features.
FEATURES_FLAG = 0x80
F_DONE = 0x01  # takes COMPLETEs in DONE frames
F_PARITY = 0x02  # rebuilds blocks from parity chunks (DATA index at or past count)
F_LEND = 0x04  # borrows the rest of a slot named in a LEND
F_TIME = 0x08  # keeps its TDMA turns on the clock TIME frames carry
#: What this version understands, and so announces.
FEATURES = F_DONE | F_PARITY | F_LEND | F_TIME
FEATURE_NAMES = {F_DONE: "DONE acks", F_PARITY: "parity repair", F_LEND: "lent turns", F_TIME: "radio time"}


def own_features(radio_time: bool) -> int:
    """What a node announces: all of :data:`FEATURES`, less :data:`F_TIME` where its turns are on
    its wall clock (``[transports.uwb] clock = "system"``): its peers are then told its turns are
    its own, as they are told of a node from before radio time."""
    return FEATURES if radio_time else FEATURES & ~F_TIME


def feature_words(features: int) -> str:
    """``features`` (``F_*`` bits) in words, for logs and ``mapd status``."""
    return ", ".join(name for bit, name in FEATURE_NAMES.items() if features & bit) or "none"


# ACK flags
COMPLETE = 0x01  # the whole message is held and its hash verified
REJECT = 0x02  # the receiver refuses the message (over its size limit); the sender gives up on it
_ACK_FLAGS = COMPLETE | REJECT

MAX_BITMAP = 32  # bytes: an ACK describes up to 256 chunks past base

#: Session ids, message ids and message sizes are 24-bit fields.
U24 = 1 << 24
MASK24 = U24 - 1
#: The largest message (payload plus hash trailer) a DATA frame can describe.
MAX_TOTAL = MASK24

# struct has no 24-bit integer: each u24 is packed as (u16 low, u8 high).
_HDR = struct.Struct("<BBBHB")
_DATA = struct.Struct("<HBBHHHB")
_ACK = struct.Struct("<HBHBBBH")
_DONE = struct.Struct("<BBH")
_LEND = struct.Struct("<H")
_TIME = struct.Struct("<BBBBHQBII")
HEADER_LEN = _HDR.size
DONE_ENTRY_LEN = _DONE.size
DATA_HEADER_LEN = _HDR.size + _DATA.size
ACK_HEADER_LEN = _HDR.size + _ACK.size
LEND_LEN = _HDR.size + _LEND.size
TIME_LEN = _HDR.size + _TIME.size
#: TIME: the latest stamp taken (us): past it (the year 2255) a float no longer holds a
#: microsecond, and a correction read from it would mean nothing.
MAX_STAMP = 1 << 53
#: TIME: bit 7 of ``hops`` says the root's clock is kept by a time service; hops are below it.
TIME_SOURCE = 0x80
#: LEND names slots modulo this.
SLOT_MOD = 1 << 16


def _split(v: int) -> tuple[int, int]:
    if not 0 <= v <= MASK24:
        raise ValueError(f"uwb: {v} does not fit a 24-bit field")
    return v & 0xFFFF, v >> 16


def msg_before(a: int, b: int) -> bool:
    """Whether message id ``a`` comes before ``b`` in 24-bit serial-number arithmetic (RFC 1982)."""
    return 0 < ((b - a) & MASK24) < (U24 >> 1)


@dataclass(frozen=True, slots=True)
class Data:
    """One chunk of a message (a DGRAM when ``reliable`` is false: no acks)."""

    src: int
    dst: int
    session: int
    msg: int
    stream: int
    index: int
    count: int
    total: int
    payload: bytes
    reliable: bool = True


@dataclass(frozen=True, slots=True)
class Ack:
    """Selective acknowledgement of message ``msg`` of the sender whose session is ``target_session``."""

    src: int
    dst: int
    session: int
    target_session: int
    msg: int
    gen: int
    flags: int
    base: int
    bitmap: bytes


@dataclass(frozen=True, slots=True)
class Hello:
    """Presence: announces a sender and its session."""

    src: int
    dst: int
    session: int


@dataclass(frozen=True, slots=True)
class Done:
    """COMPLETE for several messages: ``entries`` of (sender, target_session & 0xFF, msg & 0xFFFF),
    each as an ACK from ``src`` to ``sender`` with the COMPLETE flag would say it."""

    src: int
    dst: int
    session: int
    entries: tuple[tuple[int, int, int], ...]


@dataclass(frozen=True, slots=True)
class Lend:
    """The rest of TDMA slot ``slot`` (``floor(t / slot_s) % SLOT_MOD``), the sender's own, is ``dst``'s."""

    src: int
    dst: int
    session: int
    slot: int


@dataclass(frozen=True, slots=True)
class Time:
    """The sender's link clock (``stamp``, us, when the frame went on the air) and where it comes
    from: ``root``'s clock (kept by a time service: ``source``), ``hops`` away through ``parent``
    (0: none), its beacon ``seq`` and step ``epoch``; and an echo of the last TIME frame heard from
    ``echo_id`` (low 32 bits of its stamp, ``hold`` us since), by which that node measures its path
    delay. See ``radio_time.py``."""

    src: int
    dst: int
    session: int
    root: int
    source: bool
    hops: int
    parent: int
    epoch: int
    seq: int
    stamp: int
    echo_id: int = 0
    echo: int = 0
    hold: int = 0


Frame = Data | Ack | Hello | Done | Lend | Time


def hello_features(h: Hello) -> int | None:
    """The features ``h`` announces: its bits for a flagged dst; None for a HELLO to BROADCAST (a
    node from before the announcement: it says nothing) or to one node."""
    if h.dst != BROADCAST and h.dst & FEATURES_FLAG:
        return h.dst & ~FEATURES_FLAG
    return None


def _kind(kind: int, signed: bool) -> int:
    return kind | (VERSION << 4) | (SIGNED if signed else 0)


def _head(kind: int, signed: bool, src: int, dst: int, session: int) -> bytes:
    return _HDR.pack(_kind(kind, signed), src, dst, *_split(session))


def pack_data(d: Data, *, signed: bool = False) -> bytes:
    head = _head(DATA if d.reliable else DGRAM, signed, d.src, d.dst, d.session)
    return head + _DATA.pack(*_split(d.msg), d.stream, d.index, d.count, *_split(d.total)) + d.payload


def pack_ack(a: Ack, *, signed: bool = False) -> bytes:
    head = _head(ACK, signed, a.src, a.dst, a.session)
    fields = _ACK.pack(*_split(a.target_session), *_split(a.msg), a.gen, a.flags, a.base)
    return head + fields + a.bitmap


def pack_hello(h: Hello, *, signed: bool = False) -> bytes:
    return _head(HELLO, signed, h.src, h.dst, h.session)


def pack_done(d: Done, *, signed: bool = False) -> bytes:
    head = _head(DONE, signed, d.src, d.dst, d.session)
    return head + b"".join(
        _DONE.pack(sender, target & 0xFF, msg & 0xFFFF) for sender, target, msg in d.entries
    )


def pack_lend(f: Lend, *, signed: bool = False) -> bytes:
    return _head(LEND, signed, f.src, f.dst, f.session) + _LEND.pack(f.slot % SLOT_MOD)


def pack_time(f: Time, *, signed: bool = False) -> bytes:
    hops = min(f.hops, TIME_SOURCE - 1) | (TIME_SOURCE if f.source else 0)
    fields = _TIME.pack(f.root, hops, f.parent, f.epoch & 0xFF, f.seq, f.stamp, f.echo_id, f.echo, f.hold)
    return _head(TIME, signed, f.src, f.dst, f.session) + fields


def pack(frame: Frame, *, signed: bool = False) -> bytes:
    """The body of ``frame`` (without a signing trailer)."""
    if isinstance(frame, Time):
        return pack_time(frame, signed=signed)
    if isinstance(frame, Lend):
        return pack_lend(frame, signed=signed)
    if isinstance(frame, Done):
        return pack_done(frame, signed=signed)
    if isinstance(frame, Data):
        return pack_data(frame, signed=signed)
    if isinstance(frame, Ack):
        return pack_ack(frame, signed=signed)
    return pack_hello(frame, signed=signed)


def is_signed(body: bytes) -> bool:
    """Whether the body says it carries a signing trailer (the header is not yet validated)."""
    return bool(body) and bool(body[0] & SIGNED)


def parse(body: bytes) -> Frame:
    """Parse a body (signing trailer already stripped); :class:`ProtocolError` on any absurd field.

    Only the structure is checked here; limits that are policy (a message over the receiver's size
    limit) are the core's to answer, so the sender hears a REJECT instead of retrying into silence.
    """
    if len(body) < HEADER_LEN:
        raise ProtocolError(f"uwb: frame of {len(body)} bytes is shorter than a header")
    k, src, dst, s_lo, s_hi = _HDR.unpack_from(body)
    session = s_lo | s_hi << 16
    if (k >> 4) & 0x7 != VERSION:
        raise ProtocolError(f"uwb: frame protocol version {(k >> 4) & 0x7} is not {VERSION}")
    kind = k & 0x0F
    if not 1 <= src <= 254:
        raise ProtocolError(f"uwb: frame source id {src} is out of range")
    if not 1 <= dst <= 255:
        raise ProtocolError(f"uwb: frame destination id {dst} is out of range")
    if kind in (DATA, DGRAM):
        if len(body) <= DATA_HEADER_LEN:
            raise ProtocolError("uwb: DATA frame has no payload")
        m_lo, m_hi, stream, index, count, t_lo, t_hi = _DATA.unpack_from(body, HEADER_LEN)
        msg, total = m_lo | m_hi << 16, t_lo | t_hi << 16
        payload = body[DATA_HEADER_LEN:]
        if count == 0 or index >= (fec.index_limit(count) if kind == DATA else count):
            raise ProtocolError(f"uwb: DATA chunk index {index} is past what {count} chunks may have")
        if count > total or len(payload) > total:
            raise ProtocolError(f"uwb: DATA sizes are inconsistent ({count} chunks, {total} bytes)")
        return Data(src, dst, session, msg, stream, index, count, total, payload, kind == DATA)
    if kind == ACK:
        if len(body) < ACK_HEADER_LEN:
            raise ProtocolError("uwb: ACK frame is truncated")
        t_lo, t_hi, m_lo, m_hi, gen, flags, base = _ACK.unpack_from(body, HEADER_LEN)
        target, msg = t_lo | t_hi << 16, m_lo | m_hi << 16
        bitmap = body[ACK_HEADER_LEN:]
        if len(bitmap) > MAX_BITMAP:
            raise ProtocolError(f"uwb: ACK bitmap of {len(bitmap)} bytes is over {MAX_BITMAP}")
        if flags & ~_ACK_FLAGS:
            raise ProtocolError(f"uwb: ACK has unknown flags {flags:#x}")
        if dst == BROADCAST:
            raise ProtocolError("uwb: ACK sent to broadcast")
        return Ack(src, dst, session, target, msg, gen, flags, base, bitmap)
    if kind == DONE:
        rest = len(body) - HEADER_LEN
        if rest <= 0 or rest % DONE_ENTRY_LEN:
            raise ProtocolError(f"uwb: DONE frame of {len(body)} bytes is not whole entries")
        if dst != BROADCAST:
            raise ProtocolError("uwb: DONE frame not sent to broadcast")
        entries = []
        for off in range(HEADER_LEN, len(body), DONE_ENTRY_LEN):
            sender, target, msg = _DONE.unpack_from(body, off)
            if not 1 <= sender <= 254:
                raise ProtocolError(f"uwb: DONE entry for sender id {sender} is out of range")
            entries.append((sender, target, msg))
        return Done(src, dst, session, tuple(entries))
    if kind == LEND:
        if len(body) != LEND_LEN:
            raise ProtocolError(f"uwb: LEND frame of {len(body)} bytes is not {LEND_LEN}")
        if dst == BROADCAST:
            raise ProtocolError("uwb: LEND sent to broadcast")
        return Lend(src, dst, session, _LEND.unpack_from(body, HEADER_LEN)[0])
    if kind == TIME:
        if len(body) != TIME_LEN:
            raise ProtocolError(f"uwb: TIME frame of {len(body)} bytes is not {TIME_LEN}")
        if dst != BROADCAST:
            raise ProtocolError("uwb: TIME frame not sent to broadcast")
        root, hops, parent, epoch, seq, stamp, echo_id, echo, hold = _TIME.unpack_from(body, HEADER_LEN)
        if not 1 <= root <= 254 or parent > 254 or echo_id > 254:
            raise ProtocolError(f"uwb: TIME ids out of range (root {root}, parent {parent}, echo {echo_id})")
        if stamp > MAX_STAMP:
            raise ProtocolError(f"uwb: TIME stamp {stamp} us is past the year 2255")
        source, hops = bool(hops & TIME_SOURCE), hops & ~TIME_SOURCE
        return Time(src, dst, session, root, source, hops, parent, epoch, seq, stamp, echo_id, echo, hold)
    if kind == HELLO:
        if len(body) != HEADER_LEN:
            raise ProtocolError("uwb: HELLO frame has trailing bytes")
        return Hello(src, dst, session)
    raise ProtocolError(f"uwb: unknown frame type {kind}")


def bitmap_indices(base: int, bitmap: bytes) -> list[int]:
    """Chunk indices an ACK bitmap marks as held."""
    out = []
    for byte_i, b in enumerate(bitmap):
        while b:
            low = b & -b
            out.append(base + 1 + 8 * byte_i + low.bit_length() - 1)
            b ^= low
    return out
