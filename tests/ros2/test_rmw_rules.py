"""rmw_zenoh's rules as mapd forms them (mapd.ros2.rmw), against rmw_zenoh's examples and an independent peer."""

from __future__ import annotations

import struct
from pathlib import Path
from types import ModuleType, SimpleNamespace

import pytest

from mapd.errors import CodecError
from mapd.grid import Pose2D, StampedPose
from mapd.outputs.base import PoseUpdate
from mapd.outputs.ros2 import Ros2OutputOptions, pose_transforms
from mapd.ros2 import cdr, rmw
from mapd.ros2.tf import static_transforms

GRID = "nav_msgs/msg/OccupancyGrid"
TF = "tf2_msgs/msg/TFMessage"
JAZZY_GRID_HASH = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling"])
def test_type_hash_per_distro(distro: rmw.Distro, rmw_peer: ModuleType) -> None:
    assert rmw.type_hash(GRID, distro) == JAZZY_GRID_HASH  # as `ros2 topic info -v /map` prints it
    assert rmw.type_hash(TF, distro) == rmw_peer.type_hash(rmw_peer.TF, distro)
    assert rmw.type_hash(TF, distro).startswith("RIHS01_") and len(rmw.type_hash(TF, distro)) == 71


def test_humble_has_no_type_hash() -> None:
    assert rmw.type_hash(GRID, "humble") == "TypeHashNotSupported"
    assert (
        rmw.data_key("/map", GRID, distro="humble")
        == "0/map/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported"
    )


def test_data_keys_carry_domain_namespace_type_and_hash() -> None:
    assert rmw.dds_type(TF) == "tf2_msgs::msg::dds_::TFMessage_"
    assert rmw.fq_topic("map", "/robot1") == "/robot1/map"
    assert rmw.fq_topic("/map", "/robot1") == "/map"  # absolute names ignore the namespace
    assert rmw.data_key(rmw.fq_topic("map", "fleet/a"), GRID, domain=42) == (
        f"42/fleet/a/map/nav_msgs::msg::dds_::OccupancyGrid_/{JAZZY_GRID_HASH}"
    )
    assert rmw.data_key("/tf", TF, hash_="*") == "0/tf/tf2_msgs::msg::dds_::TFMessage_/*"
    assert rmw.bridge_key("/map", namespace="/site") == "site/map"
    for bad in ["", "/", "a//b", "m*p", "m%p"]:
        with pytest.raises(ValueError):
            rmw.data_key(bad, GRID)


def test_qos_strings_follow_rmw_zenoh_defaults() -> None:
    # rmw_zenoh's defaults (reliable, volatile, keep last 42) are left empty; durations are defaults.
    assert rmw.qos_string(rmw.LATCHED) == ":1:,1:,:,:,,"
    assert rmw.qos_string(rmw.DEFAULT_QOS) == "::,:,:,:,,"
    assert rmw.qos_string(rmw.Qos(rmw.BEST_EFFORT, rmw.VOLATILE, rmw.KEEP_ALL, 10)) == "2::2,10:,:,:,,"
    for q in (rmw.LATCHED, rmw.TF_QOS, rmw.Qos(2, 1, 2, 7)):
        assert rmw.parse_qos(rmw.qos_string(q)) == q
    with pytest.raises(ValueError):
        rmw.parse_qos("1:1:1,1")  # the pre-2024 short form lacks the duration fields


def test_tokens_mangle_names_and_match_the_independent_peer(rmw_peer: ModuleType) -> None:
    node = rmw.Entity(0, "abc123", 0, 0, "NN", "/", "mapd")
    assert node.token() == "@ros2_lv/0/abc123/0/0/NN/%/%/mapd"
    pub = rmw.Entity(
        3, "abc123", 0, 4, "MP", "/fleet/site", "mapd", topic="/fleet/site/map", type=rmw.dds_type(GRID),
        type_hash=rmw.type_hash(GRID, "jazzy"), qos=rmw.LATCHED,
    )  # fmt: skip
    token = pub.token()
    assert token == (
        f"@ros2_lv/3/abc123/0/4/MP/%/%fleet%site/mapd/%fleet%site%map/"
        f"nav_msgs::msg::dds_::OccupancyGrid_/{JAZZY_GRID_HASH}/:1:,1:,:,:,,"
    )
    assert rmw.parse_token(token) == pub
    theirs = rmw_peer.parse(token)
    assert (theirs.kind, theirs.namespace, theirs.topic, theirs.qos) == (
        "MP",
        "/fleet/site",
        "/fleet/site/map",
        rmw_peer.qos(True, 1),
    )
    with pytest.raises(ValueError):
        rmw.parse_token("@ros2_lv/0/z/0/1/MP/%/%/n")  # a publisher without its topic
    with pytest.raises(ValueError):
        rmw.Entity(0, "z", 0, 1, "MS", "/", "n").token()


