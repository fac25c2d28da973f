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
  and :meth:`ZenohCore.may_reply <transports.zenoh.answers.AnswerSide.may_reply>`).
* **Acks and Delivered.** zenoh has no per-message ack, so mapd adds one: after the daemon has
  decoded ``robot``'s ``version`` it calls :meth:`ZenohTransport.ack`, which publishes on
  ``mapd/<fleet>/<us>/ack/<robot>`` (8-byte version, signed with the acking robot's Ed25519 key). The robot
  that sent it hears the ack and emits ``Delivered(peer=us, robot=it, version)``, which makes that
  version a delta base for us. Acks are only accepted for versions that robot actually offered.
* **Routers.** zenoh reconnects a client to its router by itself, without a word, while the robots
  reached through it are gone (their tokens vanish: ``PeerDown``). A transport events listener
  follows the session's router transports (:mod:`transports.zenoh.routers`): the last router going
  is said once (WARNING), a router there again once (INFO), however many tries zenoh makes in
  between (a loss within a minute of the last one said goes to DEBUG), and ``router_connected``
  in :meth:`ZenohTransport.stats` is False meanwhile. The robots that come back query each other's
  latest keyframe as late joiners do, which also makes each send its next map whole.
* **Config drift said.** Robots whose ``robot.fleet`` differ see none of each other's keys; each
  link also declares ``mapd/@fleets/<fleet>/<robot>`` and watches those tokens only, so a robot of
  another fleet on the network is said once per fleet (WARNING) and shown in ``other_fleets``
  (:mod:`transports.zenoh.fleets`). A peer's update or reply over ``max_message_bytes`` is refused
  unread and said once per robot with the fix (``oversize_rx``, ``oversize_from``). zenoh itself
  drops, unseen, a message over the cap it is given (``max_message_bytes`` plus 64 KiB; see
  :mod:`transports.zenoh.session`) between hosts, so only maps up to that reach this line. So the
  sender says it too: each link declares ``mapd/<fleet>/<robot>/takes/<max_message_bytes>`` and
  watches its fleet's, and an offer of ours larger than a peer takes is said once per peer
  (WARNING, with the fix) while our maps stay over, shown in ``too_big_for`` (a fault in ``mapd
  status``), and emits ``Failed(again=False)`` for that peer, so the publisher does not wait for its
  ack (:mod:`transports.zenoh.limits`; the tokens are unsigned: a forged one makes a false line
  and a skipped wait, no more). A peer that announces nothing (an older robot) is taken as before.
* **Shutdown.** ``close`` stops callbacks reaching the loop, drops waiting sends, then (on the
  outbox thread, bounded by ``close_timeout_s``) undeclares the liveliness token first, so peers
  see us leave at once, then subscribers, queryable and publisher, closes the session, and waits
  for zenoh's callback threads to end (one still ending at interpreter exit aborts the process;
  see :mod:`transports.zenoh.handlers`). ``close`` never takes much longer than ``close_timeout_s``;
  the outbox thread is a daemon thread, so even a zenoh call stuck past it cannot hold the exit.

The zenoh-thread callbacks and the loop-thread handlers of what arrives are in
:mod:`transports.zenoh.intake`, the sends (offer, pose, ack) in :mod:`transports.zenoh.sending`,
both mixins over the state this class owns; here are the lifecycle and the counters together.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import asdict
from typing import Any

from mapd.envelope import Envelope
from mapd.errors import EnvelopeError, TransportError, UnreachableError
from mapd.ros2.zenoh_config import open_when_reachable, open_zenoh
from transports.base import PoseThrottle, Transport, TransportContext, TransportOptions
from transports.zenoh import keys
from transports.zenoh.answers import MAX_REPLIES_PENDING
from transports.zenoh.checks import CheckQueue
from transports.zenoh.core import ZenohCore
from transports.zenoh.core_types import NAME
from transports.zenoh.fleets import OtherFleets
from transports.zenoh.handlers import HandlerSet
from transports.zenoh.intake import (
    MAX_ACK_BYTES,
    MAX_LOOP_BACKLOG,
    MAX_POSE_BYTES,
    IntakeCounters,
    ZenohIntake,
)
from transports.zenoh.jobs import JobQueue
from transports.zenoh.limits import PeerLimits
from transports.zenoh.routers import RouterLink
from transports.zenoh.sending import SendCounters, ZenohSending
from transports.zenoh.session import ZenohOptions, build_config, zenoh_message

log = logging.getLogger(__name__)

# Importable from here as before this module was split (tests and tools use these names).
__all__ = [
    "MAX_ACK_BYTES",
    "MAX_LOOP_BACKLOG",
    "MAX_POSE_BYTES",
    "IntakeCounters",
    "SendCounters",
    "ZenohTransport",
]


