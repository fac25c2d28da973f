"""The live view's sockets, below HTTP: each counted from its accept, one past the cap refused.

At most ``max_connections`` sockets are open at once: :class:`_Counted` counts each one from the
moment it is accepted to its close (aiohttp counts only once the loop hands it over, after a whole
backlog has been accepted, so a burst slipped past its count), and one more gets
:class:`_Refused`: a 503, then closed before anything is read. Without a cap a flood of idle
sockets would use up the daemon's file descriptors; :func:`fit_open_files` raises the process's
open-file limit towards what the cap needs (the server lowers the cap to what it gets). A
malformed request is counted (``bad_requests``), and so is a client that leaves before its answer
is written (``left_early``), not logged with a traceback (:class:`_HttpLog`): a client cannot fill
the journal.

The server that owns the count and the cap is :class:`~mapd.view.server.ViewServer`.
"""

from __future__ import annotations

import asyncio
import logging
import resource
from collections.abc import Callable
from typing import Any

from aiohttp.http_exceptions import HttpProcessingError

_REFUSED = b"503: too many connections; try again later\n"


class _Refused(asyncio.Protocol):
    """A connection past ``max_connections``: one 503, then closed, before anything is read.

    A client that sent its request already may see a reset instead (the kernel resets a socket
    closed with unread input); either way it is gone at once and costs nothing.
    """

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        transport.write(
            b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
            b"Retry-After: 10\r\nConnection: close\r\n"
            + f"Content-Length: {len(_REFUSED)}\r\n\r\n".encode()
            + _REFUSED
        )
        transport.close()


def fit_open_files(need: int) -> int:
    """How many open files this process may have, raised towards ``need`` when the hard limit allows.

    systemd starts services with a soft limit of 1024 (for select(), which nothing here uses) and
    a far higher hard one, and asks programs that need more to raise the soft limit themselves.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= need:
        return need
    target = need if hard == resource.RLIM_INFINITY else min(need, hard)
    if target > soft:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    return soft


class _HttpLog(logging.LoggerAdapter):
    """aiohttp's server logger: a malformed request or a client gone is counted, not logged with a traceback.

    aiohttp logs every request it cannot parse (a doubled Host, a bare LF, a NUL in a header) as
    "Error handling request" with a traceback: 800 bytes of journal each, 1.5 MB a second from one
    client; and so a handler that a client's reset ended mid-write (2 KB each). The handlers catch
    the resets they know of; this is the backstop. A bug in a handler (anything else) is still
    logged whole.
    """

    def __init__(self, counters: dict[str, int]) -> None:
        super().__init__(logging.getLogger("mapd.view.http"), {})
        self.counters = counters

    def exception(self, msg: object, *args: object, exc_info: Any = True, **kw: Any) -> None:
        if isinstance(exc_info, HttpProcessingError):
            self.counters["bad_requests"] += 1
            self.logger.debug("view: a malformed request (%s)", exc_info.message)
            return
        if isinstance(exc_info, ConnectionError):
            self.counters["left_early"] += 1
            self.logger.debug("view: the client left (%s)", exc_info)
            return
        self.logger.error(msg, *args, exc_info=exc_info, **kw)


class _Counted(asyncio.Protocol):
    """aiohttp's protocol for one socket, counted open from its accept to its close.

    aiohttp's own count of connections grows only in ``connection_made``, which the loop calls
    after it has accepted every socket waiting in the backlog: a burst of 100 sockets all saw the
    count from before it, and all were taken past a cap of 4.
    """

    def __init__(
        self,
        inner: asyncio.Protocol,
        closed: Callable[[], None],
        admit: Callable[[str], bool] = lambda address: True,
        release: Callable[[str], None] = lambda address: None,
    ) -> None:
        self._inner = inner
        self._closed: Callable[[], None] | None = closed
        self._admit, self._release = admit, release
        #: The peer's address once admitted; None for one refused (its socket never reaches aiohttp)
        self._address: str | None = None
        self._refused = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # Per address too: one client's idle sockets (no token is asked before a request) took every
        # place, and viewers with the token got 503s for as long as it kept them open.
        peer = transport.get_extra_info("peername")
        address = str(peer[0]) if isinstance(peer, tuple) and peer else ""
        if not self._admit(address):
            self._refused = True
            _Refused().connection_made(transport)
            return
        self._address = address
        self._inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        if not self._refused:
            self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return None if self._refused else self._inner.eof_received()

    def pause_writing(self) -> None:
        self._inner.pause_writing()

    def resume_writing(self) -> None:
        self._inner.resume_writing()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)  # anything else asked of aiohttp's protocol

    def connection_lost(self, exc: Exception | None) -> None:
        try:
            if not self._refused:
                self._inner.connection_lost(exc)
        finally:
            if self._closed is not None:  # once, however often the transport says it
                self._closed()
                self._closed = None
                if self._address is not None:
                    self._release(self._address)
