"""ROS 2 OccupancyGrid CDR, key formats, and the ros2 source and sink over a loopback zenoh session."""

from __future__ import annotations

import asyncio
import math
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd import plugins
from mapd.demo.fleet import write_config
from mapd.demo.ports import free_port
from mapd.errors import CodecError, ConfigError, LimitError, TransportError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.ros2 import cdr as ros2cdr
from mapd.ros2.node import Ros2Sink
from mapd.sources.base import SourceContext
from mapd.sources.ros2 import Ros2Options, Ros2Source

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")


def _grid(k: int = 0, yaw: float = 0.3) -> OccupancyGrid:
    rng = np.random.default_rng(k)
    d = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(30 + k, 45))
    return OccupancyGrid(d, 0.05, Pose2D(-2.5, 1.25, yaw), frame_id="map", stamp=1700000000.25 + k)


@pytest.fixture
def publisher_session() -> Iterator[tuple[Any, str]]:
    """A zenoh session listening on a free loopback port, multicast scouting off."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = ros2cdr.open_session(mode="peer", listen=[endpoint])
    yield session, endpoint
    session.close()


def _source(endpoint: str, **kw: Any) -> Ros2Source:
    opts = Ros2Options(mode="peer", connect=[endpoint], **kw)
    return Ros2Source(opts, SourceContext(robot="r2"))


# -- CDR and keys --------------------------------------------------------------------------------------


def test_registered_under_mapd_sources() -> None:
    assert plugins.load("source", "ros2") is Ros2Source


def test_cdr_round_trip_and_fields_as_ros_sees_them() -> None:
    g = _grid(2, yaw=-1.2)
    payload = ros2cdr.encode(g, frame_id="world")
    assert payload[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    msg = ros2cdr._typestore().deserialize_cdr(payload, ros2cdr.MSGTYPE)
    assert (msg.info.width, msg.info.height) == (45, 32) and msg.header.frame_id == "world"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1700000002, 250000000)
    assert msg.info.origin.orientation.z == pytest.approx(math.sin(-0.6))
    assert np.array_equal(msg.data, g.data.ravel())  # row-major, row 0 at the origin, as ROS
    back = ros2cdr.decode(payload)
    assert np.array_equal(back.data, g.data) and back.resolution == 0.05
    assert back.origin.x == -2.5 and back.origin.yaw == pytest.approx(-1.2)
    assert back.stamp == pytest.approx(g.stamp) and back.frame_id == "world"


def test_keys() -> None:
    h = ros2cdr.type_hash()
    assert h.startswith("RIHS01_") and len(h) == 7 + 64
    assert ros2cdr.rmw_zenoh_key("/map") == f"0/map/nav_msgs::msg::dds_::OccupancyGrid_/{h}"
    assert ros2cdr.key_for("/robot1/map", "rmw_zenoh", domain=7, subscribe=True) == (
        "7/robot1/map/nav_msgs::msg::dds_::OccupancyGrid_/*"
    )
    assert ros2cdr.ros2dds_key("/map") == "map"
    assert ros2cdr.ros2dds_key("/map", namespace="/robot1") == "robot1/map"
    for bad in ["", "/", "a//b", "map/*", "m$p"]:
        with pytest.raises(ValueError):
            ros2cdr.rmw_zenoh_key(bad)
    with pytest.raises(ValueError):
        Ros2Options(topic="bad//topic")


@pytest.mark.parametrize(
    ("option", "value", "says"),
    [
        ("topic", "my-map", "not a ROS 2 topic name"),  # the older check let these through
        ("topic", "/map/", "not a ROS 2 topic name"),
        ("topic", "/2d/map", "not a ROS 2 topic name"),
        ("topic", "/ma p", "not a ROS 2 topic name"),
        ("topic", "~/map", "does not expand '~'"),
        ("topic", "bad//topic", "not a ROS 2 topic name"),
        ("pose_topic", "amcl-pose", "not a ROS 2 topic name"),
        ("pose_topic", "/1pose", "not a ROS 2 topic name"),
        ("pose_topic", "/{node}/pose", "does not expand"),
        ("robot_map_topic", "my-map", "not a ROS 2 topic name"),
        ("robot_map_topic", "map/", "not a ROS 2 topic name"),
        ("robot_map_topic", "2map", "not a ROS 2 topic name"),
        # rcl takes it, but discovery reads /<robot>/<one name>: no robot would ever be taken
        ("robot_map_topic", "slam/map", "one name under each robot's namespace"),
        ("namespace", "my-fleet", "not a ROS 2 namespace name"),
        ("namespace", "/fleet//a", "not a ROS 2 namespace name"),
    ],
)
def test_the_sources_topic_options_are_names_rcl_accepts(
    tmp_path: Path, option: str, value: str, says: str
) -> None:
    # [output.ros2] checks its names as rcl does; the source kept a looser check, so a name no ROS
    # node can publish on ('my-map') was taken and the source waited for maps that never came.
    from mapd import config as configmod

    def load(options: dict[str, Any]) -> Any:
        path = tmp_path / "mapd.toml"
        write_config(
            path, {"robot": {"name": "r1", "fleet": "lab"}, "source": {"use": "ros2", "ros2": options}}
        )
        return configmod.plugin_options(configmod.load(path), "source", "ros2")

    extra = {"discover_robots": True} if option == "robot_map_topic" else {}
    with pytest.raises(ConfigError) as info:
        load({option: value, **extra})
    line = str(info.value)
    assert "\n" not in line and line.count("source.ros2.") == 1, line  # one line
    assert f"source.ros2.{option}:" in line and says in line, line
    good = {
        "topic": ["/map", "map", "/robot_1/map", "fleet/map"],
        "pose_topic": ["/amcl_pose", "amcl_pose", "/robot1/amcl_pose"],
        "robot_map_topic": ["map", "grid_map", "/map"],
        "namespace": ["", "/", "robot1", "/fleet/robot_1/"],
    }[option]
    for ok in good:
        opts = load({option: ok, **extra})
        assert getattr(opts, option) in (ok, "/" + ok.lstrip("/")), (option, ok)


def test_decode_rejects_garbage_and_oversized_grids() -> None:
    good = ros2cdr.encode(_grid())
    with pytest.raises(CodecError, match="topic /map: "):
        ros2cdr.decode(good[: len(good) // 2], where="topic /map")
    with pytest.raises(CodecError, match="encapsulation"):
        ros2cdr.decode(b"\x07\x07" + good[2:])
    with pytest.raises(LimitError):
        ros2cdr.decode(good, max_cells=100)
    # A header claiming more cells than the data holds.
    msg = ros2cdr._typestore().deserialize_cdr(good, ros2cdr.MSGTYPE)
    msg.info.width = 46
    lie = bytes(ros2cdr._typestore().serialize_cdr(msg, ros2cdr.MSGTYPE))
    with pytest.raises(CodecError, match="cells for a 46 x 30 grid"):
        ros2cdr.decode(lie)


@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_fuzz_decode_only_raises_mapd_errors(data: st.DataObject) -> None:
    good = bytearray(ros2cdr.encode(_grid(1)))
    kind = data.draw(st.sampled_from(["flip", "cut", "random"]))
    if kind == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(good) - 1))
            good[i] = data.draw(st.integers(0, 255))
        payload = bytes(good)
    elif kind == "cut":
        payload = bytes(good[: data.draw(st.integers(0, len(good)))])
    else:
        payload = b"\x00\x01\x00\x00" + data.draw(st.binary(max_size=300))
    try:
        g = ros2cdr.decode(payload, max_cells=10_000)
    except (CodecError, LimitError) as exc:
        assert str(exc).startswith("CDR payload: ")
    else:
        assert g.cells <= 10_000 and g.resolution > 0


# -- over zenoh -------------------------------------------------------------------------------------------


async def _next(it: Any, timeout: float = 10.0) -> OccupancyGrid:
    grid: OccupancyGrid = await asyncio.wait_for(it.__anext__(), timeout)
    return grid


def test_late_subscriber_gets_the_current_map_then_updates(
    publisher_session: tuple[Any, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    session, endpoint = publisher_session
    # The digest that tells a new map from a repeat is a pass over every cell: never on the loop.
    hashed_on: list[threading.Thread] = []
    digest = OccupancyGrid.digest

    def recording(grid: OccupancyGrid) -> bytes:
        hashed_on.append(threading.current_thread())
        return digest(grid)

    monkeypatch.setattr(OccupancyGrid, "digest", recording)
    sink = Ros2Sink(session, "/map")
    first, second = _grid(1), _grid(2)
    sink.publish(first)  # before anyone subscribes: transient local
    src = _source(endpoint)

    async def go() -> tuple[OccupancyGrid, OccupancyGrid, dict[str, Any]]:
        it = src.maps().__aiter__()
        a = await _next(it)
        # Keep the stream waiting while the next samples arrive, so each is decoded in turn.
        waiting = asyncio.ensure_future(_next(it))
        # A payload that does not parse is counted and skipped; the stream goes on.
        session.put(ros2cdr.rmw_zenoh_key("/map"), b"\x00\x01\x00\x00garbage")
        await asyncio.sleep(0.3)
        sink.publish(first)  # the same map again: not a new version
        await asyncio.sleep(0.3)
        assert not waiting.done()
        sink.publish(second)
        b = await waiting
        stats = src.stats()
        await it.aclose()
        return a, b, stats

    a, b, stats = asyncio.run(go())
    sink.close()
    assert np.array_equal(a.data, first.data) and a.version == 1 and a.robot == "r2"
    assert np.array_equal(b.data, second.data) and b.version == 2
    assert stats["bad_payloads"] == 1 and "topic /map" in str(stats["last_error"])
    assert src._session is None  # closed with the stream
    assert len(hashed_on) == 3 and threading.main_thread() not in hashed_on  # first, first, second


def test_sink_attachment_and_liveliness_follow_rmw_zenoh(
    publisher_session: tuple[Any, str], zenoh_linked: Callable[..., None]
) -> None:
    session, endpoint = publisher_session
    other = ros2cdr.open_session(mode="peer", connect=[endpoint])
    got: list[Any] = []
    sub = other.declare_subscriber(ros2cdr.key_for("/map", "rmw_zenoh", subscribe=True), got.append)
    sink = Ros2Sink(session, "/map", node="fusion")
    zenoh_linked(other)  # the subscription reaches the sink's session
    sink.publish(_grid(3))
    sink.publish(_grid(4))
    deadline = time.time() + 5
    while len(got) < 2 and time.time() < deadline:
        time.sleep(0.05)
    tokens = [str(r.ok.key_expr) for r in other.liveliness().get("@ros2_lv/0/**", timeout=3.0) if r.ok]
    sink.close()
    sub.undeclare()
    other.close()
    assert len(got) == 2
    att = got[1].attachment.to_bytes()
    seq, stamp = struct.unpack("<qq", att[:16])
    assert seq == 2 and abs(stamp / 1e9 - time.time()) < 30 and att[16] == 16 and len(att) == 33
    assert ros2cdr.decode(got[1].payload.to_bytes()).same_map(_grid(4))
    pubs = [t for t in tokens if "/MP/" in t]
    assert any(
        t.endswith(f"/%/%/fusion/%map/{ros2cdr.DDS_TYPE}/{ros2cdr.type_hash()}/:1:,1:,:,:,,") for t in pubs
    )
    assert any("/NN/" in t and t.endswith("/fusion") for t in tokens)


def test_bridge_key_format_with_namespace(publisher_session: tuple[Any, str]) -> None:
    session, endpoint = publisher_session
    src = _source(endpoint, key_format="ros2dds", namespace="robot1", history=False)
    assert src.key == "robot1/map"

    async def go() -> OccupancyGrid:
        it = src.maps().__aiter__()
        task = asyncio.ensure_future(_next(it))
        grid = _grid(5)
        # A bridge publishes plain puts; keep putting until the subscriber is up.
        for _ in range(50):
            session.put("robot1/map", ros2cdr.encode(grid))
            done, _ = await asyncio.wait({task}, timeout=0.1)
            if done:
                break
        out = await task
        await it.aclose()
        return out

    g = asyncio.run(go())
    assert np.array_equal(g.data, _grid(5).data)


# -- what a misbehaving ROS graph sends (found by an audit against the real code) ------------------


def _payload(**fields: Any) -> bytes:
    """A valid map's CDR with ``info``/``header`` fields changed (``resolution=1e-30``, ...)."""
    msg = ros2cdr._typestore().deserialize_cdr(ros2cdr.encode(_grid()), ros2cdr.MSGTYPE)
    for name, value in fields.items():
        if name == "frame_id":
            msg.header.frame_id = value
        elif name == "q":
            o = msg.info.origin.orientation
            o.x, o.y, o.z, o.w = value
        else:
            setattr(msg.info, name, value)
    if "width" in fields:
        msg.data = np.zeros(fields["width"] * msg.info.height, np.int8)
    return bytes(ros2cdr._typestore().serialize_cdr(msg, ros2cdr.MSGTYPE))


