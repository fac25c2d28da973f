"""``ros2``: take the robot's map from a ROS 2 ``nav_msgs/msg/OccupancyGrid`` topic over zenoh.

No ROS install is needed: the source opens a zenoh session, subscribes to the topic's key and
decodes the CDR payload with ``rosbags`` (:mod:`mapd.ros2.cdr`). Two key formats:

* ``rmw_zenoh`` (ROS 2 running on rmw_zenoh): ``<domain>/<topic>/nav_msgs::msg::dds_::OccupancyGrid_/*``
  (any type hash). rmw_zenoh publishes ``/map`` as transient-local through an advanced publisher, so
  the source subscribes with an advanced subscriber that asks for history and detects late
  publishers: it gets the current map at once, not only the next one.
* ``ros2dds`` (a ``zenoh-bridge-ros2dds``): the topic without its leading slash, under an optional
  namespace.

Zenoh delivers samples on its own threads; the callback only hands the bytes to the asyncio loop
(``call_soon_threadsafe``), where the newest payload replaces any not yet decoded (latest wins).
A payload that does not parse, or is over the size limit, is logged with the topic and counted,
and the source waits for the next one. A map equal to the last one emitted is not emitted again.

Example ``config.toml`` table::

    [source.ros2]
    topic = "/map"
    key_format = "rmw_zenoh"          # or "ros2dds"
    domain = 0
    mode = "client"
    connect = ["tcp/127.0.0.1:7447"]  # rmw_zenohd, the ROS 2 zenoh router
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator

from mapd.errors import CodecError, LimitError, TransportError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.ros2 import cdr as ros2cdr
from mapd.sources.base import MapSource, SourceContext, SourceOptions

log = logging.getLogger(__name__)


class Ros2Options(SourceOptions):
    """``[source.ros2]``: which topic, which key format, and how to reach the zenoh network."""

    topic: str = Field(default="/map", description="ROS 2 topic of the nav_msgs/msg/OccupancyGrid")
    key_format: Literal["rmw_zenoh", "ros2dds"] = Field(
        default="rmw_zenoh", description="rmw_zenoh keys, or zenoh-bridge-ros2dds keys"
    )
    domain: int = Field(default=0, ge=0, le=232, description="ROS_DOMAIN_ID (rmw_zenoh keys)")
    namespace: str = Field(default="", description="bridge namespace (ros2dds keys)")
    key: str | None = Field(default=None, description="subscribe to this key expression instead")
    history: bool = Field(default=True, description="ask publishers for their cached map on start")
    mode: Literal["peer", "client"] = Field(default="client", description="zenoh session mode")
    connect: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"], description="zenoh endpoints to connect to"
    )
    listen: list[str] = Field(default_factory=list, description="zenoh endpoints to listen on")
    multicast_scouting: bool = Field(default=False, description="find peers by multicast")
    zenoh_config: Path | None = Field(default=None, description="a zenoh JSON5 config to start from")
    start_pose: list[float] | None = Field(
        default=None, description="[x, y, yaw] of the ROS map frame in the fleet frame, when known"
    )

    @field_validator("topic")
    @classmethod
    def _check_topic(cls, v: str) -> str:
        ros2cdr.rmw_zenoh_key(v, hash_="*")  # raises ValueError for a bad name
        return v

    @field_validator("start_pose")
    @classmethod
    def _check_pose(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (len(v) != 3 or not all(math.isfinite(x) for x in v)):
            raise ValueError("start_pose must be [x, y, yaw] (m, m, rad)")
        return v


class Ros2Source(MapSource):
    """Map versions from a ROS 2 OccupancyGrid topic, received over zenoh."""

    name = "ros2"
    Options = Ros2Options

    def __init__(self, options: SourceOptions | None, ctx: SourceContext) -> None:
        super().__init__(options, ctx)
        assert isinstance(self.options, Ros2Options)
        self.opts: Ros2Options = self.options
        o = self.opts
        self.key = o.key or ros2cdr.key_for(
            o.topic, o.key_format, domain=o.domain, namespace=o.namespace, subscribe=True
        )
        self._session: Any = None
        self._sub: Any = None
        self._pending: tuple[str, bytes] | None = None
        self._wake: asyncio.Event | None = None
        self._versions = 0
        self._received = 0
        self._dropped = 0
        self._bad = 0
        self._last_error = ""
        self._last_digest: bytes | None = None

    def start_pose(self) -> Pose2D | None:
        return Pose2D(*self.opts.start_pose) if self.opts.start_pose is not None else None

    # -- zenoh side (runs on zenoh threads) ------------------------------------------------------------
    def _on_sample(self, loop: asyncio.AbstractEventLoop, sample: Any) -> None:
        try:
            payload = sample.payload.to_bytes()
            key = str(sample.key_expr)
        except Exception:  # a sample we cannot read at all
            return
        # RuntimeError: the loop closed while zenoh was still delivering.
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(self._offer, key, payload)

    # -- asyncio side ----------------------------------------------------------------------------------
    def _offer(self, key: str, payload: bytes) -> None:
        self._received += 1
        if self._pending is not None:
            self._dropped += 1  # latest wins: an older, undecoded map is replaced
        self._pending = (key, payload)
        if self._wake is not None:
            self._wake.set()

    def _open(self, loop: asyncio.AbstractEventLoop) -> None:
        import zenoh.ext as zext

        o = self.opts
        self._session = ros2cdr.open_session(
            mode=o.mode,
            connect=o.connect,
            listen=o.listen,
            multicast_scouting=o.multicast_scouting,
            config_file=o.zenoh_config,
        )
        history = zext.HistoryConfig(detect_late_publishers=True) if o.history else None
        try:
            self._sub = zext.declare_advanced_subscriber(
                self._session, self.key, lambda s: self._on_sample(loop, s), history=history
            )
        except Exception as exc:  # zenoh.ZError: bad key expression
            self._session.close()
            self._session = None
            raise TransportError(f"ros2 source: cannot subscribe to '{self.key}': {exc}") from None
        log.info("ros2 source: subscribed to %s", self.key)

    def _decode(self, key: str, payload: bytes) -> OccupancyGrid | None:
        where = f"topic {self.opts.topic} (key {key})"
        try:
            grid = ros2cdr.decode(payload, max_cells=self.ctx.max_cells, where=where)
        except (CodecError, LimitError) as exc:
            self._bad += 1
            self._last_error = str(exc)
            log.warning("%s; waiting for the next map", exc)
            return None
        return grid

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        """Each new, different map received on the topic; runs until closed."""
        loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        await asyncio.to_thread(self._open, loop)
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                item, self._pending = self._pending, None
                if item is None:
                    continue
                grid = await asyncio.to_thread(self._decode, *item)
                if grid is None:
                    continue
                digest = grid.digest()
                if digest == self._last_digest:
                    continue
                self._last_digest = digest
                self._versions += 1
                yield grid.replace(robot=self.ctx.robot, version=self._versions)
        finally:
            await self.close()

    async def close(self) -> None:
        """Undeclare the subscriber and close the session."""
        sub, session = self._sub, self._session
        self._sub = self._session = None
        if sub is not None or session is not None:
            await asyncio.to_thread(_close, sub, session)

    def stats(self) -> dict[str, int | float | str]:
        return {
            "key": self.key,
            "versions": self._versions,
            "received": self._received,
            "replaced_before_decode": self._dropped,
            "bad_payloads": self._bad,
            "last_error": self._last_error,
        }


def _close(sub: Any, session: Any) -> None:
    # Both may already be gone; closing is best effort.
    if sub is not None:
        try:
            sub.undeclare()
        except Exception as exc:
            log.debug("undeclaring subscriber: %s", exc)
    if session is not None:
        try:
            session.close()
        except Exception as exc:
            log.debug("closing zenoh session: %s", exc)
