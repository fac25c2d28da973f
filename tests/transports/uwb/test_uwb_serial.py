"""The asyncio adapter on real serial ports: socat pty pairs joined by the seeded fault relay, and
ports that misbehave (a peer that stops reading, a port that vanishes and comes back): the link must
keep its loop running, say so once, and carry on when the port does."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import shutil
import subprocess
import sys
import threading
import time
import tty
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from mapd.commands.status_text import render_status
from mapd.envelope import Envelope
from mapd.errors import StateError, TransportError
from mapd.grid import Pose2D
from mapd.identity import Identity, Roster
from transports.base import (
    Delivered,
    Failed,
    KeyframeNeeded,
    OnAir,
    PeerRestarted,
    PeerUp,
    Received,
    TransportContext,
    TransportEvent,
)
from transports.uwb import arq, link_port, link_signing, signing
from transports.uwb.faults import Faults
from transports.uwb.link import UwbLink
from transports.uwb.relay import FaultRelay, MediumRelay
from transports.uwb.transport import UwbOptions, UwbTransport

pytestmark = [
    pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed"),
    pytest.mark.timeout(60),
]

RATE = 200_000
NODES = {"alpha": 1, "beta": 2, "gamma": 3}


def envelope(robot: str, version: int, size: int) -> Envelope:
    return Envelope(
        fleet="f",
        robot=robot,
        version=version,
        base_version=0,
        codec="raw",
        width=10,
        height=10,
        resolution=0.05,
        origin=Pose2D(0.0, 0.0, 0.0),
        payload=os.urandom(size),
    )


class Robot:
    """A transport plus the events it emitted."""

    def __init__(
        self,
        name: str,
        port: str,
        *,
        key: bytes | None = None,
        state: Path | None = None,
        identity: Identity | None = None,
        roster: Roster | None = None,
        **kw: Any,
    ):
        self.events: list[TransportEvent] = []
        self.name = name
        ctx = TransportContext(
            robot=name,
            fleet="f",
            link_key=key,
            max_message_bytes=1 << 20,
            emit=self.events.append,
            state_dir=state,
            identity=identity,
            roster=roster if roster is not None else Roster.open(),
        )
        kw.setdefault("link_rate_bps", RATE)
        names = kw.pop("names", list(NODES))
        opts = UwbOptions(port=port, nodes={k: v for k, v in NODES.items() if k in names}, **kw)
        self.t = UwbTransport(opts, ctx)

    def of(self, cls: type) -> list[Any]:
        return [e for e in self.events if isinstance(e, cls)]


@asynccontextmanager
async def started(*robots: Robot) -> AsyncIterator[None]:
    """Start ``robots`` in order; close every one started, in the same order, however the test ends."""
    up: list[Robot] = []
    try:
        for r in robots:
            await r.t.start()
            up.append(r)
        yield
    finally:
        for r in up:
            await r.t.close()


def signed_pair(ports: list[str], tmp_path: Path, key: bytes) -> tuple[Robot, Robot]:
    """alpha and beta on ``ports``, signing with ``key``, their state under ``tmp_path/a`` and ``/b``."""
    names = ["alpha", "beta"]
    a = Robot("alpha", ports[0], key=key, state=tmp_path / "a", names=names)
    return a, Robot("beta", ports[1], key=key, state=tmp_path / "b", names=names)


async def until(pred: Callable[[], bool], timeout: float) -> None:
    end = asyncio.get_running_loop().time() + timeout
    while not pred():
        if asyncio.get_running_loop().time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.02)


def test_envelope_crosses_a_faulty_link_intact() -> None:
    async def main() -> None:
        faults = Faults(drop=0.03, dup=0.03, flip=2e-4, reorder=0.03, outages=((0.4, 0.4),))
        async with FaultRelay(rate_bps=RATE, faults=faults, seed=7) as relay:
            a = Robot("alpha", relay.ports[0], names=["alpha", "beta"])
            b = Robot("beta", relay.ports[1], names=["alpha", "beta"])
            async with started(a, b):
                env = envelope("alpha", 3, 30_000)
                a.t.offer(env)
                await until(lambda: bool(a.of(Delivered)), 20)
                await asyncio.sleep(0.3)
                assert [r.data for r in b.of(Received)] == [env.pack()]
                assert b.of(Received)[0].peer == "alpha"
                assert a.of(Delivered) == [Delivered("uwb", "beta", "alpha", 3)]
                # wholly on the air once, before beta acked it (the publisher's P1 on a paced link)
                assert a.of(OnAir) == [OnAir("uwb", "alpha", 3)]
                assert a.events.index(OnAir("uwb", "alpha", 3)) < a.events.index(a.of(Delivered)[0])
                assert PeerUp("uwb", "beta") in a.events and PeerUp("uwb", "alpha") in b.events
                assert a.t.peers() == ["beta"]
                sa, sb = a.t.stats(), b.t.stats()
                for key in (
                    "bytes_tx",
                    "bytes_rx",
                    "goodput_bps",
                    "resends",
                    "crc_errors",
                    "duplicates",
                    "rtt_ms",
                ):
                    assert key in sa
                assert sa["resends"] > 0 and sb["crc_errors"] + sb["bad_frames"] + sb["duplicates"] > 0
                # The adapter's own record of its writes: never over the rate in any 1 s window.
                assert 0 < sa["write_peak_bps_1s"] <= RATE
                assert relay.stats()["dropped"] > 0

    asyncio.run(main())


def test_a_missing_port_is_waited_for_and_said_not_fatal(caplog: pytest.LogCaptureFixture) -> None:
    # It was one clear error that stopped the daemon; a radio named late at boot is now waited for
    # (test_a_port_not_there_yet_at_start_is_opened_once_it_is), its absence on the FAULTS line.
    async def main() -> None:
        r = Robot("alpha", "/dev/does-not-exist-uwb", names=["alpha", "beta"])
        await r.t.start()
        try:
            assert r.t.stats()["port_open"] is False
        finally:
            await r.t.close()

    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        asyncio.run(main())
    assert any(
        "serial port /dev/does-not-exist-uwb is not there" in rec.getMessage() for rec in caplog.records
    )


def test_close_is_prompt_with_a_message_in_flight() -> None:
    async def main() -> None:
        async with FaultRelay(rate_bps=12500) as relay:
            a = Robot("alpha", relay.ports[0], names=["alpha", "beta"], link_rate_bps=12500)
            b = Robot("beta", relay.ports[1], names=["alpha", "beta"], link_rate_bps=12500)
            await a.t.start()
            await b.t.start()
            a.t.offer(envelope("alpha", 1, 50_000))
            await asyncio.sleep(0.5)
            t0 = time.monotonic()
            await a.t.close()
            await b.t.close()
            assert time.monotonic() - t0 < 1.0
            assert not a.of(Delivered)

    asyncio.run(main())


def test_latest_wins_over_serial() -> None:
    async def main() -> None:
        async with FaultRelay(rate_bps=50_000, seed=2) as relay:
            a = Robot("alpha", relay.ports[0], names=["alpha", "beta"], link_rate_bps=50_000)
            b = Robot("beta", relay.ports[1], names=["alpha", "beta"], link_rate_bps=50_000)
            async with started(a, b):
                v1, v2 = envelope("alpha", 1, 40_000), envelope("alpha", 2, 2_000)
                a.t.offer(v1)
                await asyncio.sleep(0.3)
                a.t.offer(v2)
                await until(lambda: bool(a.of(Delivered)), 10)
                await asyncio.sleep(0.3)
                assert a.of(Delivered) == [Delivered("uwb", "beta", "alpha", 2)]
                assert [r.data for r in b.of(Received)] == [v2.pack()]
                assert a.t.stats()["superseded"] == 1

    asyncio.run(main())


def test_broadcast_medium_three_robots() -> None:
    async def main() -> None:
        async with MediumRelay(robots=3, rate_bps=RATE, faults=Faults(drop=0.03), seed=5) as relay:
            robots = [Robot(n, p, mac="backoff") for n, p in zip(NODES, relay.ports, strict=True)]
            async with started(*robots):
                env = envelope("alpha", 9, 12_000)
                robots[0].t.offer(env)
                await until(lambda: len(robots[0].of(Delivered)) == 2, 20)
                await asyncio.sleep(0.2)
                assert sorted(d.peer for d in robots[0].of(Delivered)) == ["beta", "gamma"]
                for r in robots[1:]:
                    assert [x.data for x in r.of(Received)] == [env.pack()]

    asyncio.run(main())


def test_signed_link_persists_counter_and_detects_restart(tmp_path: Path) -> None:
    key = os.urandom(32)

    async def main() -> None:
        async with FaultRelay(rate_bps=RATE, seed=3) as relay:
            state_a = tmp_path / "a"
            a, b = signed_pair(relay.ports, tmp_path, key)
            async with started(a, b):
                a.t.offer(envelope("alpha", 1, 5000))
                await until(lambda: bool(a.of(Delivered)), 10)
                counter_file = state_a / "uwb-1.counter"
                first = int(counter_file.read_text())
                await a.t.close()
                # A restart: new session, counters continue above everything the first run reserved.
                a2 = Robot("alpha", relay.ports[0], key=key, state=state_a, names=["alpha", "beta"])
                await a2.t.start()
                env = envelope("alpha", 2, 5000)
                a2.t.offer(env)
                await until(lambda: bool(a2.of(Delivered)), 10)
                assert PeerRestarted("uwb", "alpha") in b.events
                assert int(counter_file.read_text()) > first
                assert [r.data for r in b.of(Received)][-1] == env.pack()
                assert b.t.stats()["replayed"] == 0
                await a2.t.close()

    asyncio.run(main())


class Eavesdropper:
    """A radio of an attacker's on the medium: it records every byte on the air, and plays it back."""

    def __init__(self, port: str) -> None:
        self.fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)
        self.heard = bytearray()

    def listen(self) -> None:
        with contextlib.suppress(BlockingIOError):
            while chunk := os.read(self.fd, 65536):
                self.heard += chunk

    async def replay(self) -> None:
        for i in range(0, len(self.heard), 256):  # at about the medium's rate
            os.write(self.fd, self.heard[i : i + 256])
            await asyncio.sleep(256 * 8 / RATE)

    def close(self) -> None:
        os.close(self.fd)


