"""``[output.zenoh]``: the global map on zenoh, as a signed, lossless mapd envelope.

Each update is put on ``mapd/<fleet>/<robot>/global`` (``<robot>`` is this daemon's: a base
station's or a robot's view of the fleet), and a queryable on the same key answers late joiners
with the newest one. The payload is the ``lossless`` codec's (exact, a whole map), wrapped in an
:class:`~mapd.envelope.Envelope` whose version counts merges and which this robot signs, so a
subscriber can check who made it with the fleet's roster (``mapd.envelope.unpack(data, roster=...)``).

It opens its own zenoh session (``mode``, ``listen``, ``connect``, ``multicast_scouting``,
``config_file`` as in ``[transports.zenoh]``, and the same TLS/ACL examples apply).
"""

from __future__ import annotations

import asyncio
import functools
import threading
from pathlib import Path
from typing import Any, Literal

from pydantic import Field

from mapd.codec import encode, read_header
from mapd.config.endpoints import ZenohEndpoints
from mapd.envelope import Envelope
from mapd.errors import TransportError, UnreachableError
from mapd.outputs.base import GlobalUpdate, Output, OutputContext, OutputOptions
from mapd.outputs.retry import SessionRetry
from mapd.ros2.zenoh_config import ZenohConfigFiles, open_zenoh
from transports.zenoh.keys import global_key

MAX_MESSAGE_BYTES = 64 << 20


class ZenohOutputOptions(ZenohEndpoints, ZenohConfigFiles, OutputOptions):
    mode: Literal["peer", "client", "router"] = Field(default="peer", description="zenoh mode")
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on")
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to")
    multicast_scouting: bool = Field(default=True, description="find peers on the LAN by UDP multicast")
    config_file: Path | None = Field(default=None, description="zenoh JSON5 config (TLS, access control)")


class ZenohOutput(Output):
    """Puts every global map on zenoh and answers queries with the newest."""

    name = "zenoh"
    Options = ZenohOutputOptions

    def __init__(self, options: OutputOptions | None, ctx: OutputContext) -> None:
        super().__init__(options, ctx)
        if not isinstance(self.options, ZenohOutputOptions):
            raise TypeError("zenoh output needs ZenohOutputOptions")
        self.opts: ZenohOutputOptions = self.options
        self.key = global_key(ctx.fleet, ctx.robot)
        self._session: Any = None
        self._queryable: Any = None
        self._latest: bytes | None = None
        self._lock = threading.Lock()
        self.published = 0
        self.queries = 0
        self.bytes = 0
        #: Tries again while no router answers (a client whose router is not up yet)
        self.retry = SessionRetry("output.zenoh")
        # Held while a map is put, a session adopted or closed: a map published as the session
        # opens goes out once, after any older one, and a session opened after close() is closed.
        self._put_lock = threading.Lock()
        self._closing = False

    async def start(self) -> None:
        from transports.zenoh.session import ZenohOptions, build_config

        fields = self.opts.model_dump(exclude_unset=True)
        conf = build_config(ZenohOptions(**fields), MAX_MESSAGE_BYTES)
        try:
            self._session = await asyncio.to_thread(self._open, conf)
        except UnreachableError as exc:
            # A base station whose router is not up yet: the daemon runs, the newest global map
            # goes out once the session opens.
            self.retry.begin(exc, functools.partial(self._open_and_adopt, conf))

    def _open_and_adopt(self, conf: Any) -> None:
        """On a worker thread: open, then use the session (putting the newest map), or close it if
        the output closed meanwhile (a cancelled wait does not stop this thread)."""
        session = self._open(conf)
        with self._put_lock:
            if self._closing:
                self._close(session)
                return
            with self._lock:
                self._session, latest = session, self._latest
            self.retry.opened()
            if latest is not None:
                session.put(self.key, latest)

    def _open(self, conf: Any) -> Any:
        session = open_zenoh(conf, "output.zenoh: cannot open a session")
        try:
            self._queryable = session.declare_queryable(self.key, self._on_query)
        except Exception as exc:
            session.close()
            raise TransportError(f"output.zenoh: cannot declare {self.key}: {exc}") from None
        return session

    def _on_query(self, query: Any) -> None:
        """On a zenoh thread: reply with the newest global map, if there is one."""
        with self._lock:
            data = self._latest
            self.queries += 1
        if data is not None:
            query.reply(self.key, data)

    def publish(self, update: GlobalUpdate) -> None:
        grid = update.grid
        payload = encode(grid, "lossless")
        head = read_header(payload)
        env = Envelope(
            fleet=self.ctx.fleet,
            robot=self.ctx.robot,
            version=max(1, grid.version),
            base_version=0,
            codec="lossless",
            variant=head.variant,
            width=grid.width,
            height=grid.height,
            resolution=grid.resolution,
            origin=grid.origin,
            frame_id="map",
            stamp=update.stamp,
            payload=payload,
        )
        if self.ctx.identity is not None:
            env = env.signed(self.ctx.identity)
        data = env.pack()
        with self._put_lock:
            with self._lock:
                self._latest = data
            if self._session is not None:
                self._session.put(self.key, data)
        self.published += 1
        self.bytes += len(data)

    async def close(self) -> None:
        with self._put_lock:
            self._closing = True
            session, self._session = self._session, None
        await self.retry.stop()
        if session is not None:
            await asyncio.to_thread(self._close, session)

    def _close(self, session: Any) -> None:
        if self._queryable is not None:
            self._queryable.undeclare()
            self._queryable = None
        session.close()

    def stats(self) -> dict[str, int | float | str]:
        return {
            "key": self.key,
            "published": self.published,
            "queries": self.queries,
            "bytes": self.bytes,
            **self.retry.stats(),
        }