def test_a_decoded_map_is_one_the_lossless_codec_codes() -> None:
    # The message's cells were a read-only view of the payload: numba's kernel refused them with a
    # TypingError, no MapdError, and the daemon stopped at the first map it sent (default codec).
    from mapd.codec import decode, encode

    grid = ros2cdr.decode(ros2cdr.encode(_grid(3)))
    assert grid.data.flags.writeable
    assert decode(encode(grid, "lossless"), None).same_map(grid)
    frozen = _grid(4)
    frozen.data.flags.writeable = False  # any read-only grid, whoever made it
    assert decode(encode(frozen, "lossless", base=_grid(4)), _grid(4)).same_map(frozen)


@pytest.mark.parametrize(
    ("fields", "says"),
    [
        ({"resolution": 1e-30}, "resolution"),  # took, and froze the global map at 1e-30 until a restart
        ({"resolution": 1e6}, "resolution"),
        ({"width": 70_000}, "over 65536 cells a side"),
        ({"frame_id": "m" * 65}, "65 characters"),  # every peer refused its envelopes, unsaid
        ({"frame_id": "map\n03:00:00 ERROR forged"}, "printable"),
    ],
)
def test_a_map_no_envelope_or_map_file_could_hold_is_refused(fields: dict[str, Any], says: str) -> None:
    with pytest.raises(CodecError, match=says) as err:
        ros2cdr.decode(_payload(**fields), where="topic /map")
    assert "\n" not in str(err.value)


