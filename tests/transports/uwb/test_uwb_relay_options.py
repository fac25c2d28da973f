"""The fault relay as a reusable tool, the plugin registration and the options table."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd import plugins
from mapd.config import validate
from mapd.errors import ConfigError
from transports.base import TransportContext
from transports.uwb import wire
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.faults import FaultInjector, Faults
from transports.uwb.framing import MIN_FRAME, encode_frame
from transports.uwb.receiving import CHUNK_COST
from transports.uwb.relay import FaultRelay
from transports.uwb.transport import UwbOptions, UwbTransport

needs_socat = pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")


def test_plugin_is_registered_as_uwb() -> None:
    assert plugins.load("transport", "uwb") is UwbTransport
    assert UwbTransport.name == "uwb"


def test_options_defaults_and_errors() -> None:
    o = validate(
        UwbOptions, {"port": "/dev/ttyUSB0", "nodes": {"a": 1, "b": 2}}, "config.toml", "transports.uwb"
    )
    assert (o.link_rate_bps, o.max_frame, o.mac, o.baud) == (12500, 224, "none", 115200)
    with pytest.raises(ConfigError, match=r"transports\.uwb\.prot: unknown key"):
        validate(UwbOptions, {"prot": "x"}, "config.toml", "transports.uwb")
    with pytest.raises(ConfigError, match="share a link id"):
        validate(UwbOptions, {"nodes": {"a": 1, "b": 1}}, "config.toml", "transports.uwb")
    with pytest.raises(ConfigError, match="tdma"):
        validate(UwbOptions, {"mac": "tdma", "slot_ms": 50}, "config.toml", "transports.uwb")
    with pytest.raises(ConfigError, match="max_frame"):
        validate(UwbOptions, {"max_frame": 20}, "config.toml", "transports.uwb")
    # the pacer holds two frames: a rate that carries one frame a second but not two is refused here
    with pytest.raises(ConfigError, match="two 224-byte frames"):
        validate(UwbOptions, {"link_rate_bps": 2000}, "config.toml", "transports.uwb")
    ok = validate(UwbOptions, {"link_rate_bps": 3584, "nodes": {"zed": 1}}, "config.toml", "transports.uwb")
    ctx = TransportContext(robot="zed", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    assert ArqEndpoint(UwbTransport(ok, ctx)._config(asyncio.new_event_loop()), session=1).chunk_size >= 8


def test_transport_needs_a_link_id() -> None:
    ctx = TransportContext(robot="zed", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    with pytest.raises(ConfigError, match="no link id for robot 'zed'"):
        UwbTransport(UwbOptions(nodes={"a": 1}), ctx)
    t = UwbTransport(UwbOptions(nodes={"a": 1, "zed": 4, "b": 2}), ctx)
    assert (t.node_id, t.peer_ids) == (4, [1, 2])
    with pytest.raises(ConfigError, match="peers"):
        UwbTransport(UwbOptions(nodes={"zed": 4}, peers=["nobody"]), ctx)


def test_send_to_heard_sends_each_map_only_to_configured_robots_heard_lately() -> None:
    from types import SimpleNamespace

    ctx = TransportContext(robot="zed", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    nodes = {"a": 1, "b": 2, "c": 3, "zed": 4}
    link = SimpleNamespace(core=SimpleNamespace(peers_up=lambda: [3, 1, 9]))  # 9: heard, not configured
    every = UwbTransport(UwbOptions(nodes=nodes), ctx)
    heard = UwbTransport(UwbOptions(nodes=nodes, send_to="heard"), ctx)
    every._link = heard._link = link  # type: ignore[assignment]
    assert every._dests() == [1, 2, 3]  # the default: b too, though out of range
    assert heard._dests() == [1, 3]
    with pytest.raises(ConfigError, match="send_to"):
        validate(UwbOptions, {"send_to": "everyone"}, "config.toml", "transports.uwb")


@pytest.mark.parametrize(("node", "window", "max_frame"), [(1, 1, MIN_FRAME), (254, 256, 4096)])
def test_options_in_range_build_a_core_config(node: int, window: int, max_frame: int) -> None:
    # The core raises ValueError (a bug, not a user's error) for what the options must refuse first.
    ctx = TransportContext(
        robot="zed", fleet="f", link_key=bytes(32), max_message_bytes=1 << 20, emit=lambda e: None
    )
    opts = UwbOptions(nodes={"zed": node}, window=window, max_frame=max_frame, link_rate_bps=16 * 4096)
    cfg = UwbTransport(opts, ctx)._config(asyncio.new_event_loop())
    assert (cfg.node_id, cfg.window, cfg.max_frame) == (node, window, max_frame)
    assert ArqEndpoint(cfg, session=1).chunk_size >= 8


def test_fault_injector_is_seeded_and_cuts_outages() -> None:
    def run(seed: int) -> tuple[int, int, int]:
        inj = FaultInjector(Faults(drop=0.1, dup=0.1, flip=1e-3), seed=seed)
        for i in range(2000):
            inj.apply(os.urandom(100), i * 0.01, i * 0.01 + 0.005)
        return inj.stats.dropped, inj.stats.duplicated, inj.stats.flipped_bits

    assert run(1) == run(1) != run(2)
    dropped, dup, flips = run(1)
    assert 150 < dropped < 250 and 150 < dup < 250 and 100 < flips < 300
    inj = FaultInjector(Faults(outages=((1.0, 0.5),)))
    assert inj.apply(b"x" * 100, 1.2, 1.3) == []
    ((_, cut),) = inj.apply(b"x" * 100, 0.5, 1.5)
    assert len(cut) == 50
    assert inj.apply(b"x" * 100, 1.5, 1.6) == [(0.0, b"x" * 100)]


@needs_socat
@pytest.mark.timeout(30)
def test_relay_emulates_the_rate_and_a_cut() -> None:
    import serial_asyncio

    async def main() -> None:
        got = bytearray()

        class Sink(asyncio.Protocol):
            def data_received(self, data: bytes) -> None:
                got.extend(data)

        loop = asyncio.get_running_loop()
        async with FaultRelay(rate_bps=40_000, seed=1) as relay:
            rx, _ = await serial_asyncio.create_serial_connection(loop, Sink, relay.ports[1], baudrate=115200)
            tx, _ = await serial_asyncio.create_serial_connection(loop, asyncio.Protocol, relay.ports[0])
            frames = [encode_frame(os.urandom(150)) for _ in range(20)]
            t0 = loop.time()
            tx.write(b"".join(frames))
            while len(got) < sum(map(len, frames)) and loop.time() - t0 < 5:
                await asyncio.sleep(0.01)
            dt = loop.time() - t0
            assert bytes(got) == b"".join(frames)
            assert dt >= 0.95 * len(got) * 8 / 40_000
            relay.cut(0.3)
            tx.write(b"".join(frames[:3]))
            await asyncio.sleep(0.4)
            assert len(got) == sum(map(len, frames))  # all swallowed by the cut
            stats = relay.stats()
            assert stats["cut"] == 3 and stats["ports"][0]["frames_in"] == 23
            tx.abort()
            rx.abort()

    asyncio.run(main())


@needs_socat
@pytest.mark.timeout(30)
def test_relay_runs_as_a_module(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "transports.uwb.relay", "--robots", "3", "--dir", str(tmp_path / "r"),
         "--duration", "0.5", "--drop", "0.1", "--seed", "3"],
        capture_output=True, text=True, timeout=20,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[:3] == [f"robot {i}: {tmp_path / 'r' / f'robot{i}'}" for i in range(3)]
    stats = json.loads("\n".join(lines[3:]))
    assert len(stats["ports"]) == 3 and stats["rate_bps"] == 12500


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(st.binary(max_size=300), st.binary(min_size=7, max_size=220).map(encode_frame)), max_size=8
    )
)
def test_fuzz_core_never_raises_and_stays_bounded(chunks: list[bytes]) -> None:
    ep = ArqEndpoint(ArqConfig(node_id=2, max_message_bytes=10_000), session=1)
    for i, c in enumerate(chunks):
        ep.receive_data(c, float(i))
        ep.handle_timer(float(i))
        while ep.data_to_send(float(i)):
            pass
    s = ep.stats()
    assert s["rx_held_bytes"] <= 2 * (10_000 + 16)
    assert ep.get_timer() is not None


def test_forged_data_frames_for_many_peers_stay_bounded() -> None:
    ep = ArqEndpoint(ArqConfig(node_id=2, max_message_bytes=100_000, max_peers=8), session=1)
    for src in range(1, 255):
        if src == 2:
            continue
        d = wire.Data(src, 2, src, 1, 0, 0, 500, 99_000, os.urandom(190))
        ep.receive_data(encode_frame(wire.pack(d)), 0.0)
    s = ep.stats()
    assert s["peers_full"] == 254 - 1 - 8
    assert s["rx_held_bytes"] <= 8 * (190 + CHUNK_COST)  # eight peers of one chunk each
