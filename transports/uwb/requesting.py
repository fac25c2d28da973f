"""The uwb transport's keyframe requests: asking peers for whole maps on the control stream, and
heeding their asks.

A request goes out signed by this robot's identity with a fresh nonce, throttled per robot (the
wire format and the throttle are :mod:`transports.uwb.keyframe_requests`'s); one heard is heeded only
when it names this robot, is signed by the robot its link id names, and is fresh. This is a protocol
of its own on its own stream (255): apart from handing it control messages and its link, the rest of
:class:`~transports.uwb.transport.UwbTransport` (maps, poses, the relay, the link's events) has
nothing to do with it, so it lives here.

:class:`RequestSide` is a mixin: :class:`~transports.uwb.transport.UwbTransport` owns the state
declared here.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from mapd.errors import MapdError
from transports import signed_requests
from transports.base import KeyframeNeeded, TransportContext
from transports.uwb import arq
from transports.uwb import keyframe_requests as control
from transports.uwb.link import UwbLink
from transports.uwb.options import UwbOptions

log = logging.getLogger("mapd.uwb")


class RequestSide:
    """Keyframe requests over the control stream, out and in (a mixin:
    :class:`~transports.uwb.transport.UwbTransport` owns the state declared here)."""

    ctx: TransportContext
    opts: UwbOptions
    node_id: int
    control_counters: control.ControlCounters
    _link: UwbLink | None
    _requests: control.KeyframeRequests
    _nonces: signed_requests.NonceClock
    _fresh: signed_requests.Freshness
    _name: Callable[[int], str]
    _dests: Callable[[], list[int]]

    def _ask_keyframe(self, robot: str) -> None:
        link = self._link
        if link is None or link.core is None:
            return
        wanted = self._requests.want(robot, time.monotonic())
        if wanted is None:
            return
        dests = sorted({self.opts.nodes[r] for r in wanted if r in self.opts.nodes} - {self.node_id})
        if not dests:  # a robot we know by no link id: ask every peer, the one that has it answers
            dests = self._dests()
        if not dests:
            return
        try:
            robots = control.names(wanted)
            nonce = self._nonces.next(time.time_ns())
            sig = signed_requests.sign(
                self.ctx.identity,
                control.DOMAIN,
                fleet=self.ctx.fleet,
                asker=self.ctx.robot,
                robots=robots,
                nonce=nonce,
            )
            link.send(
                control.pack_request(robots, nonce=nonce, sig=sig), dests, stream=control.CONTROL_STREAM
            )
        except (MapdError, ValueError) as exc:  # ValueError: too many names for one message
            log.info("uwb: keyframe request for %s not sent: %s", robot, exc)
            return
        self.control_counters.keyframe_requests_tx += 1

    def _on_control(self, e: arq.MessageReceived) -> None:
        asker = self._name(e.src)
        c = self.control_counters
        try:
            req = control.parse_request(e.data)
        except MapdError as exc:
            c.bad_control += 1
            log.info("uwb: bad control message from %s: %s", asker, exc)
            return
        c.keyframe_requests_rx += 1
        if self.ctx.robot not in req.robots:
            return
        # Heeded only when signed by the robot the link id names, and fresh (keyframe_requests).
        try:
            signed_requests.verify(
                self.ctx.roster,
                control.DOMAIN,
                fleet=self.ctx.fleet,
                asker=asker,
                robots=req.robots,
                nonce=req.nonce or 0,
                sig=req.sig,
                what="uwb keyframe request",
            )
        except MapdError as exc:
            c.keyframe_requests_forged += 1
            log.info("uwb: keyframe request not heeded: %s", exc)
            return
        if req.nonce is not None and not self._fresh.fresh(asker, req.nonce):
            c.keyframe_requests_replayed += 1
            return
        self.ctx.emit(KeyframeNeeded("uwb", asker, self.ctx.robot))
