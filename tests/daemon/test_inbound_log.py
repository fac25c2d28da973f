"""What the daemon's receiving half logs about its own maps' offers."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd.daemon.versions import incarnation_at, make
from transports.base import Failed


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
