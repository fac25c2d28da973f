"""The live view's aiohttp adapter: the page, its static assets, one SSE stream, the token. Thin.

Routes (everything else is 404; with a token configured, any request without it is 401 first)::

    GET /                 the page (index.html)
    GET /static/<asset>   view.js, view.css (shipped in the package: no CDN, works offline)
    GET /events           server-sent events: hello (this server's instance), map (tiles), robots, status

Read-only: nothing here changes the daemon. Messages are encoded off the loop (the map on the
output thread) or are small (the status); the loop only hands shared ``bytes`` to each viewer's
bounded :class:`~mapd.view.queue.ClientQueue` and writes them. At most ``max_viewers`` streams run at
once; one more gets a 503. At most ``max_connections`` sockets are open at once, each counted from
its accept, one more refused, the cap fitted to the open-file limit, and malformed requests and
clients gone counted instead of logged (:mod:`mapd.view.connections`). An idle socket closes after
``IDLE_TIMEOUT_S`` and a stream that takes nothing for ``WRITE_TIMEOUT_S`` is cut, and so is a
client that does not take a page, asset or refusal within it (pipelined requests, never read); a
stream's frames go out in slices, so a stuck viewer holds a slice, not its own copy of the map.
Without a token (a loopback listen), only requests naming a loopback host are served: a web page
that rebinds its own DNS name to 127.0.0.1 still sends its own name as ``Host``. The token is
checked per request, so :meth:`ViewServer.set_token` (a reload) takes effect at once.

Each stream starts with a ``hello`` naming this server's instance (new at every start), so a page
that reconnects to a restarted daemon drops the old daemon's map instead of showing it as live.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from importlib import resources
from typing import Any
from urllib.parse import quote

from aiohttp import hdrs, web

from mapd.config import is_loopback
from mapd.errors import DaemonError
from mapd.view.connections import _Counted, _HttpLog, _Refused, fit_open_files
from mapd.view.model import StatusModel
from mapd.view.queue import ClientQueue, Message, sse

log = logging.getLogger("mapd.view")

#: Asset name -> content type. Only these are served; a name not listed is 404 (no path tricks).
ASSETS = {"view.js": "text/javascript; charset=utf-8", "view.css": "text/css; charset=utf-8"}
#: An idle stream gets an SSE comment this often, so proxies and phones keep it open.
KEEPALIVE_S = 15.0
#: A viewer that cannot take one write in this long is dropped (its socket is stuck).
WRITE_TIMEOUT_S = 30.0
#: An open connection with no request in progress (none sent yet, or a page load done) closes after
#: this long; aiohttp's default is an hour, long enough to pile up sockets.
IDLE_TIMEOUT_S = 15.0
#: Messages queued per viewer before it is resynced with the full state (see ClientQueue).
QUEUE_LIMIT = 8
#: A stream's frames are written this much at a time, each slice drained before the next: the
#: transport copies what the socket does not take, so a whole map frame written at once was one
#: copy of the map per stuck viewer (256 viewers of a 4096 x 4096 map: 1 GB).
WRITE_SLICE = 64 << 10
#: Open files kept for the rest of the daemon (ports, zenoh, state, the status socket) beside the
#: view's connections, when the connection cap is fitted to the process's limit (RLIMIT_NOFILE).
FD_RESERVE = 256
_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",  # the token may be in the URL: never pass it on
    "X-Frame-Options": "DENY",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data: blob:; style-src 'self'; "
    "script-src 'self'; connect-src 'self'",
}


def _asset(name: str) -> bytes:
    return resources.files("mapd.view").joinpath("static", name).read_bytes()


@dataclass(eq=False)
class _Viewer:
    queue: ClientQueue
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    #: Set when the stream must end (the token it was opened with is no longer the token).
    ended: bool = False


class ViewServer:
    """Serves the live view on ``host:port``; :meth:`post` hands it new messages (on the loop)."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        token: str | None = None,
        max_viewers: int = 256,
        max_connections: int | None = None,
        snapshot: Callable[[], dict[str, Any]] | None = None,
        status_every_s: float = 1.0,
    ) -> None:
        self.host, self.port = host, port
        self.token = token
        self.max_viewers = max_viewers
        #: Open sockets at most: every stream, plus room for page loads and viewers reconnecting.
        #: Without a cap a flood of idle sockets would use up the daemon's file descriptors.
        self.max_connections = 2 * max_viewers + 16 if max_connections is None else max_connections
        #: Places one address may hold at once (see _admit_address); address -> places held.
        self.max_per_address = max(4, self.max_connections // 2)
        self._per_address: dict[str, int] = {}
        self.snapshot = snapshot
        self.status_every_s = status_every_s
        self._viewers: set[_Viewer] = set()
        self._state: dict[str, Message] = {}  # kind -> the newest full message of that kind
        self._status_model = StatusModel()
        self._runner: web.AppRunner | None = None
        self._listener: asyncio.base_events.Server | None = None
        self._status_task: asyncio.Task[None] | None = None
        self._closing = False
        self._page = b""
        self._assets: dict[str, bytes] = {}
        #: Names this server's run: a page seeing another one after a reconnect clears its state.
        self.instance = secrets.token_hex(8)
        # (how often the page hears from a live daemon: silence past it says the stream is stale)
        self._hello = sse(
            "hello", {"instance": self.instance, "status_every_s": status_every_s, "keepalive_s": KEEPALIVE_S}
        ).frame
        #: Counters for ``mapd status``.
        self.counters = {
            "viewers_total": 0,
            "refused_busy": 0,
            "refused_token": 0,
            "refused_host": 0,
            "refused_conns": 0,
            "dropped_msgs": 0,
            "bad_requests": 0,
            "left_early": 0,
            "write_timeouts": 0,
        }
        self._open = 0  # sockets accepted and not yet closed (see _Counted)

    @property
    def viewers(self) -> int:
        return len(self._viewers)

    @property
    def connections(self) -> int:
        """Open HTTP connections (streams, page loads, idle keep-alives), from accept to close."""
        return self._open

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Bind and serve; raises :class:`DaemonError` (one line) when the address cannot be used."""
        allowed = fit_open_files(self.max_connections + FD_RESERVE) - FD_RESERVE
        if allowed < self.max_connections:
            log.warning(
                "view: %d connections (max_viewers = %d) do not fit the open-file limit; serving %d "
                "(raise LimitNOFILE= in the unit)",
                self.max_connections,
                self.max_viewers,
                max(1, allowed),
            )
            self.max_connections = max(1, allowed)
            self.max_per_address = max(4, self.max_connections // 2)
            # as the default cap: room beside the streams for page loads and viewers reconnecting
            self.max_viewers = min(self.max_viewers, max(1, (self.max_connections - 16) // 2))
        self._page = _asset("index.html")
        self._assets = {name: _asset(name) for name in ASSETS}
        app = web.Application(middlewares=[self._guard])
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)
        # HEAD would start a stream (taking a viewer's place) and write its body after the headers.
        app.router.add_get("/events", self._events, allow_head=False)
        # handler_cancellation: a viewer that leaves ends its stream at once, freeing its place
        # under the cap, instead of at the next write (up to KEEPALIVE_S later).
        self._runner = web.AppRunner(
            app,
            access_log=None,
            shutdown_timeout=1.0,
            handler_cancellation=True,
            keepalive_timeout=IDLE_TIMEOUT_S,
            logger=_HttpLog(self.counters),
        )
        await self._runner.setup()
        # Our own listener instead of web.TCPSite, so each new socket is counted against the cap
        # before aiohttp takes it (runner.cleanup still shuts down the connections it took).
        try:
            self._listener = await asyncio.get_running_loop().create_server(
                self._accept,
                self.host,
                self.port,
                backlog=128,  # web.TCPSite's default
            )
        except OSError as exc:
            await self._runner.cleanup()
            self._runner = None
            raise DaemonError(f"view: cannot listen on {self.host}:{self.port}: {exc.strerror}") from None
        if self.port == 0 and self._listener.sockets:  # an ephemeral port (tests): say which one
            self.port = int(self._listener.sockets[0].getsockname()[1])
        if self.snapshot is not None:
            self._status_task = asyncio.create_task(self._status_loop(), name="view-status")
        log.info("live view on %s", self.url)

    async def close(self) -> None:
        """Stop every stream and the server promptly."""
        self._closing = True
        for v in self._viewers:
            v.wake.set()
        if self._status_task is not None:
            self._status_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._status_task
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    def set_token(self, token: str | None) -> bool:
        """Check every request against ``token`` from now on (None: no token); True when it changed.

        Streams opened before a change end (the page's own reconnect then needs the new token): a
        leaked token that is rotated must not keep a stream it opened.
        """
        if token == self.token:
            return False
        self.token = token
        for v in self._viewers:
            v.ended = True
            v.wake.set()
        log.warning(
            "view: %s; %d stream(s) opened before it ended",
            "a new token is in force" if token else "the token is removed",
            len(self._viewers),
        )
        return True

    # ------------------------------------------------------------------ messages in (loop thread)
    def post(self, *msgs: Message, full_map: Message | None = None) -> None:
        """New messages for every viewer; ``full_map``: the whole map as of the ``map`` delta in ``msgs``."""
        if full_map is not None:
            self._state["map"] = full_map
        for msg in msgs:
            if msg.kind != "map":
                self._state[msg.kind] = msg
            for v in self._viewers:
                before = v.queue.dropped
                v.queue.put(msg)
                self.counters["dropped_msgs"] += v.queue.dropped - before
                v.wake.set()

    def _current(self) -> list[Message]:
        return [self._state[k] for k in ("map", "robots", "status") if k in self._state]

    async def _status_loop(self) -> None:
        assert self.snapshot is not None
        while True:
            if self._viewers:
                try:
                    msg = self._status_model.message(self.snapshot(), time.monotonic())
                except Exception:  # a status bug must never stop the view or the daemon
                    log.exception("view: status snapshot failed")
                else:
                    self.post(msg)
            await asyncio.sleep(self.status_every_s)

    # ------------------------------------------------------------------ HTTP
    def _accept(self) -> asyncio.BaseProtocol:
        """The protocol for a new socket: aiohttp's, or a 503 once ``max_connections`` are open.

        Counted here, as each socket is accepted: the loop accepts every socket waiting in the
        backlog before any of them is handed to aiohttp.
        """
        assert self._runner is not None and self._runner.server is not None
        if self._open >= self.max_connections:
            self.counters["refused_conns"] += 1
            return _Refused()
        self._open += 1
        return _Counted(self._runner.server(), self._closed, self._admit_address, self._release_address)

    def _closed(self) -> None:
        self._open -= 1

    def _admit_address(self, address: str) -> bool:
        """Whether a socket from ``address`` may have a place: one address holds at most
        :attr:`max_per_address` (half the places), so others still get in (a proxy's users share
        one address: half the places for them)."""
        held = self._per_address.get(address, 0)
        if held >= self.max_per_address:
            self.counters["refused_conns"] += 1
            return False
        self._per_address[address] = held + 1
        return True

    def _release_address(self, address: str) -> None:
        held = self._per_address.get(address, 0) - 1
        if held > 0:
            self._per_address[address] = held
        else:
            self._per_address.pop(address, None)

    def _authorized(self, request: web.Request) -> bool:
        assert self.token is not None
        given = request.query.get("token")
        auth = request.headers.get("Authorization", "")
        if given is None and auth[:7].lower() == "bearer ":  # the scheme is case-insensitive (RFC 9110)
            given = auth[7:].strip()
        # The token is ASCII (the config says so); other text cannot match, and a header's
        # undecodable bytes arrive as lone surrogates, which .encode() would raise on (a 500).
        if given is None or not given.isascii():
            return False
        return hmac.compare_digest(given.encode(), self.token.encode())

    @staticmethod
    def _loopback_host(request: web.Request) -> bool:
        """True when the ``Host`` header names a loopback host (or is absent: not a browser)."""
        host = request.headers.get(hdrs.HOST)
        if host is None:
            return True
        if host.startswith("["):  # "[::1]:8080"
            name = host[1 : host.find("]")] if "]" in host else ""
        else:
            name = host.partition(":")[0]
        return is_loopback(name.lower().removesuffix("."))

    @web.middleware
    async def _guard(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if self.token is None and not self._loopback_host(request):
            # No token means a loopback listen; a Host of another name is a page that rebound
            # its DNS name to 127.0.0.1 to read the view from a browser here (DNS rebinding).
            self.counters["refused_host"] += 1
            resp: web.StreamResponse = web.Response(
                status=403, text="403: without a token the view answers only to a loopback host name\n"
            )
        elif self.token is not None and not self._authorized(request):
            self.counters["refused_token"] += 1
            resp = web.Response(
                status=401, text="401: a valid token is needed (?token=... or Authorization: Bearer ...)\n"
            )
            resp.headers["WWW-Authenticate"] = 'Bearer realm="mapd view"'
        else:
            try:
                resp = await handler(request)
            except web.HTTPException as exc:  # 404 and 405 as plain text, with the same headers
                resp = web.Response(status=exc.status, text=f"{exc.status}: {exc.reason}\n")
                if hdrs.ALLOW in exc.headers:  # a 405 says which methods there are
                    resp.headers[hdrs.ALLOW] = exc.headers[hdrs.ALLOW]
        if not resp.prepared:  # an SSE stream has sent its headers already
            resp.headers.update(_HEADERS)
            # Sent here, within the write timeout: aiohttp would wait on a client that never
            # reads (pipelined requests) for ever, holding its socket without even the token.
            try:
                await asyncio.wait_for(self._send(request, resp), WRITE_TIMEOUT_S)
            except TimeoutError:
                self._cut(request)
            except ConnectionError:
                # The client reset the socket before taking its answer: nothing to send it any more.
                # (A reset cancels this handler, and wait_for turns that into this error.)
                self.counters["left_early"] += 1
        return resp

    @staticmethod
    async def _send(request: web.Request, resp: web.StreamResponse) -> None:
        await resp.prepare(request)
        await resp.write_eof()

    def _cut(self, request: web.Request) -> None:
        """Drop a client that took nothing for WRITE_TIMEOUT_S (its socket is stuck)."""
        self.counters["write_timeouts"] += 1
        if request.transport is not None:
            request.transport.abort()

    @staticmethod
    async def _write(resp: web.StreamResponse, frame: bytes) -> None:
        """One frame, a slice at a time (:data:`WRITE_SLICE`), each within the write timeout."""
        view = memoryview(frame)
        for at in range(0, len(view), WRITE_SLICE):
            await asyncio.wait_for(resp.write(view[at : at + WRITE_SLICE]), WRITE_TIMEOUT_S)

    async def _index(self, request: web.Request) -> web.Response:
        # The page passes the token it was opened with on to its assets and its stream: only one
        # that came in the query. One a proxy adds as a header (Authorization: Bearer) for its users
        # was written into every page they got, and into the proxy's access log with each asset.
        came = "token" in request.query and self.token is not None
        query = f"?token={quote(self.token, safe='')}" if came and self.token is not None else ""
        body = self._page.replace(b"__QUERY__", query.encode())
        return web.Response(body=body, content_type="text/html", charset="utf-8")

    async def _static(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in self._assets:
            raise web.HTTPNotFound()
        return web.Response(body=self._assets[name], headers={"Content-Type": ASSETS[name]})

    async def _events(self, request: web.Request) -> web.StreamResponse:
        if len(self._viewers) >= self.max_viewers or self._closing:
            self.counters["refused_busy"] += 1
            return web.Response(
                status=503,
                text=f"503: {self.max_viewers} viewers are watching already; try again later\n",
                headers={"Retry-After": "10"},
            )
        resp = web.StreamResponse(
            headers={**_HEADERS, "Content-Type": "text/event-stream", "X-Accel-Buffering": "no"}
        )
        viewer = _Viewer(ClientQueue(QUEUE_LIMIT))
        viewer.wake.set()  # the first write is the full current state
        self._viewers.add(viewer)
        self.counters["viewers_total"] += 1
        try:
            try:  # in here: a client that resets at once makes the headers' write fail
                await resp.prepare(request)
            except ConnectionError:
                self.counters["left_early"] += 1
                raise
            await resp.write(b"retry: 2000\n\n" + self._hello)
            while not self._closing:
                try:
                    await asyncio.wait_for(viewer.wake.wait(), KEEPALIVE_S)
                except TimeoutError:
                    await self._write(resp, b": keep-alive\n\n")
                    continue
                viewer.wake.clear()
                if viewer.ended:
                    break  # not one more message under the token it was opened with
                for msg in viewer.queue.take(self._current):
                    await self._write(resp, msg.frame)
        except TimeoutError:
            # Stuck: cut the socket, or aiohttp's final write_eof() waits on it for ever, holding
            # the connection and the frame buffered for it after the viewer's place is freed.
            self._cut(request)
        except (ConnectionError, RuntimeError):
            pass  # the viewer left: it just stops getting messages
        finally:
            self._viewers.discard(viewer)
        return resp
