"""Robot poses in the daemon: this robot's pose out to every link, peers' poses in, all to the outputs.

Every :data:`POLL_S` the daemon asks its source where the robot is (:meth:`MapSource.pose`); a pose
newer than the last one goes, signed by this robot's key, to every transport, each of which sends
it at its own ``pose_period_s`` (a radio's is seconds and yields to maps; zenoh's is sub-second).
A peer's pose message is verified off the loop against the roster, must name the robot the link
says it came from, and is kept only if it is newer than the one held (:class:`~mapd.poses.PoseBook`).
All known poses, this robot's included, reach the outputs and the recording as a
:class:`~mapd.outputs.base.PoseUpdate`, and ``mapd status`` as positions in the robot's map frame
and, once fusion has placed that map, in the fleet frame.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any

from mapd.errors import EnvelopeError
from mapd.fusion.transforms import compose
from mapd.grid import Pose2D, StampedPose
from mapd.identity import Identity, Roster
from mapd.poses import PoseBook, PoseMessage, unpack_pose
from mapd.sources.base import MapSource
from transports.base import PoseReceived, Transport

log = logging.getLogger("mapd.daemon")
#: How often the source is asked for the robot's pose (a cheap getter) and the outputs get poses.
POLL_S = 0.5


class PoseRelay:
    """The daemon's pose traffic; runs on the loop, verifies in a worker thread."""

    def __init__(
        self,
        robot: str,
        fleet: str,
        *,
        identity: Identity | None,
        roster: Roster,
        max_robots: int,
        frames: Callable[[], dict[str, Pose2D]],
        publish: Callable[[dict[str, StampedPose], dict[str, Pose2D]], None],
    ) -> None:
        self.robot = robot
        self.fleet = fleet
        self.identity = identity
        self.roster = roster
        self.book = PoseBook(max_robots=max_robots)
        self._frames = frames
        self._publish = publish
        self._sent_stamp = 0.0
        self._packed = b""
        self._published: dict[str, StampedPose] = {}
        self.refused = 0
        self.wrong_link = 0
        self.sent = 0

    async def run(self, source: MapSource | None, transports: list[Transport]) -> None:
        """Poll the source, send this robot's pose, and hand every change to the outputs."""
        while True:
            pose = source.pose() if source is not None else None
            if pose is not None:
                if pose.stamp > self._sent_stamp:
                    self.book.offer(self.robot, pose, time.time())
                    self._packed = self._pack(pose)
                    self._sent_stamp = pose.stamp
                # The latest pose goes out at each link's period even when the robot stands still,
                # so a peer that joins later (or lost one to the radio) still learns where it is.
                now = asyncio.get_running_loop().time()
                went = [t.send_pose(self._packed, now) for t in transports]
                if any(went):
                    self.sent += 1
            if self.book.poses != self._published:
                self._published = dict(self.book.poses)
                self._publish(self._published, self._frames())
            await asyncio.sleep(POLL_S)

    def _pack(self, pose: StampedPose) -> bytes:
        msg = PoseMessage(self.fleet, self.robot, pose.stamp, pose.pose)
        # Ed25519 signing takes tens of microseconds: cheap enough for the loop at this rate.
        return (msg.signed(self.identity) if self.identity is not None else msg).pack()

    async def received(self, ev: PoseReceived) -> None:
        """A peer's pose message: verified in a worker thread, bound to its link, newest wins."""
        try:
            msg = await asyncio.to_thread(unpack_pose, ev.data, roster=self.roster, fleet=self.fleet)
        except EnvelopeError as exc:  # SignatureError included
            self.refused += 1
            log.debug("dropped pose from %s: %s", ev.peer, exc)
            return
        if msg.robot != ev.peer or msg.robot == self.robot:
            # a robot may speak only for itself: over uwb the link id names the sender
            self.wrong_link += 1
            return
        if not self.roster.admits(msg.robot):  # revoked while it was checked
            self.refused += 1
            return
        self.book.offer(msg.robot, msg.stamped, time.time())

    def forget(self, robot: str) -> None:
        """Drop ``robot``'s last pose (revoked): it is no longer published or shown."""
        self.book.poses.pop(robot, None)

    def status(self, now: float) -> dict[str, Any]:
        """Each robot's position for ``mapd status``: in its map frame, and in the fleet frame when placed."""
        frames = self._frames()
        robots: dict[str, Any] = {}
        for robot, sp in sorted(self.book.poses.items()):
            entry: dict[str, Any] = {"map": _xyyaw(sp.pose), "age_s": round(max(0.0, now - sp.stamp), 1)}
            if robot in frames:
                entry["fleet"] = _xyyaw(compose(frames[robot], sp.pose))
            robots[robot] = entry
        return {
            "robots": robots,
            **self.book.stats(),
            "sent": self.sent,
            "refused": self.refused,
            "wrong_link": self.wrong_link,
        }


def _xyyaw(p: Pose2D) -> list[float]:
    return [round(p.x, 3), round(p.y, 3), round(p.yaw, 3)]  # m, m, rad (REP-103)
