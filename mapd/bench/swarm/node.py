"""One robot of the swarm: the real ARQ core and the real publisher core, joined as the daemon joins them.

:class:`SwarmRobot` is a virtual-time adapter, like ``transports/uwb/link.py`` and the daemon's
publish loop are real-time ones. It owns a real :class:`~transports.uwb.arq.ArqEndpoint` (pacing,
medium access, signing when a key is given) and a real :class:`~mapd.daemon.publisher.PublisherCore`
(what to code, against which base, when), and does what :class:`~transports.uwb.transport.UwbTransport`
and :mod:`mapd.daemon.server` do between them:

* a new own version goes to the publisher; when it says code, the payload is the size of the real
  signed envelope of the real codec's output (:class:`~mapd.bench.swarm.streams.Payloads`), sent on
  stream 0 to the :class:`~mapd.bench.swarm.policy.AckScope`'s dests (the daemon's default: every
  other robot configured); ``MessageDelivered`` / ``MessageFailed`` go back to the publisher as acks
  and failures, ``MessageFlushed`` as the offer wholly on the air, ``PeerUp`` of a robot that no map
  on its way reaches as ``Arrived`` (P6, as the transport; see :data:`ARRIVALS`); coding takes no
  virtual time;
* a received map is accepted as the daemon's receiver accepts it (newer than the newest held, and a
  delta only when its base is among the :data:`~mapd.daemon.receiver.KEEP_PEER_VERSIONS` newest
  held); a delta whose base is gone asks the origin for a keyframe on the control stream, at most once
  per ``keyframe_request_s`` per origin, and the origin's publisher sends its next version whole;
* after each accept the :class:`~mapd.bench.swarm.policy.RelayPolicy` may forward the map.

A message's bytes are a 10-byte tag (origin, version, base) padded with zeros to the envelope's size:
the ARQ core neither compresses nor looks inside, so airtime, chunking and hashing are those of the
real envelope, and the receiver learns what it got without decoding.
"""

from __future__ import annotations

import random
import struct
from collections.abc import Callable

import numpy as np

from mapd.bench.swarm.policy import AckScope, RelayPolicy, SummaryRelay
from mapd.bench.swarm.streams import Payloads, RobotStream
from mapd.config import CodecSection
from mapd.daemon.publisher import INFLIGHT_TIMEOUT_S, PublisherCore
from mapd.daemon.receiver import KEEP_PEER_VERSIONS
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import SIG_LEN
from transports.uwb import arq, forwarding
from transports.uwb import keyframe_requests as control

_TAG = struct.Struct("<HII")  # origin link id, version, base version (0: keyframe)
MAP_STREAM = 0
KEYFRAME_REQUEST_S = 5.0
#: The daemon's default (``[codec] keyframe_every``).
KEYFRAME_EVERY: int = CodecSection.model_fields["keyframe_every"].default
_TINY = np.zeros((1, 1), dtype=np.int8)

#: What a robot does when it hears another come into range: ``offer`` its newest map if no map on its
#: way reaches that robot (P6, the daemon's uwb transport); ``ask`` the other for a keyframe if no map
#: of it came yet (the transport before P6); or nothing.
ARRIVALS = ("offer", "ask", "none")
#: (time, holder index, origin index, version) of every accepted map.
AcceptLog = list[tuple[float, int, int, int]]