def test_gid_is_xxh3_128_of_the_token_low_half_first(rmw_peer: ModuleType) -> None:
    token = "@ros2_lv/0/1234abcd/0/1/MP/%/%/mapd/%map/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported/:1:,1:,:,:,,"
    ours = rmw.gid_of(token)
    assert len(ours) == 16 and ours == rmw_peer.gid(token)
    # XXH3-128 of the empty string is 99aa06d3014798d86001c324468d497f (canonical: high half first).
    assert rmw.gid_of("") == bytes.fromhex("99aa06d3014798d86001c324468d497f")[::-1]
    assert rmw.gid_of(token + "x") != ours


def test_attachment_layout() -> None:
    gid = bytes(range(16))
    att = rmw.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(att) == 33 and att[16] == 16  # two int64s, then the array as a sequence (LEB128 length 16)
    assert struct.unpack("<qq", att[:16]) == (7, 1_700_000_000_123_456_789)
    assert rmw.parse_attachment(att) == (7, 1_700_000_000_123_456_789, gid)
    with pytest.raises(CodecError):
        rmw.parse_attachment(att[:-1])
    with pytest.raises(ValueError):
        rmw.attachment(1, 0, b"short")


def test_tf_payloads_and_frames(rmw_peer: ModuleType) -> None:
    frames = {"robot1": Pose2D(1.0, -2.0, 0.5), "robot0": Pose2D()}
    items = static_transforms("world", frames, 1700000000.5)
    assert [(p, c) for p, c, _, _ in items] == [("world", "robot0/map"), ("world", "robot1/map")]
    poses = PoseUpdate(poses={"robot1": StampedPose(Pose2D(3.0, 4.0, -1.0), 1700000001.25)}, frames=frames)
    assert [(p, c) for p, c, _, _ in pose_transforms(poses)] == [("robot1/map", "robot1/base_link")]
    msg = rmw_peer.TS.deserialize_cdr(cdr.encode_tf(items + pose_transforms(poses)), rmw_peer.TF)
    t = msg.transforms[1]
    assert (t.header.frame_id, t.child_frame_id) == ("world", "robot1/map")
    assert (t.transform.translation.x, t.transform.translation.y) == (1.0, -2.0)
    assert t.transform.rotation.z == pytest.approx(0.2474039593) and t.transform.rotation.w == pytest.approx(
        0.9689124217
    )
    last = msg.transforms[2]
    assert (last.header.stamp.sec, last.header.stamp.nanosec) == (1700000001, 250000000)


def test_output_options_are_checked() -> None:
    assert Ros2OutputOptions().distro == "jazzy" and Ros2OutputOptions().frame == "map"
    assert Ros2OutputOptions().connect == ["tcp/127.0.0.1:7447"]  # rmw_zenohd, where rmw_zenoh nodes look
    for bad in ({"distro": "iron"}, {"format": "dds"}, {"topic": "a//b"}, {"domain_id": 300}, {"typo": 1}):
        with pytest.raises(ValueError):
            Ros2OutputOptions(**bad)


def test_robot_frames_are_configurable_so_poses_need_not_fight_the_robots_own_tf(
    rmw_peer: ModuleType, tmp_path: Path
) -> None:
    """A frame has one parent: where the robots' own TF (``<robot>/odom -> <robot>/base_link``)
    reaches the same ROS graph, the output's poses must move another frame, or none."""
    from mapd.outputs.base import OutputContext
    from mapd.outputs.ros2 import Ros2Output

    opts = Ros2OutputOptions(robot_map_frame="{robot}/map_fleet", robot_pose_frame="{robot}/mapd_pose")
    out = Ros2Output(opts, OutputContext(robot="base", fleet="f", state_dir=tmp_path))
    sent: list[bytes] = []
    out._tf = out._tf_static = SimpleNamespace(put=sent.append)
    frames = {"robot1": Pose2D(1.0, -2.0, 0.5)}
    poses = {"robot1": StampedPose(Pose2D(3.0, 4.0, -1.0), 1700000001.25)}
    out.publish_poses(PoseUpdate(poses=poses, frames=frames))
    got = [
        (t.header.frame_id, t.child_frame_id)
        for data in sent
        for t in rmw_peer.TS.deserialize_cdr(data, rmw_peer.TF).transforms
    ]
    assert got == [("map", "robot1/map_fleet"), ("robot1/map_fleet", "robot1/mapd_pose")]
    out.publish_poses(PoseUpdate(poses=poses, frames=frames))  # the same stamp: not again (tf2 warns)
    assert len(sent) == 2

    sent.clear()
    quiet = Ros2Output(
        Ros2OutputOptions(robot_pose_frame=""), OutputContext(robot="b", fleet="f", state_dir=tmp_path)
    )
    quiet._tf = quiet._tf_static = SimpleNamespace(put=sent.append)
    quiet.publish_poses(PoseUpdate(poses=poses, frames=frames))
    assert [t.child_frame_id for t in rmw_peer.TS.deserialize_cdr(sent[0], rmw_peer.TF).transforms] == [
        "robot1/map"
    ] and len(sent) == 1  # the map frame, and no pose

    for bad in ("map", "{robot}//x", "{robot}/*", "{robot.__class__}"):
        with pytest.raises(ValueError, match="robot"):
            Ros2OutputOptions(robot_map_frame=bad)
    with pytest.raises(ValueError):
        Ros2OutputOptions(robot_map_frame="")  # the map frames cannot be switched off: the map needs them
