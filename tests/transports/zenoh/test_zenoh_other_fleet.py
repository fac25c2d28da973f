"""Robots whose ``robot.fleet`` differ, on one zenoh network: said once per fleet, shown in stats.

Before: every key lives under ``mapd/<fleet>/``, so two such robots saw nothing of each other and
nothing said why; each just ran alone (measured with two real sessions on loopback, fleets ``f1``
and ``f2``: no event, no log line, no counter on either side). Now each link declares a token
``mapd/@fleets/<fleet>/<robot>`` and watches only those, so each side says the other fleet once
and shows it in ``other_fleets``, which is no FAULT (fleets may share a network on purpose).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.daemon.headline import link_faults, status_line
from mapd.demo.ports import free_port
from mapd.envelope import Envelope
from mapd.grid import Pose2D
from transports.base import PeerUp, Received, TransportContext, TransportEvent
from transports.zenoh import fleets, keys
from transports.zenoh.fleets import OtherFleets
from transports.zenoh.link import ZenohTransport

LOGGER = "transports.zenoh.link"


def run(coro) -> None:  # type: ignore[no-untyped-def]
    asyncio.run(asyncio.wait_for(coro, 40))


class Robot:
    """One robot's zenoh transport of ``fleet`` (the conftest's Bot is of one fleet only)."""

    def __init__(self, robot: str, fleet: str, *, listen: str | None = None, connect: str | None = None):
        self.events: list[TransportEvent] = []
        opts = ZenohTransport.Options(
            multicast_scouting=False, listen=[listen] if listen else [], connect=[connect] if connect else []
        )
        ctx = TransportContext(robot=robot, fleet=fleet, max_message_bytes=1 << 20, emit=self.events.append)
        self.t = ZenohTransport(opts, ctx)


async def wait(cond: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    """Poll ``cond`` until it holds; fail naming ``what`` after ``timeout``."""
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"not met in {timeout} s: {what}"
        await asyncio.sleep(0.02)


def shown(r: Robot) -> dict[str, list[str]]:
    """``other_fleets`` of ``r``'s link, each fleet's robots sorted (they are kept as they came)."""
    return {f: sorted(robots) for f, robots in r.t.stats()["other_fleets"].items()}


def said(caplog: pytest.LogCaptureFixture, *words: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == LOGGER and all(w in r.getMessage() for w in words)]


def envelope(fleet: str, robot: str, version: int) -> Envelope:
    return Envelope(
        fleet=fleet,
        robot=robot,
        version=version,
        base_version=0,
        codec="raw",
        width=4,
        height=3,
        resolution=0.05,
        origin=Pose2D(0.0, 0.0, 0.0),
        payload=b"cells",
    )


def test_robots_of_two_fleets_say_each_other_once_and_show_it_as_no_fault(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)

    async def main() -> None:
        ep = f"tcp/127.0.0.1:{free_port()}"
        a = Robot("a", "f1", listen=ep)
        b = Robot("b", "f2", connect=ep)
        c = Robot("c", "f2", connect=ep)
        same = Robot("s", "f1", connect=ep)
        started = [a, b, c, same]
        try:
            for r in started:
                await r.t.start()
            await wait(lambda: shown(a) == {"f2": ["b", "c"]}, "a shows b and c")
            await wait(lambda: shown(b) == {"f1": ["a", "s"]}, "b shows a and s")
            await wait(lambda: shown(same) == {"f2": ["b", "c"]}, "s shows b and c")
            await wait(lambda: PeerUp("zenoh", "s") in a.events, "a meets s, of its own fleet")
            # Each side says the other fleet once (two robots of f2, one line), naming a robot of
            # it and both fixes, as a WARNING; the robot of its own fleet is not said.
            on_a = said(caplog, "this robot 'a' is of fleet 'f1'")
            assert len(on_a) == 1 and on_a[0].levelno == logging.WARNING, [r.getMessage() for r in on_a]
            line = on_a[0].getMessage()
            assert "fleet 'f2'" in line and ("robot 'b'" in line or "robot 'c'" in line)
            assert "set robot.fleet the same on every robot of one fleet" in line.lower()
            assert "meant to be apart" in line
            assert len(said(caplog, "this robot 'b' is of fleet 'f2'", "fleet 'f1'")) == 1
            assert not said(caplog, "this robot 'a'", "fleet 'f1' is on this zenoh network")
            st = a.t.stats()
            assert st["other_fleet_tokens"] == 2
            # No fault: fleets may share a network on purpose (mapd status shows no FAULTS line).
            assert link_faults(st) == []
            # Never another fleet's traffic: b's map and a's are heard by neither.
            b.t.offer(envelope("f2", "b", 1))
            a.t.offer(envelope("f1", "a", 1))
            await wait(lambda: b.t.stats()["updates_tx"] == 1 and a.t.stats()["updates_tx"] == 1, "puts out")
            await wait(lambda: same.t.stats()["updates_rx"] == 1, "s, of a's fleet, hears a's map")
            assert not [e for e in a.events if isinstance(e, Received)] and a.t.stats()["bytes_rx"] == 0
            assert {e.peer for e in b.events if isinstance(e, PeerUp)} == {"c"}  # its own fleet's only
            assert b.t.stats()["bytes_rx"] == 0
            # b leaves: a shows what is there now; b back (a restart) is not said again.
            await b.t.close()
            await wait(lambda: a.t.stats()["other_fleets"] == {"f2": ["c"]}, "a drops b")
            await c.t.close()
            await wait(lambda: a.t.stats()["other_fleets"] == {}, "a drops c")
            again = Robot("b", "f2", connect=ep)
            started.append(again)
            await again.t.start()
            await wait(lambda: a.t.stats()["other_fleets"] == {"f2": ["b"]}, "a sees b again")
            assert len(said(caplog, "this robot 'a' is of fleet 'f1'")) == 1
        finally:
            for r in reversed(started):
                await r.t.close()

    run(main())


def test_a_flood_of_made_up_fleet_tokens_keeps_and_says_a_bounded_few(
    zk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """Anyone on the network can declare tokens: 40 fleets of 12 robots cost a bounded few names
    in stats and at most MAX_FLEETS_SAID lines, and every one is still counted."""
    caplog.set_level(logging.INFO, logger=LOGGER)
    n_fleets, n_robots = 40, 12

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep])
            with zk.raw_session(f.ep, watch="a") as raw:
                await wait(lambda: bool(raw.seen), "the raw session sees a")
                tokens = [
                    raw.session.liveliness().declare_token(keys.fleet_presence_key(f"x{i}", f"r{j}"))
                    for i in range(n_fleets)
                    for j in range(n_robots)
                ]
                # Not fleet tokens: ignored (wrong shape; a robot name no fleet id can hold).
                tokens.append(raw.session.liveliness().declare_token("mapd/@fleets/x0"))
                tokens.append(raw.session.liveliness().declare_token("mapd/@fleets/x0/r0/extra"))
                total = n_fleets * n_robots
                await wait(lambda: a.t.stats()["other_fleet_tokens"] == total, f"{total} tokens counted")
                shown = a.t.stats()["other_fleets"]
                assert len(shown) == fleets.MAX_FLEETS_SHOWN
                assert all(len(r) == fleets.MAX_ROBOTS_SHOWN for r in shown.values()), shown
                assert len(said(caplog, "is on this zenoh network")) == fleets.MAX_FLEETS_SAID
                for tok in tokens:
                    tok.undeclare()
                await wait(lambda: a.t.stats()["other_fleets"] == {}, "all gone")
                assert a.t.stats()["other_fleet_tokens"] == total

    run(main())


def test_other_fleets_bookkeeping() -> None:
    """The rules alone: own fleet and malformed keys ignored, one line per fleet, bounds kept."""
    o = OtherFleets("f1", "a")
    assert o.seen(keys.fleet_presence_key("f1", "b"), True) is None  # one of ours
    assert o.seen("mapd/f2/b", True) is None and o.seen("mapd/@fleets/f2", True) is None
    line = o.seen(keys.fleet_presence_key("f2", "b"), True)
    assert line is not None and "robot 'b' of fleet 'f2'" in line and "robot 'a' is of fleet 'f1'" in line
    assert o.seen(keys.fleet_presence_key("f2", "c"), True) is None  # same fleet: said already
    assert o.seen(keys.fleet_presence_key("f2", "b"), False) is None
    assert o.stats() == {"other_fleets": {"f2": ["c"]}, "other_fleet_tokens": 2}
    assert o.seen(keys.fleet_presence_key("f2", "c"), False) is None
    assert o.seen(keys.fleet_presence_key("f2", "d"), True) is None  # gone and back: once per run
    lines = [o.seen(keys.fleet_presence_key(f"g{i}", "r"), True) for i in range(fleets.MAX_FLEETS_SAID + 5)]
    # f2 and MAX_FLEETS_SAID - 1 of these said, shown or not; the rest only counted
    assert sum(x is not None for x in lines) == fleets.MAX_FLEETS_SAID - 1
    st = o.stats()
    assert len(st["other_fleets"]) == fleets.MAX_FLEETS_SHOWN and st["other_fleet_tokens"] == 3 + 21
    # a vanishing token of a fleet never kept changes nothing
    assert o.seen(keys.fleet_presence_key("g20", "r"), False) is None and o.stats() == st


@pytest.mark.slow
def test_two_daemons_of_different_fleets_say_so_once_in_the_log_and_status(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    """Two ``mapd run`` over zenoh on loopback, robot1's config with ``fleet = "other"``. Before,
    both ran alone for as long as they ran: no line in either log, nothing in ``mapd status``."""
    from mapd.commands.status_text import render_status

    f = fk.demo_fleet(tmp_path, 2, duration=30.0, edit={"robot1": lambda c: c["robot"].update(fleet="other")})
    f.start()
    try:

        def seen(s: dict[str, Any], who: str, fleet: str, other: str) -> bool:
            zenoh = s.get(who, {}).get("links", {}).get("zenoh", {})
            return zenoh.get("other_fleets") == {fleet: [other]}

        snaps = fk.wait_for(
            lambda s: seen(s, "robot0", "other", "robot1") and seen(s, "robot1", "demo", "robot0"), 30, f
        )
        # No fault: fleets apart on purpose share networks (robot0 alone, but as it was told).
        assert not status_line(snaps["robot0"]).startswith("FAULTS"), status_line(snaps["robot0"])
        assert "other fleets on this network: other (robot1)" in render_status(snaps["robot0"])
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    for me, fleet, other in (("robot0", "other", "robot1"), ("robot1", "demo", "robot0")):
        log = (f.run_dir / me / "daemon.log").read_text(errors="replace")
        lines = [ln for ln in log.splitlines() if "is on this zenoh network" in ln]
        assert len(lines) == 1 and "WARNING" in lines[0], lines
        assert f"robot '{other}' of fleet '{fleet}'" in lines[0], lines
        assert "Traceback" not in log
