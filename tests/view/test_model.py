"""The view's sans-I/O parts: tile diffs, the map/robots/status messages, and the bounded viewer queue."""

from __future__ import annotations

import base64
import json
import math
from typing import Any

import numpy as np
import pytest

from mapd.grid import OCCUPIED, UNKNOWN, OccupancyGrid, Pose2D, StampedPose
from mapd.outputs.base import GlobalUpdate
from mapd.view.model import TRAIL, MapModel, RobotMap, StatusModel
from mapd.view.queue import ClientQueue, Message, sse
from mapd.view.tiles import (
    CLASS_FREE,
    CLASS_OCCUPIED,
    CLASS_UNKNOWN,
    TILE,
    changed_tiles,
    class_image,
    decode_tile,
    encode_tile,
)


def grid(h: int = 300, w: int = 400) -> OccupancyGrid:
    d = np.zeros((h, w), np.int8)
    d[:, 300:] = UNKNOWN
    d[10:20, 10:20] = OCCUPIED
    return OccupancyGrid(d, 0.05, Pose2D(-1.0, -2.0, 0.0), version=1)


def body(msg: Message) -> dict:
    head, data = msg.frame.decode().split("\ndata: ")
    assert head == f"event: {msg.kind}" and data.endswith("\n\n")
    return json.loads(data)


def test_class_image_is_flipped_so_row_zero_is_the_top() -> None:
    g = grid()
    img = class_image(g)
    assert img.shape == (300, 400)
    # map row 10..19 (near the origin, the bottom) is image row 280..289
    assert (img[280:290, 10:20] == CLASS_OCCUPIED).all()
    assert img[0, 0] == CLASS_FREE and img[0, 350] == CLASS_UNKNOWN


def test_changed_tiles_finds_exactly_the_tiles_with_a_changed_cell() -> None:
    a = class_image(grid())
    assert changed_tiles(a, a.copy()) == []
    b = a.copy()
    b[5, 5] = CLASS_OCCUPIED  # tile (0, 0)
    b[299, 399] = CLASS_OCCUPIED  # the last, partial tile (3, 2)
    assert sorted(changed_tiles(a, b)) == [(0, 0), (3, 2)]
    # another shape: every tile
    assert len(changed_tiles(a, np.zeros((10, 10), np.uint8))) == 1
    assert len(changed_tiles(None, a)) == math.ceil(400 / TILE) * math.ceil(300 / TILE)


def test_tile_png_round_trips_with_the_palette_and_edge_tiles_are_not_padded() -> None:
    img = class_image(grid())
    png = encode_tile(img, 3, 2)
    back = decode_tile(png)
    assert back.shape == (300 - 2 * TILE, 400 - 3 * TILE)
    assert np.array_equal(back, img[2 * TILE :, 3 * TILE :])
    assert len(png) < 400  # a mostly uniform tile is tiny


def test_map_model_sends_all_tiles_first_then_only_the_changed_ones() -> None:
    m = MapModel()
    g1 = grid()
    first = body(m.global_map(GlobalUpdate(g1, {}, 1.0)))
    assert first["full"] and len(first["tiles"]) == 12 and first["seq"] == 1
    assert first["geometry"]["origin"] == [-1.0, -2.0] and first["geometry"]["width"] == 400

    d = g1.data.copy()
    d[150, 200] = OCCUPIED  # map row 150 -> image row 149 -> tile (1, 1)
    second = body(m.global_map(GlobalUpdate(g1.replace(data=d, version=2), {}, 2.0)))
    assert not second["full"] and [t[:2] for t in second["tiles"]] == [[1, 1]]
    tile = decode_tile(base64.b64decode(second["tiles"][0][2]))
    assert tile[149 - TILE, 200 - TILE] == CLASS_OCCUPIED
    assert np.array_equal(tile, class_image(g1.replace(data=d))[TILE : 2 * TILE, TILE : 2 * TILE])

    # the full state a new viewer gets holds every tile, the changed one as it is now
    full = m.full_map()
    assert full is not None
    fb = body(full)
    assert fb["full"] and fb["seq"] == 2 and len(fb["tiles"]) == 12
    assert next(t for t in fb["tiles"] if t[:2] == [1, 1])[2] == second["tiles"][0][2]
    assert m.tiles_encoded == 13

    # an unchanged map: a message with no tiles (the viewer's version still advances)
    third = body(m.global_map(GlobalUpdate(g1.replace(data=d, version=3), {}, 3.0)))
    assert third["tiles"] == [] and not third["full"]

    # the map grew: everything again
    bigger = OccupancyGrid(np.zeros((300, 464), np.int8), 0.05, Pose2D(-4.2, -2.0, 0.0))
    fourth = body(m.global_map(GlobalUpdate(bigger, {}, 4.0)))
    assert fourth["full"] and len(fourth["tiles"]) == 4 * 3


