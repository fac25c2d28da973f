"""The asyncio side of the UWB relay: :class:`~transports.uwb.forwarding.ForwardingCore` on a link.

:class:`UwbTransport` owns one :class:`RelayDriver` when ``[transports.uwb] relay`` is on and the
fleet is signed (in an ``allow_unsigned`` fleet a receiver takes a map over UWB only from the robot
that made it, so a relayed one would be refused: no point sending it). The driver is thin: it feeds
the core the summaries heard and the maps the daemon accepted (through :meth:`held`, with the
envelope bytes as received), and one task wakes at the core's deadline or the next summary to send
this robot's summary (an unreliable background message, like a pose) and start the relay the core
picks. Every decision is the core's; this module only moves bytes and clocks.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

from mapd.errors import MapdError, TransportError
from transports.uwb import forwarding
from transports.uwb.link import failure_reason

log = logging.getLogger("mapd.uwb")

#: Sends ``data`` to ``dests`` on ``stream`` (the link's send); returns the message id.
SendFn = Callable[..., int]


class RelayDriver:
    """Summaries out and in, relays out, for link id ``me`` on a started link."""

    def __init__(
        self,
        me: int,
        *,
        summary_period_s: float,
        relay_period_s: float,
        stream_of: Callable[[int], int],
        share_bps: float | None = None,
        max_relay_s: float | None = None,
    ) -> None:
        self.core = forwarding.ForwardingCore.for_summaries(
            me,
            summary_period_s=summary_period_s,
            relay_period_s=relay_period_s,
            share_bps=share_bps,
            max_relay_s=max_relay_s,
        )
        self.summary_period_s = summary_period_s
        self._stream_of = stream_of  # origin link id -> the map stream its relays ride on
        self._relay_msg: int | None = None
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.summaries_tx = 0
        self.summaries_rx = 0
        self.bad_summaries = 0
        self.relays_tx = 0
        self.relays_failed = 0
        self.overheard_rx = 0

    # --- inputs from the transport ----------------------------------------------------------------
    def held(self, origin: int, version: int, base: int, data: bytes) -> None:
        """The daemon accepted ``origin``'s map (``data``: the envelope bytes, still origin-signed)."""
        self.core.on_held(origin, version, base, data)
        self._wake.set()

    def restored(self, origin: int, version: int) -> None:
        """The daemon holds ``origin``'s ``version`` from its state directory: summaries list it."""
        self.core.on_restored(origin, version)

    def overheard(self, origin: int, version: int, now: float) -> None:
        """Another robot forwarded ``origin``'s ``version`` (the daemon saw it come from a third)."""
        self.core.on_overheard(origin, version, now)
        self.overheard_rx += 1

    def summary(self, src: int, data: bytes, now: float) -> forwarding.Summary | None:
        """A summary arrived on :data:`~transports.uwb.forwarding.SUMMARY_STREAM`: returns it
        parsed (what ``src`` holds also says whether its daemon took our maps), None if malformed."""
        try:
            s = forwarding.unpack_summary(data)
        except forwarding.SummaryError as exc:
            self.bad_summaries += 1
            log.info("uwb: bad summary from link id %d: %s", src, exc)
            return None
        self.summaries_rx += 1
        self.core.on_summary(src, s, now)
        self._wake.set()
        return s

    def closed(self, msg: int, outcome: str = "delivered") -> None:
        """A message left the send queue: if it was the relay in flight, another may start."""
        if msg == self._relay_msg:
            if outcome == "failed":  # a receiver did not take it by its deadline (or refused it)
                self.relays_failed += 1
            self._relay_msg = None
            self.core.relay_done()
            self._wake.set()

    # --- the task ---------------------------------------------------------------------------------
    def start(
        self,
        send: SendFn,
        peers: Callable[[], list[int]],
        dests: Callable[[], list[int]],
        ask: Callable[[int], None] | None = None,
    ) -> None:
        """Run the task: ``peers()`` are the link ids heard lately, ``dests()`` whom summaries go
        to, ``ask(origin)`` asks a robot for a whole map (for a neighbour the chain cannot serve)."""
        self._task = asyncio.get_running_loop().create_task(self._run(send, peers, dests, ask))
        self._task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            exc = task.exception()
            log.error("uwb: relay stopped: %s", exc, exc_info=None if isinstance(exc, MapdError) else exc)

    async def stopped(self) -> None:
        """Wait while the relay runs; return once closed, raise :class:`TransportError` (one line)
        if its task ended any other way."""
        task = self._task
        if task is None:
            raise TransportError("uwb: relay not started")
        await asyncio.wait([task])
        if task.cancelled():
            return
        exc = task.exception()
        why = "its task returned" if exc is None else failure_reason(exc)
        raise TransportError(f"uwb: relay stopped: {why}")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            # a task that died has said why (logged, and to stopped()): closing is not the place
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task

    async def _run(
        self,
        send: SendFn,
        peers: Callable[[], list[int]],
        dests: Callable[[], list[int]],
        ask: Callable[[int], None] | None,
    ) -> None:
        loop = asyncio.get_running_loop()
        next_summary = loop.time()
        while True:
            self._wake.clear()
            now = loop.time()
            if now >= next_summary:
                next_summary = now + self.summary_period_s
                self._send_summary(send, peers(), dests())
            r = self.core.next_forward(now)
            if r is not None:
                try:
                    self._relay_msg = send(
                        r.data, list(r.dests), stream=self._stream_of(r.origin), deadline_s=r.deadline_s
                    )
                    self.relays_tx += 1
                except (MapdError, ValueError) as exc:
                    log.info("uwb: relay of link id %d v%d not sent: %s", r.origin, r.version, exc)
                    self.core.relay_done()
            if ask is not None:
                for origin in self.core.keyframes_wanted(now, set(peers())):
                    ask(origin)
            deadline = self.core.next_deadline()
            wake_at = next_summary if deadline is None else min(next_summary, deadline)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), max(0.0, wake_at - loop.time()))

    def _send_summary(self, send: SendFn, heard: list[int], dests: list[int]) -> None:
        if not dests:
            return
        data = forwarding.pack_summary(forwarding.Summary(self.core.holds(), frozenset(heard)))
        try:
            # Once, unacknowledged, behind every map chunk (as poses): a lost one is replaced by the next.
            send(
                data,
                dests,
                stream=forwarding.SUMMARY_STREAM,
                deadline_s=2 * self.summary_period_s,
                background=True,
                reliable=False,
            )
            self.summaries_tx += 1
        except (MapdError, ValueError) as exc:
            log.info("uwb: summary not sent: %s", exc)

    def stats(self) -> dict[str, int]:
        return {
            "relay_summaries_tx": self.summaries_tx,
            "relay_summaries_rx": self.summaries_rx,
            "relay_bad_summaries": self.bad_summaries,
            "relays_tx": self.relays_tx,
            "relays_failed": self.relays_failed,
            "relays_overheard": self.overheard_rx,
            "relay_keyframes_asked": self.core.keyframes_asked,
        }
