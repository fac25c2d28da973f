"""Robots whose zenoh router goes away mid-run (SIGKILL) and comes back on the same port.

zenoh reconnects a client to its router by itself; meanwhile the robots reached through it are gone
(``PeerDown``), and when it is back they meet again as late joiners (each queries the others' latest
keyframe). Before, the daemon said nothing at all, neither when the router went nor when it came
back, and ``mapd status`` had nothing that told a lost router from peers that left: now the loss is
said once and the return once, however many tries zenoh makes in between, and the link's
``router_connected`` is False meanwhile (:mod:`transports.zenoh.routers`).

With real router processes: two clients of one router, killed for 5 s and then restarted at
once, while the robots go on offering maps (nothing queues up); two routers in a mesh, one of which
goes (only its robots are cut off, and rejoin through its restart); and three ``mapd run`` daemons
whose router is gone for 20 s, ten times their keyframe queries' timeout: they converge on each
other's newest maps and go back to deltas. (The publisher's in-flight timeout, 30 s, plays no part:
the peers' tokens vanish with the router, which settles every offer waiting for them at once.)
"""

from __future__ import annotations

import asyncio
import logging
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.data import REPO_ROOT
from mapd.envelope import Envelope
from transports.base import PeerDown
from transports.zenoh import routers
from transports.zenoh.routers import RouterLink

ROUTER_CONFIG = REPO_ROOT / "deploy" / "zenoh" / "router.json5"
LOST = "lost the connection to router"
BACK = "connected to a router again"
#: Bytes of each map offered while the router is down: 300 of them would hold 150 MiB if queued.
BIG = 512 * 1024


