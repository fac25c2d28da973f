"""The serial port under a :class:`~transports.uwb.link.UwbLink`: opening it (one line when it
cannot be), its bytes in, each frame out and drained, and a port that vanishes or stalls dropped
and reopened, as a mixin over the link's state.

A write counts as done only once it has left the transport's buffer (:class:`_Proto` pauses after
every write), so nothing queues behind the core's pacing. A port that takes no bytes for
:data:`WRITE_STALL_S` is stuck and is reopened like one that vanished (a USB radio unplugged): the
link's loop never waits on one write for ever, and a close never waits on a radio that drains
nothing (:func:`_discard_on_close`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from typing import Any

from mapd.errors import TransportError
from transports.uwb import arq
from transports.uwb.pacing import ByteWindow

log = logging.getLogger("mapd.uwb")

#: A frame that has not left the port's buffer after this long means the port is stuck (a peer or
#: a driver that stopped reading, flow control held): the port is dropped and reopened, so the loop
#: (timers, deadlines, events) never waits on one write for ever.
WRITE_STALL_S = 5.0


def port_error(port: str, exc: BaseException | None = None) -> TransportError:
    """The one line for a serial port that is not there or cannot be opened (``exc``: why not)."""
    if not os.path.exists(port):
        return TransportError(f"uwb: serial port {port} does not exist")
    detail = str(exc).splitlines()[0] if exc is not None and str(exc) else "cannot be opened"
    return TransportError(f"uwb: cannot open serial port {port}: {detail}")


class _Proto(asyncio.Protocol):
    def __init__(self, link: PortSide) -> None:
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


class PortSide:
    """The port's half of a link (a mixin: :class:`~transports.uwb.link.UwbLink` owns the state
    declared here)."""

    port: str
    baud: int
    reopen_s: float
    core: arq.ArqEndpoint | None
    _proto: _Proto | None
    _ever_open: bool
    #: Why the last try to open the port failed, as said (None: nothing said since it was open).
    _reopen_error: str | None
    _closing: bool
    _wake: asyncio.Event
    _reopen_at: float
    _writes: ByteWindow
    write_peak_bps: float
    reconnects: int
    first_rx_at: float | None
    write_stalls: int
    _stall_logged: bool

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
            self._reopen_error = None
            if first:
                log.warning("uwb: serial port %s is there now: opened", self.port)
            else:
                self.reconnects += 1
                log.warning("uwb: serial port %s reopened", self.port)
        except TransportError as exc:
            self._reopen_at = now + self.reopen_s
            # Said when why changes, not at every try: a port that is there but refused (a unit's
            # device policy that took no ttyUSB at boot, a missing dialout group) was retried every
            # second for ever without a word. A port not there was said already (at start, or lost).
            if str(exc) != self._reopen_error and os.path.exists(self.port):
                log.warning("%s; trying again every %.1f s", exc, self.reopen_s)
            self._reopen_error = str(exc)

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