class SwarmRobot:
    """Robot ``index`` (link id ``index + 1``) of ``n``."""

    def __init__(
        self,
        index: int,
        n: int,
        streams: list[RobotStream],
        payloads: Payloads,
        config: arq.ArqConfig,
        *,
        relay: RelayPolicy,
        acks: AckScope,
        accepted: AcceptLog,
        session: int,
        seed: int,
        inflight_s: float = INFLIGHT_TIMEOUT_S,
        keyframe_every: int = KEYFRAME_EVERY,
        hold: bool = True,
        arrival: str = "offer",
    ) -> None:
        self.index = index
        self.id = index + 1
        self.streams = streams
        self.payloads = payloads
        self.arq = arq.ArqEndpoint(config, session=session, seed=seed)
        self._confirm()
        self.pub = PublisherCore(
            uses_base=payloads.uses_base,
            keyframe_every=keyframe_every,
            inflight_timeout_s=inflight_s,
            paced={"uwb"} if hold else set(),  # as the daemon's uwb transport (P1)
        )
        if arrival not in ARRIVALS:
            raise ValueError(f"arrival {arrival!r}: one of {', '.join(ARRIVALS)}")
        self.arrival = arrival
        self.relay = relay
        self.acks = acks
        self.accepted = accepted
        self.configured = [j + 1 for j in range(n) if j != index]
        self.held: dict[int, list[int]] = {}  # origin index -> newest versions held, oldest first
        self._own_msgs: dict[int, int] = {}  # ARQ message id -> own version
        self._late: dict[int, int] = {}  # superseded ARQ message id -> own version
        self._asked: dict[int, float] = {}  # origin index -> when a keyframe was last asked of it
        self._maps_from: set[int] = set()  # link ids a map came from (for arrival "ask")
        self.coded_bytes = 0
        self.keyframes = 0
        self.deltas = 0
        self.kf_requests = 0
        self.relayed = 0
        self.summaries = 0  # queued (background: they go on the air only in gaps the maps leave)
        self.summaries_rx = 0  # neighbours' summaries received
        # The summary relay: the real forwarding core, summaries on their own stream at a random phase.
        self.fwd: forwarding.ForwardingCore | None = None
        self._summary_period = 0.0
        self._next_summary = 0.0
        self._relay_msg: int | None = None
        if isinstance(relay, SummaryRelay):
            p = self._summary_period = relay.summary_period_s
            self.fwd = forwarding.ForwardingCore.for_summaries(
                self.id,
                summary_period_s=p,
                relay_period_s=relay.relay_period_s,
                share_bps=config.rate_bps / n,  # as the daemon's uwb transport: an equal turn
                max_relay_s=config.deadline_s,
            )
            self._next_summary = random.Random(seed).uniform(0.0, p)

    # --- inputs ---------------------------------------------------------------------------------
    def new_version(self, version: int, now: float) -> None:
        self.pub.new_version(OccupancyGrid(_TINY, 0.05, robot=self.streams[self.index].name, version=version))
        self._poll(now)

    def receive(self, data: bytes, now: float) -> None:
        self.arq.receive_data(data, now)

    # --- the service routine the event loop calls -------------------------------------------------
    def service(self, now: float, radio_free: float, emit: Callable[[bytes, str], float]) -> None:
        """Fire due timers, handle events, and while the radio is free (``radio_free <= now``) hand
        the next frame that may go to ``emit(frame, kind)``, which returns when the radio is free again.

        As the real adapter (``link.py``) waits for each write to drain before asking for the next
        frame, a robot never hands its radio a frame while the previous one is still on the air."""
        self.arq.handle_timer(now)  # fires only what is due at now (cheaper than asking get_timer first)
        d = self.pub.next_deadline()
        if d is not None and d <= now:
            self._poll(now)
        self._events(now)
        if self.fwd is not None:
            self._forward(now)
        c = self.arq.counters
        while radio_free <= now:
            before = (c.acks_tx, c.hellos_tx, c.lends_tx)
            frame = self.arq.data_to_send(now)
            if not frame:
                break
            kind = (
                "ack" if c.acks_tx > before[0]
                else "hello" if c.hellos_tx > before[1]
                else "control" if c.lends_tx > before[2]
                else "data"
            )  # fmt: skip
            self._confirm()
            radio_free = emit(frame, kind)
            self._events(now)

    def next_wake(self) -> float | None:
        times = [t for t in (self.arq.get_timer(), self.pub.next_deadline()) if t is not None]
        if self.fwd is not None:
            times.append(self._next_summary)
            d = self.fwd.next_deadline()
            if d is not None:
                times.append(d)
        return min(times) if times else None

    # --- internals ------------------------------------------------------------------------------
    def _confirm(self) -> None:
        upto = self.arq.counter_reservation()
        if upto is not None:
            self.arq.confirm_counter(upto)

    def _forward(self, now: float) -> None:
        """Send a due summary, then start the relay the forwarding core picks, if any."""
        assert self.fwd is not None
        if now >= self._next_summary:
            self._next_summary = now + self._summary_period
            s = forwarding.Summary(self.fwd.holds(), frozenset(self.arq.peers_up()))
            self.arq.send(
                forwarding.pack_summary(s), now, dests=self.configured, stream=forwarding.SUMMARY_STREAM,
                deadline=now + self._summary_period, background=True, reliable=False,
            )  # fmt: skip
            self.summaries += 1
        r = self.fwd.next_forward(now)
        if r is not None:
            deadline = None if r.deadline_s is None else now + r.deadline_s
            self._relay_msg = self.arq.send(
                r.data, now, dests=list(r.dests), stream=r.origin, deadline=deadline
            )
            self.relayed += 1
        for origin_id in self.fwd.keyframes_wanted(now, set(self.arq.peers_up())):
            self._ask_keyframe(origin_id - 1, now)  # for a neighbour the chain cannot serve

    def _ask_keyframe(self, origin: int, now: float) -> None:
        """Ask robot ``origin`` (an index) for a whole map, at most once per ``KEYFRAME_REQUEST_S``,
        as the daemon's uwb transport does (``keyframe_requests``)."""
        last = self._asked.get(origin)
        if last is None or now - last >= KEYFRAME_REQUEST_S:
            self._asked[origin] = now
            self.kf_requests += 1
            # The signature's bytes as the daemon's: the bench checks no signature, it times them.
            req = control.pack_request(
                [self.streams[origin].name], nonce=1 + int(now * 1e9), sig=bytes(SIG_LEN)
            )
            self.arq.send(req, now, dests=[origin + 1], stream=control.CONTROL_STREAM)

    def _peers(self) -> dict[str, list[str]]:
        return {"uwb": [str(p) for p in self.arq.peers_up()]}

    def _poll(self, now: float) -> None:
        peers = self._peers()
        job = self.pub.poll(now, peers)
        if job is None:
            return
        version = job.grid.version
        base = job.base.version if job.base is not None else 0
        if not self.payloads.uses_base:
            base = 0
        size = self.payloads.size(self.streams[self.index], version, base)
        env = Envelope(
            fleet="swarm", robot=job.grid.robot, version=version, base_version=base, codec=self.payloads.codec,
            width=1, height=1, resolution=0.05, origin=Pose2D(0.0, 0.0, 0.0), payload=b"",
        )  # fmt: skip
        self.pub.encoded(job, env, now, peers)
        self.coded_bytes += size
        if base:
            self.deltas += 1
        else:
            self.keyframes += 1
        dests = self.acks.dests(self.id, self.configured, self.arq.peers_up())
        if not dests:
            self.pub.on_air("uwb", version, now)  # as the daemon's uwb transport: nothing goes out
            return  # no peer to send to: the next version tries again
        data = self._message(self.id, version, base, size)
        msg = self.arq.send(data, now, dests=dests, stream=MAP_STREAM)
        self._own_msgs[msg] = version
        # As the daemon's outbound does with the uwb transport's offer_deadline_s (P1).
        self.pub.hold("uwb", version, now + self.arq.message_deadline_s(len(data)))

    @staticmethod
    def _message(origin: int, version: int, base: int, size: int) -> bytes:
        tag = _TAG.pack(origin, version, base)
        return tag + bytes(max(0, size - len(tag)))

    def _events(self, now: float) -> None:
        for e in self.arq.events():
            if isinstance(e, arq.MessageReceived):
                if e.stream == forwarding.SUMMARY_STREAM:
                    self.summaries_rx += 1
                    if self.fwd is not None:
                        self.fwd.on_summary(e.src, forwarding.unpack_summary(e.data), now)
                elif e.stream == control.CONTROL_STREAM:
                    if self.pub.keyframe_needed(str(e.src)):
                        self._poll(now)
                else:
                    self._maps_from.add(e.src)
                    self._on_map(e.src, e.data, now)
            elif isinstance(e, arq.MessageDelivered):
                v = self._own_msgs.get(e.msg) or self._late.get(e.msg)
                if v is not None:
                    free, _ = self.pub.acked("uwb", str(e.peer), v)
                    if free:
                        self._poll(now)
            elif isinstance(e, arq.MessageFailed):
                v = self._own_msgs.get(e.msg)
                if v is not None and self.pub.failed("uwb", str(e.peer), v, again=not e.final):
                    self._poll(now)
            elif isinstance(e, arq.MessageFlushed):
                v = self._own_msgs.get(e.msg)
                if v is not None and self.pub.on_air("uwb", v, now):
                    self._poll(now)  # as the daemon: the offer's timeout may have passed already
            elif isinstance(e, arq.PeerUp):
                if self.arrival == "offer":
                    reached = any(self.arq.reaches(m, e.peer) for m in self._own_msgs)
                    if not reached and self.pub.arrived("uwb", str(e.peer)):
                        self._poll(now)  # as transport.py: back in range, offered the newest (P6)
                elif (
                    self.arrival == "ask"
                    and e.peer not in self._maps_from
                    and 1 <= e.peer <= len(self.streams)
                ):
                    self._ask_keyframe(e.peer - 1, now)  # the daemon before P6: heard, but no map of it yet
            elif isinstance(e, arq.PeerDown):
                if self.pub.peer_gone("uwb", str(e.peer)):  # as the daemon: not waited for any more
                    self._poll(now)
            elif isinstance(e, arq.MessageClosed):
                v = self._own_msgs.pop(e.msg, None)
                if v is not None and e.outcome == "superseded":
                    self._late[e.msg] = v  # as transport.py: its late COMPLETEs still count
                    while len(self._late) > arq.MAX_LATE:
                        del self._late[next(iter(self._late))]
                if e.msg == self._relay_msg and self.fwd is not None:
                    self._relay_msg = None
                    self.fwd.relay_done()

    def _on_map(self, src: int, data: bytes, now: float) -> None:
        origin_id, version, base = _TAG.unpack_from(data)
        origin = origin_id - 1
        if origin == self.index or not 0 <= origin < len(self.streams):
            return
        if self.fwd is not None and src != origin_id:
            self.fwd.on_overheard(origin_id, version, now)  # another robot forwarded it: do not repeat
        held = self.held.setdefault(origin, [])
        if held and version <= held[-1]:
            if self.fwd is not None and version == held[-1] and not base:
                # a whole map of the version held (asked for on a neighbour's behalf), as the
                # daemon's inbound does: kept to forward to a neighbour the delta cannot serve
                self.fwd.on_held(origin_id, version, base, data)
            return  # old or duplicate
        if base and base not in held:
            self._ask_keyframe(origin, now)
            return
        held.append(version)
        del held[:-KEEP_PEER_VERSIONS]
        self.accepted.append((now, self.index, origin, version))
        if self.fwd is not None:
            self.fwd.on_held(origin_id, version, base, data)  # the bytes as received: still the origin's
        fwd = self.relay.on_accept(self.id, origin_id, version, src, now, self.arq.peers_up())
        if fwd is not None and fwd.dests:
            size = self.payloads.size(self.streams[origin], version, 0)
            self.arq.send(
                self._message(origin_id, version, 0, size), now, dests=list(fwd.dests), stream=origin_id
            )
            self.relayed += 1