class ZenohTransport(ZenohIntake, ZenohSending, Transport):
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
        self._oversize_said: set[str] = set()
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
        #: The routers the session is connected to (zenoh's transport events; loop thread only).
        self._routers = RouterLink()
        #: Robots of other fleets on this zenoh network (their fleet tokens; thread-safe).
        self._fleets = OtherFleets(ctx.fleet, ctx.robot)
        #: What each peer takes (its ``takes`` token), for offers over it (thread-safe).
        self._limits = PeerLimits(ctx.robot, opts.max_peers)

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
            # First, so the router the session has just connected to is seen (history) before it
            # can go. Without it (a zenoh older than the listener), router losses go unsaid.
            listen = getattr(session.info, "declare_transport_events_listener", None)
            if listen is not None:
                ents.append(listen(cb(self._cb_transport), history=True))
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
            # Fleet tokens of every fleet, never their maps: a robot of another fleet is said once
            # (transports.zenoh.fleets). Unsigned, as they carry no authority: nothing acts on them.
            ents.append(
                session.liveliness().declare_subscriber(
                    keys.all_fleet_presence(), cb(self._cb_fleet), history=True
                )
            )
            # What each peer takes (older robots announce nothing: they are taken as before).
            ents.append(
                session.liveliness().declare_subscriber(
                    keys.all_takes(fleet), cb(self._cb_takes), history=True
                )
            )
            ents.append(
                session.declare_queryable(keys.latest_key(fleet, me), cb(self._cb_query), complete=True)
            )
            self._publisher = session.declare_publisher(keys.update_key(fleet, me), congestion_control=cc)
            ents.append(self._publisher)
            # Before the presence token, so a peer that sees us knows what we take.
            self._announce(session, ents)
            # Last, so a peer that sees us can already query us.
            self._token = session.liveliness().declare_token(keys.presence_key(fleet, me))
            # Which fleet we are of, for robots of every fleet to see (undeclared right after the
            # token above at close: entities go in reverse).
            ents.append(session.liveliness().declare_token(keys.fleet_presence_key(fleet, me)))
        except BaseException:
            self._entities.clear()
            self._publisher = None
            session.close()
            raise
        self._session = session

    def _announce(self, session: Any, ents: list[Any]) -> None:
        """Declare what this robot takes (``limits.max_message_bytes``, at most ``MAX_TAKES``)."""
        nbytes = min(self.ctx.max_message_bytes, keys.MAX_TAKES)
        if nbytes < keys.MIN_TAKES:
            return  # below what the config allows (a tool's context): announce nothing, as before
        key = keys.takes_key(self.ctx.fleet, self.ctx.robot, nbytes)
        ents.append(session.liveliness().declare_token(key))

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

    # -- the Transport API (offer, send_pose and ack are in ZenohSending) ----------------------------

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
        ``session_open``: False while no router could be reached at start (tries go on);
        ``router_connected``: False while the session has lost its router(s) and zenoh reconnects,
        None where no router was ever connected (a fleet of peers); ``router_losses``: how many
        times it lost them. ``oversize_rx``: peers' updates and replies over ``max_message_bytes``
        (refused unread), ``oversize_from``: robot -> the size of its largest; ``other_fleets``:
        fleet -> robots of other fleets seen on this network now, ``other_fleet_tokens``: how many
        such tokens appeared (both bounded: :mod:`transports.zenoh.fleets`); ``too_big_for``: peer ->
        size and limit, for peers whose announced limit our last map was over, ``too_big_peers``:
        how many (a fault: :mod:`transports.zenoh.limits`).
        """
        with self._tx_lock:
            tx = asdict(self._tx)
        with self._rx_lock:
            rx = self._rx.dropped, self._rx.unadmitted
        out: dict[str, Any] = {**tx, **self.core.stats(), "replaced": 0, "superseded": 0}
        # False while no router could be reached (and tries go on): a FAULTS line in mapd status
        out["session_open"] = self._retry_conf is None
        # False while the session has lost its router(s) and zenoh reconnects; None in a fleet
        # that never had a router (peers only)
        out["router_connected"] = self._routers.connected
        out["router_losses"] = self._routers.losses
        out["dropped"] += rx[0]
        out["unadmitted"] += rx[1]
        # Robots of other fleets on this network: no fault (fleets may share it on purpose), but
        # the one thing that tells why a robot configured with another robot.fleet is never seen.
        out.update(self._fleets.stats())
        # Peers that refuse our maps for their size (they announced their limit): a fault
        out.update(self._limits.stats())
        if self._checks is not None:
            out["superseded"] = self._checks.superseded
        if self._jobs is not None:
            out["replaced"] = self._jobs.replaced
            out["dropped"] += self._jobs.rejected
        return out