@pytest.mark.parametrize("how", ["close", "kill"])
def test_frames_recorded_before_a_restart_are_not_taken_again_after_it(tmp_path: Path, how: str) -> None:
    # Each receiver kept its replay windows in memory only: after a restart, every signed frame an
    # attacker had recorded off the air was taken once more (here: a whole old map, delivered as
    # new). The highest counter from each sender is now kept in the state directory: saved at a
    # clean close, and every few seconds for a kill -9.
    key = os.urandom(32)

    async def main() -> None:
        async with MediumRelay(robots=3, rate_bps=RATE, seed=4) as relay:
            a, b = signed_pair(relay.ports[:2], tmp_path, key)
            spy = Eavesdropper(relay.ports[2])
            loop = asyncio.get_running_loop()
            loop.add_reader(spy.fd, spy.listen)
            try:
                async with started(a, b):
                    a.t.offer(envelope("alpha", 1, 5000))
                    await until(lambda: bool(b.of(Received)) and bool(a.of(Delivered)), 10)
                    if how == "kill":
                        await asyncio.sleep(link_signing.REPLAY_SAVE_S + 1.0)  # a periodic save since the map
                        assert (tmp_path / "b" / "uwb-2.replay").exists()
                        b.t._link._replay = signing.ReplayStore(None)  # type: ignore[union-attr]  # dies: no more saves
                    loop.remove_reader(spy.fd)
                assert len(spy.heard) > 5000  # the map, recorded off the air
                b2 = Robot("beta", relay.ports[1], key=key, state=tmp_path / "b", names=["alpha", "beta"])
                async with started(b2):
                    await spy.replay()
                    await asyncio.sleep(1.0)
                    assert b2.of(Received) == []
                    assert b2.t.stats()["replayed"] > 0
                    if how == "close":  # every frame heard before it is refused, beacons too
                        assert b2.of(PeerUp) == []
            finally:
                spy.close()

    asyncio.run(main())


