"""A peer's map over this robot's ``limits.max_message_bytes``: said once per robot, shown in stats.

Before (two real sessions on loopback, the receiver's limit 64 KiB, the sender's 4 MiB, a 100 KiB
map): the receiver counted it in ``dropped``, among every other malformed sample, and said nothing;
the daemon's look at its links (``LinkRefusals``) reads only ``unadmitted`` and ``bad_signature``,
so no line came from there either, and the sender heard no ack, nothing more. Now the link refuses
it unread, says it once per robot with the size, the limit and the fix, and counts it apart
(``oversize_rx``, ``oversize_from``).
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.identity import Identity, Roster
from transports.base import Received
from transports.zenoh import core as core_mod
from transports.zenoh import keys
from transports.zenoh.core import ZenohCore

LOGGER = "transports.zenoh.link"
LIMIT = 64 << 10


def run(coro) -> None:  # type: ignore[no-untyped-def]
    asyncio.run(asyncio.wait_for(coro, 40))


def said(caplog: pytest.LogCaptureFixture, *words: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == LOGGER and all(w in r.getMessage() for w in words)]


def test_a_map_over_the_limit_is_said_once_with_size_limit_and_fix(
    zk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep])  # 4 MiB: it sends maps b does not take
            b = await f.start("b", connect=[f.ep], max_message_bytes=LIMIT)
            await zk.meet(a, b)
            # Within the cap zenoh is given (the limit plus 64 KiB), so it reaches b's link on any
            # host (larger ones zenoh drops unseen between hosts: see transports.zenoh.session).
            big = [zk.envelope("a", v, payload=bytes(LIMIT + 1000 * v)) for v in (1, 2, 3)]
            for env in big:
                a.offer(env)
                # The largest so far (each is larger; a reply to b's join query may come late)
                await b.wait(lambda env=env: b.t.stats()["oversize_from"].get("a") == len(env.pack()))
            st = b.t.stats()
            assert st["oversize_rx"] >= 3 and st["oversize_from"] == {"a": len(big[-1].pack())}
            assert st["dropped"] == 0 and st["bytes_rx"] == 0 and not b.of(Received)
            lines = said(caplog, "maps of a refused")
            assert len(lines) == 1 and lines[0].levelno == logging.WARNING, [r.getMessage() for r in lines]
            line = lines[0].getMessage()
            size = len(big[0].pack())
            assert f"{size} bytes" in line and f"limits.max_message_bytes ({LIMIT})" in line, line
            assert f"raise it on b to at least {size}" in line and "make a's maps smaller" in line, line
            # A map within the limit is taken as before; a's side says nothing of b's limit.
            a.offer(zk.envelope("a", 4))
            await b.wait(lambda: b.received("a") == [("a", 4, 0)])
            assert not said(caplog, "maps of b refused")

    run(main())


def test_oversize_in_the_core_is_counted_apart_said_once_per_robot_and_bounded(zk: SimpleNamespace) -> None:
    """The sans-I/O rules: the same via ``on_update`` (tools, tests), names bounded, roster first."""
    c = ZenohCore(robot="b", fleet=zk.FLEET, identity=None, roster=Roster.open(), max_message_bytes=2048)
    big = zk.envelope("a", 1, payload=bytes(4096)).pack()
    step = c.on_update(keys.update_key(zk.FLEET, "a"), big, now=0.0)
    assert not step.events and len(step.warnings) == 1 and "maps of a refused" in step.warnings[0]
    assert c.on_update(keys.update_key(zk.FLEET, "a"), big, now=0.0).warnings == []
    # A smaller one later (a late query reply) leaves the largest: what the limit must be raised to
    assert c.oversize("a", 3000).warnings == [] and c.stats()["oversize_from"] == {"a": len(big)}
    robots = [f"r{i}" for i in range(core_mod.MAX_OVERSIZE_SHOWN + 4)]
    lines = [w for r in robots for w in c.oversize(r, 5000).warnings]
    st = c.stats()
    assert len(lines) == core_mod.MAX_OVERSIZE_SHOWN - 1  # "a" took one of the places
    assert len(st["oversize_from"]) == core_mod.MAX_OVERSIZE_SHOWN
    assert st["oversize_rx"] == 3 + len(robots) and st["dropped"] == 0 and st["bytes_rx"] == 0
    # A robot the roster does not admit is refused for that, unread and unsaid.
    signed = ZenohCore(
        robot="b",
        fleet=zk.FLEET,
        identity=None,
        roster=Roster({"a": Identity.generate("a").public_key}),
        max_message_bytes=2048,
    )
    step = signed.on_update(keys.update_key(zk.FLEET, "x"), big, now=0.0)
    assert step.warnings == [] and signed.stats()["unadmitted"] == 1 and signed.stats()["oversize_rx"] == 0


@pytest.mark.slow
def test_a_daemon_says_once_that_a_peers_maps_are_over_its_limit(tmp_path: Path, fk: SimpleNamespace) -> None:
    """Two ``mapd run`` over zenoh on loopback: robot0 (no map of its own) with
    ``limits.max_message_bytes = 1024``, robot1 with the default. Before: robot0's log said nothing
    and its status counted robot1's maps in ``dropped``, among anything malformed."""
    from mapd.commands.status_text import render_status
    from mapd.daemon.headline import status_line

    def limited(cfg: dict[str, Any]) -> None:
        cfg["limits"] = {"max_message_bytes": 1024}
        cfg["source"] = {"use": "none"}  # it sends nothing: only robot1's maps are over a limit

    f = fk.demo_fleet(tmp_path, 2, duration=30.0, edit={"robot0": limited})
    f.start()

    def link(s: dict[str, Any]) -> dict[str, Any]:
        return s.get("robot0", {}).get("links", {}).get("zenoh", {})

    try:
        # (robot1 knows robot0's limit from its token, says so, and does not wait for its ack;
        # robot0 still sees what robot1 sends: one oversize map at least, maybe its keyframe reply)
        snaps = fk.wait_for(lambda s: link(s).get("oversize_rx", 0) >= 1, 30, f)
        st = link(snaps)
        assert list(st["oversize_from"]) == ["robot1"] and st["oversize_from"]["robot1"] > 1024, st
        assert st["dropped"] == 0, st
        # ... and said as a fault (config drift within a fleet), with whose and how big in mapd status
        assert "peer maps over this robot's limits.max_message_bytes refused" in status_line(snaps["robot0"])
        assert "maps over limits.max_message_bytes from robot1 (" in render_status(snaps["robot0"])
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    log = (f.run_dir / "robot0" / "daemon.log").read_text(errors="replace")
    lines = [ln for ln in log.splitlines() if "maps of robot1 refused" in ln]
    assert len(lines) == 1 and "WARNING" in lines[0], lines
    assert "limits.max_message_bytes (1024)" in lines[0] and "raise it on robot0" in lines[0], lines
    assert "Traceback" not in log