class RouterProc:
    """``python -m transports.zenoh.router`` on one endpoint, killed and started again by the test."""

    def __init__(self, listen: str, config: Path = ROUTER_CONFIG) -> None:
        self.cmd = [
            sys.executable,
            "-m",
            "transports.zenoh.router",
            "--config",
            str(config),
            "--listen",
            listen,
        ]
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        """Start it and wait until it listens."""
        self.proc = subprocess.Popen(
            self.cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO_ROOT
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        assert line.startswith("listening on"), line

    def kill(self) -> None:
        """SIGKILL: no goodbye to anyone, as a crash or a power cut of its host (its sockets close)."""
        assert self.proc is not None and self.proc.poll() is None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        """End it however the test ended."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def _lines(caplog: pytest.LogCaptureFixture, words: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if words in r.getMessage()]


def _rss_mib() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS in /proc/self/status")


def _has(bot: Any, robot: str, version: int) -> bool:
    return any(v == version for _, v, _ in bot.received(robot))


def test_the_last_router_lost_and_the_first_back_are_each_said_once() -> None:
    link = RouterLink()
    assert link.connected is None  # no router yet: a fleet of peers says nothing
    assert link.opened("aaaa1111bbbb", 0.0) is None  # the router the session opened with
    assert link.connected is True
    lost = link.closed("aaaa1111bbbb", 100.0)
    assert lost is not None and lost[0] == logging.WARNING
    assert "lost the connection to router aaaa1111;" in lost[1]
    assert link.closed("aaaa1111bbbb", 101.0) is None and link.connected is False
    back = link.opened("cccc2222dddd", 121.0)  # a restarted router has another id
    assert back is not None and back[0] == logging.INFO
    assert "again after 21 s (router cccc2222)" in back[1]
    assert link.opened("cccc2222dddd", 122.0) is None and link.connected is True
    # connected to two routers (a peer in a mesh): losing one of them is no loss worth a line
    assert link.opened("eeee3333", 130.0) is None
    assert link.closed("cccc2222dddd", 131.0) is None and link.connected is True
    # A router that flaps (or anyone who opens transports as a router) says one pair a minute;
    # the others go to DEBUG, counted.
    lost, back = link.closed("eeee3333", 140.0), link.opened("eeee3333", 141.0)
    assert lost is not None and lost[0] == logging.DEBUG and "(loss 2;" in lost[1]
    assert back is not None and back[0] == logging.DEBUG
    lost = link.closed("eeee3333", 100.0 + routers.SAID_EVERY_S)
    assert lost is not None and lost[0] == logging.WARNING and link.losses == 3


@pytest.mark.slow  # a router process
def test_clients_say_a_lost_router_once_and_its_return_once_and_catch_up(
    zk: SimpleNamespace, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    caplog.set_level(logging.INFO, logger="transports.zenoh.link")
    monkeypatch.setattr(routers, "SAID_EVERY_S", 0.0)  # two outages within a minute, both said
    router = RouterProc(zk.endpoint(zk.free_port()))
    router.start()
    ep = router.cmd[-1]

    def env(version: int, base: int = 0, payload: bytes = b"cells") -> Envelope:
        return zk.envelope("a", version, base, payload)

    async def main() -> None:
        async with zk.fleet() as f:
            # unsigned, so that peers() lists every token up (a signed fleet waits for a signed message)
            a = await f.start("a", connect=[ep], mode="client")
            b = await f.start("b", connect=[ep], mode="client")
            await zk.meet(a, b, timeout=20)
            assert a.t.stats()["router_connected"] is True and b.t.stats()["router_connected"] is True
            v = 1
            a.offer(env(v))
            await b.wait(lambda: _has(b, "a", v), 10)
            for quick in (False, True):  # down for 5 s, then killed and started again at once
                router.kill()
                await b.wait(
                    lambda: (
                        not a.t.peers()
                        and not b.t.peers()
                        and a.t.stats()["router_connected"] is False
                        and b.t.stats()["router_connected"] is False
                    ),
                    10,
                )
                assert PeerDown("zenoh", "a") in b.events
                if not quick:
                    # The robot goes on making maps: each offer replaces the one before (latest
                    # wins), so neither mapd nor zenoh holds them while no router takes them.
                    before = _rss_mib()
                    end = time.monotonic() + 5.0  # several of zenoh's tries to reconnect
                    while time.monotonic() < end:
                        v += 1
                        a.offer(env(v, v - 1, bytes([v % 251]) * BIG))
                        a.t.ack("b", v)
                        a.t.send_pose(b"pose", time.monotonic())
                        assert a.t._jobs is not None and a.t._jobs.pending() <= 3  # an update, an ack, a pose
                        await asyncio.sleep(0.01)
                    assert v > 100
                    assert _rss_mib() - before < 64, f"{v} maps of {BIG} bytes offered"
                    assert a.t.stats()["errors"] == 0
                # Its newest map, a keyframe, then nothing newer: b gets it when they meet again
                # (its late-join query), not only with the next map a makes.
                v += 1
                a.offer(env(v))
                router.start()
                await b.wait(lambda v=v: _has(b, "a", v), 20)
                await b.wait(lambda: b.t.peers() == ["a"] and a.t.peers() == ["b"], 10)
                assert a.t.stats()["router_connected"] is True and b.t.stats()["router_connected"] is True
                # ... and a delta on that version, which both hold, is taken as it is
                v += 1
                a.offer(env(v, v - 1))
                await b.wait(lambda v=v: _has(b, "a", v), 10)
            versions = [ver for _, ver, _ in b.received("a")]
            assert versions == sorted(versions)  # never one older after a newer
            assert b.t.stats()["gaps"] == 0
            # One line each way per robot and outage, however many tries zenoh made meanwhile.
            lost, back = _lines(caplog, LOST), _lines(caplog, BACK)
            assert len(lost) == 4 and all(r.levelno == logging.WARNING for r in lost), lost
            assert len(back) == 4 and all(r.levelno == logging.INFO for r in back), back
            assert a.t.stats()["router_losses"] == 2 and b.t.stats()["router_losses"] == 2

    try:
        asyncio.run(main())
    finally:
        router.stop()
    # closing the sessions is no loss of the router
    assert len(_lines(caplog, LOST)) == 4


@pytest.mark.slow  # two router processes
def test_a_mesh_router_that_goes_cuts_off_only_its_robots(
    tmp_path: Path, zk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="transports.zenoh.link")
    first = RouterProc(zk.endpoint(zk.free_port()))
    first.start()
    conf = tmp_path / "second.json5"
    conf.write_text(  # the second router of a mesh connects to the first, as router.json5 says
        f'{{ mode: "router", connect: {{ endpoints: ["{first.cmd[-1]}"] }}, '
        "scouting: { multicast: { enabled: false } } }"
    )
    second = RouterProc(zk.endpoint(zk.free_port()), conf)
    second.start()

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", connect=[first.cmd[-1]], mode="client")
            b = await f.start("b", connect=[first.cmd[-1]], mode="client")
            c = await f.start("c", connect=[second.cmd[-1]], mode="client")
            await zk.meet(a, b, c, timeout=30)
            second.kill()
            await c.wait(lambda: not c.t.peers() and c.t.stats()["router_connected"] is False, 10)
            await a.wait(lambda: a.t.peers() == ["b"], 10)
            assert a.t.stats()["router_connected"] is True and b.t.stats()["router_connected"] is True
            # a and b, on the router still there, go on exchanging
            a.offer(zk.envelope("a", 1))
            await b.wait(lambda: _has(b, "a", 1), 10)
            c.offer(zk.envelope("c", 1))  # made while cut off
            await asyncio.sleep(2.0)  # zenoh tries to reconnect c meanwhile
            assert not _has(c, "a", 1)
            assert len(_lines(caplog, LOST)) == 1  # c's: a and b lost no router
            second.start()  # c's robots rejoin through it: each gets the other's newest
            await c.wait(lambda: _has(c, "a", 1), 20)
            await a.wait(lambda: _has(a, "c", 1), 20)
            await b.wait(lambda: _has(b, "c", 1), 20)
            assert c.t.stats()["router_connected"] is True
            assert len(_lines(caplog, LOST)) == 1 and len(_lines(caplog, BACK)) == 1

    try:
        asyncio.run(main())
    finally:
        second.stop()
        first.stop()


def _zenoh(s: dict[str, Any]) -> dict[str, Any]:
    return s["links"]["zenoh"]


@pytest.mark.slow  # a router and three daemons
def test_daemons_ride_out_a_router_gone_for_20_s(tmp_path: Path, fk: SimpleNamespace) -> None:
    from mapd.codec.api import warm_up
    from mapd.daemon.versions import split

    warm_up("lossless")  # compiled once into the cache the daemons read, not by each in its window
    f = fk.router_fleet(tmp_path)
    assert f.router is not None
    cmd = [str(x) for x in f.router.args]  # to start it again on the same port
    pairs = [(a, b) for a in f.names for b in f.names if a != b]

    def logged(name: str, words: str) -> int:
        return (f.run_dir / name / "daemon.log").read_text(errors="replace").count(words)

    f.start()
    try:
        snaps = fk.wait_for(lambda s: len(s) == 3 and all(fk.held(s, a, b) >= 2 for a, b in pairs), 60, f)
        pids = {n: s["pid"] for n, s in snaps.items()}
        queries = {n: _zenoh(s)["keyframe_queries"] for n, s in snaps.items()}
        f.router.send_signal(signal.SIGKILL)
        f.router.wait(10)
        killed = time.monotonic()
        # mapd status while it is down: every peer gone, and the router said lost
        down = fk.wait_for(
            lambda s: (
                len(s) == 3
                and all(
                    _zenoh(x)["router_connected"] is False
                    and _zenoh(x)["peers"] == []
                    and all(p["present"] is False for p in x["peers"].values())
                    for x in s.values()
                )
            ),
            15,
            f,
        )
        made = {n: split(s["source"]["version"])[1] for n, s in down.items()}
        text = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--socket", str(f.run_dir / "robot0" / "run" / "mapd.sock")],
            capture_output=True, text=True, timeout=30,
        ).stdout  # fmt: skip
        assert "gone" in text and "FAULTS router lost (zenoh reconnects by itself)" in text, text
        time.sleep(max(0.0, 20.0 - (time.monotonic() - killed)))
        at_return = {n: split(s["source"]["version"])[1] for n, s in f.status().items()}
        assert all(at_return[n] > made[n] for n in f.names), (made, at_return)  # maps made meanwhile
        f.router = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert f.router.stdout is not None and f.router.stdout.readline().startswith("listening on")
        # every robot holds every other's map as new as it was at the return, fused too, within a
        # few map periods (1.25 s): their late-join queries fetch them
        back = fk.wait_for(
            lambda s: (
                len(s) == 3
                and all(
                    fk.held(s, a, b) >= at_return[b]
                    and split(s[a]["fusion"]["robots"].get(b, {}).get("version") or 0)[1] >= at_return[b]
                    for a, b in pairs
                )
            ),
            20,
            f,
        )
        # deltas go again, on versions both sides hold: no refused map, no undecodable one
        deltas = {n: s["codec"]["deltas"] for n, s in back.items()}
        after = fk.wait_for(
            lambda s: len(s) == 3 and all(s[n]["codec"]["deltas"] >= deltas[n] + 2 for n in f.names), 20, f
        )
        for name, s in after.items():
            assert s["pid"] == pids[name]  # no daemon restarted
            assert _zenoh(s)["router_losses"] == 1
            assert _zenoh(s)["router_connected"] is True and sorted(_zenoh(s)["peers"]) == sorted(
                n for n in f.names if n != name
            )
            c = s["counters"]
            assert c["refused_versions"] == 0 and c["decode_errors"] == 0 and c["keyframe_requests"] == 0, c
            # one late-join query per peer when they met again, then none: no endless keyframe requests
            assert _zenoh(s)["keyframe_queries"] - queries[name] <= 2 * 2, _zenoh(s)
            assert all(o["age_s"] < 10 for o in s["offers"].values()), s["offers"]  # none stuck in flight
            # the loss said once and the return once, not once per zenoh try
            assert logged(name, LOST) == 1 and logged(name, BACK) == 1, name
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0, "robot2": 0}