def test_unsigned_robot_is_ignored_by_a_signed_one() -> None:
    async def main() -> None:
        async with FaultRelay(rate_bps=RATE) as relay:
            a = Robot("alpha", relay.ports[0], names=["alpha", "beta"], deadline_s=1.5)
            b = Robot("beta", relay.ports[1], key=os.urandom(32), names=["alpha", "beta"])
            async with started(a, b):
                a.t.offer(envelope("alpha", 1, 3000))
                await asyncio.sleep(2.0)
                assert not b.of(Received) and not b.of(PeerUp)
                assert b.t.stats()["unsigned"] > 0
                assert [f.reason for f in a.of(Failed)] == ["deadline"]
                assert [f.again for f in a.of(Failed)] == [True]  # a deadline may pass next time

    asyncio.run(main())


def test_a_map_the_peer_refuses_for_its_size_fails_for_good() -> None:
    # The peer refuses a message over its limit at the first chunk, and would every time: the
    # publisher must not offer that very version again (P7), as it does after a deadline.
    async def main() -> None:
        async with FaultRelay(rate_bps=RATE) as relay:
            a = Robot("alpha", relay.ports[0], names=["alpha", "beta"])
            b = Robot("beta", relay.ports[1], names=["alpha", "beta"], max_message_bytes=2048)
            async with started(a, b):
                await until(lambda: bool(a.of(PeerUp)), 10)
                a.t.offer(envelope("alpha", 1, 5000))
                await until(lambda: bool(a.of(Failed)), 10)
                (f,) = a.of(Failed)
                assert "refused" in f.reason and f.again is False and not b.of(Received)

    asyncio.run(main())


