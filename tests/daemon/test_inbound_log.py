"""What the daemon's receiving half logs about its own maps' offers."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd.daemon.versions import incarnation_at, make
from mapd.envelope import Envelope
from mapd.grid import Pose2D
from mapd.identity import read_identity
from transports.base import Delivered, Failed, Received


def test_a_failed_offer_is_logged_with_the_short_version(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """Audit finding 6: the one line a failed map gets said "update v396599934402428929 to robot1
    failed: deadline", while `mapd status` and the rest of the log say v1."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    version = make(incarnation_at(1.8e9), 1)
    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        asyncio.run(d.inbound.handle(Failed("virtual", "robot1", "robot0", version, "deadline")))
    said = [r.getMessage() for r in caplog.records if "failed" in r.getMessage()]
    assert said == ["update v1 to robot1 failed: deadline"], said


def test_a_map_that_does_not_decode_is_logged_with_the_short_version(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    robot1 = read_identity(tmp_path / "keys" / "robot1.key", "robot1")
    version = make(incarnation_at(time.time() - 60), 4)
    env = Envelope(
        fleet="default", robot="robot1", version=version, base_version=0, codec="raw", width=10,
        height=10, resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"not a raw payload",
    ).signed(robot1)  # fmt: skip
    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        asyncio.run(d.inbound.handle(Received("virtual", "robot1", env.pack())))
    said = [r.getMessage() for r in caplog.records if "decode" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("cannot decode v4 from robot1:"), said


def test_an_offer_failing_again_for_the_same_reason_is_said_once_until_it_goes_through(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """Each version of a map over a peer's limit is refused again: one INFO line each time filled
    a day's log with the same words. The first failure and a change of reason are
    said; repeats go to DEBUG, and the first delivery after them says how many there were."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    versions = [make(incarnation_at(1.8e9), n) for n in (1, 2, 3, 4, 5)]
    over = "refused by peer (over its message limit)"
    events = [
        Failed("virtual", "robot1", "robot0", versions[0], over),
        Failed("virtual", "robot1", "robot0", versions[1], over),
        Failed("virtual", "robot2", "robot0", versions[1], over),  # another peer: said
        Failed("virtual", "robot1", "robot0", versions[2], over),
        Failed("virtual", "robot1", "robot0", versions[3], "deadline"),  # a new reason: said
        Delivered("virtual", "robot1", "robot0", versions[4]),
        Failed("virtual", "robot1", "robot0", versions[4], "deadline"),  # failing anew: said
    ]

    async def feed() -> None:
        for ev in events:
            await d.inbound.handle(ev)

    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        asyncio.run(feed())
    said = [
        r.getMessage()
        for r in caplog.records
        if r.levelno >= logging.INFO and r.getMessage().startswith("update")
    ]
    assert said == [
        f"update v1 to robot1 failed: {over}",
        f"update v2 to robot2 failed: {over}",
        "update v4 to robot1 failed: deadline",
        "update v5 to robot1 delivered after 4 failed offers",
        "update v5 to robot1 failed: deadline",
    ], said
