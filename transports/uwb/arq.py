"""The sans-I/O core of the UWB link: reliable, paced, signed messages over a lossy shared byte stream.

No asyncio, no serial port, no clock: bytes and ``now`` come in (:meth:`ArqEndpoint.receive_data`),
frames go out one at a time (:meth:`~ArqEndpoint.data_to_send`), one timer says when to call back
(:meth:`~ArqEndpoint.get_timer` / :meth:`~ArqEndpoint.handle_timer`), and events come out
(:meth:`~ArqEndpoint.events`). An adapter owns the port and the clock (see ``link.py``).
Here are the rules and the endpoint's state and message API; the code of each part of the rules
is a mixin in its own module: frame input ``arq_input``, receiving ``arq_rx``, ack handling
``arq_acks``, sending ``arq_tx``, timers ``arq_timers``.

The rules
---------
Framing and trust
  R1. Every frame is COBS-encoded with a 0x00 delimiter (``framing.py``), at most ``max_frame`` bytes
      on the wire, and checked: by a CRC-32 without a key, by its signature with one. Frames failing
      COBS, the check or parsing are counted and dropped.
  R2. With a key, frames without a valid signature or with a replayed counter (one seen already,
      or at or below the sender's mark from before a restart: ``replay_marks``) are counted and dropped
      before anything else looks at them (``signing.py``); so is a counter far ahead of this node's
      clock (``check_counter_clock``), which a key holder could send to make the real sender's later
      frames look replayed. Without a key, signed frames are dropped (counted ``signed_no_key``):
      they carry no CRC, so a node that cannot check their tag cannot tell them from damage.
  R3. A frame carries its sender's link id and session id. The first frame of an unknown sender makes
      it a peer (PeerUp). A new session id from a known peer means it restarted (PeerRestarted): all it
      was reassembling from us is forgotten, and all it had acked of our messages counts for nothing,
      so it gets a clean start. Frames of a session it left are stale and dropped. A peer silent for
      ``peer_timeout_s`` is down (PeerDown) until it is heard again; with TDMA, where a peer speaks
      only in its own slot, silent for ``beacon_s`` and two cycles if that is longer (one lost
      HELLO is not a peer gone). Nodes announce themselves with HELLO at start and after
      ``beacon_s`` of silence, with the features they understand in its dst (``wire.py``,
      *Features*); also soon after first hearing a peer or hearing one restart, and at least every
      ``HELLO_REFRESH_S`` however busy, so newcomers hear them. A peer gets only what it announced:
      without DONE, selective acks (R13) for its messages; without parity, none in a message it
      receives; without LEND, no LEND (PeerFeatures says a peer that lacks any). One that announced
      nothing (a node from before the announcement) gets what this node understands, as before.
Sending
  R4. A message is the bytes given to :meth:`send` plus a 16-byte SHA-256 prefix of them, cut into
      chunks that fill a frame; a chunk is addressed by (message id, index), so sending it twice is
      harmless. Message ids rise within a session (24-bit, compared modulo 2^24).
  R5. Latest wins: sending on a stream that already has a message in flight drops that message at
      once (MessageClosed "superseded"); no radio time is spent on a stale map. A receiver that
      already holds every chunk of it still says COMPLETE, and that still counts (MessageDelivered,
      for the last ``MAX_LATE`` superseded messages): the sender learns which delta bases its peers
      hold. So a reliable message says when every chunk has been on the air once (MessageFlushed):
      an adapter that supersedes before then starts the next message over from nothing (P1 in
      ``mapd/daemon/publisher.py``). A background message (a pose) is sent only when no other
      message has a chunk to send.
  R6. A message goes to one peer (unicast) or to several (broadcast); it is delivered to a peer when
      that peer acks it COMPLETE (MessageDelivered), and closes when every intended peer has, or has
      failed. Past its deadline every peer still pending fails (MessageFailed "deadline"). Unless
      the caller gives one, the deadline is ``deadline_s`` after :meth:`~ArqEndpoint.send`, or
      ``DEADLINE_AIRTIMES`` times the message's airtime at this node's share of the channel
      (``rate_bps`` over ``slots``) if longer (:meth:`~ArqEndpoint.message_deadline_s`): a fixed
      120 s never carried a map over about 150 kB at 12.5 kb/s, and the limits allow 8 MiB.
  R7. Chunks go in order within a window of ``window`` chunks past what the most advanced peer holds,
      so a silent peer never stops the others (no window in NACK mode, R16). Queued resends go
      before new chunks.
  R8. Loss is detected two ways: a chunk a peer lacks is resent once the peer has acked a chunk sent
      ``reorder_tolerance`` transmissions after it (so reordering is harmless); and when a peer's
      retransmission timer expires, its oldest missing chunk is resent as a probe and the timer backs
      off (doubles). The timer follows RFC 6298 over RTT samples from chunks sent once (Karn).
  R9. An ACK whose ``gen`` differs from the one a peer acked before means the peer threw its buffer
      away: its acks are reset and everything it lacks is queued again. A REJECT fails that peer.
Receiving
  R10. DATA for another node is ignored. A message larger than ``max_message_bytes`` is refused with a
      REJECT. A chunk of a message already delivered is a duplicate: it is answered COMPLETE again and
      never delivered twice. A chunk of a message older than the newest one seen on its stream is stale.
  R11. A new message on a stream replaces a partial older one of that stream. A peer has at most
      ``max_partials_per_peer`` partial messages, and all peers together at most ``rx_budget_bytes``
      held (each chunk counted with ``CHUNK_COST`` bytes for the memory it takes beyond its own:
      1-byte chunks cost 100 times their bytes); past either, the least recently active partial is dropped. Partials idle for
      ``partial_ttl_s`` are dropped. So memory stays bounded whatever arrives.
  R12. A complete message is delivered (MessageReceived) only when its length and hash check out; a
      message failing the hash is dropped and its buffer starts over under a new ``gen``.
  R13. ACKs are selective (lowest missing index + a bitmap of 256 chunks after it). An ACK is owed
      ``ack_delay_s`` after new data, at once after ``ack_every`` new chunks, a gap, a duplicate, a
      completion or a refusal; owed ACKs coalesce, and each one describes the state when it is sent.
      This is ``acks = "each"``, and what ``auto`` (the default) does for unicast messages.
Scalable acks (NACK mode)
  R16. With ``acks = "auto"`` a broadcast message (dst 255: more than one intended peer), with
      ``"nack"`` every reliable message, is acked as reliable multicast does it (NORM, RFC 5740:
      NACK-based repair, receiver backoff and suppression, sender flush probe; SRM's overheard
      repair requests). Gap reports are ordinary ACKs; only COMPLETEs travel in a new frame.
      A receiver stays silent while chunks arrive in order. It owes COMPLETE when the message
      verifies (the sender learns delivery per peer), said in a DONE frame (``wire.py``) due
      ``ack_delay_s`` later that carries every COMPLETE owed by then, to any sender (else N robots
      would cost N (N - 1) ack frames a round of maps); and a gap report (an ordinary selective
      ACK) only on new evidence of loss: a chunk past the next expected, a resend while a
      hole is left below it, or a duplicate while it lacks chunks. The report waits a random backoff
      (NORM's truncated exponential over ``nack_backoff_s``, skewed by the number of peers heard),
      and is dropped if, meanwhile, another receiver's ACK for the same message (every radio hears
      every frame of a shared channel) asked for every chunk this one lacks, or the holes filled.
      It asks for the chunks missing below the highest one it holds. The sender resends each asked
      chunk once for all (R7's queue); it does not hold new chunks to a window (receivers buffer a
      whole message); and it runs a peer's retransmission timer only after its last chunk to send
      (the flush): when it expires, the last chunk goes again as a probe (the lowest known-missing
      one once the peer holds the last), which a receiver lacking anything answers with its gaps,
      and one holding all with COMPLETE again (at most once per ``min_rto_s``: a burst of
      repairs for others is not a probe). With TDMA the timer
      is at least one cycle of slots (no receiver can answer sooner).
      With ``fec`` the repairs are parity chunks (``fec.py``): a gap report counts, of each block,
      the missing chunks less the parity it already holds, and the sender queues fresh parity
      until as many of that block are queued and unsent, so one parity chunk serves every
      receiver lacking any chunk of its block and a round costs what the worst receiver lacks,
      not the union of all their losses. A receiver rebuilds a block once it holds as many
      chunks and parity as the block has chunks; the message hash still decides delivery.
      Behind a broadcast's first pass the sender queues parity unasked, a share of each block
      (at most ``PROACTIVE_MAX``) that a gap report after the pass raises by what its round sent
      and a message without one lowers by ``PROACTIVE_DOWN``: on a lossy channel the round trip a
      repair costs is skipped more often, and a clean one never carries parity.
      A receiver holding parity drops its report for another's that asks for as many chunks of
      each block, whichever they are: the parity answering it serves both.
Pacing and access
  R14. Every frame waits for the pacer (``pacing.Pacer``: never over ``rate_bps`` in any 1 s window,
      resends and acks included) and for medium access (``pacing.MediumAccess``: none, tdma, backoff).
      With TDMA a frame must end a guard time before the slot does, counted from when the radio
      is done with the frames handed to it before (a write drains into its buffer long before).
      Priority: HELLO, then owed ACKs, then owed DONEs, then DATA round-robin over messages.
  R15. With a key, no frame is sent until the adapter has persisted the counter block it will use
      (:meth:`counter_reservation` / :meth:`confirm_counter`).
  R17. With ``lend`` and TDMA, a node in its own slot with nothing to send and nothing owed, and
      room left for a LEND and a full frame, names in a LEND the peer it last heard with the most
      chunks still to send (``lending.py``), and sends nothing more in that slot; the peer it named
      may send until the slot's end, if the LEND names the slot it arrived in. So one robot still
      sends per slot, and one with a large map is not held to 1/N of the channel while others idle.
  R18. With TDMA, a frame of another node that was certainly on the air during this node's own
      slot (one it did not lend) is counted ``out_of_turn``. Its bytes end at ``now``, at most
      ``rx_slack_s`` after the frame ended on the air, and it lasted at least its bytes' airtime, so
      it was on the air throughout ``[now - airtime, now - rx_slack_s]``. Such frames collide with
      this node's own: the robots' clocks disagree by more than the guard, or two were given one
      slot. The adapter shows the count on ``mapd status``'s FAULTS line.
Time
  R19. With TDMA and ``radio_time``, the turns are kept on a clock the fleet agrees over the radio
      (``radio_time.py``): TIME frames from the best clock heard (one a time service keeps, else
      the lowest id), passed on over hops, each stamped when it went on the air, and the path delay
      measured both ways. The wall clock keeps everything else (the signing counters' check). A
      fleet whose every robot says a time service keeps its clock (:meth:`set_clock_source`)
      sends no TIME frame. A TIME frame goes after a due HELLO, before anything else.
"""

