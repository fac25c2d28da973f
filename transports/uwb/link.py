"""The asyncio adapter: a serial port (pyserial-asyncio) driving the sans-I/O core in ``arq.py``.

It is thin on purpose. One task loops: feed what the port read, fire the core's timer, persist the
signing counter when the core asks, write the frames the core hands out one at a time (waiting for
each to leave the transport's buffer, so nothing queues behind the pacing), hand events on, and sleep
until the core's next deadline or new input. A port that vanishes (a USB radio unplugged) is reopened
every ``reopen_s``; meanwhile the core sees an outage and resumes where the receiver left off.
Here are the link's life (start, stop, a failure said in one line) and its loop; the port, the
signing state kept on disk and the wall clock each have a mixin of their own (``link_port.py``,
``link_signing.py``, ``link_clock.py``).

:class:`UwbLink` carries raw byte messages (``mapd link`` uses it);
:class:`~transports.uwb.transport.UwbTransport`, the daemon's ``uwb`` transport, drives one.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from mapd import wallclock
from mapd.errors import MapdError, TransportError
from transports.uwb import arq
from transports.uwb.link_clock import CLOCK_CHECK_S, ClockSide
from transports.uwb.link_port import PortSide
from transports.uwb.link_signing import COUNTER_RETRY_S, SigningSide
from transports.uwb.pacing import ByteWindow
from transports.uwb.signing import (
    MAX_AHEAD_S,
    CounterStore,
    ReplayStore,
    bound_marks,
    clock_floor,
    counter_bound,
)

#: The stream robot poses travel on (255 is control, 253 relay summaries; maps use 0..252).
POSE_STREAM = 254

log = logging.getLogger("mapd.uwb")
T = TypeVar("T")


def failure_reason(exc: BaseException) -> str:
    """Why a task stopped, on one line: a typed fault's own words, a bug's type and message."""
    text = " ".join(str(exc).split())
    if isinstance(exc, MapdError) and text:
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class UwbLink(PortSide, SigningSide, ClockSide):
    """A serial port driving one :class:`~transports.uwb.arq.ArqEndpoint`; raw byte messages (the
    port's half is in :class:`~transports.uwb.link_port.PortSide`, the signing state kept on disk
    in :class:`~transports.uwb.link_signing.SigningSide`, following the wall clock in
    :class:`~transports.uwb.link_clock.ClockSide`)."""

    def __init__(
        self,
        config: arq.ArqConfig,
        port: str,
        *,
        baud: int = 115200,
        on_event: Callable[[arq.Event], None] | None = None,
        counter_store: CounterStore | None = None,
        replay_store: ReplayStore | None = None,
        reopen_s: float = 1.0,
        session: int | None = None,
        wall_clock: Callable[[], float] = time.time,
        time_service: Callable[[], bool | None] | None = None,
        wait_for_port: bool = False,
    ) -> None:
        self.port = port
        #: A port not there at start is opened once it is (the daemon), rather than an error (a
        #: one-shot command such as ``mapd link send``, where a typo must not look like a wait).
        self.wait_for_port = wait_for_port
        self._wall = wall_clock  # the clock TDMA slots are counted on (a test steps its own)
        # whether a time service keeps the wall clock (the kernel's answer, asked when read)
        self._time_service = time_service or (lambda: wallclock.synchronized())
        self._source_at = -float("inf")
        self.baud = baud
        self.reopen_s = reopen_s
        self._on_event = on_event or (lambda e: None)
        self._store = counter_store or CounterStore(None)
        self._replay = replay_store or ReplayStore(None)
        self._replay_saved: dict[int, int] = {}
        self._replay_save_at = 0.0
        #: Times the replay marks could not be saved (a full disk): said once, retried.
        self.replay_save_errors = 0
        self._cfg = config
        self._session = (
            session if session is not None else int.from_bytes(os.urandom(3), "little")
        )  # 24-bit on the wire
        self.core: arq.ArqEndpoint | None = None
        self._proto = None  # typed where PortSide declares it
        #: False until the port first opened (it may not be there yet at start)
        self._ever_open = False
        self._reopen_error = None
        self._task: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self._closing = False
        self._reopen_at = 0.0
        self._writes = ByteWindow(1.0)
        self.write_peak_bps = 0.0
        self.reconnects = 0
        self.started_at = 0.0
        self.first_rx_at: float | None = None
        self.write_stalls = 0
        self._stall_logged = False
        #: Times the signing counter could not be saved (a full or read-only disk): the core signs
        #: on within the block saved before, then goes quiet until a save goes through.
        self.counter_save_errors = 0
        #: Times the wall clock stepped (NTP) while the link ran; TDMA slots followed each step.
        self.clock_steps = 0
        #: The wall clock's offset from the loop's at the last read, and when (loop time): a step is
        #: told from a slew by how fast the offset moved since.
        self._clock_read: tuple[float, float] | None = None
        self._counter_fault = ""
        self._counter_retry_at = 0.0
        self._replay_fault = False  # the last save of the replay marks failed
        #: The signing counter began from the wall clock, none being saved (see _follow_clock).
        self._counter_from_clock = False

    async def start(self) -> None:
        """Open the port and start the loop; :class:`TransportError` with one line when it cannot
        (with ``wait_for_port``, only when it is there: one not there yet is opened when it is)."""
        if self._cfg.key is not None:
            wall = self._wall()
            stored = await asyncio.to_thread(self._store.load)
            start = max(stored, clock_floor(wall))
            self._counter_from_clock = stored == 0  # none saved: a new or lost state
            if stored > counter_bound(wall):
                # Never lowered (a restart must not reuse a counter): the clock was set ahead while
                # this node signed, and its peers refuse its frames until the clock catches up.
                log.warning(
                    "uwb %s: the signing counter saved is %.0f s ahead of the wall clock (was the "
                    "clock set ahead?); peers refuse this node's frames until it is within %.0f s",
                    self.port,
                    (stored - clock_floor(wall)) / 100_000,
                    MAX_AHEAD_S,
                )
            self._replay_saved = await asyncio.to_thread(self._replay.load, self._cfg.key)
            marks = bound_marks(self._replay_saved, wall)
            lowered = sorted(src for src, mark in marks.items() if mark != self._replay_saved[src])
            if lowered:
                log.warning(
                    "uwb %s: replay marks of link id %s lay more than %.0f s ahead of the wall clock "
                    "(a forged counter, or a clock set back since); lowered to that",
                    self.port,
                    ", ".join(map(str, lowered)),
                    MAX_AHEAD_S,
                )
            self._cfg = dataclasses.replace(self._cfg, counter_start=start, replay_marks=marks)
        self.core = arq.ArqEndpoint(self._cfg, session=self._session, seed=self._session)
        if self._cfg.mac == "tdma" and not self._cfg.radio_time and self._time_service() is False:
            log.warning(
                "uwb %s: the kernel says the wall clock is not synchronized; TDMA turns need the "
                "fleet's clocks to agree within guard_ms (run chrony: docs/uwb.md)",
                self.port,
            )
        # A state dir that cannot be written fails here, but not a full disk: a robot restarted on
        # one went down again every 2 s under systemd, where it can run on (receiving, fusing)
        # and sign once a save goes through, as a link whose disk fills later does.
        await self._persist_counter(strict=True)
        try:
            await self._open()
        except TransportError:
            if not self.wait_for_port or os.path.exists(self.port):
                raise  # there but not a port this user can open as serial: the config's to fix
            # A USB radio the kernel has not named yet at boot, or one unplugged: the link runs
            # and opens it once it is there, as it reopens one that vanishes later; the daemon's
            # other links run meanwhile.
            log.warning(
                "uwb: serial port %s is not there; opening it once it is (every %.1f s)",
                self.port,
                self.reopen_s,
            )
        self.started_at = asyncio.get_running_loop().time()
        self._task = asyncio.create_task(self._run(), name=f"uwb-{self.port}")
        self._task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            exc = task.exception()
            # A bug gets its traceback in the log; a typed fault is its one line (see stopped()).
            trace = None if isinstance(exc, MapdError) else exc
            log.error("uwb: link on %s stopped: %s", self.port, exc, exc_info=trace)

    async def stopped(self) -> None:
        """Wait while the link runs; return when it is closed, raise :class:`TransportError` (one
        line, with the cause) if its loop ended any other way, so its owner need not poll."""
        task = self._task
        if task is None:
            raise TransportError(f"uwb: link on {self.port} not started")
        await asyncio.wait([task])
        if self._closing or task.cancelled():
            return
        exc = task.exception()
        why = "its loop returned" if exc is None else failure_reason(exc)
        raise TransportError(f"uwb: link on {self.port} stopped: {why}")

    async def close(self) -> None:
        """Stop at once: cancel the loop, drop the port (unsent frames are abandoned), save the
        replay marks."""
        self._closing = True
        self._wake.set()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(self._task, 2.0)
        if self._proto is not None and self._proto.transport is not None:
            self._proto.transport.abort()
        self._proto = None
        await self._save_replay(force=True)

    def send(
        self,
        data: bytes,
        dests: list[int],
        *,
        stream: int = 0,
        deadline_s: float | None = None,
        background: bool = False,
        reliable: bool = True,
    ) -> int:
        """Queue a message (latest wins per stream); returns its id for the events that follow."""
        if self.core is None:
            raise TransportError("uwb: link not started")
        now = asyncio.get_running_loop().time()
        deadline = None if deadline_s is None else now + deadline_s
        msg = self.core.send(
            data, now, dests=dests, stream=stream, deadline=deadline, background=background, reliable=reliable
        )
        self._wake.set()
        return msg

    def stats(self) -> dict[str, Any]:
        out = self.core.stats() if self.core is not None else {}
        if self._cfg.mac == "tdma" and not self._cfg.radio_time:
            # (with radio time a clock no time service keeps follows the fleet's: no fault)
            synced = self._time_service()  # one syscall; status asks now and then
            if synced is not None:
                out["clock_synchronized"] = synced
        if self.core is not None and (radio := self.core.radio_clock()) is not None:
            out["radio_clock"] = radio
        out.update(
            port=self.port,
            port_open=self._proto is not None and not self._proto.lost,
            reconnects=self.reconnects,
            write_stalls=self.write_stalls,
            counter_save_errors=self.counter_save_errors,
            replay_save_errors=self.replay_save_errors,
            clock_steps=self.clock_steps,
            write_peak_bps_1s=round(self.write_peak_bps, 1),
        )
        return out

    # --- the loop -------------------------------------------------------------------------------

    async def run_until(self, aw: Awaitable[T]) -> T:
        """``aw``'s result, or :class:`TransportError` if the link stops first (never a hang on a
        link whose loop has died)."""
        waiter = asyncio.ensure_future(aw)
        stop = asyncio.ensure_future(self.stopped())
        try:
            await asyncio.wait([waiter, stop], return_when=asyncio.FIRST_COMPLETED)
            if waiter.done():
                return waiter.result()
            stop.result()  # the loop's fault, as one line
            raise TransportError(f"uwb: link on {self.port} was closed")
        finally:
            waiter.cancel()
            stop.cancel()

    def _dispatch(self) -> None:
        assert self.core is not None
        for event in self.core.events():
            try:
                self._on_event(event)
            except MapdError:
                raise
            except Exception:  # a consumer's bug must not stop the link
                log.exception("uwb: event handler failed on %s", event)

    async def _run(self) -> None:
        core = self.core
        assert core is not None
        loop = asyncio.get_running_loop()
        while not self._closing:
            self._wake.clear()
            now = loop.time()
            self._follow_clock(core, now)
            await self._maybe_reopen(now)
            timer = core.get_timer()
            if timer is not None and timer <= now:
                core.handle_timer(now)
            await self._persist_counter()
            await self._save_replay()
            self._dispatch()
            while not self._closing:
                now = loop.time()
                frame = core.data_to_send(now)
                if not frame:
                    break
                proto = self._proto
                if proto is not None and not proto.lost and proto.transport is not None:
                    proto.transport.write(frame)
                    self._record_write(now, len(frame))
                    await self._drain(proto)
                # else: the line is down; the frame is lost like any other and will be resent
                await self._persist_counter()
                self._dispatch()
            self._dispatch()
            timer = core.get_timer()
            wait = None if timer is None else max(0.0, timer - loop.time())
            if self._proto is None or self._proto.lost:
                wait = min(wait if wait is not None else self.reopen_s, self.reopen_s)
            if self._counter_fault:
                wait = min(wait if wait is not None else COUNTER_RETRY_S, COUNTER_RETRY_S)
            if self._cfg.mac == "tdma":
                wait = min(wait if wait is not None else CLOCK_CHECK_S, CLOCK_CHECK_S)
            if self._wake.is_set():
                continue
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), wait)