def test_mapd_link_send_to_nobody_fails_cleanly(tmp_path: Path) -> None:
    src = tmp_path / "x.bin"
    src.write_bytes(b"hello")

    async def main() -> None:
        async with FaultRelay(rate_bps=100_000) as relay:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "mapd.cli", "link", "send", "--port", relay.ports[0], str(src),
                "--rate-bps", "100000", "--deadline", "1",
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            )  # fmt: skip
            _, err = await asyncio.wait_for(proc.communicate(), 20)
            assert proc.returncode == 1 and b"Traceback" not in err
            # "sending ... waiting for peer 2" first, then the one error line.
            lines = err.decode().strip().splitlines()
            assert [ln for ln in lines if ln.startswith("mapd: error: ")] == lines[-1:]
            assert lines[-1].startswith("mapd: error: uwb:") and len(lines) == 2

    asyncio.run(main())


def test_request_over_serial_reaches_the_map_owner_only_as_a_keyframe_need() -> None:
    """A signed fleet: beta signs its request with its own key, and alpha checks it."""
    ids = {n: Identity.generate(n) for n in ("alpha", "beta")}
    roster = Roster({n: i.public_key for n, i in ids.items()})

    async def main() -> None:
        async with FaultRelay(rate_bps=50_000, seed=4) as relay:
            kw: dict[str, Any] = {"names": ["alpha", "beta"], "link_rate_bps": 50_000, "roster": roster}
            a = Robot("alpha", relay.ports[0], identity=ids["alpha"], **kw)
            b = Robot("beta", relay.ports[1], identity=ids["beta"], **kw)
            async with started(a, b):
                await b.t.request_keyframe("alpha")
                await until(lambda: bool(a.of(KeyframeNeeded)), 10)
                assert a.of(KeyframeNeeded) == [KeyframeNeeded("uwb", "beta", "alpha")]
                await b.t.request_keyframe("alpha")  # within keyframe_request_s: not sent again
                # A map still flows on its own stream, and the control message never shows up as data.
                env = envelope("alpha", 2, 3000)
                a.t.offer(env)
                await until(lambda: bool(b.of(Received)), 10)
                assert [r.data for r in b.of(Received)] == [env.pack()]
                assert not a.of(Received)
                assert b.t.stats()["keyframe_requests_tx"] == 1
                assert a.t.stats()["keyframe_requests_rx"] == 1
                assert a.t.stats()["keyframe_requests_forged"] == 0
                assert len(a.of(KeyframeNeeded)) == 1

    asyncio.run(main())


# --- ports that misbehave -------------------------------------------------------------------------


