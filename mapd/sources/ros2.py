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

The source announces itself to the ROS 2 graph as rmw_zenoh does: a node token (``node``) and a
subscription token per topic it takes, so ``ros2 node list`` and ``ros2 topic info`` show it.

**The robot's pose** (:meth:`Ros2Source.pose`, one robot only): with ``pose_topic`` set, the latest
``geometry_msgs/msg/PoseWithCovarianceStamped`` (AMCL's ``/amcl_pose``) or ``PoseStamped``
(``pose_type``) in frame ``pose_frame``, stamped at reception (:mod:`mapd.sources.ros2_pose`).
Refused with ``discover_robots``: the other robots' poses are not this daemon's to send.

**Several robots on one machine** (a drop-in for m-explore's ``multirobot_map_merge``): with
``discover_robots = true`` the source takes ``/<robot>/<robot_map_topic>`` of every robot that
appears (a key-expression wildcard on the data, and the publishers' liveliness tokens) and yields
each robot's maps with ``robot`` set to that name, for the daemon to fuse as it fuses a peer's map.
Which robots it takes, and where each started (``init_poses``), is :mod:`mapd.sources.ros2_robots`.

Example ``config.toml`` tables::

    [source.ros2]
    topic = "/map"
    pose_topic = "/amcl_pose"         # the robot's pose (off when unset)
    key_format = "rmw_zenoh"          # or "ros2dds"
    domain = 0
    mode = "client"
    connect = ["tcp/127.0.0.1:7447"]  # rmw_zenohd, the ROS 2 zenoh router

    [source.ros2]                     # a base station merging /robot1/map, /robot2/map, ...
    discover_robots = true
    robot_map_topic = "map"
    robot_namespace = "robot"
    known_init_poses = true
    [source.ros2.init_poses]
    robot1 = [0.0, 0.0, 0.0]
    robot2 = [4.0, -1.0, 1.5708]
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import threading
from collections.abc import AsyncIterator
from typing import Any

from mapd.errors import CodecError, LimitError, TransportError, UnreachableError
from mapd.grid import OccupancyGrid, Pose2D, StampedPose, on_lattice
from mapd.grid.reprs import short_repr
from mapd.ros2 import cdr as ros2cdr
from mapd.ros2 import rmw
from mapd.ros2.node import own_publishers
from mapd.ros2.zenoh_config import open_when_reachable
from mapd.sources.base import MapSource, SourceContext, SourceOptions
from mapd.sources.ros2_options import Ros2Options
from mapd.sources.ros2_pose import PoseSubscription
from mapd.sources.ros2_robots import Ros2Robots

__all__ = ["Ros2Options", "Ros2Source"]

log = logging.getLogger(__name__)


class Ros2Source(Ros2Robots, MapSource):
    """Map versions from ROS 2 OccupancyGrid topics received over zenoh: one robot's, or many robots'."""

    name = "ros2"
    Options = Ros2Options

    def __init__(self, options: SourceOptions | None, ctx: SourceContext) -> None:
        super().__init__(options, ctx)
        assert isinstance(self.options, Ros2Options)
        self.opts: Ros2Options = self.options
        o = self.opts
        self.key = o.map_key_expr()
        self._pose = (
            PoseSubscription(
                o.pose_topic,
                o.pose_type,
                frame=o.pose_frame,
                key_format=o.key_format,
                domain=o.domain,
                distro=o.distro,
                namespace=o.namespace,
            )
            if o.pose_topic is not None
            else None
        )
        self._pose_sub: PoseSubscription | None = None  # the pose subscription while declared
        self._session: Any = None
        self._sub: Any = None
        self._lv_sub: Any = None
        self._node: Any = None
        #: (key, payload): zenoh's ZBytes, or bytes (copied only once its size is checked)
        self._pending: dict[str, tuple[str, Any]] = {}
        self._wake: asyncio.Event | None = None
        self._robots: dict[str, int] = {}  # robot -> versions yielded
        self._digests: dict[str, bytes] = {}
        #: robot -> the resolution and origin of its first map (snap_origin: the lattice kept)
        self._lattice: dict[str, tuple[float, Pose2D]] = {}
        self._announced: set[str] = set()
        #: The robots counted against ``max_robots`` (a sample or a publisher's token seen).
        self._taken: set[str] = set()
        self._waiting_pose: set[str] = set()
        self._ignored: set[str] = set()
        self._versions = 0
        self._received = 0
        self._dropped = 0
        #: Payloads from zenoh's threads not yet taken by the loop, the newest per key.
        self._inbox: dict[str, Any] = {}
        self._inbox_due = False  # a call to _take_inbox is on its way to the loop
        self._inbox_lock = threading.Lock()
        self._bad = 0
        #: Samples (and publisher tokens) of this daemon's own ros2 output, dropped unread.
        self._own_dropped = 0
        self._last_error = ""
        #: Why the session is not open yet, while no router answers (tries go on)
        self._unreached: str | None = None

    def start_pose(self) -> Pose2D | None:
        return Pose2D(*self.opts.start_pose) if self.opts.start_pose is not None else None

    def pose(self) -> StampedPose | None:
        """The robot's latest pose from ``pose_topic`` (in its map frame, stamped at reception)."""
        return self._pose.latest() if self._pose is not None else None

    # -- zenoh side (runs on zenoh threads) ------------------------------------------------------------
    def _on_sample(self, loop: asyncio.AbstractEventLoop, sample: Any) -> None:
        try:
            # Not copied here: a payload over what a grid of max_cells needs is refused by its size
            # in _decode, before any copy (a 300 MiB sample on /map cost 600 MiB, copied to be refused).
            payload = sample.payload
            key = str(sample.key_expr)
        except Exception:  # a sample we cannot read at all
            return
        if _from_own_output(sample):
            self._drop_own(key)
            return
        # Latest wins here already, on zenoh's thread: one callback a sample queued every payload
        # on the loop while it was busy (a 16 MiB map at 100 Hz: a gigabyte a few seconds).
        with self._inbox_lock:
            if key in self._inbox:
                self._dropped += 1
            self._inbox[key] = payload
            if self._inbox_due:
                return
            self._inbox_due = True
        # RuntimeError: the loop closed while zenoh was still delivering.
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(self._take_inbox)

    def _drop_own(self, what: str) -> None:
        """A sample or publisher of this daemon's own ros2 output: never taken as a robot's map."""
        with self._inbox_lock:
            self._own_dropped += 1
            first = self._own_dropped == 1
        if first:  # a layout config.check refuses: said once, should a daemon run with it anyway
            log.warning(
                "ros2 source: ignoring this daemon's own ros2 output on %s; give [output.ros2] another topic",
                short_repr(what, 120),
            )

    def _take_inbox(self) -> None:
        with self._inbox_lock:
            items, self._inbox = self._inbox, {}
            self._inbox_due = False
        for key, payload in items.items():
            self._offer(key, payload)

    def _on_token(self, loop: asyncio.AbstractEventLoop, sample: Any) -> None:
        import zenoh

        try:
            entity = rmw.parse_token(str(sample.key_expr))
        except ValueError:
            return
        if entity.kind != "MP" or entity.topic is None or entity.type != rmw.dds_type(ros2cdr.MSGTYPE):
            return
        try:
            own = own_publishers.is_own(gid=rmw.gid_of(str(sample.key_expr)))
        except CodecError:  # no xxhash: then no rmw_zenoh output in this process either
            own = False
        if own:  # its own output's /fleet/map is no robot "fleet"'s map
            self._drop_own(entity.topic)
            return
        gone = sample.kind != zenoh.SampleKind.PUT
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(self._publisher_gone if gone else self._discovered, entity.topic)

    # -- asyncio side ----------------------------------------------------------------------------------
    def _offer(self, key: str, payload: Any) -> None:
        robot = self.robot_of_key(key)
        if robot is None:
            return
        self._received += 1
        if robot in self._pending:
            self._dropped += 1  # latest wins: an older, undecoded map of that robot is replaced
        self._pending[robot] = (key, payload)
        self._announce(robot, f"/{robot}/{self.opts.robot_map_topic}")
        if self._wake is not None:
            self._wake.set()

    def _discovered(self, topic: str) -> None:
        robot = self.robot_of_topic(topic)
        if robot is not None:
            self._announce(robot, topic)

    def _announce(self, robot: str, topic: str) -> None:
        """Declare mapd's subscription to a robot's topic (once), off the loop."""
        if not self.opts.discover_robots or robot in self._announced or self._node is None:
            return
        self._announced.add(robot)
        log.info("ros2 source: taking %s", topic)
        node = self._node
        asyncio.get_running_loop().run_in_executor(None, _declare_sub, node, topic)

    def _open(self, loop: asyncio.AbstractEventLoop) -> None:
        import zenoh.ext as zext

        from mapd.ros2.node import Ros2Node

        o = self.opts
        self._session = ros2cdr.open_session_for(o)
        history = zext.HistoryConfig(detect_late_publishers=True) if o.history else None
        try:
            # recovery: a sample lost on the way (a large /map over Wi-Fi, rmw_zenoh publishing keep-last
            # topics with congestion control drop) is asked for again on the publisher's heartbeat, as
            # rmw_zenoh's own subscribers do; map_server publishes once, and it was never had
            self._sub = zext.declare_advanced_subscriber(
                self._session,
                self.key,
                lambda s: self._on_sample(loop, s),
                history=history,
                recovery=zext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            )
            if o.key_format == "rmw_zenoh" and o.key is None:
                self._node = Ros2Node(self._session, o.node, domain=o.domain, distro=o.distro)
                if o.discover_robots:
                    self._lv_sub = self._session.liveliness().declare_subscriber(
                        f"{rmw.ADMIN_SPACE}/{o.domain}/**", lambda s: self._on_token(loop, s), history=True
                    )
                else:
                    self._node.subscription(o.topic, ros2cdr.MSGTYPE, rmw.LATCHED)
            if self._pose is not None:
                self._pose_sub = self._pose
                self._pose.declare(self._session, self._node)
        except Exception as exc:  # zenoh.ZError: bad key expression
            _close(self._node, self._pose_sub, self._lv_sub, self._sub, self._session)
            self._session = self._sub = self._lv_sub = self._node = self._pose_sub = None
            if isinstance(exc, TransportError):  # a token or the pose topic: it names what failed
                raise
            raise TransportError(f"ros2 source: cannot subscribe to '{self.key}': {exc}") from None
        log.info("ros2 source: subscribed to %s", self.key)

    def _decode(self, key: str, payload: Any) -> tuple[OccupancyGrid, bytes] | None:
        """The map and its digest (a worker thread: both are a pass over every cell)."""
        # The key as its repr, cut short: a publisher's key is anyone's text (a newline and a forged
        # log line in it, 4 kB of it).
        shown = short_repr(key, 120)
        where = f"key {shown}" if self.opts.discover_robots else f"topic {self.opts.topic} (key {shown})"
        try:
            ros2cdr.check_size(len(payload), self.ctx.max_cells, where)  # (zenoh's ZBytes: not copied yet)
            data = payload if isinstance(payload, bytes) else payload.to_bytes()
            grid = ros2cdr.decode(data, max_cells=self.ctx.max_cells, where=where)
        except (CodecError, LimitError) as exc:
            self._bad += 1
            self._last_error = str(exc)
            log.warning("%s; waiting for the next map", exc)
            return None
        return grid, grid.digest()

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        """Each new, different map received (per robot when discovering); runs until closed."""
        loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        await self._open_when_reachable(loop)
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                items, self._pending = self._pending, {}
                for robot, item in sorted(items.items()):
                    if self._waiting_for_pose(robot):
                        continue
                    decoded = await asyncio.to_thread(self._decode, *item)
                    if decoded is None:
                        continue
                    grid, digest = decoded
                    if digest == self._digests.get(robot):
                        continue
                    if self.opts.snap_origin:
                        ref = self._lattice.setdefault(robot, (grid.resolution, grid.origin))
                        if math.isclose(ref[0], grid.resolution, rel_tol=1e-9):
                            grid = grid.replace(origin=on_lattice(grid.origin, grid.resolution, ref[1]))
                    self._digests[robot] = digest
                    self._robots[robot] = self._robots.get(robot, 0) + 1
                    self._versions += 1
                    yield grid.replace(robot=robot, version=self._robots[robot])
        finally:
            await self.close()

    async def _open_when_reachable(self, loop: asyncio.AbstractEventLoop) -> None:
        """Open the session; while no router answers (rmw_zenohd not up yet at boot), try again
        after 1 s, doubling to 30 s, rather than stop the daemon: its links run meanwhile."""
        try:
            await asyncio.to_thread(self._open, loop)
            return
        except UnreachableError as exc:
            log.warning("ros2 source: %s; trying again (the daemon's links run meanwhile)", exc)
            self._unreached = self._last_error = str(exc)
        await open_when_reachable(functools.partial(self._open, loop))
        if self._last_error == self._unreached:
            self._last_error = ""  # (the wait is over: not an error to show any more)
        self._unreached = None
        log.info("ros2 source: session open")

    async def close(self) -> None:
        """Undeclare the subscribers and tokens and close the session."""
        things = (self._node, self._pose_sub, self._lv_sub, self._sub, self._session)
        self._node = self._pose_sub = self._lv_sub = self._sub = self._session = None
        if any(t is not None for t in things):
            await asyncio.to_thread(_close, *things)

    def stats(self) -> dict[str, int | float | str]:
        out: dict[str, int | float | str] = {
            "key": self.key,
            "versions": self._versions,
            "received": self._received,
            "replaced_before_decode": self._dropped,
            "bad_payloads": self._bad,
            "own_output_dropped": self._own_dropped,
            "last_error": self._last_error,
            # False while no router answers (a FAULTS line in mapd status)
            "session_open": self._unreached is None,
        }
        if self.opts.discover_robots:
            out["robots"] = ",".join(f"{r}:{n}" for r, n in sorted(self._robots.items())) or "-"
            out["waiting_for_init_pose"] = ",".join(sorted(self._waiting_pose)) or "-"
        if self._pose is not None:
            out.update(self._pose.stats())
        return out


def _from_own_output(sample: Any) -> bool:
    """Whether a sample comes from this process's ros2 output: by the publisher GID in its
    rmw_zenoh attachment, else (``ros2dds``: no attachment) by the session its timestamp names."""
    gid = zid = None
    try:
        if sample.attachment is not None:
            gid = rmw.parse_attachment(sample.attachment.to_bytes())[2]
    except Exception:  # CodecError: not rmw_zenoh's; anyone may attach anything
        gid = None
    try:
        if sample.timestamp is not None:
            zid = str(sample.timestamp.get_id())
    except Exception:  # (a sample we cannot read the timestamp of: not ours, we stamp ours)
        zid = None
    return own_publishers.is_own(gid=gid, zid=zid)


def _declare_sub(node: Any, topic: str) -> None:
    try:
        node.subscription(topic, ros2cdr.MSGTYPE, rmw.LATCHED)
    except Exception as exc:  # TransportError, or the session closed meanwhile
        log.debug("declaring the subscription token of %s: %s", topic, exc)


def _close(node: Any, *things: Any) -> None:
    # All may already be gone; closing is best effort (the session last).
    if node is not None:
        try:
            node.close()
        except Exception as exc:
            log.debug("closing the ROS 2 node: %s", exc)
    for thing in things:
        if thing is None:
            continue
        try:
            if hasattr(thing, "undeclare"):
                thing.undeclare()
            else:
                thing.close()
        except Exception as exc:
            log.debug("closing zenoh %s: %s", type(thing).__name__, exc)