from __future__ import annotations

import dataclasses
import math
import random
from collections import OrderedDict, deque
from typing import Any

from mapd.errors import LimitError
from transports.rtt import RttEstimator
from transports.uwb import wire
from transports.uwb.arq_acks import GoodputWindow
from transports.uwb.arq_input import InputSide
from transports.uwb.arq_rx import MAX_CHUNKS
from transports.uwb.arq_timers import TimerSide
from transports.uwb.arq_types import (
    ArqConfig,
    ArqCounters,
    Event,
    MessageClosed,
    MessageDelivered,
    MessageFailed,
    MessageFlushed,
    MessageReceived,
    PeerDown,
    PeerFeatures,
    PeerRestarted,
    PeerUp,
)
from transports.uwb.framing import MIN_FRAME, FrameReader, max_body
from transports.uwb.lending import Backlogs
from transports.uwb.pacing import MediumAccess, Pacer
from transports.uwb.radio_time import RadioTime
from transports.uwb.receiving import CHUNK_COST, PeerState
from transports.uwb.sending import HASH_LEN, Outgoing
from transports.uwb.signing import TRAILER_LEN, Signer, Verifier

# The config, events and counters live in arq_types; callers reach them through this module.
__all__ = [
    "MAX_CHUNKS",
    "ArqConfig",
    "ArqCounters",
    "ArqEndpoint",
    "Event",
    "MessageClosed",
    "MessageDelivered",
    "MessageFailed",
    "MessageFlushed",
    "MessageReceived",
    "PeerDown",
    "PeerFeatures",
    "PeerRestarted",
    "PeerUp",
]