@pytest.mark.parametrize("driver", ["pty", "hung usb-serial"])
def test_a_port_nobody_reads_does_not_freeze_the_loop(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, driver: str
) -> None:
    monkeypatch.setattr(link_port, "WRITE_STALL_S", 0.5)
    drains: list[int] = []
    if driver != "pty":
        # A pty's tcdrain returns at once; a USB-serial driver with bytes it cannot send (a hung
        # radio, flow control held) makes it wait for ever. serial_asyncio's close called it on
        # the event loop (Serial.flush), so each reopen of a stuck port froze the whole daemon.
        import termios

        def tcdrain(fd: int) -> None:
            drains.append(fd)
            time.sleep(20)

        monkeypatch.setattr(termios, "tcdrain", tcdrain)
    master, slave = os.openpty()  # the master end is never read: the slave's buffer fills up
    path = os.ttyname(slave)
    events: list[arq.Event] = []

    async def main() -> None:
        cfg = arq.ArqConfig(node_id=1, rate_bps=10_000_000.0, deadline_s=2.0)
        lk = UwbLink(cfg, path, on_event=events.append, reopen_s=0.2)
        await lk.start()
        try:
            lk.send(os.urandom(1 << 20), [2], deadline_s=2.0)
            # The deadline is the core's timer: it only fires while the loop is alive, not stuck
            # in a drain that never ends.
            await until(lambda: any(isinstance(e, arq.MessageFailed) for e in events), 15.0)
            assert lk.stats()["write_stalls"] >= 1
        finally:
            t0 = time.monotonic()
            await lk.close()
            assert time.monotonic() - t0 < 3.0

    try:
        with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
            asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)
    stalls = [r for r in caplog.records if "took no bytes" in r.getMessage()]
    assert len(stalls) == 1  # said once, however many times the stuck port is reopened
    assert drains == []  # unsent bytes are dropped at a close, never waited for


