"""The latest-wins outbox thread, the options table, and start-up failures (one clear line each)."""

from __future__ import annotations

import asyncio
import os
import threading
from pathlib import Path

import pytest

from mapd.config import validate
from mapd.errors import ConfigError, TransportError
from transports.base import TransportContext, TransportOptions
from transports.zenoh.jobs import JobQueue
from transports.zenoh.link import ZenohTransport
from transports.zenoh.session import ZenohOptions, build_config, zenoh_message

# -- outbox ----------------------------------------------------------------------------------------


def test_outbox_latest_wins_while_a_job_blocks() -> None:
    gate, started = threading.Event(), threading.Event()
    ran: list[str] = []
    box = JobQueue("t-outbox")

    def blocker() -> None:
        started.set()
        gate.wait(5)
        ran.append("block")

    box.submit("first", blocker)
    assert started.wait(5)
    for i in range(10):  # queued while the thread is busy: only the last survives
        assert box.submit("update", lambda i=i: ran.append(f"v{i}"))
    assert box.submit("ack", lambda: ran.append("ack"))
    done = box.call(lambda: "done")
    gate.set()
    assert done.result(5) == "done"
    assert ran == ["block", "v9", "ack"]
    assert box.replaced == 9
    assert box.stop(1.0)


def test_outbox_bounds_pending_and_survives_errors() -> None:
    errors: list[object] = []
    gate, started = threading.Event(), threading.Event()
    box = JobQueue("t-outbox", max_pending=8, on_error=lambda key, exc: errors.append((key, str(exc))))
    box.submit("b", lambda: (started.set(), gate.wait(5)))
    assert started.wait(5)
    accepted = [box.submit(i, lambda: None) for i in range(12)]
    assert accepted.count(True) == 8 and box.rejected == 4

    def boom() -> None:
        raise RuntimeError("link down")

    box.discard_pending()
    box.submit("x", boom)
    gate.set()
    assert box.call(lambda: 1).result(5) == 1
    assert errors == [("x", "link down")] and box.failed == 1
    assert box.stop(1.0)


def test_outbox_stop_does_not_wait_for_a_stuck_job() -> None:
    gate, started = threading.Event(), threading.Event()
    box = JobQueue("t-outbox-stuck")
    box.submit("stuck", lambda: (started.set(), gate.wait(10)))
    assert started.wait(5)
    pending = box.call(lambda: 1)
    assert box.stop(0.1) is False  # still inside the stuck job: we return anyway
    assert pending.cancelled()
    assert not box.submit("late", lambda: None)
    gate.set()


# -- options and config ----------------------------------------------------------------------------


def test_options_validate_with_clear_errors() -> None:
    ok = validate(
        ZenohOptions, {"mode": "client", "connect": ["tcp/10.0.0.2:7447"]}, "cfg.toml", "transports.zenoh"
    )
    assert ok.mode == "client" and ok.multicast_scouting is True
    with pytest.raises(ConfigError, match=r"transports\.zenoh\.connect: .*not a zenoh endpoint"):
        validate(ZenohOptions, {"connect": ["10.0.0.2:7447"]}, "cfg.toml", "transports.zenoh")
    with pytest.raises(ConfigError, match=r"transports\.zenoh\.mode"):
        validate(ZenohOptions, {"mode": "server"}, "cfg.toml", "transports.zenoh")
    with pytest.raises(ConfigError, match="unknown key"):
        validate(ZenohOptions, {"listen_on": []}, "cfg.toml", "transports.zenoh")


def test_options_of_another_transport_are_a_type_error() -> None:
    ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    with pytest.raises(TypeError, match="ZenohOptions"):
        ZenohTransport(TransportOptions(), ctx)


def test_table_overrides_file_but_unset_keys_keep_it(tmp_path: Path) -> None:
    import json

    f = tmp_path / "zenoh.json5"
    f.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:9"] },\n'
        "  scouting: { multicast: { enabled: false } } }"
    )
    conf = build_config(ZenohOptions(config_file=f), 1 << 20)
    assert json.loads(conf.get_json("mode")) == "client"  # type: ignore[attr-defined]
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:9"]  # type: ignore[attr-defined]
    conf = build_config(ZenohOptions(config_file=f, mode="peer", multicast_scouting=True), 1 << 20)
    assert json.loads(conf.get_json("mode")) == "peer"  # type: ignore[attr-defined]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is True  # type: ignore[attr-defined]
    # The message cap follows limits.max_message_bytes (plus framing room).
    cap = int(json.loads(conf.get_json("transport/link/rx/max_message_size")))  # type: ignore[attr-defined]
    assert (1 << 20) < cap < (1 << 21)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (None, "cannot use config file"),
        ("{ mode: ", "cannot use config file"),
        ('{ mode: "boss" }', "cannot use"),
    ],
)
def test_bad_config_file_is_one_line(tmp_path: Path, content: str | None, match: str) -> None:
    f = tmp_path / "zenoh.json5"
    if content is not None:
        f.write_text(content)
    with pytest.raises(TransportError, match=match) as info:
        build_config(ZenohOptions(config_file=f), 1 << 20)
    assert "\n" not in str(info.value) and ".rs:" not in str(info.value)


