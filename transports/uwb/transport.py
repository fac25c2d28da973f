"""The daemon's ``uwb`` transport: envelopes in, :mod:`transports.base` events out, over one
:class:`~transports.uwb.link.UwbLink`.

It gives each robot's maps a stream of their own (latest wins per robot), sends to the peers the
options name (or those heard lately), turns the core's events into the daemon's (``Delivered``,
``OnAir``, ``PeerUp``, ``Arrived`` ...), asks for whole maps on the control stream and heeds the
asks heard there (``requesting.py``), carries poses in the gaps maps leave, and drives the multi-hop
relay (``relaying.py``) in signed fleets, whose summaries also say which peers' daemons refuse the
maps their radios ack (``refused.py``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
import zlib
from collections import OrderedDict
from pathlib import Path
from typing import Any

from mapd.envelope import Envelope
from mapd.errors import LimitError, MapdError, TransportError
from transports import signed_requests
from transports.base import (
    Arrived,
    Delivered,
    Failed,
    OnAir,
    PeerDown,
    PeerRestarted,
    PeerUp,
    PoseReceived,
    PoseThrottle,
    Received,
    Transport,
    TransportContext,
    TransportOptions,
)
from transports.uwb import arq, forwarding, wire
from transports.uwb import keyframe_requests as control
from transports.uwb.link import POSE_STREAM, UwbLink
from transports.uwb.options import MAX_MESSAGE, UwbOptions
from transports.uwb.refused import Cleared, RefusalCore, Refused, words
from transports.uwb.relaying import RelayDriver
from transports.uwb.requesting import RequestSide
from transports.uwb.signing import CounterStore, ReplayStore

log = logging.getLogger("mapd.uwb")
#: A peer's features are said at most this often (seconds), so HELLOs that keep changing what they
#: announce (forged) cannot fill the log; ``mapd status`` (``older_mapd``) always shows the last.
FEATURES_SAY_S = 300.0


class UwbTransport(RequestSide, Transport):
    """The daemon's ``uwb`` transport: maps over a UWB serial radio, latest wins per robot."""

    name = "uwb"
    Options = UwbOptions
    paced = True  # each robot has a share of one 12.5 kb/s channel: maps take many seconds to go out

    def __init__(self, options: TransportOptions | None, ctx: TransportContext) -> None:
        super().__init__(options, ctx)
        opts = self.options
        assert isinstance(opts, UwbOptions)
        self.opts = opts
        self.node_id, self.peer_ids = opts.link_ids(ctx.robot)
        self._names = {i: name for name, i in opts.nodes.items()}
        self._streams: dict[str, int] = {}
        self._msgs: dict[int, tuple[str, int]] = {}
        self._late: OrderedDict[int, tuple[str, int]] = OrderedDict()  # superseded offers (arq R5)
        self._features_said: dict[int, float] = {}  # link id -> when its features were last said
        self._link: UwbLink | None = None
        self._requests = control.KeyframeRequests(opts.keyframe_request_s)
        self._nonces = signed_requests.NonceClock()
        self._fresh = signed_requests.Freshness()
        self._poses = PoseThrottle(opts.pose_period_s)
        self._said_long = False  # a map longer on the air than deadline_s was warned of
        self._offered: tuple[str, int, float] | None = None  # the last map sent: robot, version, deadline
        self.control_counters = control.ControlCounters()
        # Multi-hop relay: only in signed fleets, where a relayed map proves its robot by signature.
        self._relay: RelayDriver | None = None
        # Whose daemon refuses the maps its radio acks: told by relay summaries, so only with them.
        self._refusals: RefusalCore | None = None
        if opts.relay and not ctx.roster.allow_unsigned:
            self._refusals = RefusalCore(opts.summary_period_s)
            self._relay = RelayDriver(
                self.node_id,
                summary_period_s=opts.summary_period_s,
                relay_period_s=opts.relay_period_s,
                stream_of=lambda origin: self._stream(self._name(origin)),
                # TDMA gives each robot an equal turn: its share is the rate over the slots
                share_bps=opts.link_rate_bps / (opts.slots or max(1, len(opts.nodes))),
                max_relay_s=opts.deadline_s,
            )

    def _name(self, link_id: int) -> str:
        return self._names.get(link_id, f"uwb-{link_id}")

    def _stream(self, robot: str) -> int:
        if robot not in self._streams:
            n = len(self._streams)
            # Stream 255 carries control messages (keyframe requests), 254 poses, 253 relay summaries,
            # maps 0..252.
            top = forwarding.SUMMARY_STREAM
            self._streams[robot] = n if n < top else zlib.crc32(robot.encode()) % top
        return self._streams[robot]

    def _config(self, loop: asyncio.AbstractEventLoop) -> arq.ArqConfig:
        o = self.opts
        ids = sorted({*self.opts.nodes.values(), self.node_id})
        return arq.ArqConfig(
            node_id=self.node_id,
            max_frame=o.max_frame,
            rate_bps=float(o.link_rate_bps),
            # the wire describes messages up to 16 MiB; limits.max_message_bytes may allow more (zenoh)
            max_message_bytes=o.max_message_bytes or min(self.ctx.max_message_bytes, MAX_MESSAGE),
            window=o.window,
            acks=o.acks,
            fec=o.fec,
            deadline_s=o.deadline_s,
            beacon_s=o.beacon_s,
            peer_timeout_s=o.peer_timeout_s,
            mac=o.mac,
            slot_s=o.slot_length_ms / 1000,
            slots=o.slots or len(ids),
            slot_index=o.slot_index if o.slot_index is not None else ids.index(self.node_id),
            lend=o.lend,
            guard_s=o.guard_ms / 1000,
            clock_offset=time.time() - loop.time(),
            radio_time=self._radio_time,
            rx_slack_s=o.rx_latency_s,
            check_counter_clock=True,
            sense_s=o.sense_ms / 1000,
            backoff_min_s=o.backoff_min_ms / 1000,
            backoff_max_s=o.backoff_max_ms / 1000,
            key=self.ctx.link_key,
        )

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        state = self.ctx.state_dir
        store = CounterStore(Path(state) / f"uwb-{self.node_id}.counter" if state is not None else None)
        replay = ReplayStore(Path(state) / f"uwb-{self.node_id}.replay" if state is not None else None)
        self._link = UwbLink(
            self._config(loop),
            self.opts.port,
            baud=self.opts.baud,
            on_event=self._on_event,
            counter_store=store,
            replay_store=replay,
            reopen_s=self.opts.reopen_s,
            wait_for_port=True,  # a radio named late at boot must not stop the daemon's other links
        )
        await self._link.start()
        if self._relay is not None:
            link = self._link
            self._relay.start(
                link.send,
                lambda: link.core.peers_up() if link.core else [],
                self._dests,
                ask=lambda origin: self._ask_keyframe(self._name(origin)),
            )

    async def watch(self) -> None:
        # The serial loop and the relay task: the first to stop for a fault ends the watch.
        assert self._link is not None, "watch() before start()"
        waits = [asyncio.ensure_future(self._link.stopped())]
        if self._relay is not None:
            waits.append(asyncio.ensure_future(self._relay.stopped()))
        try:
            while waits:
                done, pending = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
                for w in done:
                    w.result()  # raises the TransportError of one that stopped for a fault
                waits = list(pending)
        finally:
            for w in waits:
                w.cancel()

    async def close(self) -> None:
        if self._relay is not None:
            await self._relay.close()
        if self._link is not None:
            await self._link.close()

    def _dests(self) -> list[int]:
        link = self._link
        if link is None or link.core is None:
            return []
        if self.opts.send_to == "heard":
            up = set(link.core.peers_up())
            return [p for p in self.peer_ids if p in up]
        return self.peer_ids or link.core.peers_up()

    def held(self, envelope: Envelope, data: bytes) -> None:
        """The daemon accepted ``envelope`` (``data``: its bytes as received): a map to relay."""
        origin = self.opts.nodes.get(envelope.robot)
        if self._relay is not None and origin is not None and envelope.sig:
            self._relay.held(origin, envelope.version, envelope.base_version, data)

    def restored(self, robot: str, version: int) -> None:
        """The daemon holds ``robot``'s ``version`` from its state directory: our summaries say so."""
        origin = self.opts.nodes.get(robot)
        if self._relay is not None and origin is not None:
            self._relay.restored(origin, version)

    def relayed(self, envelope: Envelope) -> None:
        """Another robot forwarded ``envelope``: do not forward the same version for a while."""
        origin = self.opts.nodes.get(envelope.robot)
        if self._relay is not None and origin is not None:
            self._relay.overheard(origin, envelope.version, time.monotonic())

    def forget(self, robot: str) -> None:
        """A revoked robot's maps are no longer relayed (its peers refuse them now too)."""
        origin = self.opts.nodes.get(robot)
        if self._relay is not None and origin is not None:
            self._relay.core.forget(origin)

    def offer(self, envelope: Envelope) -> None:
        link = self._link
        if link is None or link.core is None:
            raise TransportError("uwb: offer() before start()")
        self._offered = None
        dests = self._dests()
        if not dests:
            log.debug("uwb: no peer to send %s v%d to", envelope.robot, envelope.version)
            # nothing goes out, so nothing is left to wait for: the publisher's plain timeout applies
            self.ctx.emit(OnAir("uwb", envelope.robot, envelope.version))
            return
        data = envelope.pack()
        try:
            msg = link.send(data, dests, stream=self._stream(envelope.robot))
        except LimitError as exc:
            for d in dests:
                self.ctx.emit(
                    Failed("uwb", self._name(d), envelope.robot, envelope.version, str(exc), again=False)
                )
            self.ctx.emit(OnAir("uwb", envelope.robot, envelope.version))
            return
        self._msgs[msg] = (envelope.robot, envelope.version)
        if self._refusals is not None and envelope.robot == self.ctx.robot:
            self._refusals.offered(envelope.version)
        self._offered = (envelope.robot, envelope.version, link.core.message_deadline_s(len(data)))
        if not self._said_long:
            self._say_if_long(link.core, envelope, len(data))

    def offer_deadline_s(self, envelope: Envelope) -> float | None:
        """How long after :meth:`offer` the link may still be sending ``envelope`` before it gives
        it up: its deadline for a map of that size (arq R6); None if it sent nothing of it. The
        daemon's publisher holds the offer that long if that is longer than its own hold (P1), so
        a map longer on the air than that is not superseded half sent by the next version."""
        last = self._offered
        if last is None or last[:2] != (envelope.robot, envelope.version):
            return None
        return last[2]

    def _say_if_long(self, core: arq.ArqEndpoint, envelope: Envelope, nbytes: int) -> None:
        """Warn, once a run, of a map longer on the air at this robot's share of the link than
        ``deadline_s``: the link gives it longer (arq R6), but its peers get it that late."""
        airtime = core.airtime_s(nbytes)
        if airtime <= self.opts.deadline_s:
            return
        self._said_long = True
        share = core.cfg.rate_bps / max(1, core.cfg.slots)
        log.warning(
            "uwb: map v%d (%d B) takes up to %.0f s on the air at this robot's equal share of the "
            "link (%.0f b/s), more than deadline_s = %g s: it is given %.0f s, and peers get maps "
            "this large late (a smaller map, or codec pooled, sends fewer bytes)",
            envelope.seq or envelope.version,
            nbytes,
            airtime,
            share,
            self.opts.deadline_s,
            core.message_deadline_s(nbytes),
        )

    def send_pose(self, data: bytes, now: float) -> bool:
        """Broadcast this robot's pose on the pose stream, behind every map chunk (latest wins)."""
        link = self._link
        if link is None or link.core is None:
            return False
        dests = self._dests()
        if not dests or not self._poses.due(now):
            return False
        try:
            # Sent once, unacknowledged (the next pose replaces a lost one), and only in the gaps
            # maps leave; superseded by the next pose if maps keep the channel busy until then.
            link.send(
                data,
                dests,
                stream=POSE_STREAM,
                deadline_s=2 * self.opts.pose_period_s,
                background=True,
                reliable=False,
            )
        except (MapdError, ValueError) as exc:
            log.info("uwb: pose not sent: %s", exc)
            return False
        return True

    async def request_keyframe(self, robot: str) -> None:
        """Ask ``robot`` (over this link) for a whole map: a control message, throttled per robot."""
        self._ask_keyframe(robot)

    def peers(self) -> list[str]:
        if self._link is None or self._link.core is None:
            return []
        return [self._name(i) for i in self._link.core.peers_up()]

    @property
    def _radio_time(self) -> bool:
        """Whether this link keeps its turns on the radio clock (R19): TDMA with ``clock = "radio"``."""
        return self.opts.mac == "tdma" and self.opts.clock == "radio"

    def stats(self) -> dict[str, Any]:
        out = self._link.stats() if self._link is not None else {}
        out["node_id"] = self.node_id
        out.update(dataclasses.asdict(self.control_counters))
        if self._relay is not None:
            out.update(self._relay.stats())
        if self._refusals is not None:
            out.update(self._refusals.stats(self._name))
        # robot -> what its older mapd lacks, by name (mapd status: under the link)
        older = out.pop("older_peers", {})
        out["older_mapd"] = {
            self._name(n): wire.feature_words(f & ~wire.F_TIME) for n, f in older.items() if f & ~wire.F_TIME
        }
        # the robots whose turns are not on the radio clock this one keeps (older, or clock = "system")
        out["own_clock"] = sorted(self._name(n) for n, f in older.items() if f & wire.F_TIME)
        if isinstance(radio := out.get("radio_clock"), dict):  # link ids by robot name
            for key in ("root", "parent"):
                if isinstance(radio.get(key), int):
                    radio[key] = self._name(radio[key])
        return out

    def _on_event(self, e: arq.Event) -> None:
        emit = self.ctx.emit
        if isinstance(e, arq.MessageReceived):
            if e.stream == control.CONTROL_STREAM:
                self._on_control(e)
            elif e.stream == POSE_STREAM:
                emit(PoseReceived("uwb", self._name(e.src), e.data))
            elif e.stream == forwarding.SUMMARY_STREAM:
                if self._relay is not None:
                    now = time.monotonic()
                    s = self._relay.summary(e.src, e.data, now)
                    if s is not None and self._refusals is not None and e.src in self._names:
                        self._say(self._refusals.summary(e.src, s.holds.get(self.node_id, 0), now))
            else:
                emit(Received("uwb", self._name(e.src), e.data))
        elif isinstance(e, arq.MessageDelivered):
            meta = self._msgs.get(e.msg) or self._late.get(e.msg)
            if meta is not None:
                emit(Delivered("uwb", self._name(e.peer), *meta))
                if self._refusals is not None and meta[0] == self.ctx.robot and e.peer in self._names:
                    self._refusals.acked(e.peer, meta[1], time.monotonic())  # own maps only
        elif isinstance(e, arq.MessageFailed):
            if e.msg in self._msgs:
                robot, version = self._msgs[e.msg]
                emit(Failed("uwb", self._name(e.peer), robot, version, e.reason, again=not e.final))
        elif isinstance(e, arq.MessageFlushed):
            meta = self._msgs.get(e.msg)
            if meta is not None:
                emit(OnAir("uwb", *meta))
        elif isinstance(e, arq.MessageClosed):
            meta = self._msgs.pop(e.msg, None)
            if meta is not None and e.outcome == "superseded":
                self._late[e.msg] = meta  # its late COMPLETEs still say who holds that version
                while len(self._late) > arq.MAX_LATE:
                    self._late.popitem(last=False)
            if self._relay is not None:
                self._relay.closed(e.msg, e.outcome)
        elif isinstance(e, arq.PeerUp):
            emit(PeerUp("uwb", self._name(e.peer)))
            core = self._link.core if self._link is not None else None
            known = e.peer in self._names  # a robot of the fleet, not any link id heard (a bound)
            if known and core is not None and not any(core.reaches(m, e.peer) for m in self._msgs):
                # A robot that comes into range (a late joiner, or one back from out of range) gets
                # the newest map now (P6), not with the next version, which for a map that no longer
                # changes never comes; unless the map on its way already goes to it.
                emit(Arrived("uwb", self._name(e.peer)))
        elif isinstance(e, arq.PeerDown):
            emit(PeerDown("uwb", self._name(e.peer)))
        elif isinstance(e, arq.PeerRestarted):
            emit(PeerRestarted("uwb", self._name(e.peer)))
            if self._refusals is not None:
                self._refusals.restarted(e.peer)
        elif isinstance(e, arq.PeerFeatures):
            now, last = time.monotonic(), self._features_said.get(e.peer)
            if last is not None and now - last < FEATURES_SAY_S:
                return  # (HELLOs that keep changing their word: forged, say; once in a while)
            self._features_said[e.peer] = now
            lacks = wire.own_features(self._radio_time) & ~e.features
            if lacks == wire.F_TIME:  # an older mapd, or a config that differs: the HELLO cannot tell
                log.warning(
                    "uwb: %s counts its TDMA turns on its own clock, not the fleet's radio clock (its HELLO "
                    'says so: a mapd from before radio time, or clock = "system" in its [transports.uwb]); '
                    "its frames go out of turn as far as its wall clock is off: set one clock on every robot",
                    self._name(e.peer),
                )
            elif lacks:  # a rolling upgrade: nothing to set, but the channel carries more meanwhile
                frames, what = lacks & ~wire.F_TIME, []
                which = "none" if frames == lacks else f"no {wire.feature_words(frames)}"
                what.append(
                    f"{which} go to it until it is upgraded, and maps it receives too are sent without them"
                )
                if lacks & wire.F_TIME:  # TIME frames are broadcast: it drops them, and its turns are its own
                    what.append("it counts its TDMA turns on its own clock, not the fleet's radio clock")
                log.info(
                    "uwb: %s runs a mapd from before %s (its HELLO says so): %s; nothing needs setting",
                    self._name(e.peer),
                    wire.feature_words(lacks),
                    "; ".join(what),
                )
            else:
                log.info("uwb: %s understands all of this link's frames now", self._name(e.peer))

    def _say(self, change: Refused | Cleared | None) -> None:
        """Say that a peer's daemon refuses our maps (once while it lasts), or takes them again."""
        if change is not None:
            (log.warning if isinstance(change, Refused) else log.info)(
                "%s", words(change, self._name(change.peer))
            )
