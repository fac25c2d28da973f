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
from mapd.view.model import MAP_FORMAT, TRAIL, MapModel, RobotMap, StatusModel
from mapd.view.queue import ClientQueue, Message, sse
from mapd.view.tiles import (
    CLASS_FREE,
    CLASS_OCCUPIED,
    CLASS_UNKNOWN,
    Geometry,
    all_tiles,
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
    g = grid()
    geo = Geometry.of(g)
    # on the fleet frame's lattice: cell (0, 0) at (-1, -2) m is lattice column -20; the top row
    # (y = 13 m, cell 259 up from -40) is lattice row -260, counted downwards
    assert (geo.col0, geo.row0) == (-20, -260) and geo.span == (-1, 3, -3, 1)
    a = class_image(g)
    assert changed_tiles(a, a.copy(), geo) == []
    b = a.copy()
    b[5, 5] = CLASS_OCCUPIED  # lattice (-15, -255): tile (-1, -2), the clipped top-left one
    b[299, 399] = CLASS_OCCUPIED  # lattice (379, 39): the clipped bottom-right tile (2, 0)
    assert sorted(changed_tiles(a, b, geo)) == [(-1, -2), (2, 0)]
    # another shape for the same geometry: every tile
    assert len(changed_tiles(np.zeros((10, 10), np.uint8), a, geo)) == 16
    assert len(changed_tiles(None, a, geo)) == 4 * 4 == len(all_tiles(geo))


def test_tile_png_round_trips_with_the_palette_and_edge_tiles_are_clipped_on_every_side() -> None:
    g = grid()
    geo = Geometry.of(g)
    img = class_image(g)
    png = encode_tile(img, geo, 2, 0)  # lattice columns 256..379 of -20..379, rows 0..39 of -260..39
    back = decode_tile(png)
    assert back.shape == (40, 124)
    assert np.array_equal(back, img[260:, 276:])
    assert len(png) < 400  # a mostly uniform tile is tiny
    top_left = decode_tile(encode_tile(img, geo, -1, -3))  # lattice columns -20..-1, rows -260..-257
    assert np.array_equal(top_left, img[:4, :20])
    # every cell is in exactly one tile
    cover = np.zeros(img.shape, int)
    for tx, ty in all_tiles(geo):
        rows, cols = geo.block(tx, ty)
        cover[rows, cols] += 1
    assert (cover == 1).all()


def test_map_model_sends_all_tiles_first_then_only_the_changed_ones() -> None:
    m = MapModel()
    g1 = grid()
    first = body(m.global_map(GlobalUpdate(g1, {}, 1.0)))
    assert first["full"] and len(first["tiles"]) == 16 and first["seq"] == 1
    assert first["geometry"]["origin"] == [-1.0, -2.0] and first["geometry"]["width"] == 400
    assert first["geometry"]["lattice"] == [-20, -260] and first["format"] == MAP_FORMAT

    d = g1.data.copy()
    d[150, 200] = OCCUPIED  # map row 150 -> image row 149 -> lattice (180, -111) -> tile (1, -1)
    second = body(m.global_map(GlobalUpdate(g1.replace(data=d, version=2), {}, 2.0)))
    assert not second["full"] and [t[:2] for t in second["tiles"]] == [[1, -1]]
    tile = decode_tile(base64.b64decode(second["tiles"][0][2]))
    assert tile[149 - 132, 200 - 148] == CLASS_OCCUPIED  # the tile starts at image row 132, column 148
    assert np.array_equal(tile, class_image(g1.replace(data=d))[132:260, 148:276])

    # the full state a new viewer gets holds every tile, the changed one as it is now
    full = m.full_map()
    assert full is not None
    fb = body(full)
    assert fb["full"] and fb["seq"] == 2 and len(fb["tiles"]) == 16
    assert next(t for t in fb["tiles"] if t[:2] == [1, -1])[2] == second["tiles"][0][2]
    assert m.tiles_encoded == 17

    # an unchanged map: a message with no tiles (the viewer's version still advances)
    third = body(m.global_map(GlobalUpdate(g1.replace(data=d, version=3), {}, 3.0)))
    assert third["tiles"] == [] and not third["full"]

    # the map grew by 64 columns toward -x, and all its cells are free now: the tiles whose extent
    # changed (the left column) and those with a changed cell (the unknown ones on the right and
    # the occupied ones), not everything
    bigger = OccupancyGrid(np.zeros((300, 464), np.int8), 0.05, Pose2D(-4.2, -2.0, 0.0))
    fourth = body(m.global_map(GlobalUpdate(bigger, {}, 4.0)))
    assert not fourth["full"] and fourth["geometry"]["lattice"] == [-84, -260]
    left = {(-1, ty) for ty in range(-3, 1)}
    right = {(2, ty) for ty in range(-3, 1)}
    assert {tuple(t[:2]) for t in fourth["tiles"]} == left | right | {(1, -1)}


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


# ---------------------------------------------------------------- a map that grows while robots explore


class Canvas:
    """What the page does with ``map`` messages (view.js onMap), in numpy: its canvas of cells."""

    def __init__(self) -> None:
        self.geometry: dict[str, Any] | None = None
        self.cells = np.zeros((0, 0), np.uint8)

    def apply(self, msg: dict[str, Any]) -> None:
        g = msg["geometry"]
        if msg["full"] or g != self.geometry:
            cells = np.full((g["height"], g["width"]), CLASS_UNKNOWN, np.uint8)
            if not msg["full"]:  # grown on the same lattice: the old canvas, copied where it lies now
                assert self.geometry is not None and g["resolution"] == self.geometry["resolution"]
                dx = self.geometry["lattice"][0] - g["lattice"][0]
                dy = self.geometry["lattice"][1] - g["lattice"][1]
                h, w = self.cells.shape
                r0, r1 = max(0, dy), min(g["height"], dy + h)
                c0, c1 = max(0, dx), min(g["width"], dx + w)
                cells[r0:r1, c0:c1] = self.cells[r0 - dy : r1 - dy, c0 - dx : c1 - dx]
            self.cells = cells
        self.geometry = g
        tile, (lc, lr) = g["tile"], g["lattice"]
        for tx, ty, b64 in msg["tiles"]:
            t = decode_tile(base64.b64decode(b64))
            x, y = max(tx * tile, lc) - lc, max(ty * tile, lr) - lr
            assert x >= 0 and y >= 0 and y + t.shape[0] <= g["height"] and x + t.shape[1] <= g["width"]
            self.cells[y : y + t.shape[0], x : x + t.shape[1]] = t


def _explored(h: int = 512, w: int = 640) -> np.ndarray:
    """A map with something in every tile (free room, noise walls), so a re-sent tile is visible."""
    rng = np.random.default_rng(3)
    d = np.full((h, w), UNKNOWN, np.int8)
    d[20:-20, 20:-20] = 0
    d[rng.random(d.shape) < 0.01] = OCCUPIED
    return d


def _grown(d: np.ndarray, side: str, k: int = 64) -> tuple[np.ndarray, float, float]:
    """``d`` with ``k`` unknown cells more on one side, and how far (m) its origin moved in x and y."""
    h, w = d.shape
    out = np.full((h + k * (side in "-y+y"), w + k * (side in "-x+x")), UNKNOWN, np.int8)
    r, c = (k if side == "-y" else 0), (k if side == "-x" else 0)  # row 0 is the lowest y
    out[r : r + h, c : c + w] = d
    return out, -k * RES if side == "-x" else 0.0, -k * RES if side == "-y" else 0.0


RES = 0.05


@pytest.mark.parametrize(
    ("side", "sent"),
    [
        # the map starts at lattice (0, -512): 5 x 4 whole tiles. Toward -x / -y: a new column / row
        # of tiles; toward +x / +y: the same, as the map is on the tile lattice (edges fall on it)
        ("-x", {(-1, ty) for ty in range(-4, 0)}),
        ("+x", {(5, ty) for ty in range(-4, 0)}),
        ("-y", {(tx, 0) for tx in range(5)}),
        ("+y", {(tx, -5) for tx in range(5)}),
    ],
)
def test_a_map_grown_by_one_chunk_sends_only_the_new_tiles(side: str, sent: set[tuple[int, int]]) -> None:
    """Before: any change of geometry sent every tile again (a 2000 x 2000 map: 183 kB, not 3)."""
    m, page = MapModel(), Canvas()
    d = _explored()
    page.apply(body(m.global_map(GlobalUpdate(OccupancyGrid(d, RES, Pose2D(0.0, 0.0, 0.0)), {}, 1.0))))
    assert len(all_tiles(Geometry.of(OccupancyGrid(d, RES)))) == 20
    grown, ox, oy = _grown(d, side)
    g2 = OccupancyGrid(grown, RES, Pose2D(ox, oy, 0.0))
    msg = body(m.global_map(GlobalUpdate(g2, {}, 2.0)))
    assert not msg["full"] and {tuple(t[:2]) for t in msg["tiles"]} == sent
    page.apply(msg)
    assert np.array_equal(page.cells, class_image(g2))  # the page's pixels: as if sent whole

    # and a cell changed inside the new map's old part: that one tile (its old lattice place)
    grown[300, 300] = OCCUPIED if grown[300, 300] != OCCUPIED else 0
    g3 = g2.replace(data=grown)
    msg = body(m.global_map(GlobalUpdate(g3, {}, 3.0)))
    assert len(msg["tiles"]) == 1
    page.apply(msg)
    assert np.array_equal(page.cells, class_image(g3))


def test_a_map_grown_off_the_tile_lattice_resends_its_edge_tiles_and_shrinks_too() -> None:
    """Half-tile chunks (merge.py grows by 64 of the 128 cells): the clipped edge tile grows to a
    whole one and is sent again, and a map that lost a side drops the tiles now off it."""
    m, page = MapModel(), Canvas()
    d = _explored(384, 512)  # origin (-64, -64) cells: lattice columns -64..447, rows -320..63
    g1 = OccupancyGrid(d, RES, Pose2D(-3.2, -3.2, 0.0))
    page.apply(body(m.global_map(GlobalUpdate(g1, {}, 1.0))))
    assert Geometry.of(g1).span == (-1, 4, -3, 1)  # 4 x 4 tiles, each side's half a tile
    cur, ox, oy = d, -3.2, -3.2
    for side in ("-x", "+y", "+x", "-y"):
        cur, dx, dy = _grown(cur, side)
        ox, oy = ox + dx, oy + dy
        g = OccupancyGrid(cur, RES, Pose2D(ox, oy, 0.0))
        msg = body(m.global_map(GlobalUpdate(g, {}, 2.0)))
        assert not msg["full"]
        # 64 cells more on a side of a map whose edge was mid-tile: the edge tiles become whole
        assert len(msg["tiles"]) == (Geometry.of(g).rows if side in "-x+x" else Geometry.of(g).cols), side
        page.apply(msg)
        assert np.array_equal(page.cells, class_image(g)), side
    # shrunk by 100 cells toward +x and 30 rows on the top: tiles off the map go from the full state
    cut = OccupancyGrid(cur[:-30, 100:], RES, Pose2D(ox + 100 * RES, oy, 0.0))
    msg = body(m.global_map(GlobalUpdate(cut, {}, 3.0)))
    assert not msg["full"]
    page.apply(msg)
    assert np.array_equal(page.cells, class_image(cut))
    full = m.full_map()
    assert full is not None
    assert {tuple(t[:2]) for t in body(full)["tiles"]} == set(all_tiles(Geometry.of(cut)))


def test_the_full_state_after_growth_is_a_fresh_models() -> None:
    """A new viewer of a grown map gets exactly what it would from a model that saw only that map."""
    m = MapModel()
    d = _explored()
    ox = oy = 0.0
    m.global_map(GlobalUpdate(OccupancyGrid(d, RES, Pose2D(ox, oy, 0.0)), {}, 1.0))
    for side in ("-x", "+y", "+x", "-y"):
        d, dx, dy = _grown(d, side)
        ox, oy = ox + dx, oy + dy
        m.global_map(GlobalUpdate(OccupancyGrid(d, RES, Pose2D(ox, oy, 0.0)), {}, 1.0))
    d[100:140, 200:260] = OCCUPIED  # and a change after the growth
    g = OccupancyGrid(d, RES, Pose2D(ox, oy, 0.0), version=7)
    assert (ox, oy) == (-3.2, -3.2)
    m.global_map(GlobalUpdate(g, {}, 5.0))
    fresh = MapModel()
    fresh.global_map(GlobalUpdate(g, {}, 5.0))
    grown_full, fresh_full = m.full_map(), fresh.full_map()
    assert grown_full is not None and fresh_full is not None
    a, b = body(grown_full), body(fresh_full)
    assert a.pop("seq") == 6 and b.pop("seq") == 1
    assert a == b and a["full"]
    page = Canvas()
    page.apply(body(grown_full))
    assert np.array_equal(page.cells, class_image(g))


def test_a_change_of_resolution_or_a_fractional_move_still_sends_everything() -> None:
    m = MapModel()
    d = _explored()
    m.global_map(GlobalUpdate(OccupancyGrid(d, RES, Pose2D(0.0, 0.0, 0.0)), {}, 1.0))
    coarser = OccupancyGrid(d[::2, ::2].copy(), 2 * RES, Pose2D(0.0, 0.0, 0.0))
    msg = body(m.global_map(GlobalUpdate(coarser, {}, 2.0)))
    assert msg["full"] and len(msg["tiles"]) == len(all_tiles(Geometry.of(coarser)))
    half = OccupancyGrid(coarser.data, 2 * RES, Pose2D(0.05, 0.0, 0.0))  # half a cell over
    msg = body(m.global_map(GlobalUpdate(half, {}, 3.0)))
    assert msg["full"] and len(msg["tiles"]) == len(all_tiles(Geometry.of(half)))
    page = Canvas()
    page.apply(msg)
    assert np.array_equal(page.cells, class_image(half))
