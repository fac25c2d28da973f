"""The serial adapter when the port misbehaves: a peer that stops reading, a port that vanishes and
comes back. The link must keep its loop running, say so once, and carry on when the port does."""

from __future__ import annotations

import asyncio
import logging
import os
import shutil
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from transports.uwb import arq, link
from transports.uwb.link import UwbLink

pytestmark = [pytest.mark.timeout(60)]


async def until(pred: Callable[[], bool], timeout: float) -> None:
    end = asyncio.get_running_loop().time() + timeout
    while not pred():
        if asyncio.get_running_loop().time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.02)


def test_a_port_nobody_reads_does_not_freeze_the_loop(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(link, "WRITE_STALL_S", 0.5)
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


@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
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
