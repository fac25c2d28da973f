"""What arrives over zenoh, from zenoh's threads to the core on the event loop.

The receiving half of :class:`~transports.zenoh.link.ZenohTransport`, as a mixin over the state the
transport owns (declared here; see that module's docstring for the threads and the rules):

* **zenoh threads** copy the key and payload and hand them on, nothing more: updates and query
  replies to the check thread (:class:`~transports.zenoh.checks.CheckQueue`), acks, poses and
  keyframe queries to the loop, at most :data:`MAX_LOOP_BACKLOG` waiting, and liveliness changes
  coalesced per token. Samples of robots the roster does not admit, and oversized poses and acks,
  are refused before they are copied (:class:`IntakeCounters`), as are updates and replies over
  ``max_message_bytes`` (said once per robot, on the loop). Other fleets' fleet tokens are counted
  and said right there (:mod:`transports.zenoh.fleets`), and peers' ``takes`` tokens kept right
  there for our offers (:mod:`transports.zenoh.limits`).
* **the loop thread** feeds each arrival to the sans-I/O :class:`~transports.zenoh.core.ZenohCore`
  and applies its :class:`~transports.zenoh.core_types.Step`: events to the daemon, keyframe
  queries out, and answers to the queries of peers (rationed, on the job thread).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mapd.envelope import Envelope
from mapd.errors import EnvelopeError
from mapd.identity import SIG_LEN
from transports.base import PoseReceived, TransportContext
from transports.zenoh import keys
from transports.zenoh.checks import CheckQueue
from transports.zenoh.core import ZenohCore
from transports.zenoh.core_types import NAME, Step
from transports.zenoh.fleets import OtherFleets
from transports.zenoh.handlers import HandlerSet
from transports.zenoh.jobs import JobQueue
from transports.zenoh.limits import PeerLimits
from transports.zenoh.routers import RouterLink
from transports.zenoh.sending import SendCounters
from transports.zenoh.session import ZenohOptions

# The name these lines have always been logged under (log filters and journal searches use it).
log = logging.getLogger("transports.zenoh.link")

#: Pose messages are about 100 bytes; larger samples on a pose key are dropped before they are read.
MAX_POSE_BYTES = 512
#: An ack is an 8-byte version and, in a signed fleet, a signature (``core.pack_ack``); a larger
#: sample on an ack key is refused before it is read.
MAX_ACK_BYTES = 8 + SIG_LEN
#: Acks, poses and keyframe queries waiting for the event loop at most; more are dropped (counted
#: ``dropped``). Each is checked on the loop (a signature), and anyone on the bus can send them
#: faster than it checks: unbounded, 273,000 waited after 47 s and every timer ran 16 s late.
MAX_LOOP_BACKLOG = 1024


@dataclass
class IntakeCounters:
    """Samples refused on zenoh's threads, unread; :meth:`ZenohTransport.stats` adds these to the core's."""

    #: On an update key that is not a peer's (ours, malformed), or refused by the check queue
    #: (``max_peers`` robots already waiting).
    dropped: int = 0
    #: Updates, replies, poses and liveliness tokens of a robot the roster does not admit.
    unadmitted: int = 0
    #: Acks, poses and queries waiting for the loop (at most :data:`MAX_LOOP_BACKLOG`).
    backlog: int = 0


class ZenohIntake:
    """The receiving side (a mixin: :class:`~transports.zenoh.link.ZenohTransport` owns the state
    declared here)."""

    ctx: TransportContext
    opts: ZenohOptions
    core: ZenohCore
    _loop: asyncio.AbstractEventLoop | None
    _jobs: JobQueue | None
    _checks: CheckQueue[Envelope | EnvelopeError] | None
    _session: Any
    _closing: bool
    _last_keyframe: bytes | None
    _kf_cache: tuple[Envelope, bytes] | None
    _handlers: HandlerSet
    _rx_lock: threading.Lock
    _rx: IntakeCounters
    _tx_lock: threading.Lock
    _tx: SendCounters
    _presence: dict[str, list[bool]]
    _reply_slots: threading.BoundedSemaphore
    _routers: RouterLink
    _fleets: OtherFleets
    _limits: PeerLimits

    # -- zenoh threads: copy and hand over, nothing else -------------------------------------------

    def _post(self, fn: Callable[..., None], *args: Any) -> bool:
        loop = self._loop
        if self._closing or loop is None:
            return False
        try:
            loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:
            return False  # the loop has closed under us: we are shutting down
        return True

    def _cb_update(self, sample: Any) -> None:
        robot = self.core.update_robot(str(sample.key_expr))
        if robot is None:
            with self._rx_lock:
                self._rx.dropped += 1
            return
        self._check_later(robot, sample, self._on_update_checked)

    def _check_later(
        self, robot: str, sample: Any, then: Callable[[str, bytes, Envelope | EnvelopeError], None]
    ) -> None:
        """Verify ``sample`` on the check thread, then hand the result to ``then`` on the loop."""
        checks = self._checks
        if self._closing or checks is None:
            return
        if not self.core.admits(robot):
            # It could only fail verification: refuse it before copying up to max_message_bytes.
            with self._rx_lock:
                self._rx.unadmitted += 1
            return
        size = len(sample.payload)
        if size > self.ctx.max_message_bytes:
            # It could only fail unpack's size check: refuse it uncopied, and let the loop say whose
            # it was once (a peer with larger limits: every one of its maps comes to this).
            self._post_bounded(self._on_oversize, robot, size)
            return
        data = sample.payload.to_bytes()

        def checked(data: bytes, result: Envelope | EnvelopeError) -> None:
            self._post(then, robot, data, result)

        # Latest wins past the robot's budget: neither memory nor the loop's work grows with what a
        # peer (or anyone on the bus) sends.
        if not checks.submit(robot, data, checked):
            with self._rx_lock:
                self._rx.dropped += 1

    def _query_ended(self, robot: str) -> None:
        # Through the check queue, behind the query's replies still waiting there, so the core
        # sees them before it hears the query has ended (it may then query again).
        def job() -> None:
            self._post(self._on_query_done, robot)

        checks = self._checks
        if checks is None or not checks.after(job):
            job()

    def _post_bounded(self, fn: Callable[..., None], *args: Any) -> bool:
        """:meth:`_post`, unless :data:`MAX_LOOP_BACKLOG` such calls already wait (then counted)."""
        with self._rx_lock:
            if self._rx.backlog >= MAX_LOOP_BACKLOG:
                self._rx.dropped += 1
                return False
            self._rx.backlog += 1

        def run(*a: Any) -> None:
            with self._rx_lock:
                self._rx.backlog -= 1
            fn(*a)

        if self._post(run, *args):
            return True
        with self._rx_lock:
            self._rx.backlog -= 1
        return False

    def _cb_pose(self, sample: Any) -> None:
        if len(sample.payload) > MAX_POSE_BYTES:  # a pose is ~100 bytes: drop anything larger unread
            return
        key = str(sample.key_expr)
        # Its signature could only fail; and each made-up name would take one of the daemon's
        # event queue's peer slots, which real robots' maps need.
        if not self._unadmitted(keys.parse_pose(self.ctx.fleet, key)):
            self._post_bounded(self._on_pose, key, sample.payload.to_bytes())

    def _unadmitted(self, robot: str | None) -> bool:
        """Whether ``robot`` is one the roster does not admit (then counted ``unadmitted``)."""
        if robot is None or self.core.admits(robot):
            return False
        with self._rx_lock:
            self._rx.unadmitted += 1
        return True

    def _cb_ack(self, sample: Any) -> None:
        if len(sample.payload) > MAX_ACK_BYTES:
            # zenoh takes samples up to max_message_bytes: copying one (8 MiB) and queueing it on the
            # loop only for the core to refuse its length would cost a million times the ack's size.
            self._post_bounded(self._ack_oversize)
            return
        self._post_bounded(self._on_ack, str(sample.key_expr), sample.payload.to_bytes())

    def _cb_presence(self, sample: Any) -> None:
        """Token changes wait for the loop coalesced per token, never dropped for a robot held.

        A token's appearing or vanishing is state, not a message: losing one would leave a robot
        counted up or down for good. So they are not bounded by dropping, as acks are, but by
        keeping per token only its last two changes (a vanish then appear is a restart, which the
        core must see), for at most :data:`MAX_LOOP_BACKLOG` tokens, and only for robots the roster
        admits: made-up names, which anyone on the bus can declare, are refused here.
        """
        import zenoh

        key = str(sample.key_expr)
        if self._unadmitted(keys.parse_presence(self.ctx.fleet, key)):
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._rx_lock:
            waiting = self._presence.get(key)
            if waiting is None and len(self._presence) >= MAX_LOOP_BACKLOG:
                self._rx.dropped += 1
                return
            first = not self._presence
            changes = self._presence.setdefault(key, [])
            if not changes or changes[-1] != alive:
                changes.append(alive)
                del changes[:-2]
        if first:
            self._post(self._drain_presence)

    def _drain_presence(self) -> None:
        with self._rx_lock:
            pending, self._presence = self._presence, {}
        for key, changes in pending.items():
            for alive in changes:
                self._on_presence(key, alive)

    def _cb_fleet(self, sample: Any) -> None:
        """A robot's fleet token appeared or vanished: one of another fleet is said once per fleet.

        Said here, on zenoh's thread: :class:`~transports.zenoh.fleets.OtherFleets` bounds what it
        keeps and says, so a flood of made-up tokens costs a lookup each and no loop work.
        """
        import zenoh

        line = self._fleets.seen(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
        if line is not None:
            log.warning("%s", line)

    def _cb_takes(self, sample: Any) -> None:
        """A peer's ``takes`` token appeared or vanished: what it takes, kept for our offers.

        Fed right here, on zenoh's thread: :class:`~transports.zenoh.limits.PeerLimits` keeps a
        bounded few limits per admitted robot, so a flood of made-up tokens costs a parse each and
        no loop work; a malformed one (a value out of bounds) is counted ``dropped``.
        """
        import zenoh

        parsed = keys.parse_takes(self.ctx.fleet, str(sample.key_expr))
        if parsed is None:
            with self._rx_lock:
                self._rx.dropped += 1
            return
        if self._unadmitted(parsed[0]):
            return
        self._limits.announced(parsed[0], parsed[1], sample.kind == zenoh.SampleKind.PUT)

    def _cb_transport(self, event: Any) -> None:
        """A transport to another zenoh node opened or closed: routers' go to the loop, one post each.

        Not bounded by dropping, as acks are: a router's coming or going is state, and each follows
        a whole zenoh handshake or close, far slower than the loop takes the post."""
        import zenoh

        transport = event.transport
        if transport.whatami != zenoh.WhatAmI.ROUTER:
            return
        self._post(self._on_router, str(transport.zid), event.kind == zenoh.SampleKind.PUT)

    def _cb_query(self, query: Any) -> None:
        if not self._post_bounded(self._on_query, query):
            query.drop()  # finalize it, so the asker is not left waiting for its timeout

    def _cb_reply(self, robot: str, reply: Any) -> None:
        sample = reply.ok
        if sample is not None:
            self._check_later(robot, sample, self._on_reply_checked)

    # -- loop thread -------------------------------------------------------------------------------

    def _apply(self, step: Step) -> None:
        for line in step.warnings:
            log.warning("%s", line)
        for event in step.events:
            self.ctx.emit(event)
        for robot in step.queries:
            self._send_query(robot)

    def _on_update_checked(self, robot: str, data: bytes, checked: Envelope | EnvelopeError) -> None:
        self._apply(self.core.on_update_checked(robot, data, checked, time.monotonic()))

    def _on_reply_checked(self, robot: str, data: bytes, checked: Envelope | EnvelopeError) -> None:
        self._apply(self.core.on_reply_checked(robot, data, checked, time.monotonic()))

    def _on_oversize(self, robot: str, size: int) -> None:
        self._apply(self.core.oversize(robot, size))

    def _on_query_done(self, robot: str) -> None:
        self._apply(self.core.query_done(robot, time.monotonic()))

    def _on_pose(self, key_expr: str, data: bytes) -> None:
        robot = keys.parse_pose(self.ctx.fleet, key_expr)
        if robot is not None and robot != self.ctx.robot:
            self.ctx.emit(PoseReceived(NAME, robot, data))

    def _on_ack(self, key_expr: str, data: bytes) -> None:
        self._apply(self.core.on_ack(key_expr, data, time.monotonic()))

    def _ack_oversize(self) -> None:
        self.core.counters.dropped += 1  # counted as the core counts an ack of the wrong length

    def _on_presence(self, key_expr: str, alive: bool) -> None:
        self._apply(self.core.on_presence(key_expr, alive, time.monotonic()))

    def _on_router(self, zid: str, up: bool) -> None:
        # One line when the last router goes and one when a router is back, whatever zenoh's tries
        # in between (see transports.zenoh.routers).
        now = time.monotonic()
        said = self._routers.opened(zid, now) if up else self._routers.closed(zid, now)
        if said is not None:
            log.log(*said)

    def _on_query(self, query: Any) -> None:
        params = query.parameters
        self._apply(self.core.on_query(params.get("from"), params.get("n"), params.get("sig")))
        # Anyone may query: answers are rationed so that a flood of queries neither crowds our map
        # updates out of the job queue nor fills the uplink with keyframes.
        slot = self._reply_slots.acquire(blocking=False)
        if not self.core.may_reply(time.monotonic(), slot_free=slot):
            if slot:
                self._reply_slots.release()
            query.drop()
            return
        reply_key = keys.latest_key(self.ctx.fleet, self.ctx.robot)

        def job() -> None:
            try:
                # On the job thread: the daemon may have to encode a keyframe first (seconds for a
                # large map), which must never stall the event loop.
                payload = self._keyframe_bytes()
                if payload is not None:
                    query.reply(reply_key, payload)
                    with self._tx_lock:
                        self._tx.bytes_tx += len(payload)
                        self._tx.replies_tx += 1
                        self._tx.reply_bytes_tx += len(payload)
            finally:
                query.drop()  # finalizes the query so the asker is not left waiting
                self._reply_slots.release()

        assert self._jobs is not None
        if not self._jobs.submit(("reply", id(query)), job):
            self._reply_slots.release()
            query.drop()

    def _send_query(self, robot: str) -> None:
        params = self.core.query_parameters(robot, time.time_ns())
        selector = f"{keys.latest_key(self.ctx.fleet, robot)}?{params}"
        timeout = self.opts.query_timeout_s

        def job() -> None:
            if self._session is None:
                return
            handler = self._handlers.callback(
                lambda reply: self._cb_reply(robot, reply), lambda: self._query_ended(robot)
            )
            self._session.get(selector, handler, timeout=timeout)

        if self._jobs is None or not self._jobs.submit(("get", robot), job):
            self.core.query_done(robot, time.monotonic())  # not sent: do not wait for it

    def _keyframe_bytes(self) -> bytes | None:
        env = self.ctx.latest_keyframe()
        if env is None:
            return self._last_keyframe
        # The asker will ack this version: tell the core it was offered before the reply goes out
        # (the loop runs posted calls in order, so this lands before any ack of it), or the ack is
        # taken for one of a version never sent and dropped, and the publisher waits out its timeout.
        self._post(self.core.offered, env, time.monotonic())
        if self._kf_cache is None or self._kf_cache[0] is not env:
            self._kf_cache = (env, env.pack())
        return self._kf_cache[1]

    # -- check thread ------------------------------------------------------------------------------

    def _check_failed(self, exc: BaseException) -> None:
        # core.check returns every EnvelopeError, so this is a bug, not a peer's doing: say so.
        log.error("zenoh: checking a received sample failed: %r", exc)
