"""Transport ``zenoh``: map updates over eclipse-zenoh (pub/sub, liveliness, a keyframe queryable).

Where robots have Wi-Fi, and in every multi-robot test on one machine, maps move over zenoh: peer
to peer with no server, through zenoh routers as a fleet grows, and on the same bus as ROS 2's
rmw_zenoh. The key expressions are in :mod:`transports.zenoh.keys`; what happens to each arrival
(verification, gaps, keyframe queries, presence, acks) is decided by the sans-I/O core in
:mod:`transports.zenoh.core`. This module is the adapter between zenoh's threads and asyncio:

* **Threads.** zenoh's callbacks run on zenoh's threads; they copy the key and payload and hand
  them on, nothing more. Updates and query replies go to the *check* thread
  (:class:`~transports.zenoh.checks.CheckQueue`), which unpacks and verifies them
  (:meth:`ZenohCore.check <transports.zenoh.core.ZenohCore.check>`: msgpack and Ed25519 over up to
  ``max_message_bytes``) and posts the result to the loop, where the core applies it; everything
  else goes to the loop with ``call_soon_threadsafe``. The check queue runs in arrival order, so an
  older update is never applied after a newer one, and holds per robot at most
  ``max_message_bytes`` of waiting samples (latest wins: a newer sample that does not fit pushes
  out the oldest, counted in ``superseded``), for at most ``max_peers`` robots. Samples on a key that
  is no peer's update key, or of a robot the roster does not admit (``unadmitted``), are refused
  before they are copied.
  Every blocking zenoh call (open, declare, put, get, reply, undeclare, close) runs on one daemon
  thread, the :class:`~transports.zenoh.jobs.JobQueue`.
* **Latest wins.** ``offer`` packs the envelope and puts it in the outbox under the key
  ``("update", robot)``: while a put is in flight, a newer offer replaces the one still waiting, so
  no stale version is ever queued. Acks are latest-wins per robot too.
* **Keyframes.** The queryable ``mapd/<fleet>/<robot>/latest`` answers with
  ``ctx.latest_keyframe()`` (the daemon's latest keyframe), or else the last keyframe offered here.
  A query with ``?from=<peer>`` also emits ``KeyframeNeeded`` so the daemon can send a fresh one,
  when the roster admits ``<peer>``, ``<peer>`` signed the query and it is no replay (any asker
  still gets the reply, while answers stay within their ration; see :mod:`transports.zenoh.queries`
  and :meth:`ZenohCore.may_reply <transports.zenoh.core.ZenohCore.may_reply>`).
* **Acks and Delivered.** zenoh has no per-message ack, so mapd adds one: after the daemon has
  decoded ``robot``'s ``version`` it calls :meth:`ZenohTransport.ack`, which publishes on
  ``mapd/<fleet>/<us>/ack/<robot>`` (8-byte version, signed with the acking robot's Ed25519 key). The robot
  that sent it hears the ack and emits ``Delivered(peer=us, robot=it, version)``, which makes that
  version a delta base for us. Acks are only accepted for versions that robot actually offered.
* **Shutdown.** ``close`` stops callbacks reaching the loop, drops waiting sends, then (on the
  outbox thread, bounded by ``close_timeout_s``) undeclares the liveliness token first, so peers
  see us leave at once, then subscribers, queryable and publisher, closes the session, and waits
  for zenoh's callback threads to end (one still ending at interpreter exit aborts the process;
  see :mod:`transports.zenoh.handlers`). ``close`` never takes much longer than ``close_timeout_s``;
  the outbox thread is a daemon thread, so even a zenoh call stuck past it cannot hold the exit.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
import time
from collections.abc import Awaitable, Callable, Hashable
from dataclasses import asdict, dataclass
from typing import Any

from mapd.envelope import Envelope
from mapd.errors import EnvelopeError, TransportError, UnreachableError
from mapd.identity import SIG_LEN
from mapd.ros2.zenoh_config import open_when_reachable, open_zenoh
from transports.base import PoseReceived, PoseThrottle, Transport, TransportContext, TransportOptions
from transports.zenoh import keys
from transports.zenoh.checks import CheckQueue
from transports.zenoh.core import MAX_REPLIES_PENDING, NAME, Step, ZenohCore
from transports.zenoh.handlers import HandlerSet
from transports.zenoh.jobs import JobQueue
from transports.zenoh.session import ZenohOptions, build_config, zenoh_message

log = logging.getLogger(__name__)
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
class SendCounters:
    """What the outbox thread sent or refused; :meth:`ZenohTransport.stats` shows these names."""

    bytes_tx: int = 0
    updates_tx: int = 0
    acks_tx: int = 0
    #: zenoh calls that raised (a put, a reply, a query).
    errors: int = 0
    #: Own envelopes over limits.max_message_bytes, never sent.
    oversize: int = 0
    poses_tx: int = 0


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


class ZenohTransport(Transport):
    """The ``zenoh`` transport plugin (options: :class:`~transports.zenoh.session.ZenohOptions`)."""

    name = NAME
    Options = ZenohOptions

    def __init__(self, options: TransportOptions | None, ctx: TransportContext) -> None:
        super().__init__(options, ctx)
        opts = self.options
        if not isinstance(opts, ZenohOptions):
            raise TypeError(f"zenoh: options must be ZenohOptions, not {type(opts).__name__}")
        self.opts: ZenohOptions = opts
        if not keys.valid_name(ctx.robot) or not keys.valid_name(ctx.fleet):
            raise TransportError(f"zenoh: robot '{ctx.robot}' or fleet '{ctx.fleet}' is not a valid id")
        self.core = ZenohCore(
            robot=ctx.robot,
            fleet=ctx.fleet,
            identity=ctx.identity,
            roster=ctx.roster,
            max_message_bytes=ctx.max_message_bytes,
            query_timeout_s=opts.query_timeout_s,
            base_window=opts.base_window,
            max_peers=opts.max_peers,
        )
        self._loop: asyncio.AbstractEventLoop | None = None
        self._jobs: JobQueue | None = None
        # Where updates and replies are unpacked and verified, off the loop (see the module docstring).
        self._checks: CheckQueue[Envelope | EnvelopeError] | None = None
        self._session: Any = None
        self._publisher: Any = None
        self._entities: list[Any] = []  # undeclared in reverse order at close
        self._token: Any = None
        self._closing = False
        self._closed = False
        self._last_keyframe: bytes | None = None
        self._kf_cache: tuple[Envelope, bytes] | None = None
        self._handlers = HandlerSet()
        # Written on the outbox thread and read on the loop's (stats), hence the lock.
        self._tx_lock = threading.Lock()
        self._tx = SendCounters()
        # Written on zenoh's threads and read on the loop's (stats), hence the lock.
        self._rx_lock = threading.Lock()
        self._rx = IntakeCounters()
        #: Token key -> its changes not yet seen on the loop (see :meth:`_cb_presence`).
        self._presence: dict[str, list[bool]] = {}
        self._poses = PoseThrottle(self.opts.pose_period_s)
        # Answers to keyframe queries waiting on the job thread: taken on the loop, given back by the
        # job thread once the answer is out.
        self._reply_slots = threading.BoundedSemaphore(MAX_REPLIES_PENDING)
        #: The session config while no router could be reached (``watch`` tries it again), and why.
        self._retry_conf: Any = None
        self.unreached: str | None = None

    # -- lifecycle ---------------------------------------------------------------------------------

    async def start(self) -> None:
        """Open the zenoh session and declare everything; :class:`TransportError` on failure."""
        if self._jobs is not None:
            raise TransportError("zenoh: transport already started")
        conf = build_config(self.opts, self.ctx.max_message_bytes)
        self._loop = asyncio.get_running_loop()
        self._jobs = JobQueue(
            f"mapd-zenoh-{self.ctx.robot}", max_pending=self.opts.max_pending, on_error=self._send_failed
        )
        # At most one full-size message's worth waiting per robot, for max_peers robots: memory
        # held for checking is bounded by about max_peers large samples, whatever peers send.
        self._checks = CheckQueue(
            f"mapd-zenoh-check-{self.ctx.robot}",
            self.core.check,
            budget=self.ctx.max_message_bytes,
            max_robots=self.opts.max_peers,
            on_error=self._check_failed,
        )
        try:
            await asyncio.wrap_future(self._jobs.call(lambda: self._open(conf)))
        except BaseException as exc:
            if isinstance(exc, UnreachableError):
                # A robot that boots out of its router's reach (or before it): the daemon and its
                # other links run, and watch() keeps trying, rather than stop them all with it.
                self._retry_conf, self.unreached = conf, zenoh_message(exc)
                log.warning("%s; trying again (the other links run meanwhile)", self.unreached)
                return
            # Cancelled mid-open, the session may still come up: close whatever did, then end.
            outbox, self._jobs = self._jobs, None
            self._checks.stop()
            outbox.call(lambda: self._shutdown(time.monotonic() + self.opts.close_timeout_s))
            outbox.finish()
            if isinstance(exc, Exception) and not isinstance(exc, TransportError):
                raise TransportError(f"zenoh: cannot open session: {zenoh_message(exc)}") from None
            raise

    def _open(self, conf: Any) -> None:
        import zenoh

        fleet, me, cb = self.ctx.fleet, self.ctx.robot, self._handlers.callback
        session = open_zenoh(conf, "zenoh: cannot open session")
        if self._closing:
            # close() gave up waiting for this open (a retry's, which can take seconds) and may
            # have stopped the outbox that would have closed it: close it here, or its threads
            # outlive the interpreter and abort the process at exit
            session.close()
            return
        try:
            remote = zenoh.Locality.REMOTE
            cc = (
                zenoh.CongestionControl.BLOCK
                if self.opts.congestion == "block"
                else zenoh.CongestionControl.DROP
            )
            ents = self._entities
            ents.append(
                session.declare_subscriber(
                    keys.all_updates(fleet), cb(self._cb_update), allowed_origin=remote
                )
            )
            ents.append(
                session.declare_subscriber(keys.acks_for(fleet, me), cb(self._cb_ack), allowed_origin=remote)
            )
            ents.append(
                session.declare_subscriber(keys.all_poses(fleet), cb(self._cb_pose), allowed_origin=remote)
            )
            ents.append(
                session.liveliness().declare_subscriber(
                    keys.all_presence(fleet), cb(self._cb_presence), history=True
                )
            )
            ents.append(
                session.declare_queryable(keys.latest_key(fleet, me), cb(self._cb_query), complete=True)
            )
            self._publisher = session.declare_publisher(keys.update_key(fleet, me), congestion_control=cc)
            ents.append(self._publisher)
            # Last, so a peer that sees us can already query us.
            self._token = session.liveliness().declare_token(keys.presence_key(fleet, me))
        except BaseException:
            self._entities.clear()
            self._publisher = None
            session.close()
            raise
        self._session = session

    async def watch(self) -> None:
        """While no router could be reached, try to open the session again (1 s, doubling to 30 s;
        on the job thread, so a close waits for a try under way); :class:`TransportError` if a try
        fails for another cause. Then wait while the link works."""
        conf, jobs = self._retry_conf, self._jobs
        if conf is not None and jobs is not None and not self._closing:
            since = time.monotonic()

            def on_jobs(fn: Callable[[], None]) -> Awaitable[None]:
                return asyncio.wrap_future(jobs.call(fn))

            try:
                await open_when_reachable(functools.partial(self._open, conf), run=on_jobs)
            except asyncio.CancelledError:
                task = asyncio.current_task()
                if not self._closing or (task is not None and task.cancelling()):
                    raise  # (the close stopping the job thread cancels only the try's future)
            except TransportError:
                raise  # a router that answered and refused us, or a config fault: its line
            except Exception as exc:
                raise TransportError(f"zenoh: cannot open session: {zenoh_message(exc)}") from None
            if self._session is not None:  # (not when a close came first: _open closed it)
                self._retry_conf = self.unreached = None
                log.info("zenoh: session open, %.0f s after the first try", time.monotonic() - since)
        await asyncio.Event().wait()

    async def close(self) -> None:
        """Undeclare and close, in order, within ``close_timeout_s``; safe to call twice."""
        if self._closed:
            return
        self._closed = self._closing = True
        if self._checks is not None:
            # Drop waiting checks; one running ends on its own, and its result is no longer posted.
            self._checks.stop()
        outbox = self._jobs
        if outbox is None:
            return
        outbox.discard_pending()
        deadline = time.monotonic() + self.opts.close_timeout_s
        fut = outbox.call(lambda: self._shutdown(deadline))
        try:
            await asyncio.wait_for(asyncio.wrap_future(fut), self.opts.close_timeout_s)
        except TimeoutError:
            log.warning(
                "zenoh: session did not close within %.1f s; leaving it to the exit",
                self.opts.close_timeout_s,
            )
        except asyncio.CancelledError:
            task = asyncio.current_task()
            if task is not None and task.cancelling():
                outbox.stop(0.0)
                raise
            # Otherwise the outbox had stopped already and cancelled the job: nothing is open.
        except Exception as exc:
            log.warning("zenoh: error while closing: %s", zenoh_message(exc))
        outbox.stop(0.2)

    def _shutdown(self, deadline: float) -> None:
        for ent in [self._token, *reversed(self._entities)]:
            if ent is None:
                continue
            try:
                ent.undeclare()
            except Exception as exc:
                log.debug("zenoh: undeclare failed: %s", exc)
        self._token = self._publisher = None
        self._entities.clear()
        if self._session is not None:
            self._session.close()
            self._session = None
        # zenoh's callback threads end after the close; one still ending at interpreter exit
        # would abort the process (see transports.zenoh.handlers).
        if not self._handlers.wait(deadline):
            log.warning("zenoh: %d callback threads still running after close", self._handlers.live)

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

    def _cb_query(self, query: Any) -> None:
        if not self._post_bounded(self._on_query, query):
            query.drop()  # finalize it, so the asker is not left waiting for its timeout

    def _cb_reply(self, robot: str, reply: Any) -> None:
        sample = reply.ok
        if sample is not None:
            self._check_later(robot, sample, self._on_reply_checked)

    # -- loop thread -------------------------------------------------------------------------------

    def _apply(self, step: Step) -> None:
        for event in step.events:
            self.ctx.emit(event)
        for robot in step.queries:
            self._send_query(robot)

    def _on_update_checked(self, robot: str, data: bytes, checked: Envelope | EnvelopeError) -> None:
        self._apply(self.core.on_update_checked(robot, data, checked, time.monotonic()))

    def _on_reply_checked(self, robot: str, data: bytes, checked: Envelope | EnvelopeError) -> None:
        self._apply(self.core.on_reply_checked(robot, data, checked, time.monotonic()))

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

    # -- outbox thread -----------------------------------------------------------------------------

    def _send_failed(self, key: Hashable, exc: BaseException) -> None:
        with self._tx_lock:
            self._tx.errors += 1
        log.warning("zenoh: %s failed: %s", key[0] if isinstance(key, tuple) else key, zenoh_message(exc))

    # -- the Transport API -------------------------------------------------------------------------

    def offer(self, envelope: Envelope) -> None:
        """Publish ``envelope`` on its robot's update key; replaces a still-unsent older one."""
        if self._closing or self._jobs is None:
            return
        data = envelope.pack()
        if len(data) > self.ctx.max_message_bytes:
            with self._tx_lock:
                self._tx.oversize += 1
            log.warning(
                "zenoh: not sending %s v%d: %d bytes is over limits.max_message_bytes",
                envelope.robot,
                envelope.version,
                len(data),
            )
            return
        if envelope.robot == self.ctx.robot and envelope.is_keyframe:
            self._last_keyframe = data
        self.core.offered(envelope, time.monotonic())
        robot = envelope.robot
        key = keys.update_key(self.ctx.fleet, robot)

        def job() -> None:
            if self._session is None:
                return
            if robot == self.ctx.robot and self._publisher is not None:
                self._publisher.put(data)
            else:
                self._session.put(key, data)
            with self._tx_lock:
                self._tx.bytes_tx += len(data)
                self._tx.updates_tx += 1

        self._jobs.submit(("update", robot), job)

    def send_pose(self, data: bytes, now: float) -> bool:
        """Put this robot's pose message (best effort: zenoh may drop it under congestion)."""
        if self._closing or self._jobs is None or not self._poses.due(now):
            return False
        key = keys.pose_key(self.ctx.fleet, self.ctx.robot)

        def job() -> None:
            if self._session is None:
                return
            import zenoh

            self._session.put(key, data, congestion_control=zenoh.CongestionControl.DROP)
            with self._tx_lock:
                self._tx.bytes_tx += len(data)
                self._tx.poses_tx += 1

        self._jobs.submit(("pose",), job)  # latest wins: a pose not yet put is replaced
        return True

    def ack(self, robot: str, version: int) -> None:
        """Tell ``robot`` that its ``version`` has been decoded here (call after a successful decode).

        The robot's transport turns this into ``Delivered`` for us, so it may code deltas against
        ``version``. Latest wins: a newer ack of the same robot replaces one not yet sent. A
        ``version`` outside 1..2**63-1 is a caller bug (``ValueError``).
        """
        if self._closing or self._jobs is None or not keys.valid_name(robot) or robot == self.ctx.robot:
            return
        key, payload = self.core.ack(robot, version)

        def job() -> None:
            if self._session is not None:
                self._session.put(key, payload)
                with self._tx_lock:
                    self._tx.acks_tx += 1

        self._jobs.submit(("ack", robot), job)

    async def request_keyframe(self, robot: str) -> None:
        """Forget what we hold of ``robot`` and query its latest keyframe (the daemon cannot decode)."""
        if self._closing or self._jobs is None:
            return
        self._apply(self.core.request_keyframe(robot, time.monotonic()))

    def peers(self) -> list[str]:
        """Robots whose liveliness token we see."""
        return self.core.peers()

    def stats(self) -> dict[str, Any]:
        """Flat counters: bytes/updates each way, gaps, keyframe queries, bad signatures, drops, peers.

        ``superseded``: updates and replies pushed out, unchecked, by newer ones of the same robot
        (past its byte budget while waiting to be checked); ``unadmitted``: those of robots off the roster, refused unread (and their
        poses and liveliness tokens), and keyframe queries from such robots (answered, but no
        ``KeyframeNeeded``); ``dropped`` also counts acks, poses and queries past the loop's backlog.
        """
        with self._tx_lock:
            tx = asdict(self._tx)
        with self._rx_lock:
            rx = self._rx.dropped, self._rx.unadmitted
        out: dict[str, Any] = {**tx, **self.core.stats(), "replaced": 0, "superseded": 0}
        # False while no router could be reached (and tries go on): a FAULTS line in mapd status
        out["session_open"] = self._retry_conf is None
        out["dropped"] += rx[0]
        out["unadmitted"] += rx[1]
        if self._checks is not None:
            out["superseded"] = self._checks.superseded
        if self._jobs is not None:
            out["replaced"] = self._jobs.replaced
            out["dropped"] += self._jobs.rejected
        return out