def test_a_fifo_or_device_as_the_config_file_is_one_line_at_once(tmp_path: Path) -> None:
    """zenoh.Config.from_file blocked for ever on a FIFO without a writer (in a thread that ignored
    SIGTERM) and read /dev/zero until memory ran out; the ros2 output's config reads the same way."""
    import time

    from mapd.ros2.cdr import session_config

    fifo = tmp_path / "zenoh.json5"
    os.mkfifo(fifo)
    big = tmp_path / "big.json5"
    big.write_bytes(b" " * (2 << 20))
    for path, says in (
        (fifo, "not a regular file"),
        (Path("/dev/zero"), "not a regular file"),
        (big, "over 1 MiB"),
    ):
        t0 = time.monotonic()
        with pytest.raises(TransportError, match=says):
            build_config(ZenohOptions(config_file=path), 1 << 20)
        with pytest.raises(TransportError, match=says):
            session_config(config_file=path)
        assert time.monotonic() - t0 < 5.0


def test_a_yaml_config_file_is_read_as_zenoh_reads_it(tmp_path: Path) -> None:
    import json

    f = tmp_path / "zenoh.yaml"
    f.write_text("mode: client\nconnect:\n  endpoints: [tcp/127.0.0.1:9]\n")
    conf = build_config(ZenohOptions(config_file=f), 1 << 20)
    assert json.loads(conf.get_json("mode")) == "client"  # type: ignore[attr-defined]
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:9"]  # type: ignore[attr-defined]
    f.write_text("mode: [client\n")
    with pytest.raises(TransportError, match="malformed YAML"):
        build_config(ZenohOptions(config_file=f), 1 << 20)


def _ctx() -> TransportContext:
    return TransportContext(robot="r1", fleet="testfleet", max_message_bytes=1 << 20, emit=lambda e: None)


@pytest.mark.parametrize("endpoint", ["tcp/no-such-host.invalid:7447", "nosuchproto/127.0.0.1:1"])
def test_start_with_bad_endpoint_is_one_line(endpoint: str) -> None:
    # (not validated: the options refuse a protocol zenoh lacks since check-config does, and the
    # start must still say in one line whatever reaches it, from an embedding as from a config)
    options = ZenohOptions.model_construct(listen=[endpoint], multicast_scouting=False)
    t = ZenohTransport(options, _ctx())
    with pytest.raises(TransportError, match="cannot open session") as info:
        asyncio.run(t.start())
    assert "\n" not in str(info.value) and ".rs:" not in str(info.value)


def test_start_on_a_port_in_use_fails_cleanly(zk) -> None:
    async def main() -> None:
        ep = zk.endpoint(zk.free_port())
        first = ZenohTransport(ZenohOptions(listen=[ep], multicast_scouting=False), _ctx())
        await first.start()
        try:
            second = ZenohTransport(ZenohOptions(listen=[ep], multicast_scouting=False), _ctx())
            with pytest.raises(TransportError, match="Address already in use"):
                await second.start()
            await second.close()  # closing a transport that never started is fine
        finally:
            await first.close()

    asyncio.run(main())


def test_zenoh_message_strips_rust_locations() -> None:
    exc = RuntimeError(
        "Address already in use (os error 98) at /root/.cargo/x/src/tcp.rs:61.] at /y/unicast.rs:338."
    )
    assert zenoh_message(exc) == "Address already in use (os error 98)]"


def test_close_is_bounded_even_when_zenoh_blocks(zk) -> None:
    """A send stuck in zenoh (say, a full queue to a dead peer) cannot hold close() past its timeout."""

    async def main() -> None:
        opts = ZenohOptions(
            listen=[zk.endpoint(zk.free_port())], multicast_scouting=False, close_timeout_s=0.3
        )
        t = ZenohTransport(opts, _ctx())
        await t.start()
        gate, started = threading.Event(), threading.Event()
        assert t._jobs is not None
        t._jobs.submit("stuck-put", lambda: (started.set(), gate.wait(10)))
        assert started.wait(5)
        begin = asyncio.get_running_loop().time()
        await t.close()
        took = asyncio.get_running_loop().time() - begin
        gate.set()
        assert took < 0.8, f"close took {took:.2f} s"

    asyncio.run(main())


def test_handler_threads_are_waited_for() -> None:
    import time

    import zenoh

    from transports.zenoh.handlers import HandlerSet

    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    hs = HandlerSet()
    dropped: list[str] = []
    session.declare_subscriber("mapd/t/**", hs.callback(lambda s: None, lambda: dropped.append("sub")))
    session.declare_queryable("mapd/t/q", hs.callback(lambda q: q.drop()))
    session.get("mapd/t/q", hs.callback(lambda r: None, lambda: dropped.append("get")), timeout=1.0)
    assert hs.live >= 2
    session.close()
    assert hs.wait(time.monotonic() + 2.0)
    assert hs.live == 0 and sorted(dropped) == ["get", "sub"]


def test_config_toml_table_reaches_the_plugin(tmp_path: Path) -> None:
    from mapd import config

    cfg_file = tmp_path / "config.toml"
    cfg_file.write_text(
        '[robot]\nname = "r1"\n[transports]\nuse = ["zenoh"]\n'
        '[transports.zenoh]\nmode = "client"\nconnect = ["tcp/10.0.0.1:7447"]\nmulticast_scouting = false\n'
    )
    opts = config.plugin_options(config.load(cfg_file), "transports", "zenoh")
    assert isinstance(opts, ZenohOptions)
    assert opts.mode == "client" and opts.connect == ["tcp/10.0.0.1:7447"] and not opts.multicast_scouting
    cfg_file.write_text(
        '[robot]\nname = "r1"\n[transports]\nuse = ["zenoh"]\n[transports.zenoh]\nlisten = ["7447"]\n'
    )
    with pytest.raises(ConfigError, match=r"config\.toml: transports\.zenoh\.listen"):
        config.plugin_options(config.load(cfg_file), "transports", "zenoh")
