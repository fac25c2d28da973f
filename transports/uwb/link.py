"""The asyncio adapter: a serial port (pyserial-asyncio) driving the sans-I/O core in ``arq.py``.

It is thin on purpose. One task loops: feed what the port read, fire the core's timer, persist the
signing counter when the core asks, write the frames the core hands out one at a time (waiting for
each to leave the transport's buffer, so nothing queues behind the pacing), hand events on, and sleep
until the core's next deadline or new input. A port that vanishes (a USB radio unplugged) is reopened
every ``reopen_s``; meanwhile the core sees an outage and resumes where the receiver left off.

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
from mapd.errors import DiskFullError, MapdError, StateError, TransportError
from transports.uwb import arq
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

#: A frame that has not left the port's buffer after this long means the port is stuck (a peer or
#: a driver that stopped reading, flow control held): the port is dropped and reopened, so the loop
#: (timers, deadlines, events) never waits on one write for ever.
WRITE_STALL_S = 5.0
#: How often a signing counter that could not be saved is tried again.
COUNTER_RETRY_S = 1.0
#: Seconds between saves of the replay marks: frames a sender signed in the last few seconds
#: before a kill -9 are all a restart could take again (a clean close saves them all).
REPLAY_SAVE_S = 5.0
#: TDMA: the wall clock is read at least this often, so a step (NTP) moves the slots within it.
CLOCK_CHECK_S = 1.0
#: A change of the wall clock against the loop's smaller than this is scheduling jitter: followed,
#: but not counted or logged as a step.
CLOCK_STEP_S = 0.005
#: The fastest a time service slews the wall clock (chrony's maxslewrate is 83,333 ppm; ntpd's
#: 500 ppm): a change between two reads within this rate, plus CLOCK_STEP_S, is a slew (followed,
#: not counted); only a faster one is a step. A host slewing at 5 ms a second was logged as stepping.
MAX_SLEW_RATE = 0.1
#: Smaller changes than this are the two clocks read a few microseconds apart: not passed on.
CLOCK_FOLLOW_S = 1e-4


def port_error(port: str, exc: BaseException | None = None) -> TransportError:
    if not os.path.exists(port):
        return TransportError(f"uwb: serial port {port} does not exist")
    detail = str(exc).splitlines()[0] if exc is not None and str(exc) else "cannot be opened"
    return TransportError(f"uwb: cannot open serial port {port}: {detail}")


def failure_reason(exc: BaseException) -> str:
    """Why a task stopped, on one line: a typed fault's own words, a bug's type and message."""
    text = " ".join(str(exc).split())
    if isinstance(exc, MapdError) and text:
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class _Proto(asyncio.Protocol):
    def __init__(self, link: UwbLink) -> None:
        self.link = link
        self.transport: asyncio.Transport | None = None
        self._writable: asyncio.Future[None] | None = None
        self.lost = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        # Pause after every write until it has left the buffer: drain() then means "on the wire".
        transport.set_write_buffer_limits(high=0, low=0)

    def data_received(self, data: bytes) -> None:
        self.link._on_bytes(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost = True
        self.resume_writing()
        self.link._on_lost(exc)

    def pause_writing(self) -> None:
        if self._writable is None or self._writable.done():
            self._writable = asyncio.get_running_loop().create_future()

    def resume_writing(self) -> None:
        if self._writable is not None and not self._writable.done():
            self._writable.set_result(None)

    async def drain(self) -> None:
        if self._writable is not None and not self._writable.done():
            await self._writable


def _discard_on_close(port: Any) -> None:
    """Make the transport's close drop the bytes ``port`` still holds instead of waiting for them.

    serial_asyncio closes a port with ``Serial.flush()``, a tcdrain, on the event loop: a USB
    radio that takes no bytes (hung, or holding flow control) never drains, so closing it (at a
    stall's reopen, or at stop) froze the daemon for ever. Unsent frames are abandoned at a close
    anyway (the ARQ resends what matters), so they are discarded (tcflush), which never waits.
    """

    def discard() -> None:
        with contextlib.suppress(Exception):  # a port unplugged meanwhile: nothing left to drop
            port.reset_output_buffer()

    port.flush = discard


class UwbLink:
    """A serial port driving one :class:`~transports.uwb.arq.ArqEndpoint`; raw byte messages."""

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
        wait_for_port: bool = False,
    ) -> None:
        self.port = port
        #: A port not there at start is opened once it is (the daemon), rather than an error (a
        #: one-shot command such as ``mapd link send``, where a typo must not look like a wait).
        self.wait_for_port = wait_for_port
        self._wall = wall_clock  # the clock TDMA slots are counted on (a test steps its own)
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
        self._proto: _Proto | None = None
        #: False until the port first opened (it may not be there yet at start)
        self._ever_open = False
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
        if self._cfg.mac == "tdma" and wallclock.synchronized() is False:
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

    async def _open(self) -> None:
        import serial
        import serial_asyncio

        if not os.path.exists(self.port):
            raise port_error(self.port)
        loop = asyncio.get_running_loop()
        try:
            transport, proto = await serial_asyncio.create_serial_connection(
                loop, lambda: _Proto(self), self.port, baudrate=self.baud
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise port_error(self.port, exc) from None
        _discard_on_close(transport.serial)
        self._proto = proto
        self._ever_open = True

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

    async def _save_replay(self, *, force: bool = False) -> None:
        """Save the highest counter accepted from each sender, at most every :data:`REPLAY_SAVE_S`
        (on a worker thread), when it changed."""
        if self.core is None:
            return
        now = asyncio.get_running_loop().time()
        if not force and now < self._replay_save_at:
            return
        marks = self.core.replay_marks()
        if marks == self._replay_saved:
            return
        self._replay_save_at = now + REPLAY_SAVE_S
        try:
            await asyncio.to_thread(self._replay.save, marks, self._cfg.key)
        except StateError as exc:
            self.replay_save_errors += 1
            if not self._replay_fault:  # said once an outage (it was once a process), not each try
                log.warning("%s; frames from before a restart may be taken again after it", exc)
            self._replay_fault = True
            return
        if self._replay_fault:
            self._replay_fault = False
            log.warning("uwb: replay marks saved again on %s", self.port)
        self._replay_saved = marks

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
        if self._cfg.mac == "tdma":
            synced = wallclock.synchronized()  # one syscall; status asks now and then
            if synced is not None:
                out["clock_synchronized"] = synced
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

    # --- callbacks from the protocol ------------------------------------------------------------

    def _on_bytes(self, data: bytes) -> None:
        now = asyncio.get_running_loop().time()
        if self.first_rx_at is None:
            self.first_rx_at = now
        if self.core is not None:
            self.core.receive_data(data, now)
        self._wake.set()

    def _on_lost(self, exc: Exception | None) -> None:
        if not self._closing:
            log.warning(
                "uwb: serial port %s lost (%s); reopening every %.1f s", self.port, exc, self.reopen_s
            )
            self._reopen_at = asyncio.get_running_loop().time() + self.reopen_s
        self._wake.set()

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

    async def _persist_counter(self, *, strict: bool = False) -> None:
        """Save the counter bound the core asks for, then let it sign below it.

        Only at start (``strict``) does a failed save raise, unless the disk is full: then, as
        later, the loop goes on. The core still has the rest of the block saved before (half a
        block, minutes of frames; none at start), after which it sends nothing signed; each wake
        retries, and a save that goes through resumes it. The save
        (two fsyncs, which an SD card under load can take seconds over) runs on a worker thread:
        this link waits for it, the event loop does not.
        """
        assert self.core is not None
        upto = self.core.counter_reservation()
        if upto is None:
            return
        now = asyncio.get_running_loop().time()
        if self._counter_fault and now < self._counter_retry_at:
            return  # not a write per frame to a disk that refused the last one
        try:
            await asyncio.to_thread(self._store.save, upto)
        except StateError as exc:
            if strict and not isinstance(exc, DiskFullError):
                raise
            self._counter_retry_at = now + COUNTER_RETRY_S
            self.counter_save_errors += 1
            if str(exc) != self._counter_fault:
                self._counter_fault = str(exc)
                if strict:
                    log.warning(
                        "%s; this link signs and sends nothing until a save goes through, retrying", exc
                    )
                else:
                    log.warning("%s; signing on within the counters saved before, retrying", exc)
            return
        if self._counter_fault:
            self._counter_fault = ""
            log.warning("uwb: signing counter saved again on %s", self.port)
        self.core.confirm_counter(upto)

    def _dispatch(self) -> None:
        assert self.core is not None
        for event in self.core.events():
            try:
                self._on_event(event)
            except MapdError:
                raise
            except Exception:  # a consumer's bug must not stop the link
                log.exception("uwb: event handler failed on %s", event)

    def _record_write(self, now: float, n: int) -> None:
        self._writes.add(n, now)
        self.write_peak_bps = 8.0 * self._writes.peak

    async def _maybe_reopen(self, now: float) -> None:
        if self._proto is not None and not self._proto.lost:
            return
        if now < self._reopen_at:
            return
        try:
            first = not self._ever_open
            await self._open()
            if first:
                log.warning("uwb: serial port %s is there now: opened", self.port)
            else:
                self.reconnects += 1
                log.warning("uwb: serial port %s reopened", self.port)
        except TransportError:
            self._reopen_at = now + self.reopen_s

    async def _drain(self, proto: _Proto) -> None:
        try:
            await asyncio.wait_for(proto.drain(), WRITE_STALL_S)
        except TimeoutError:
            self.write_stalls += 1
            if not self._stall_logged:  # once until a write goes through again, not every reopen
                self._stall_logged = True
                log.warning(
                    "uwb: serial port %s took no bytes for %.0f s; reopening it", self.port, WRITE_STALL_S
                )
            if proto.transport is not None:
                proto.transport.abort()  # connection_lost follows: the reopen path takes over
            proto.lost = True
            proto.resume_writing()
            self._reopen_at = asyncio.get_running_loop().time() + self.reopen_s
            return
        self._stall_logged = False

    def _follow_clock(self, core: arq.ArqEndpoint, now: float) -> None:
        """Pass the wall clock's offset from the loop's to the core when it moved (slew or step)."""
        offset = self._wall() - now
        last, self._clock_read = self._clock_read, (now, offset)
        if abs(offset - core.cfg.clock_offset) >= CLOCK_FOLLOW_S:
            core.set_clock_offset(offset)
        if last is None:  # the first read (a config built without the offset is no step)
            return
        jump = offset - last[1]
        if abs(jump) >= CLOCK_STEP_S + MAX_SLEW_RATE * max(0.0, now - last[0]):
            self.clock_steps += 1
            log.warning("uwb %s: the wall clock stepped %+.3f s; TDMA slots follow it", self.port, jump)
            # A step ahead (NTP setting a clock that booted behind) left a counter begun from the
            # clock behind, with no saved one (a new or lost state), under the marks peers hold
            # from before: all its frames were "replayed" until a restart. It goes on from the
            # clock. Not a counter that was saved: a wrong step ahead (a GPS glitch) would put it
            # in the future, where peers refuse it even once the clock is right again.
            if jump > 0 and self._counter_from_clock and core.raise_counter(clock_floor(now + offset)):
                log.warning("uwb %s: the signing counter (begun from the clock) goes on from it", self.port)

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