def test_robots_message_places_outline_pose_and_a_bounded_trail() -> None:
    m = MapModel(trail=5)
    frame = Pose2D(10.0, 0.0, math.pi / 2)
    m.robot_maps({"r1": RobotMap(40, 20, 0.5, Pose2D(-1.0, -1.0, 0.0))})
    m.global_map(GlobalUpdate(grid(), {"r1": frame}, 1.0))
    r = body(m.robots())["robots"]["r1"]
    assert r["frame"] == [10.0, 0.0, round(math.pi / 2, 4)] and r["pose"] is None
    # the map's corners (-1,-1), (19,-1), (19,9), (-1,9) turned 90 degrees and shifted by 10 m
    flat = [v for corner in r["outline"] for v in corner]
    assert flat == pytest.approx([11, -1, 11, 19, 1, 19, 1, -1], abs=1e-3)
    for i in range(8):
        msg = m.poses({"r1": StampedPose(Pose2D(float(i), 0.0, 0.0), 100.0 + i)}, {})
    r = body(msg)["robots"]["r1"]
    assert r["pose"][:2] == pytest.approx([10.0, 7.0]) and r["pose_stamp"] == 107.0
    assert len(r["trail"]) == 5 and r["trail"][-1] == pytest.approx([10.0, 7.0])
    # an older pose (a global map made before the last pose update) changes nothing
    m.global_map(GlobalUpdate(grid(), {"r1": frame}, 2.0, poses={"r1": StampedPose(Pose2D(), 50.0)}))
    assert body(m.robots())["robots"]["r1"]["pose"][:2] == pytest.approx([10.0, 7.0])
    # standing still adds no point
    body(m.poses({"r1": StampedPose(Pose2D(7.0, 0.0, 0.0), 108.0)}, {}))
    assert len(m._trails["r1"]) == 5 and TRAIL >= 100
    assert r["colour"] != body(m.robots())["robots"].get("x", {}).get("colour")


def test_status_model_measures_link_rate_against_the_budget() -> None:
    s = StatusModel()
    snap: dict[str, Any] = {
        "robot": "r0",
        "fleet": "f",
        "links": {
            "uwb": {"bytes_tx": 1000, "bytes_rx": 0, "link_rate_bps": 12500, "rtt_ms": 80.5, "resends": 3}
        },
        "peers": {"r1": {"link": "uwb", "age_s": 1.5, "version": (7 << 32) | 12, "bytes": 900, "updates": 4}},
        "codec": {"keyframes": 2, "deltas": 9, "last_bytes": 120},
        "source": {"version": 11},
        "fusion": {"robots": {"r1": {"accepted": False, "confidence": 0.2, "reason": "too little overlap"}}},
    }
    first = body(s.message(snap, 100.0))
    assert first["links"][0]["tx_bps"] is None  # a rate needs two snapshots
    snap["links"]["uwb"]["bytes_tx"] = 1000 + 2500  # 2500 B in 4 s = 5000 bit/s
    link = body(s.message(snap, 104.0))["links"][0]
    assert link["tx_bps"] == 5000.0 and link["use"] == 0.4 and link["rtt_ms"] == 80.5
    assert link["resends"] == 3 and link["last_heard_s"] == 1.5
    # the rate is over the last 10 s: older samples fall out of the window
    snap["links"]["uwb"]["bytes_tx"] = 3500 + 1250
    assert body(s.message(snap, 108.0))["links"][0]["tx_bps"] == pytest.approx(8 * 3750 / 8)
    assert body(s.message(snap, 113.0))["links"][0]["tx_bps"] == pytest.approx(8 * 1250 / 9, abs=0.1)
    robots = body(s.message(snap, 116.0))["robots"]
    assert robots["r1"]["label"] == "v12" and robots["r1"]["reason"] == "too little overlap"
    assert robots["r0"]["own"] and robots["r0"]["keyframes"] == 2 and robots["r0"]["deltas"] == 9


