"""A robot that boots before its zenoh router, or out of its reach, runs on and joins once it is up.

Before, a client that found no router stopped ``start()``, and with it the daemon and its other
links (a robot with UWB and zenoh shared nothing over UWB either); systemd's start limit then
left it failed for good after a few restarts.
"""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.errors import TransportError
from mapd.ros2 import zenoh_config
from transports.zenoh import link


def _router(ep: str) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([ep]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def test_clients_run_without_their_router_and_meet_once_it_is_up(
    zk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(zenoh_config, "RETRY_FIRST_S", 0.2)
    ep = zk.endpoint(zk.free_port())

    async def main() -> None:
        a = await zk.Bot("a", connect=[ep], mode="client").start()
        b = await zk.Bot("b", connect=[ep], mode="client").start()
        watches = [asyncio.create_task(bot.t.watch()) for bot in (a, b)]
        try:
            for bot in (a, b):
                assert bot.t.stats()["session_open"] is False
                assert "Unable to connect" in (bot.t.unreached or "")
            a.offer(zk.envelope("a", 1))  # no session to put it on: b asks for it once they meet
            await asyncio.sleep(1.0)
            assert not any(w.done() for w in watches)
            router = await asyncio.to_thread(_router, ep)
            try:
                await zk.meet(a, b, timeout=20.0)
                assert a.t.stats()["session_open"] and b.t.unreached is None
                await b.wait(lambda: [v for _, v, _ in b.received("a")] == [1], 10.0)
                a.offer(zk.envelope("a", 2))
                await b.wait(lambda: [v for _, v, _ in b.received("a")] == [1, 2], 10.0)
            finally:
                for bot in (a, b):
                    await bot.t.close()
                await asyncio.to_thread(router.close)
        finally:
            for w in watches:
                w.cancel()

    asyncio.run(main())


def test_a_session_zenoh_refuses_for_another_cause_still_stops_start(zk: SimpleNamespace) -> None:
    async def main() -> None:
        port = zk.free_port()
        holder = await zk.Bot("a", listen=[zk.endpoint(port)]).start()
        try:
            with pytest.raises(TransportError, match="Address already in use"):
                await zk.Bot("b", listen=[zk.endpoint(port)]).start()
        finally:
            await holder.t.close()

    asyncio.run(main())


@pytest.mark.slow
def test_a_daemon_whose_router_is_down_runs_says_so_and_joins_later(
    tmp_path: Path, zk: SimpleNamespace
) -> None:
    from mapd.grid.save import save_map
    from mapd.mapping.synthetic import room_grid

    ep = zk.endpoint(zk.free_port())
    save_map(room_grid(60, 80, seed=3), tmp_path / "map.yaml")
    (tmp_path / "config.toml").write_text(
        '[robot]\nname = "a"\nfleet = "testfleet"\n[fleet]\nallow_unsigned = true\n'
        '[source]\nuse = "mapfile"\n[source.mapfile]\npath = "map.yaml"\npoll_s = 0.1\nsettle_s = 0.1\n'
        '[codec]\nuse = "raw"\n[state]\ndir = "state"\nruntime_dir = "run"\n'
        f'[transports]\nuse = ["zenoh"]\n[transports.zenoh]\nmode = "client"\nconnect = ["{ep}"]\n'
        "multicast_scouting = false\n"
    )

    def status(human: bool = False) -> Any:
        out = subprocess.run(
            [sys.executable, "-m", "mapd", "status", *([] if human else ["--json"]), "--config",
             str(tmp_path / "config.toml")],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        if out.returncode != 0:
            return None
        return out.stdout if human else json.loads(out.stdout)

    def wait(cond: Any, what: str) -> Any:
        end = time.monotonic() + 60
        while time.monotonic() < end:
            assert proc.poll() is None, (tmp_path / "d.log").read_text()[-2000:]
            s = status()
            if s is not None and cond(s):
                return s
            time.sleep(0.3)
        raise AssertionError(f"{what}: {(tmp_path / 'd.log').read_text()[-2000:]}")

    log = (tmp_path / "d.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapd", "run", "--config", str(tmp_path / "config.toml")],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    router = None
    try:
        wait(lambda s: s["links"]["zenoh"]["session_open"] is False, "the daemon up without its router")
        assert "FAULTS zenoh session not open yet (trying again)" in status(human=True)
        router = subprocess.Popen(
            [sys.executable, "-m", "transports.zenoh.router", "--listen", ep],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        assert router.stdout is not None and "listening on" in router.stdout.readline()
        wait(lambda s: s["links"]["zenoh"]["session_open"] is True, "the session open once the router is")
        assert "no zenoh router" not in status(human=True)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    finally:
        for p in (proc, router):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(10)
        log.close()


def test_a_router_that_answers_and_refuses_is_not_waited_for(zk: SimpleNamespace) -> None:
    # "Unable to connect" is all zenoh says both when nothing listens and when a router there
    # refuses us (a certificate from another CA, an ACL): only the first is worth waiting for.
    import socket

    from mapd.errors import UnreachableError
    from mapd.ros2.zenoh_config import open_zenoh
    from transports.zenoh.session import ZenohOptions, build_config

    def client(ep: str) -> Any:
        return build_config(ZenohOptions(mode="client", connect=[ep], multicast_scouting=False), 1 << 20)

    with pytest.raises(UnreachableError, match=r"^test: Unable to connect to any of"):
        open_zenoh(client(zk.endpoint(zk.free_port())), "test")
    with socket.socket() as listener:  # something answers on the port, but speaks no zenoh
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        ep = zk.endpoint(listener.getsockname()[1])
        with pytest.raises(TransportError, match=r"^test: Unable to connect") as refused:
            open_zenoh(client(ep), "test")
        assert not isinstance(refused.value, UnreachableError)


def test_a_retry_that_opens_after_close_gave_up_waiting_closes_its_session(
    zk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    import threading

    from mapd.errors import UnreachableError

    monkeypatch.setattr(zenoh_config, "RETRY_FIRST_S", 0.05)
    opening, release = threading.Event(), threading.Event()
    tries: list[int] = []

    from unittest import mock

    late = mock.MagicMock(name="session")  # takes every declaration, as a real one would

    def fake_open(conf: Any, what: str) -> Any:
        tries.append(1)
        if len(tries) == 1:
            raise UnreachableError(f"{what}: Unable to connect to any of [x]")
        opening.set()
        release.wait(10)  # longer than close() waits (close_timeout_s)
        return late

    monkeypatch.setattr(link, "open_zenoh", fake_open)

    async def main() -> None:
        bot = await zk.Bot("a", connect=["tcp/127.0.0.1:9"], mode="client", close_timeout_s=0.2).start()
        watch = asyncio.create_task(bot.t.watch())
        await asyncio.to_thread(opening.wait, 10)
        await bot.t.close()  # gives up waiting for the open under way
        watch.cancel()
        release.set()
        for _ in range(100):
            if late.close.called:
                break
            await asyncio.sleep(0.02)

    asyncio.run(main())
    assert late.close.called
