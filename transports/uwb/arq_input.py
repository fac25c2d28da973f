"""What :class:`~transports.uwb.arq.ArqEndpoint` does with the bytes it hears, before any rule of
a side looks at a frame: framing and its check (R1), the signature and replay checks (R2), the
sender as a peer with its session (R3), frames heard in this node's own TDMA slot (R18), then the
frame handed to the side whose rule it is (rules in ``arq.py``'s docstring), as a mixin over the
endpoint's state. TIME frames go to the radio clock (R19).

DATA goes to the receiving rules (``arq_rx.py``), ACKs and DONE entries to the sender's ack
handling (``arq_acks.py``), a LEND to the sending rules (``arq_tx.py``). A peer that restarted gets
a clean start here, on both sides at once: what it was reassembling from us is forgotten, and what
it had acked of our messages is sent again.
"""

from __future__ import annotations

from mapd.errors import ProtocolError
from transports.uwb import wire
from transports.uwb.arq_tx import SenderSide
from transports.uwb.arq_types import PeerFeatures, PeerRestarted, PeerUp
from transports.uwb.framing import FrameReader, check_len
from transports.uwb.receiving import PeerState
from transports.uwb.signing import Verifier


class InputSide(SenderSide):
    """Frame input (a mixin: :class:`~transports.uwb.arq.ArqEndpoint` owns the state declared here
    and in the sides it builds on)."""

    _reader: FrameReader
    _verifier: Verifier | None
    _now: float
    #: Damaged frames counted when the last valid frame came (``damaged_since_valid`` in stats).
    _damage_at_valid: int
    _out_of_turn_from: int | None

    def receive_data(self, data: bytes, now: float) -> None:
        """Bytes from the line (any split, any garbage)."""
        self._now = now
        self.counters.bytes_rx += len(data)
        if data:
            self._mac.heard(now)
        for body in self._reader.feed(data):
            self._on_body(body, now)

    def _damage_total(self) -> int:
        """Frames the line spoiled so far, whatever caught them (framing, CRC, the link tag)."""
        r = self._reader.stats
        tag = self._verifier.stats.bad_signature if self._verifier is not None else 0
        return r.crc_errors + r.cobs_errors + r.oversize + r.runts + tag

    def _on_body(self, body: bytes, now: float) -> None:
        signed = wire.is_signed(body)
        plain: bytes | None
        if self._verifier is not None:
            wall = now + self.cfg.clock_offset if self.cfg.check_counter_clock else None
            plain = self._verifier.check(body, signed, wall)
            if plain is None:
                return
        elif signed:
            self.counters.signed_no_key += 1
            return
        else:
            plain = body
        try:
            frame = wire.parse(plain)
        except ProtocolError:
            self.counters.bad_frames += 1
            return
        self.counters.frames_rx += 1
        self._damage_at_valid = self._damage_total()
        if frame.src == self.node:
            self.counters.own_id += 1  # another node uses our id, or the medium echoes
            return
        if self.cfg.mac == "tdma":  # R18
            airtime = (len(body) + 2) * self._mac.byte_time  # (the delimiter and COBS add at least 2)
            if self._mac.in_own_slot(now - airtime, now - self.cfg.rx_slack_s):
                self.counters.out_of_turn += 1
                self._out_of_turn_from = frame.src
        peer = self._peer_for(frame, now)
        if peer is None:
            return
        if isinstance(frame, wire.Hello):
            features = wire.hello_features(frame)
            if features is not None:
                peer.features, was, peer.announced = features, peer.announced, features
                # said when it lacks any, or no longer does: not for every peer of this version
                own = wire.own_features(self.cfg.radio_time)
                lacks, lacked = own & ~features, was is not None and own & ~was
                if features != was and (lacks or lacked):
                    self._events.append(PeerFeatures(peer.id, features))
                if not features & wire.F_PARITY:  # maps on their way to it: repairs resend chunks
                    for m in self._out.values():
                        if peer.id in m.peers:
                            m.fec = False
        elif isinstance(frame, wire.Data):
            if frame.reliable:  # how much it still has to send (R17)
                self._backlogs.heard(peer.id, frame.msg, frame.index, frame.count, now)
            self._on_data(peer, frame, now)
        elif isinstance(frame, wire.Lend):
            self._on_lend(frame, now)
        elif isinstance(frame, wire.Time):
            self.counters.times_rx += 1
            if self._radio is not None:  # R19: its stamp, plus its airtime, is the root's clock now
                wire_len = len(body) + 2 + check_len(self._crc)  # COBS overhead, delimiter, check
                local = now + self.cfg.clock_offset
                if self._radio.heard(frame, local, wire_len * self._mac.byte_time):
                    self._follow_radio(now)
        elif isinstance(frame, wire.Ack):
            self._on_ack(peer, frame, now)
        elif isinstance(frame, wire.Done):
            for sender, target, low in frame.entries:
                if sender == self.node:  # each entry is a COMPLETE ack (the others are for others)
                    self._on_done_entry(peer, target, low, now)

    def _peer_for(self, f: wire.Frame, now: float) -> PeerState | None:
        peer = self._peers.get(f.src)
        if peer is None:
            if len(self._peers) >= self.cfg.max_peers and not self._evict_peer():
                self.counters.peers_full += 1
                return None
            peer = PeerState(f.src, f.session, now, self.cfg.max_partials_per_peer)
            self._peers[f.src] = peer
            self._events.append(PeerUp(f.src))
            self._hello_soon(now)  # a newcomer: tell it what we understand
        elif f.session != peer.session:
            if f.session in peer.retired:
                self.counters.stale_session += 1
                return None
            self._rx_held -= peer.restart(f.session)
            self._events.append(PeerRestarted(f.src))
            self._hello_soon(now)  # it forgot what we understand
            self._backlogs.forget(f.src)  # its message ids start afresh
            for m in self._out.values():
                prog = m.peers.get(f.src)
                if prog is not None and prog.pending:
                    prog.reset()
                    prog.rto_at = None
                    for i in m.outstanding(prog):
                        m.queue_resend(i)
        if not peer.up:
            peer.up = True
            self._events.append(PeerUp(f.src))
        peer.last_heard = now
        return peer

    def _evict_peer(self) -> bool:
        """Make room by forgetting a peer that is down and holds nothing; False when none is."""
        for pid, peer in self._peers.items():
            if not peer.up and not peer.partials:
                del self._peers[pid]
                return True
        return False
