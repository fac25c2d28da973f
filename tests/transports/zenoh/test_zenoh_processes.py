"""Robots as separate processes (tests/transports/zenoh/zenoh_robot_proc.py), and a clean exit on SIGTERM."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from transports.base import PeerDown, PeerUp, Received

SCRIPT = Path(__file__).with_name("zenoh_robot_proc.py")
ROOT = Path(__file__).resolve().parents[2]
SEED = bytes(range(100, 132))

pytestmark = pytest.mark.slow


class Proc:
    """A robot process: JSON commands in, JSON events out."""

    def __init__(self, robot: str, proc: asyncio.subprocess.Process) -> None:
        self.robot = robot
        self.proc = proc
        self.lines: list[dict[str, Any]] = []

    @classmethod
    async def spawn(cls, robot: str, *args: str) -> Proc:
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            str(SCRIPT),
            "--robot",
            robot,
            *args,
            cwd=ROOT,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
        )
        p = cls(robot, proc)
        await p.expect(lambda e: e["event"] == "ready", timeout=15)
        return p

    async def expect(
        self, pred: Callable[[dict[str, Any]], bool], timeout: float = 5.0, since: int = 0
    ) -> dict[str, Any]:
        """The first event from line ``since`` on that matches, reading more as needed."""
        for e in self.lines[since:]:
            if pred(e):
                return e
        assert self.proc.stdout is not None
        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise AssertionError(f"{self.robot}: no matching event in {timeout} s; saw {self.lines}")
            try:
                raw = await asyncio.wait_for(self.proc.stdout.readline(), left)
            except TimeoutError:
                continue
            if not raw:
                raise AssertionError(f"{self.robot}: exited ({self.proc.returncode}); saw {self.lines}")
            e = json.loads(raw)
            self.lines.append(e)
            if pred(e):
                return e

    def send(self, **cmd: Any) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write((json.dumps(cmd) + "\n").encode())

    async def stats(self) -> dict[str, Any]:
        since = len(self.lines)
        self.send(stats=True)
        return await self.expect(lambda e: e["event"] == "stats", since=since)

    async def stop(self) -> int:
        if self.proc.returncode is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(self.proc.wait(), 5)
            except TimeoutError:
                self.proc.kill()
                await self.proc.wait()
        return self.proc.returncode or 0


def got(version: int, base: int, peer: str = "a") -> Callable[[dict[str, Any]], bool]:
    return lambda e: e == {"event": "Received", "peer": peer, "version": version, "base": base}


def test_three_robot_processes(zk) -> None:
    async def main() -> None:
        pa, pb, pc = (zk.endpoint(zk.free_port()) for _ in range(3))
        key = ["--fleet-seed", SEED.hex()]
        a = await Proc.spawn("a", "--listen", pa, *key)
        procs = [a]
        try:
            b = await Proc.spawn("b", "--listen", pb, "--connect", pa, *key)
            procs.append(b)
            await b.expect(lambda e: e == {"event": "PeerUp", "peer": "a"})
            a.send(offer=[1, 0])
            await b.expect(got(1, 0))
            # c joins late: it gets a's keyframe by query, then follows the stream like b.
            c = await Proc.spawn("c", "--listen", pc, "--connect", pa, "--connect", pb, *key)
            procs.append(c)
            await c.expect(got(1, 0))
            await a.expect(lambda e: e == {"event": "Delivered", "peer": "c", "robot": "a", "version": 1})
            await a.expect(lambda e: e == {"event": "Delivered", "peer": "b", "robot": "a", "version": 1})
            a.send(offer=[2, 1])
            await b.expect(got(2, 1))
            await c.expect(got(2, 1))
            await a.expect(lambda e: e == {"event": "Delivered", "peer": "c", "robot": "a", "version": 2})
            # A lost update: 3 never reaches anyone, 4 is coded on it; both recover by query.
            since = len(a.lines)
            a.send(offer=[4, 3])
            for peer in ("b", "c"):  # their queries tell a's daemon to send a keyframe next
                await a.expect(
                    lambda e, p=peer: e["event"] == "KeyframeNeeded" and e["peer"] == p, since=since
                )
            a.send(offer=[5, 0])
            await b.expect(got(5, 0))
            await c.expect(got(5, 0))
            for p in (b, c):
                st = await p.stats()
                assert st["gaps"] == 1 and st["bad_signature"] == 0
                # b and c hear each other's tokens, but only a signs anything to them (maps); in a
                # signed fleet a token alone does not make a robot one to wait for
                assert st["peer_list"] == ["a"] and st["peers"] == 1
                assert not [e for e in p.lines if e["event"] == "Received" and e["version"] == 4]
            st = await a.stats()
            assert st["peer_list"] == ["b", "c"]  # both acked a's maps, signed
            # c leaves: the others see it go.
            assert await c.stop() == 0
            await a.expect(lambda e: e == {"event": PeerDown.__name__, "peer": "c"})
            await b.expect(lambda e: e == {"event": PeerDown.__name__, "peer": "c"})
        finally:
            for p in procs:
                await p.stop()

    asyncio.run(asyncio.wait_for(main(), 60))


def test_sigterm_with_live_subscriber_exits_within_2s(zk) -> None:
    async def main() -> None:
        ep = zk.endpoint(zk.free_port())
        pub = await zk.Bot("pub", listen=[ep]).start()
        child = await Proc.spawn("sub", "--connect", ep)
        stop = asyncio.Event()

        async def stream() -> None:
            v = 0
            while not stop.is_set():
                v += 1
                pub.offer(zk.envelope("pub", v))
                await asyncio.sleep(0.01)

        feeder = asyncio.create_task(stream())
        try:
            await pub.wait(lambda: PeerUp("zenoh", "sub") in pub.events)
            await child.expect(lambda e: e["event"] == Received.__name__ and e["version"] > 3)
            started = time.monotonic()
            child.proc.send_signal(signal.SIGTERM)
            rc = await asyncio.wait_for(child.proc.wait(), 5)
            took = time.monotonic() - started
            assert rc == 0, child.lines
            assert took < 2.0, f"exit took {took:.2f} s"
            await child.expect(lambda e: e["event"] == "closed", timeout=0.5)
            await pub.wait(lambda: PeerDown("zenoh", "sub") in pub.events, timeout=2.0)
        finally:
            stop.set()
            await feeder
            await child.stop()
            await pub.t.close()

    asyncio.run(asyncio.wait_for(main(), 40))