def test_a_quaternion_of_huge_numbers_is_a_yaw_not_nan() -> None:
    g = ros2cdr.decode(_payload(q=(1e200, -1e200, 1e200, 1e200)))  # the products overflowed: NaN
    assert math.isfinite(g.origin.yaw)
    assert ros2cdr.decode(_payload(q=(0.0, 0.0, 0.0, 0.0))).origin.yaw == 0.0


def _discovering(robot: str = "base", **kw: Any) -> Ros2Source:
    return Ros2Source(Ros2Options(discover_robots=True, **kw), SourceContext(robot=robot))


def test_a_ros_robot_named_as_this_robot_or_with_a_newline_is_not_taken(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # "base/map" was taken as the base station's own map: signed and sent to the fleet as its own.
    src = _discovering()
    assert src.robot_of_topic("/base/map") is None
    assert src.robot_of_topic("/robot1\n/map") is None and src.robot_of_key("0/robot1\n/map/x/y") is None
    assert src.robot_of_topic("/robot1/map") == "robot1"
    assert sum("as this robot is" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.parametrize("key_format", ["rmw_zenoh", "ros2dds"])
def test_robot_names_are_bounded_in_every_key_format(key_format: str) -> None:
    # ros2dds has no node and no tokens: every made-up name was kept (17,940 of them in an audit).
    src = _discovering(max_robots=4, key_format=key_format, known_init_poses=True)
    keys = [f"0/r{i}/map/t/h" if key_format == "rmw_zenoh" else f"r{i}/map" for i in range(1000)]
    taken = {src.robot_of_key(k) for k in keys} - {None}
    assert taken == {"r0", "r1", "r2", "r3"} and len(src._taken) == 4 and len(src._ignored) <= 64


def test_a_publisher_that_leaves_without_a_map_frees_its_place() -> None:
    # Four made-up publisher tokens, withdrawn a second later, held every place for ever.
    src = _discovering(max_robots=4)
    assert all(src.robot_of_topic(f"/robotx{i}/map") for i in range(4))
    assert src.robot_of_topic("/robot1/map") is None
    for i in range(4):
        src._publisher_gone(f"/robotx{i}/map")
    assert src.robot_of_topic("/robot1/map") == "robot1"


def test_a_key_is_logged_as_one_short_line(caplog: pytest.LogCaptureFixture) -> None:
    src = _discovering()
    key = "0/robot1/map/x\n03:00:00 ERROR mapd.daemon: forged " + "A" * 4000
    assert src._decode(key, b"junk") is None
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "\n" not in said[0] and len(said[0]) < 400


def test_samples_arriving_while_the_loop_is_busy_are_held_one_per_key() -> None:
    # One callback a sample was queued on the loop, each holding its payload: a 16 MiB map at
    # 100 Hz while the loop was busy held a gigabyte within seconds.
    class Sample:
        def __init__(self, data: bytes) -> None:
            self.key_expr = "0/map/nav_msgs::msg::dds_::OccupancyGrid_/x"
            self.payload = zenoh.ZBytes(data)  # held as zenoh gave it: copied only once its size is checked

    src = Ros2Source(Ros2Options(), SourceContext(robot="r2"))
    loop = asyncio.new_event_loop()
    try:
        big = b"\x00" * (1 << 20)
        threads = [
            threading.Thread(target=lambda: [src._on_sample(loop, Sample(big)) for _ in range(250)])
            for _ in range(4)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(src._inbox) == 1 and len(loop._ready) == 1  # type: ignore[attr-defined]
        src._on_sample(loop, Sample(b"newest"))
        loop.run_until_complete(asyncio.sleep(0))
        assert list(src._pending) == ["r2"] and src._inbox == {}
        key, payload = src._pending["r2"]
        assert (key, payload.to_bytes()) == (Sample(b"").key_expr, b"newest")
        assert src.stats()["replaced_before_decode"] == 1000 and src.stats()["received"] == 1
    finally:
        loop.close()


def test_a_client_that_finds_no_router_waits_for_it_and_then_takes_maps(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # rmw_zenohd starting after mapd at boot stopped the daemon (its links too) until it was up.
    from mapd.commands.status_text import render_status
    from mapd.daemon.headline import status_line
    from mapd.ros2 import zenoh_config

    monkeypatch.setattr(zenoh_config, "RETRY_FIRST_S", 0.2)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    src = Ros2Source(Ros2Options(mode="client", connect=[endpoint]), SourceContext(robot="r2"))

    async def go() -> OccupancyGrid:
        it = src.maps().__aiter__()
        first = asyncio.ensure_future(_next(it, 20.0))
        await asyncio.sleep(1.0)  # several tries, no router
        assert not first.done() and src.stats()["session_open"] is False
        doc = {"source": {"name": "ros2", "version": 0, "stats": src.stats()}}
        assert "FAULTS zenoh session not open yet (trying again)" in render_status(doc)
        assert status_line(doc).startswith("FAULTS source zenoh session not open yet")
        router = await asyncio.to_thread(ros2cdr.open_session, mode="router", listen=[endpoint])
        sink = Ros2Sink(router, "/map")
        try:
            sink.publish(_grid(3))  # transient local: the source gets it once it is in
            grid = await first
            assert src.stats()["session_open"] is True and src.stats()["last_error"] == ""
            await it.aclose()
        finally:
            sink.close()
            router.close()
        return grid

    assert np.array_equal(asyncio.run(go()).data, _grid(3).data)


def test_a_session_refused_for_another_cause_still_stops_the_source() -> None:
    # (not validated: the options refuse such an endpoint since check-config does; what reaches the
    # session all the same, from an embedding, must still stop the source)
    options = Ros2Options.model_construct(mode="peer", listen=["tcp/127.0.0.1:notaport"])
    src = Ros2Source(options, SourceContext(robot="r2"))

    async def go() -> None:
        with pytest.raises(TransportError):
            await src.maps().__anext__()

    asyncio.run(go())


def test_a_payload_over_what_a_grid_needs_is_refused_by_its_size_before_it_is_copied() -> None:
    # It was copied out of zenoh first (to_bytes) and refused after: a 300 MiB sample on /map,
    # which any node on the robot's graph may publish, cost the daemon 600 MiB.
    class Huge:
        def __len__(self) -> int:
            return 300 << 20

        def to_bytes(self) -> bytes:
            raise AssertionError("copied before its size was checked")

    src = Ros2Source(Ros2Options(), SourceContext(robot="r2", max_cells=1 << 20))
    assert src._decode("0/map/x", Huge()) is None
    assert src.stats()["last_error"].endswith(
        f"{300 << 20} bytes is more than a grid of {1 << 20} cells needs"
    )


@pytest.mark.parametrize("snap", [False, True])
def test_snap_origin_puts_a_slam_maps_fractional_origin_moves_on_the_first_maps_lattice(
    publisher_session: tuple[Any, str], snap: bool
) -> None:
    # slam_toolbox (Karto) sets its map's origin to its scans' bounding-box corner, which moves by a
    # fraction of a cell as the map grows: no delta aligned the versions, and each went whole.
    from mapd.codec.lossless import alignment

    session, endpoint = publisher_session
    first = _grid(1, yaw=0.3)
    grown = _grid(2, yaw=0.3)
    # grown by 7.26 cells towards -x (in the map's own axes), as Karto's corner moves
    shift = -7.26 * 0.05
    grown = grown.replace(
        origin=Pose2D(first.origin.x + shift * math.cos(0.3), first.origin.y + shift * math.sin(0.3), 0.3)
    )
    sink = Ros2Sink(session, "/map")
    sink.publish(first)
    src = _source(endpoint, snap_origin=snap)

    async def go() -> tuple[OccupancyGrid, OccupancyGrid]:
        it = src.maps().__aiter__()
        a = await _next(it)
        sink.publish(grown)
        b = await _next(it)
        await it.aclose()
        return a, b

    a, b = asyncio.run(go())
    sink.close()
    assert a.origin == first.origin  # the first map sets the lattice, as it came
    moved = math.hypot(b.origin.x - grown.origin.x, b.origin.y - grown.origin.y)
    if snap:
        assert alignment(b.resolution, b.origin, a) == (0, -7)  # a delta codes against it
        assert moved == pytest.approx(0.26 * 0.05, abs=1e-9)  # under half a cell
    else:
        assert alignment(b.resolution, b.origin, a) is None and moved == 0.0
