"""Robot poses between daemons: sent signed, taken only from the robot they name, shown and output."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd import config as configmod
from mapd.daemon.server import Daemon
from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.identity import read_identity
from mapd.outputs.base import GlobalUpdate, Output, OutputContext, PoseUpdate
from mapd.poses import PoseMessage
from mapd.sources.base import MapSource, SourceContext
from transports.base import PoseReceived


class PoseSource(MapSource):
    """No maps, a pose the test moves."""

    name = "pose"

    def __init__(self, robot: str) -> None:
        super().__init__(None, SourceContext(robot=robot))
        self.now: StampedPose | None = None

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        await asyncio.Event().wait()
        yield  # type: ignore[misc]  # never: an async generator that waits forever

    def pose(self) -> StampedPose | None:
        return self.now


class Capture(Output):
    """An output that keeps what it is given."""

    name = "capture"

    def __init__(self) -> None:
        super().__init__(None, OutputContext(robot="robot1", fleet="default"))
        self.updates: list[PoseUpdate] = []

    def publish(self, update: GlobalUpdate) -> None:
        pass

    def publish_poses(self, update: PoseUpdate) -> None:
        self.updates.append(update)


def daemon(tmp_path: Path, dk: SimpleNamespace, robot: str, channel: str) -> tuple[Daemon, PoseSource]:
    cfg = configmod.load(
        dk.write_config(
            tmp_path,
            robot,
            extra='[transports]\nuse = ["virtual"]\n',
            **{"transports.virtual": f'channel = "{channel}"\npose_period_s = 0.2'},
        )
    )
    source = PoseSource(robot)
    return Daemon(cfg, source=source), source


def test_poses_travel_signed_and_only_as_themselves(tmp_path: Path, dk: SimpleNamespace) -> None:
    async def main() -> None:
        channel = dk.channel()
        d0, s0 = daemon(tmp_path, dk, "robot0", channel)
        d1, s1 = daemon(tmp_path, dk, "robot1", channel)
        cap = Capture()
        d1.outputs.append(cap)
        tasks = [asyncio.create_task(d.run()) for d in (d0, d1)]
        try:
            await dk.wait_for(lambda: bool(d1.transports) and d1.transports[0].peers() == ["robot0"], 20)
            s0.now = StampedPose(Pose2D(1.0, 2.0, 0.5), time.time())
            s1.now = StampedPose(Pose2D(-3.0, 0.0, 0.0), time.time())
            both = {"robot0", "robot1"}
            await dk.wait_for(
                lambda: set(d1.poses.book.poses) == both, 10, "robot0's pose at robot1, and its own"
            )
            st = d1.snapshot()["poses"]
            assert st["robots"]["robot0"]["map"] == [1.0, 2.0, 0.5]
            assert st["robots"]["robot1"]["map"] == [-3.0, 0.0, 0.0]  # its own, too
            # the outputs got both robots' poses, off the loop
            await dk.wait_for(lambda: any(len(u.poses) == 2 for u in cap.updates), 10, "poses at the outputs")
            # the robot moves: the newer pose replaces the older
            s0.now = StampedPose(Pose2D(4.0, 2.0, 0.5), time.time())
            await dk.wait_for(lambda: d1.poses.book.poses["robot0"].pose.x == 4.0, 10, "the newer pose")

            # robot2 holds its own key and speaks for robot0: refused either way it tries
            r2 = read_identity(tmp_path / "keys" / "robot2.key", "robot2")
            lie = PoseMessage("default", "robot0", time.time() + 1, Pose2D(99, 99, 0))
            forged = lie._body() + r2.sign(b"mapd-pose/1\x00" + lie._body())
            await d1.poses.received(PoseReceived("virtual", "robot0", forged))
            own = PoseMessage("default", "robot2", time.time(), Pose2D(7, 7, 0)).signed(r2).pack()
            await d1.poses.received(PoseReceived("virtual", "robot0", own))  # its own pose, on robot0's link
            await d1.poses.received(PoseReceived("virtual", "robot0", lie.pack()))  # unsigned
            st = d1.snapshot()["poses"]
            assert st["robots"]["robot0"]["map"][0] == 4.0 and "robot2" not in st["robots"]
            assert st["refused"] == 2 and st["wrong_link"] == 1
            # a replay of an old, genuine pose is older than the one held
            old = PoseMessage("default", "robot0", 1.0, Pose2D(5, 5, 0))
            r0 = read_identity(tmp_path / "keys" / "robot0.key", "robot0")
            await d1.poses.received(PoseReceived("virtual", "robot0", old.signed(r0).pack()))
            assert d1.poses.book.poses["robot0"].pose.x == 4.0 and d1.poses.book.refused_old >= 1
        finally:
            for d in (d0, d1):
                d.request_stop()
            await asyncio.gather(*tasks)

    asyncio.run(main())


def test_a_pose_whose_robot_is_revoked_while_it_is_checked_is_dropped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from mapd.daemon import poses as posesmod
    from mapd.daemon.poses import PoseRelay
    from mapd.identity import Identity, Roster

    r0 = Identity.generate("robot0")
    roster = Roster({"robot0": r0.public_key})
    relay = PoseRelay(
        "robot1",
        "default",
        identity=None,
        roster=roster,
        max_robots=8,
        frames=dict,
        publish=lambda a, b: None,
    )
    real = posesmod.unpack_pose

    def revoked_meanwhile(*args: object, **kw: object) -> object:
        msg = real(*args, **kw)  # type: ignore[arg-type]
        roster.adopt(Roster({}))  # systemctl reload on the loop, while this ran on its worker
        return msg

    monkeypatch.setattr(posesmod, "unpack_pose", revoked_meanwhile)
    pose = PoseMessage("default", "robot0", time.time(), Pose2D(1, 2, 0)).signed(r0).pack()
    asyncio.run(relay.received(PoseReceived("virtual", "robot0", pose)))
    assert "robot0" not in relay.book.poses and relay.refused == 1