def test_ports_that_vanish_and_come_back_are_reopened_and_carry_maps_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    a_path, b_path = str(tmp_path / "a"), str(tmp_path / "b")

    def socat() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(
            ["socat", f"pty,raw,echo=0,link={a_path}", f"pty,raw,echo=0,link={b_path}"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        end = time.monotonic() + 5.0
        while not (os.path.exists(a_path) and os.path.exists(b_path)):
            assert time.monotonic() < end, "socat did not make its ptys"
            time.sleep(0.02)
        return proc

    got: list[arq.Event] = []

    async def main() -> None:
        proc = socat()
        cfg_a = arq.ArqConfig(node_id=1, rate_bps=200_000.0)
        cfg_b = arq.ArqConfig(node_id=2, rate_bps=200_000.0)
        a = UwbLink(cfg_a, a_path, reopen_s=0.2)
        b = UwbLink(cfg_b, b_path, on_event=got.append, reopen_s=0.2)
        await a.start()
        await b.start()
        try:
            a.send(b"one" * 1000, [2])
            await until(lambda: any(isinstance(e, arq.MessageReceived) for e in got), 10.0)
            proc.kill()  # both radios unplugged: the pty pair is gone
            proc.wait()
            # and their device links with them, as udev removes /dev/mapd-uwb (a killed socat
            # cannot; its stale links could point at a pty another test has opened since)
            for path in (a_path, b_path):
                Path(path).unlink(missing_ok=True)
            await until(lambda: not a.stats()["port_open"] and not b.stats()["port_open"], 5.0)
            assert "FAULTS serial port closed (reopening)" in render_status({"links": {"uwb": a.stats()}})
            await asyncio.sleep(1.0)  # several failed reopen attempts while the ports are gone
            proc = socat()  # plugged back in, at the same paths
            await until(lambda: a.stats()["port_open"] and b.stats()["port_open"], 10.0)
            assert a.stats()["reconnects"] == 1 and b.stats()["reconnects"] == 1
            got.clear()
            a.send(b"two" * 1000, [2])
            await until(lambda: any(isinstance(e, arq.MessageReceived) for e in got), 15.0)
            rx = [e for e in got if isinstance(e, arq.MessageReceived)]
            assert rx[-1].data == b"two" * 1000
        finally:
            await a.close()
            await b.close()
            proc.kill()
            proc.wait()

    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        asyncio.run(main())
    lost = [r for r in caplog.records if "lost" in r.getMessage()]
    assert len(lost) == 2  # one line per link, not one per reopen attempt
    assert not [r for r in caplog.records if r.exc_info]


def test_a_port_not_there_yet_at_start_is_opened_once_it_is(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A USB radio the kernel names a little after mapd starts at boot stopped the daemon, and with
    # it every other link, until systemd had restarted it into a port that was there.
    a_path, b_path = str(tmp_path / "a"), str(tmp_path / "b")
    got: list[arq.Event] = []

    async def main() -> None:
        a = UwbLink(arq.ArqConfig(node_id=1, rate_bps=200_000.0), a_path, reopen_s=0.2, wait_for_port=True)
        await a.start()  # no port yet: the link runs
        proc = None
        try:
            await asyncio.sleep(0.7)  # a few tries while it is not there
            assert a.stats()["port_open"] is False
            assert "FAULTS serial port closed (reopening)" in render_status({"links": {"uwb": a.stats()}})
            proc = subprocess.Popen(
                ["socat", f"pty,raw,echo=0,link={a_path}", f"pty,raw,echo=0,link={b_path}"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            await until(lambda: os.path.exists(b_path), 5.0)
            b = UwbLink(arq.ArqConfig(node_id=2, rate_bps=200_000.0), b_path, on_event=got.append)
            await b.start()
            try:
                await until(lambda: a.stats()["port_open"], 5.0)
                assert a.stats()["reconnects"] == 0  # opened, not reopened
                a.send(b"late" * 500, [2])
                await until(lambda: any(isinstance(e, arq.MessageReceived) for e in got), 10.0)
            finally:
                await b.close()
        finally:
            await a.close()
            if proc is not None:
                proc.kill()
                proc.wait()

    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        asyncio.run(main())
    said = [r.getMessage() for r in caplog.records]
    assert sum("is not there" in m for m in said) == 1  # once, not at every try
    assert sum("is there now: opened" in m for m in said) == 1


def test_a_port_that_comes_but_cannot_be_opened_is_said_once_not_tried_in_silence(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Under the unit's DevicePolicy=closed, a USB radio plugged in after a boot that had no ttyUSB
    # driver loaded came, and every open was refused (EPERM), retried each second without a word.
    path = tmp_path / "radio"

    async def main() -> None:
        link = UwbLink(
            arq.ArqConfig(node_id=1, rate_bps=200_000.0), str(path), reopen_s=0.1, wait_for_port=True
        )
        await link.start()  # not there: said once, waited for
        try:
            await asyncio.sleep(0.4)
            path.write_text("x")  # there now, but no serial port: every open fails
            await asyncio.sleep(0.8)
            assert link.stats()["port_open"] is False
        finally:
            await link.close()

    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        asyncio.run(main())
    said = [r.getMessage() for r in caplog.records]
    assert sum("is not there" in m for m in said) == 1, said
    refused = [m for m in said if "cannot open serial port" in m]
    assert len(refused) == 1 and refused[0].endswith("; trying again every 0.1 s"), said


def test_a_port_that_is_there_but_no_serial_port_still_stops_start(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")

    async def main() -> None:
        link = UwbLink(
            arq.ArqConfig(node_id=1, rate_bps=200_000.0), str(tmp_path / "file"), wait_for_port=True
        )
        with pytest.raises(TransportError, match="cannot open serial port"):
            await link.start()
        # and a one-shot command (mapd link) is told at once of a port that is not there
        once = UwbLink(arq.ArqConfig(node_id=1, rate_bps=200_000.0), str(tmp_path / "typo"))
        with pytest.raises(TransportError, match="does not exist"):
            await once.start()

    asyncio.run(main())


def test_a_signing_counter_that_cannot_be_saved_quiets_the_link_until_it_can(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # Small blocks, so that a 20 kB map needs many saves (the daemon's block lasts minutes).
    monkeypatch.setattr(arq, "Signer", functools.partial(signing.Signer, block=16))
    key = os.urandom(32)
    # Each save is a write and two fsyncs (seconds on a loaded SD card): never on the event loop.
    saved_on: list[threading.Thread] = []
    save = signing.CounterStore.save

    def recording(store: signing.CounterStore, value: int) -> None:
        saved_on.append(threading.current_thread())
        save(store, value)

    monkeypatch.setattr(signing.CounterStore, "save", recording)

    async def main() -> None:
        async with FaultRelay(rate_bps=RATE, seed=5) as relay:
            a, b = signed_pair(relay.ports, tmp_path, key)
            counter = tmp_path / "a" / "uwb-1.counter"
            async with started(a, b):
                saved = int(counter.read_text())
                counter.unlink()
                counter.mkdir()  # the save's rename onto it fails, as on a full or read-only disk
                a.t.offer(envelope("alpha", 1, 20_000))
                await until(lambda: a.t.stats()["counter_save_errors"] >= 3, 10)
                # `mapd status` says so on a line of its own, not among the link's many figures.
                shown = render_status({"links": {"uwb": a.t.stats()}}).splitlines()
                assert any("FAULTS" in ln and "signing counter not saved" in ln for ln in shown)
                # It signs on within the block saved before (half a block left at the first
                # fault), then uses no counter past it: the link goes quiet, but lives.
                await asyncio.sleep(0.5)
                sent = a.t.stats()["frames_tx"]
                await asyncio.sleep(0.5)
                assert a.t.stats()["frames_tx"] == sent and not a.of(Delivered)
                counter.rmdir()
                await until(lambda: bool(a.of(Delivered)), 20)
                assert int(counter.read_text()) > saved
                assert b.t.stats()["bad_signature"] == 0 and b.t.stats()["replayed"] == 0

    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        asyncio.run(main())
    said = [r.getMessage() for r in caplog.records]
    assert sum("cannot write signing counter" in m for m in said) == 1  # once, not once a retry
    assert sum("signing counter saved again" in m for m in said) == 1
    assert not [r for r in caplog.records if "stopped" in r.getMessage()]
    assert len(saved_on) > 10 and threading.main_thread() not in saved_on


def test_a_link_whose_loop_dies_says_why_to_its_watcher() -> None:
    class Refuses(Robot):
        def __init__(self, name: str, port: str) -> None:
            super().__init__(name, port, names=["alpha", "beta"])
            self.t.ctx.emit = self.refuse

        def refuse(self, e: TransportEvent) -> None:
            if isinstance(e, Received):
                raise StateError("state: cannot write /var/lib/mapd/peers: No space left on device")

    async def main() -> None:
        async with FaultRelay(rate_bps=RATE, seed=6) as relay:
            a = Refuses("alpha", relay.ports[0])
            b = Robot("beta", relay.ports[1], names=["alpha", "beta"])
            async with started(a, b):
                watch = asyncio.ensure_future(a.t.watch())
                await asyncio.sleep(0.3)
                assert not watch.done()  # a link at work is not reported
                b.t.offer(envelope("beta", 1, 100))  # alpha's handler raises on beta's map
                with pytest.raises(TransportError) as err:
                    await asyncio.wait_for(watch, 10)
                assert str(err.value) == (
                    f"uwb: link on {relay.ports[0]} stopped: "
                    "state: cannot write /var/lib/mapd/peers: No space left on device"
                )
                # The healthy link's watch ends quietly when it is closed.
                healthy = asyncio.ensure_future(b.t.watch())
                await b.t.close()
                await asyncio.wait_for(healthy, 5)

    asyncio.run(main())


def test_waiting_on_a_link_whose_loop_died_is_an_error_not_a_hang() -> None:
    # What `mapd link send` waits on (its message closing) never comes once the loop is dead.
    master, slave = os.openpty()
    path = os.ttyname(slave)

    def on_event(e: arq.Event) -> None:
        if isinstance(e, arq.MessageFailed):
            raise StateError("state: disk full")

    async def main() -> None:
        lk = UwbLink(arq.ArqConfig(node_id=1, rate_bps=1_000_000.0), path, on_event=on_event)
        await lk.start()
        try:
            lk.send(b"x" * 100, [2], deadline_s=0.3)  # nobody answers: it fails, the handler raises
            with pytest.raises(TransportError) as err:
                await asyncio.wait_for(lk.run_until(asyncio.Event().wait()), 10)
            assert str(err.value) == f"uwb: link on {path} stopped: state: disk full"
        finally:
            await lk.close()

    try:
        asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)


def test_tdma_slots_follow_the_wall_clock_when_ntp_steps_it(caplog: pytest.LogCaptureFixture) -> None:
    """A robot that booted before it had a time source gets its clock stepped after mapd started.
    Its TDMA slots must move with the wall clock, or they sit over its neighbours' until a restart."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    step = [0.0]
    # The robot's wall clock, stepped by the test alone: counted on the monotonic clock, so that
    # the host's own clock, slewed now and then (seen here at 5 ms a second), adds no step of its own.
    base = time.time() - time.monotonic()

    def wall() -> float:
        return time.monotonic() + base + step[0]

    slot, cycle = 0.2, 0.4  # two slots; ours is the first of each cycle
    cfg = arq.ArqConfig(node_id=1, rate_bps=100_000.0, mac="tdma", slots=2, slot_s=slot, slot_index=0)

    async def main() -> list[float]:
        loop = asyncio.get_running_loop()
        phases: list[float] = []
        os.set_blocking(master, False)

        def on_readable() -> None:
            with contextlib.suppress(BlockingIOError):
                if os.read(master, 1 << 16):
                    phases.append(wall() % cycle)  # when our frame came out, on the robot's clock

        loop.add_reader(master, on_readable)
        lk = UwbLink(cfg, path, reopen_s=0.2, wall_clock=wall)
        await lk.start()
        try:
            await asyncio.sleep(0.3)
            step[0] = 0.3  # NTP steps the clock (ntpd steps past 128 ms), here by a slot and a half
            await until(lambda: abs(lk.core.cfg.clock_offset - (wall() - loop.time())) < 0.01, 3.0)
            assert lk.stats()["clock_steps"] == 1
            phases.clear()
            lk.send(os.urandom(8000), [2], deadline_s=5.0)  # nobody acks: the first pass is enough
            await asyncio.sleep(2.0)
            return phases
        finally:
            loop.remove_reader(master)
            await lk.close()

    try:
        with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
            phases = asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)
    assert len(phases) >= 10, phases
    # Every frame in our slot of the stepped clock (plus a little for the pty and the scheduler).
    # Counted on the old clock, half of them would fall in the other robot's slot.
    assert max(phases) < slot + 0.03, sorted(phases)
    assert any("the wall clock stepped +0.300 s" in r.getMessage() for r in caplog.records)


def test_a_slewed_wall_clock_is_followed_but_not_counted_as_a_step(caplog: pytest.LogCaptureFixture) -> None:
    """chrony slews a clock up to 83 ms a second; the link follows it but logs no step.

    Between two of the idle link's clock checks (a second apart) such a slew moves the clock 50 ms,
    which was counted and logged as a step each second (a host slewing 5 ms a second did that too).
    """
    master, slave = os.openpty()
    path = os.ttyname(slave)
    t0 = time.monotonic()
    base = time.time() - t0

    def wall() -> float:  # slewed 50 ms a second (50,000 ppm) from the start
        return time.monotonic() + base + 0.05 * (time.monotonic() - t0)

    cfg = arq.ArqConfig(node_id=1, rate_bps=100_000.0, mac="tdma", slots=2, slot_s=0.2, slot_index=0)

    async def main() -> tuple[float, float, int]:
        loop = asyncio.get_running_loop()
        lk = UwbLink(cfg, path, reopen_s=0.2, wall_clock=wall)
        await lk.start()
        try:
            await asyncio.sleep(3.5)  # the idle link checks the clock every second
            return lk.core.cfg.clock_offset, wall() - loop.time(), lk.stats()["clock_steps"]
        finally:
            await lk.close()

    try:
        with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
            followed, actual, steps = asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)
    assert abs(followed - actual) < 0.06, (followed, actual)  # followed within a check's slew
    assert steps == 0
    assert not [r for r in caplog.records if "stepped" in r.getMessage()]


def test_two_robots_given_one_tdma_slot_see_each_other_out_of_turn() -> None:
    """A fleet whose configs disagree (here both robots set slot_index 0) sends over itself. Over the
    emulated radio each robot hears the other in its own slot (R18) and `mapd status` says so."""

    async def main() -> None:
        async with FaultRelay(rate_bps=12_500, seed=5) as relay:
            kw: dict[str, Any] = {
                "names": ["alpha", "beta"], "link_rate_bps": 12_500, "mac": "tdma", "slot_index": 0,
            }  # fmt: skip
            a = Robot("alpha", relay.ports[0], **kw)
            b = Robot("beta", relay.ports[1], **kw)
            async with started(a, b):
                a.t.offer(envelope("alpha", 2, 3000))  # some twenty frames each way
                b.t.offer(envelope("beta", 2, 3000))
                await until(lambda: a.t.stats()["out_of_turn"] > 0 and b.t.stats()["out_of_turn"] > 0, 20)
                assert a.t.stats()["out_of_turn_from"] == NODES["beta"]
                shown = render_status({"links": {"uwb": a.t.stats()}})
                assert "FAULTS" in shown and "own TDMA slot (do the clocks agree?)" in shown

    asyncio.run(main())
