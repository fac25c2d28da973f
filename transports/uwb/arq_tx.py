"""What :class:`~transports.uwb.arq.ArqEndpoint` sends next, and how it builds each frame: HELLO,
TIME (R19), an owed ACK or DONE, a data or parity chunk (R4-R8, R16), or a LEND of the rest of an
idle own slot (R17), as a mixin over the endpoint's state (rules in ``arq.py``'s docstring); and the
frame handed to the adapter, signed, framed and let through by the pacer and medium access (R14,
R15).

Order: a due HELLO, a due TIME, an owed ACK, a due DONE, then the next chunk, round-robin over
messages with background ones last; a node with nothing of its own left may lend its slot. The
rest of the API stays in ``arq.py``, the timers in ``arq_timers.py``, frame input in
``arq_input.py``; the ack rules in ``arq_acks.py``, the receiving rules in ``arq_rx.py``.
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from typing import TYPE_CHECKING, Any

from transports.uwb import wire
from transports.uwb.arq_acks import AckSide
from transports.uwb.arq_rx import ReceiverSide
from transports.uwb.arq_types import Event, MessageFlushed
from transports.uwb.framing import encode_frame
from transports.uwb.lending import Backlogs
from transports.uwb.pacing import MediumAccess, Pacer
from transports.uwb.radio_time import RadioTime
from transports.uwb.sending import Outgoing
from transports.uwb.signing import Signer

#: However busy a node is, it sends a HELLO at least this often (seconds): a HELLO carries its
#: features (wire.py), and a robot that came into range or restarted while this one was never
#: silent for ``beacon_s`` would otherwise never hear them.
HELLO_REFRESH_S = 60.0
#: A HELLO for newcomers goes no sooner than this after the last one: one answers every robot first
#: heard meanwhile. Without TDMA to merge them, 32 robots starting at once sent one per robot heard
#: (1,184 in 30 s against 224), and a map to all of them sent half a second in took twice as long.
HELLO_MIN_GAP_S = 0.3


class SenderSide(ReceiverSide, AckSide):
    """The sending rules (a mixin: :class:`~transports.uwb.arq.ArqEndpoint` owns the state declared
    here and in the two sides it builds on)."""

    _out: OrderedDict[int, Outgoing]
    _events: deque[Event]
    _now: float
    _pacer: Pacer
    _mac: MediumAccess
    #: None on a link without a key (R15: with one, nothing is sent past the counters saved).
    _signer: Signer | None
    _backlogs: Backlogs
    #: R17 is on (TDMA with ``lend``), and the room a LEND and one full frame need in a slot (s).
    _lending: bool
    _lend_need: float
    _hello_due: float
    _hello_at: float
    #: One TDMA cycle (0 without TDMA): no probe timer runs shorter.
    _cycle: float
    #: R19: the fleet's radio clock (None: turns on the wall clock alone).
    _radio: RadioTime | None

    if TYPE_CHECKING:

        def peers_up(self) -> list[int]: ...

    def data_to_send(self, now: float) -> bytes:
        """The next frame to write, or b"" when pacing, access or signing says wait (see get_timer)."""
        self._now = now
        if self._radio is not None:
            self._follow_radio(now)
        if self._signer is not None and not self._signer.can_sign():
            return b""
        while True:
            pick = self._choose(now)
            if pick is None:
                pick = self._lend_pick(now)
            if pick is None:
                return b""
            kind, ref, est = pick
            if max(self._pacer.ready_at(est, now), self._mac.ready_at(est, now)) > now:
                return b""
            frame = self._build(kind, ref, now)
            if frame is not None:
                break
        body = wire.pack(frame, signed=self._signer is not None)
        if self._signer is not None:
            body = self._signer.sign(body)
        out = encode_frame(body, crc=self._crc)
        self._pacer.consume(len(out), now)
        self._mac.sent(len(out), now)
        # after beacon_s of silence, and at least every HELLO_REFRESH_S (features for newcomers)
        self._hello_due = min(now + self.cfg.beacon_s, self._hello_at + HELLO_REFRESH_S)
        self.counters.bytes_tx += len(out)
        self.counters.frames_tx += 1
        return out

    def _follow_radio(self, now: float) -> None:
        """R19: the turns follow the wall clock plus the radio clock's correction at ``now``
        (which moves between TIME frames by the rate the leader's clock runs at against ours)."""
        local = now + self.cfg.clock_offset
        correction = (
            self._radio.correction_at(local) if self._radio is not None and math.isfinite(local) else 0.0
        )
        self._mac.clock_offset = self.cfg.clock_offset + correction

    def _time_due(self, now: float) -> float | None:
        """When a TIME frame is due (R19), on the endpoint's clock; None: none is."""
        if self._radio is None:
            return None
        due = self._radio.due(now + self.cfg.clock_offset, any(p.up for p in self._peers.values()))
        return None if due is None else due - self.cfg.clock_offset

    def _hello_soon(self, now: float) -> None:
        """A HELLO is wanted soon (a peer first heard, or one that restarted: it must hear what
        this node understands), no sooner than :data:`HELLO_MIN_GAP_S` after the last."""
        self._hello_due = min(self._hello_due, max(now, self._hello_at + HELLO_MIN_GAP_S))

    def _on_lend(self, f: wire.Lend, now: float) -> None:
        """R17: the rest of the sender's slot is ours, if it names the slot we are in (a LEND that
        arrived late names one already over) and that slot is not ours."""
        if f.dst != self.node or not self._lending:
            return
        k = self._mac.slot_number(now)
        if f.slot == k % wire.SLOT_MOD and self._mac.own_slot_left(now) == 0.0:
            self._mac.borrow(now)
            self.counters.borrowed += 1

    def _lend_to(self, now: float) -> tuple[float, int] | None:
        """When this node could lend the rest of an own slot, and to whom (R17); None while it has
        anything to send or owes anything, or no peer is known to have chunks left."""
        if not self._lending or self._hello_due <= now or self._done_owed or self._owed_ack() is not None:
            return None
        time_due = self._time_due(now)
        if time_due is not None and time_due <= now:
            return None
        if self._next_data() is not None:
            return None
        peer = self._backlogs.pick(now, [p for p in self.peers_up() if self._understands(p, wire.F_LEND)])
        if peer is None:
            return None
        room = self._mac.own_slot_left(now) >= self._lend_need
        return (now if room else self._mac.next_own_slot(now)), peer

    def _lend_pick(self, now: float) -> tuple[str, Any, int] | None:
        lend = self._lend_to(now)
        if lend is None or lend[0] != now:
            return None
        return "lend", lend[1], self._est(wire.LEND_LEN)

    def _send_dues(self, now: float) -> list[tuple[float, int]]:
        """(due time, size estimate) of each kind of frame waiting to go."""
        dues = [(self._hello_due, self._est(wire.HEADER_LEN))]
        time_due = self._time_due(now)
        if time_due is not None:
            dues.append((time_due, self._est(wire.TIME_LEN)))
        owed = self._owed_ack()
        if owed is not None:
            dues.append((owed[0], self._est(wire.ACK_HEADER_LEN + wire.MAX_BITMAP)))
        done = self._done_due()
        if done is not None:
            dues.append((done, self._done_est()))
        data = self._next_data()
        if data is not None:
            # the frame _choose would build, at its size: a short last chunk may still fit a slot
            dues.append((now, self._est(wire.DATA_HEADER_LEN + len(data[0].chunk(data[1])))))
        return dues

    def _next_data(self) -> tuple[Outgoing, int] | None:
        """The chunk to send next: round-robin over messages, background ones (poses) only when no
        other has a chunk to go."""
        for m in sorted(self._out.values(), key=lambda m: m.background):
            i = m.next_index(self.cfg.window)
            if i is not None:
                return m, i
        return None

    def _choose(self, now: float) -> tuple[str, Any, int] | None:
        if self._hello_due <= now:
            return "hello", None, self._est(wire.HEADER_LEN)
        time_due = self._time_due(now)
        if time_due is not None and time_due <= now:
            return "time", None, self._est(wire.TIME_LEN)
        owed = self._owed_ack()
        if owed is not None and owed[0] <= now:
            return "ack", (owed[1], owed[2]), self._est(wire.ACK_HEADER_LEN + wire.MAX_BITMAP)
        done = self._done_due()
        if done is not None and done <= now:
            return "done", None, self._done_est()
        data = self._next_data()
        if data is not None:
            m, i = data
            return "data", (m, i), self._est(wire.DATA_HEADER_LEN + len(m.chunk(i)))
        return None

    def _build(self, kind: str, ref: Any, now: float) -> wire.Frame | None:
        if kind == "hello":
            self.counters.hellos_tx += 1
            self._hello_at = now
            return wire.Hello(
                self.node, wire.FEATURES_FLAG | wire.own_features(self.cfg.radio_time), self.session
            )
        if kind == "time" and self._radio is not None:
            self.counters.times_tx += 1
            # stamped with when it goes on the air: TDMA lets a frame go only once the one before is out
            return self._radio.beacon(now + self.cfg.clock_offset, self.node, self.session)
        if kind == "ack":
            peer, msg = ref
            return self._build_ack(peer, msg, now)
        if kind == "done":
            return self._build_done(now)
        if kind == "lend":
            self._mac.lend(now)  # nothing more of ours in this slot: it is the peer's
            self._backlogs.lent(ref, now)
            self.counters.lends_tx += 1
            return wire.Lend(self.node, ref, self.session, self._mac.slot_number(now) % wire.SLOT_MOD)
        m, i = ref
        resend = m.mark_sent(i, now)
        self._out.move_to_end(m.msg)  # round-robin between messages
        self.counters.data_tx += 1
        if i >= m.count:
            self.counters.parity_tx += 1
        elif resend:
            self.counters.resends += 1
        frame = wire.Data(
            self.node, m.dst, self.session, m.msg, m.stream, i, m.count, m.total, m.chunk(i), m.reliable
        )
        if not m.reliable:
            if m.next_new >= m.count:  # every chunk went once: nothing more will
                self._close(m, "sent")
            return frame
        if m.next_new >= m.count and not m.flushed:
            m.flushed = True  # a receiver may now complete it even if it is superseded (R5)
            self._events.append(MessageFlushed(m.msg))
        if m.nack:
            # R16: receivers stay silent while chunks arrive in order, so the probe timer runs only
            # once the sender has nothing left to send for this message (its flush point).
            more = m.has_work(self.cfg.window)
            for p in m.pending():
                p.rto_at = None if more else now + max(self._rtt_of(p.peer).rto, self._cycle)
            return frame
        for p in m.pending():
            if p.rto_at is None:
                p.rto_at = now + self._rtt_of(p.peer).rto
        return frame