#: Superseded messages whose late COMPLETEs still count as deliveries (R5): a few versions back.
MAX_LATE = 16
#: A message is tried for at least this many times its airtime at the node's share of the channel
#: (R6), if that is longer than ``deadline_s``: room for repairs, acks and others' turns. At two the
#: maps of ``mapd bench swarm`` (a few kB, 16 robots) keep the configured deadline.
DEADLINE_AIRTIMES = 2.0


class ArqEndpoint(InputSide, TimerSide):
    """One node's protocol state: many peers, many messages, one byte stream (the receiving rules
    are in :class:`~transports.uwb.arq_rx.ReceiverSide`, what a sender does with acks in
    :class:`~transports.uwb.arq_acks.AckSide`, what it sends next in
    :class:`~transports.uwb.arq_tx.SenderSide`, which holds :meth:`data_to_send`; bytes in,
    :meth:`receive_data`, in :class:`~transports.uwb.arq_input.InputSide`; :meth:`get_timer` and
    :meth:`handle_timer` in :class:`~transports.uwb.arq_timers.TimerSide`)."""

    def __init__(self, config: ArqConfig, *, session: int, seed: int = 0) -> None:
        self.cfg = config
        self.node = config.node_id
        self.session = session & wire.MASK24
        self._rng = random.Random(seed)
        # A keyed link's frames end with their signature, which is their check too: no CRC.
        self._crc = not config.key
        self._out_of_turn_from: int | None = None  # R18: the link id last heard in our own slot
        self._reader = FrameReader(config.max_frame, crc=self._crc)
        # Two frames deep, so a late wake-up can catch up; the 1 s window still bounds every second.
        self._pacer = Pacer(config.rate_bps, 2 * config.max_frame)
        self._mac = MediumAccess(
            config.mac,
            config.rate_bps,
            slot_s=config.slot_s,
            slots=config.slots,
            slot_index=config.slot_index,
            guard_s=config.guard_s,
            clock_offset=config.clock_offset,
            sense_s=config.sense_s,
            backoff_min_s=config.backoff_min_s,
            backoff_max_s=config.backoff_max_s,
            rng=self._rng,
        )
        self._signer = Signer(config.key, config.counter_start) if config.key else None
        self._verifier = Verifier(config.key, config.replay_marks) if config.key else None
        self._damage_at_valid = 0  # damaged frames counted when the last valid frame came
        self._trailer = TRAILER_LEN if config.key else 0
        # A frame size that divides the 1 s byte budget evenly: 7 frames of 223 bytes fit in the
        # 1562 bytes of 12.5 kb/s, where frames of 224 would leave room for only 6.
        budget = self._pacer.budget
        self.frame_size = min(config.max_frame, int(budget // math.ceil(budget / config.max_frame)))
        body = max_body(max(self.frame_size, MIN_FRAME), crc=self._crc)
        self.chunk_size = body - wire.DATA_HEADER_LEN - self._trailer
        if self.chunk_size < 8:
            raise ValueError(f"uwb: max_frame {config.max_frame} leaves no room for data")
        self._max_total = config.max_message_bytes + HASH_LEN
        # Room for two messages of the largest size, each chunk with its CHUNK_COST.
        self._rx_budget = config.rx_budget_bytes or 2 * (
            self._max_total + CHUNK_COST * -(-self._max_total // self.chunk_size)
        )
        self._partial_ttl = config.partial_ttl_s or 2 * config.deadline_s
        self._ack_delay = config.ack_delay_s or 4 * 8 * config.max_frame / config.rate_bps
        self._nack_backoff = config.nack_backoff_s or 8 * self._ack_delay
        # With TDMA no receiver can answer a probe before its own slot comes round: the probe
        # timer never runs shorter than one cycle (each probe would take a data frame's place).
        self._cycle = config.slots * config.slot_s if config.mac == "tdma" else 0.0
        # R3: a TDMA peer speaks only in its own slot, so an idle one is heard once in beacon_s plus
        # a cycle, and one lost HELLO costs a cycle more. With 36 default slots at 12.5 kb/s the
        # cycle (21 s) outgrew the 20 s timeout: every peer went down and up each cycle, and each
        # PeerDown let the publisher supersede the map on the air (P1).
        self._presence_s = max(config.peer_timeout_s, config.beacon_s + 2 * self._cycle)
        # R19: the turns' clock agreed over the radio (only TDMA has turns to agree on)
        self._radio: RadioTime | None = None
        if config.radio_time and config.mac == "tdma":
            self._radio = RadioTime(self.node, session=self.session, cycle_s=self._cycle)
        self._peers: dict[int, PeerState] = {}
        # R17: lending the rest of an own slot, for which a LEND and one full frame must still fit.
        self._lending = config.lend and config.mac == "tdma"
        self._backlogs = Backlogs(2 * self._cycle, config.max_peers)
        full = self._est(wire.DATA_HEADER_LEN + self.chunk_size)
        self._lend_need = 8 * (full + self._est(wire.LEND_LEN)) / config.rate_bps
        # (peer, msg) -> (due, the peer's session then): COMPLETEs to go in the next DONE frame.
        self._done_owed: OrderedDict[tuple[int, int], tuple[float, int]] = OrderedDict()
        self._done_max = max(1, (body - self._trailer - wire.HEADER_LEN) // wire.DONE_ENTRY_LEN)
        self._rtt: dict[int, RttEstimator] = {}
        self._out: OrderedDict[int, Outgoing] = OrderedDict()
        self._late: OrderedDict[int, set[int]] = OrderedDict()  # superseded msg -> peers not yet COMPLETE
        self._next_msg = self._rng.getrandbits(23)
        self._events: deque[Event] = deque()
        self._now = -math.inf
        self._hello_due = -math.inf
        self._hello_at = -math.inf  # when the last HELLO went
        self._housekeeping_at = -math.inf
        self._rx_held = 0
        self._delivered = GoodputWindow()
        self._proactive = 0.0  # parity sent with a broadcast's first pass, as a share (R16, fec)
        self.counters = ArqCounters()

    # --- the API an adapter drives --------------------------------------------------------------

    def send(
        self,
        data: bytes,
        now: float,
        *,
        dests: list[int],
        stream: int = 0,
        deadline: float | None = None,
        background: bool = False,
        reliable: bool = True,
    ) -> int:
        """Queue ``data`` for ``dests`` (link ids); return its message id (latest wins per stream).

        A ``background`` message (a pose) gets a frame only when no other message has one to send.
        An unreliable one is sent once, unacknowledged, and closes ("sent") after its last chunk.

        :class:`LimitError` when the message is too large to send; ValueError for a stream outside
        0..255 or no valid peer in ``dests`` (the caller's mistakes).
        """
        self._now = now
        if len(data) > self.cfg.max_message_bytes:
            raise LimitError(
                f"uwb: message of {len(data)} bytes is over the limit of {self.cfg.max_message_bytes}"
            )
        if len(data) + HASH_LEN > wire.MAX_TOTAL:
            raise LimitError(
                f"uwb: message of {len(data)} bytes is over the wire's limit of {wire.MAX_TOTAL}"
            )
        if -(-(len(data) + HASH_LEN) // self.chunk_size) > MAX_CHUNKS:
            raise LimitError(f"uwb: message of {len(data)} bytes needs more than {MAX_CHUNKS} chunks")
        if not 0 <= stream <= 255:
            raise ValueError(f"uwb: stream {stream} is not in 0..255")
        targets = sorted({d for d in dests if d != self.node})
        if not targets or not all(1 <= d <= 254 for d in targets):
            raise ValueError(f"uwb: no valid peer to send to (got {dests})")
        for old in [m for m in self._out.values() if m.stream == stream]:
            del self._out[old.msg]
            self.counters.superseded += 1
            if old.flushed and old.pending():
                # Receivers that got every chunk still say COMPLETE (R5): keep hearing them.
                self._late[old.msg] = {p.peer for p in old.pending()}
                while len(self._late) > MAX_LATE:
                    self._late.popitem(last=False)
            self._events.append(MessageClosed(old.msg, "superseded"))
        msg = self._next_msg
        self._next_msg = (self._next_msg + 1) & wire.MASK24
        dst = targets[0] if len(targets) == 1 else wire.BROADCAST
        when = now + self.message_deadline_s(len(data)) if deadline is None else deadline
        out = Outgoing(msg, stream, data, self.chunk_size, targets, dst, now, when)
        out.background = background
        out.reliable = reliable
        out.nack = reliable and self._nack_mode(dst)
        # Parity only where every receiver rebuilds from it: one from before would refuse it as
        # malformed and never complete the map (its HELLO says: wire.hello_features).
        out.fec = out.nack and self.cfg.fec and all(self._understands(d, wire.F_PARITY) for d in targets)
        out.proactive = self._proactive if out.fec else 0.0
        self._out[msg] = out
        for d in targets:
            self._rtt_of(d)
        self.counters.messages_tx += 1
        return msg

    def airtime_s(self, nbytes: int) -> float:
        """How long a message of ``nbytes`` takes on the air, each frame once, at this node's share
        of the channel: ``rate_bps`` over ``slots`` (an equal turn of the robots on it)."""
        frames = -(-(nbytes + HASH_LEN) // self.chunk_size)
        return frames * self.frame_size * 8 / (self.cfg.rate_bps / max(1, self.cfg.slots))

    def message_deadline_s(self, nbytes: int) -> float:
        """How long after :meth:`send` a message of ``nbytes`` is given up without a deadline of
        the caller's (R6): ``deadline_s``, or :data:`DEADLINE_AIRTIMES` times its airtime if longer."""
        return max(self.cfg.deadline_s, DEADLINE_AIRTIMES * self.airtime_s(nbytes))

    def set_clock_offset(self, offset: float) -> None:
        """The shared (wall) clock is now ``offset`` seconds ahead of the ``now`` passed in.

        TDMA slots and the signing counters' clock check count on the wall clock. The adapter reads
        it as it runs and passes a change here: NTP stepping the clock after the link started (a
        robot that booted before it had a time source) would otherwise leave this robot's slots
        where the old clock put them, over its neighbours'.
        """
        moved, self.cfg = offset - self.cfg.clock_offset, dataclasses.replace(self.cfg, clock_offset=offset)
        if self._radio is not None and math.isfinite(self._now):  # (no time counted on the old one yet)
            self._radio.wall_moved(moved)
        self._follow_radio(self._now)

    def set_clock_source(self, source: bool) -> None:
        """Whether a time service keeps this node's wall clock (``mapd.wallclock``): with
        ``radio_time``, such a node leads the fleet's turns and never follows another (R19)."""
        if self._radio is not None:
            self._radio.set_source(source, self._now + self.cfg.clock_offset)
            self._follow_radio(self._now)

    def radio_clock(self) -> dict[str, Any] | None:
        """The radio clock's state (R19) for ``mapd status``; None when the link has none."""
        return None if self._radio is None else self._radio.stats(self._now + self.cfg.clock_offset)

    def events(self) -> list[Event]:
        """Drain the events produced so far."""
        out = list(self._events)
        self._events.clear()
        return out

    def counter_reservation(self) -> int | None:
        """A signing-counter bound the adapter must persist, then :meth:`confirm_counter`; or None."""
        return self._signer.reservation() if self._signer is not None else None

    def confirm_counter(self, upto: int) -> None:
        """The adapter has persisted ``upto`` (from :meth:`counter_reservation`): sign below it."""
        if self._signer is not None:
            self._signer.confirm(upto)

    def raise_counter(self, floor: int) -> bool:
        """Sign on from counter ``floor`` if that is higher than the next (the wall clock stepped
        ahead: the counter began from a clock behind, under the marks peers hold from before).
        Nothing is signed until :meth:`counter_reservation` past it is saved. True when it rose."""
        return self._signer is not None and self._signer.raise_to(floor)

    def replay_marks(self) -> dict[int, int]:
        """Sender id -> the highest signed counter accepted: for the adapter to keep across restarts."""
        return self._verifier.marks() if self._verifier is not None else {}

    def peers_up(self) -> list[int]:
        """Link ids of the peers heard within ``peer_timeout_s`` (with TDMA: within ``beacon_s``
        and two cycles, if longer; R3)."""
        return sorted(p.id for p in self._peers.values() if p.up)

    def older_peers(self) -> dict[int, int]:
        """Link id -> the features it lacks (``wire.F_*`` bits) of the peers whose HELLO announced
        fewer than this node announces: a mapd from before them (wire.py, *Features*), or, for
        :data:`~wire.F_TIME` alone, one whose turns are on its wall clock (``clock = "system"``)."""
        own = wire.own_features(self.cfg.radio_time)
        return {
            p.id: own & ~p.features
            for p in self._peers.values()
            if p.features is not None and own & ~p.features
        }

    def reaches(self, msg: int, peer: int) -> bool:
        """Whether message ``msg`` is still being sent and ``peer`` is one of its receivers that has
        not got it all (so a map in flight will reach a robot that just came into range)."""
        m = self._out.get(msg)
        p = m.peers.get(peer) if m is not None else None
        return p is not None and p.pending

    def in_flight(self) -> int:
        """Messages still in the send queue (neither delivered to all, failed nor superseded)."""
        return len(self._out)

    def stats(self) -> dict[str, Any]:
        """Flat counters and gauges (bytes, frames, resends, errors, RTT, goodput, peak rate)."""
        r = self._reader.stats
        out: dict[str, Any] = dataclasses.asdict(self.counters)
        out.update(crc_errors=r.crc_errors, cobs_errors=r.cobs_errors, oversize=r.oversize, runts=r.runts)
        if self._verifier is not None:
            out.update(dataclasses.asdict(self._verifier.stats))
        srtts = [e.srtt for e in self._rtt.values() if e.srtt is not None]
        out["rtt_ms"] = round(1000 * sum(srtts) / len(srtts), 1) if srtts else None
        out["rto_ms"] = round(1000 * max((e.rto for e in self._rtt.values()), default=0.0), 1)
        out["goodput_bps"] = round(self._delivered.rate_bps(self._now), 1)  # over the last 30 s
        out["fec_proactive"] = round(self._proactive, 3)  # parity sent with a first pass, per chunk
        out["peak_bps_1s"] = round(8 * self._pacer.peak_window_bytes / self._pacer.window, 1)
        out["link_rate_bps"] = self.cfg.rate_bps
        if self._out_of_turn_from is not None:
            out["out_of_turn_from"] = self._out_of_turn_from  # the link id last heard out of turn
        out["in_flight"] = len(self._out)
        out["rx_held_bytes"] = self._rx_held
        out["peers_up"] = len(self.peers_up())
        out["older_peers"] = self.older_peers()  # link id -> features lacked (the adapter names them)
        # Frames the line spoiled, whatever caught them; and since the last valid frame: a wrong
        # baud or a broken line, not noise long past while the robot is now merely alone (mapd
        # status raises a FAULT on that, not on the total).
        out["damaged"] = self._damage_total()
        out["damaged_since_valid"] = out["damaged"] - self._damage_at_valid
        return out