def _msg(kind: str, i: int) -> Message:
    return sse(kind, {"i": i}, i)


def test_queue_starts_with_the_full_state_and_keeps_order() -> None:
    q = ClientQueue(limit=4)
    full = [_msg("map", 0)]
    q.put(_msg("map", 1))  # before the first take: the full state covers it
    assert q.take(lambda: full) == full
    q.put(_msg("map", 2))
    q.put(_msg("map", 3))
    assert [m.seq for m in q.take(lambda: full)] == [2, 3]
    assert q.take(lambda: full) == []


def test_queue_latest_wins_for_robots_and_status() -> None:
    q = ClientQueue(limit=4)
    q.take(list)
    for i in range(50):
        q.put(_msg("status", i))
        q.put(_msg("robots", i))
    got = q.take(list)
    assert [(m.kind, body(m)["i"]) for m in got] == [("status", 49), ("robots", 49)]
    assert q.dropped == 98


def test_a_slow_viewer_is_bounded_and_resyncs_to_the_newest_state() -> None:
    q = ClientQueue(limit=8)
    q.take(list)
    newest = [_msg("map", 0)]
    for i in range(1, 10_000):  # a viewer that never reads
        q.put(_msg("map", i))
        newest = [_msg("map", i)]
        assert len(q) <= 8
    got = q.take(lambda: newest)
    assert [m.seq for m in got] == [9999]  # the full state as of now, not 9999 deltas
    assert q.dropped >= 9990
    with pytest.raises(ValueError):
        ClientQueue(limit=1)


def test_a_trail_moves_with_its_robot_when_fusion_places_it_anew_and_goes_when_unplaced() -> None:
    """Trail points are kept in the robot's own map frame; the placement in force puts them in the fleet
    frame. Kept in the fleet frame under the placement of the moment, a re-placed robot's old trail
    stayed where its old placement put it, away from the robot."""
    m = MapModel()
    m.robot_maps({"r1": RobotMap(40, 20, 0.5, Pose2D(-1.0, -1.0, 0.0))})  # listed while unplaced
    for i in range(5):  # along its own map's x axis, placed at the fleet origin
        m.poses({"r1": StampedPose(Pose2D(float(i), 0.0, 0.0), 10.0 + i)}, {"r1": Pose2D()})
    before = body(m.robots())["robots"]["r1"]
    assert np.allclose(before["trail"], [[float(i), 0.0] for i in range(5)])
    # fusion places r1's map anew: turned 90 degrees and shifted by (1, 2) m
    m.global_map(GlobalUpdate(grid(), {"r1": Pose2D(1.0, 2.0, math.pi / 2)}, 1.0))
    r = body(m.robots())["robots"]["r1"]
    assert r["pose"][:2] == pytest.approx([1.0, 6.0], abs=1e-3)
    assert np.allclose(r["trail"], [[1.0, 2.0 + i] for i in range(5)], atol=1e-3)
    # no longer placed: its trail and pose go (they would be in no frame), not kept for later
    m.global_map(GlobalUpdate(grid(), {}, 2.0, poses={"r1": StampedPose(Pose2D(5.0, 0.0, 0.0), 16.0)}))
    r = body(m.robots())["robots"]["r1"]
    assert (r["frame"], r["pose"], r["pose_stamp"], r["trail"]) == (None, None, None, [])
    # placed again: a new trail starts where it is now
    m.poses({"r1": StampedPose(Pose2D(6.0, 0.0, 0.0), 17.0)}, {"r1": Pose2D()})
    assert body(m.robots())["robots"]["r1"]["trail"] == [[6.0, 0.0]]
