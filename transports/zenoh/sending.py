"""What goes out over zenoh: own and relayed updates, poses and acks, put on the job thread.

The sending half of :class:`~transports.zenoh.link.ZenohTransport`, as a mixin over the state the
transport owns (declared here). Each send is a job on the :class:`~transports.zenoh.jobs.JobQueue`
under a key that makes it latest-wins: ``("update", robot)``, ``("pose",)``, ``("ack", robot)``, so
a newer offer, pose or ack replaces one still waiting and no stale version is ever queued. What
was sent or refused is counted in :class:`SendCounters`. An own map larger than a peer announced
it takes is said, and ``Failed(again=False)`` for that peer (:mod:`transports.zenoh.limits`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

from mapd.envelope import Envelope
from transports.base import Failed, PoseThrottle, TransportContext
from transports.zenoh import keys
from transports.zenoh.core import ZenohCore
from transports.zenoh.core_types import NAME
from transports.zenoh.jobs import JobQueue
from transports.zenoh.limits import PeerLimits
from transports.zenoh.session import zenoh_message

# The name these lines have always been logged under (log filters and journal searches use it).
log = logging.getLogger("transports.zenoh.link")


@dataclass
class SendCounters:
    """What the outbox thread sent or refused; :meth:`ZenohTransport.stats` shows these names."""

    #: Every byte this robot put or answered with: updates, poses, acks and keyframe replies (the
    #: three after updates also by themselves below; zenoh's own framing is not counted).
    bytes_tx: int = 0
    updates_tx: int = 0
    acks_tx: int = 0
    ack_bytes_tx: int = 0
    pose_bytes_tx: int = 0
    #: Keyframes sent as answers to late joiners' queries.
    replies_tx: int = 0
    reply_bytes_tx: int = 0
    #: zenoh calls that raised (a put, a reply, a query).
    errors: int = 0
    #: Own envelopes over limits.max_message_bytes, never sent.
    oversize: int = 0
    poses_tx: int = 0


class ZenohSending:
    """The sending side (a mixin: :class:`~transports.zenoh.link.ZenohTransport` owns the state
    declared here)."""

    ctx: TransportContext
    core: ZenohCore
    _jobs: JobQueue | None
    _session: Any
    _publisher: Any
    _closing: bool
    _last_keyframe: bytes | None
    _poses: PoseThrottle
    _tx_lock: threading.Lock
    _tx: SendCounters
    #: Robots whose maps over ``max_message_bytes`` were said (until one of theirs fits again).
    _oversize_said: set[str]
    #: What each peer announced it takes (:mod:`transports.zenoh.limits`).
    _limits: PeerLimits

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
            # Said once while that robot's maps stay over (one a map period, all day, said nothing
            # new); counted in ``oversize`` every time.
            if envelope.robot not in self._oversize_said:
                self._oversize_said.add(envelope.robot)
                log.warning(
                    "zenoh: not sending %s v%d, nor its next maps while they are over the limit: %d "
                    "bytes is over limits.max_message_bytes (%d): raise it on every robot (each "
                    "refuses larger maps), or make the maps smaller",
                    envelope.robot,
                    envelope.version,
                    len(data),
                    self.ctx.max_message_bytes,
                )
            return
        self._oversize_said.discard(envelope.robot)
        if envelope.robot == self.ctx.robot:
            self._over_peers(envelope, len(data))
            if envelope.is_keyframe:
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

    def _over_peers(self, envelope: Envelope, size: int) -> None:
        """Our ``envelope`` of ``size`` bytes goes out: say the peers that announced a smaller limit
        (once each while our maps stay over it), and tell the publisher not to wait for their acks.

        It is published all the same: other peers take it. ``Failed`` goes only for peers the core
        lists (those the publisher waits for).
        """
        verdict = self._limits.offered(size, set(self.core.peers()))
        for line in verdict.warnings:
            log.warning("%s", line)
        for over in verdict.failed:
            self.ctx.emit(
                Failed(NAME, over.peer, envelope.robot, envelope.version, over.reason(), again=False)
            )

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
                self._tx.pose_bytes_tx += len(data)
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
                    self._tx.bytes_tx += len(payload)  # not counted before: the wire figure lacked acks
                    self._tx.ack_bytes_tx += len(payload)

        self._jobs.submit(("ack", robot), job)
