"""``mapd bench swarm --bound``: the all-knowing scheduler is a bound, not a protocol, and must act like one."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.bench.swarm.bound import Bound, BoundResult, summarize_bound
from mapd.bench.swarm.links import link_matrices
from mapd.bench.swarm.metrics import summarize
from mapd.bench.swarm.sim import Swarm, SwarmConfig
from mapd.bench.swarm.streams import Fleet, Payloads, RobotStream
from mapd.cli import main
from mapd.codec import encode
from mapd.grid import OccupancyGrid


def _cfg(**kw: Any) -> SwarmConfig:
    return SwarmConfig(**{"duration": 90.0, "drain": 60.0, "start_spread": 5.0, **kw})


def _bound(fleet: Fleet, tmp_path: Path, mode: str, **kw: Any) -> tuple[BoundResult, dict[str, Any]]:
    cfg = _cfg(**kw)
    res = Bound(fleet, Payloads(tmp_path, "lossless"), cfg, mode).run()
    return res, summarize_bound(res, cfg)


def test_two_robots_in_range_get_every_version(swarm: SimpleNamespace, tmp_path: Path) -> None:
    res, row = _bound(swarm.fleet([(0.0, 0.0), (5.0, 0.0)]), tmp_path, "one")
    assert sorted((h, o, v) for _, h, o, v in res.accepted) == [(0, 1, v) for v in (1, 2, 3)] + [
        (1, 0, v) for v in (1, 2, 3)
    ]
    assert math.isfinite(row["converge_s"])
    assert row["stale_p95_s"] < 5.0  # a small map takes a slot or two, not a period


def test_later_versions_go_as_deltas_on_what_the_neighbour_holds(
    swarm: SimpleNamespace, tmp_path: Path
) -> None:
    """A large map of noise that changes a little each version: a delta costs fewer slots than the
    whole map, so after the first version only deltas go, each on the version the other holds."""
    rng = np.random.default_rng(0)
    data = rng.choice(np.array([-1, 0, 100], dtype=np.int8), (120, 120))
    kfs = []
    for v in range(4):
        data[v, :] = 0
        kfs.append(encode(OccupancyGrid(data.copy(), 0.05), "lossless"))
    poses = np.zeros((10, 2))
    big = RobotStream("r0", "bound-big", [30.0 * v for v in range(4)], kfs, poses)
    fleet = Fleet([big, swarm.stream(1, (5.0, 0.0))], None, "test")
    res, _ = _bound(fleet, tmp_path, "one", duration=120.0)
    own = [item for _, _, s, item, _ in res.schedule if s == 0]
    assert [v for _, v, _ in own] == [1, 2, 3, 4]
    assert own[0][2] == 0 and [b for _, _, b in own[1:]] == [1, 2, 3]


def test_maps_cross_two_hops_and_relays_send_only_what_they_received(
    swarm: SimpleNamespace, tmp_path: Path
) -> None:
    fleet = swarm.fleet([(0.0, 0.0), (40.0, 0.0), (80.0, 0.0)])
    res, row = _bound(fleet, tmp_path, "one", range_m=50.0)
    newest = {(h, o): v for _, h, o, v in res.accepted}
    assert newest[(2, 0)] == newest[(0, 2)] == 3
    assert math.isfinite(row["converge_s"])
    slot = res.slot_s
    got = {(h, o, v): t for t, h, o, v in res.accepted}
    relayed = [(k, s, item) for k, _, s, item, _ in res.schedule if item[0] != s]
    assert relayed, "robot 1 must relay"
    for k, s, (o, v, _) in relayed:
        assert (s, o, v) in got and got[(s, o, v)] <= k * slot + 1e-9  # held before it was sent on


@pytest.mark.parametrize("mode", ["one", "reuse"])
def test_senders_share_a_slot_only_where_no_receiver_hears_two(
    swarm: SimpleNamespace, tmp_path: Path, mode: str
) -> None:
    """Two pairs 200 m apart, and robot 4 between that hears only one pair: with reuse the pairs send
    at once; never does a served receiver hear a second sender, and one at a time never overlaps."""
    pos = [(0.0, 0.0), (5.0, 0.0), (200.0, 0.0), (205.0, 0.0), (60.0, 0.0)]
    res, row = _bound(swarm.fleet(pos), tmp_path, mode, range_m=100.0)
    hears, _ = link_matrices(np.asarray(pos), 100.0, None)
    overlaps = 0
    for i, (a0, a1, sa, _, served_a) in enumerate(res.schedule):
        for b0, b1, sb, _, served_b in res.schedule[i + 1 :]:
            if b0 < a1 and a0 < b1:
                overlaps += 1
                assert not hears[sa, sb]
                assert not any(hears[sb, r] for r in served_a)
                assert not any(hears[sa, r] for r in served_b)
    if mode == "one":
        assert overlaps == 0 and row["senders_per_slot"] == 1.0
    else:
        assert overlaps > 0 and row["senders_per_slot"] > 1.0
    newest = {(h, o): v for _, h, o, v in res.accepted}
    assert newest[(4, 0)] == newest[(0, 4)] == 3 and (4, 2) not in newest  # 4 hears only 0 and 1


def test_the_bound_is_no_staler_than_the_real_protocol(swarm: SimpleNamespace, tmp_path: Path) -> None:
    fleet = swarm.fleet([(0.0, 0.0), (40.0, 0.0), (80.0, 0.0), (40.0, 30.0)])
    kw: dict[str, Any] = {"range_m": 50.0, "relay": "summary", "acks": "up", "drain": 200.0}
    real = summarize(Swarm(fleet, Payloads(tmp_path, "lossless"), _cfg(**kw)).run())
    for mode in ("one", "reuse"):
        _, bound = _bound(fleet, tmp_path, mode, **kw)
        assert bound["stale_p95_s"] <= real["stale_p95_s"], (mode, bound["stale_p95_s"], real["stale_p95_s"])
        assert bound["accepted"] >= real["accepted"]


def test_walls_and_loss_cost_slots_not_maps(swarm: SimpleNamespace, tmp_path: Path) -> None:
    fleet = swarm.fleet([(0.0, 0.0), (5.0, 0.0)])
    clear, _ = _bound(fleet, tmp_path, "one")
    lossy, _ = _bound(fleet, tmp_path, "one", loss=0.8)  # a small map then needs two slots, not one
    assert len(lossy.accepted) == len(clear.accepted) == 6
    cost = [sum(e - s for s, e, *_ in r.schedule) for r in (clear, lossy)]
    assert cost[1] > cost[0]


def test_reach_is_the_unlimited_channel_and_stops_only_at_the_edge_of_range(
    swarm: SimpleNamespace, tmp_path: Path
) -> None:
    """With an unlimited channel, a map crosses any number of hops the moment it is made; a robot
    out of everyone's range never gets one."""
    pos = [(0.0, 0.0), (40.0, 0.0), (80.0, 0.0), (120.0, 0.0), (500.0, 0.0)]
    res, row = _bound(swarm.fleet(pos), tmp_path, "reach", range_m=50.0)
    got = {(h, o): v for _, h, o, v in res.accepted}
    line = range(4)
    assert all(got[(h, o)] == 3 for h in line for o in line if h != o)
    assert not [a for a in res.accepted if 4 in (a[1], a[2])]
    made = {(o, v): t for o, ts in enumerate(res.made) for v, t in enumerate(ts, 1)}
    assert max(t - made[(o, v)] for t, _, o, v in res.accepted) <= res.slot_s  # within the slot it is made
    assert row["converge_s"] == math.inf


def test_turns_go_round_the_robots_and_idle_turns_are_lent(swarm: SimpleNamespace, tmp_path: Path) -> None:
    """Six robots in range, robot 0's map large: its items go one slot per turn, every sixth slot,
    but the turns the others do not need are lent to it, so they end well before six slots apiece."""
    rng = np.random.default_rng(1)
    kfs = [
        encode(OccupancyGrid(rng.choice(np.array([-1, 0, 100], dtype=np.int8), (120, 120)), 0.05), "lossless")
        for _ in range(3)
    ]
    heavy = RobotStream("r0", "bound-heavy", [0.0, 30.0, 60.0], kfs, np.zeros((10, 2)))
    fleet = Fleet([heavy] + [swarm.stream(i, (2.0 * i, 0.0)) for i in range(1, 6)], None, "test")
    res, row = _bound(fleet, tmp_path, "turns")
    assert row["senders_per_slot"] == 1.0
    heavy_items = [(a, e) for a, e, s, _, _ in res.schedule if s == 0]
    assert len(heavy_items) == 3
    b = Bound(fleet, Payloads(tmp_path, "lossless"), _cfg(), "turns")
    slots_each = math.ceil(b._size((0, 1, 0)) / b.slot_bytes)
    assert slots_each >= 5  # a large map: several slots
    assert all(e - a < 6 * slots_each for a, e in heavy_items)
    got = {(h, o): v for _, h, o, v in res.accepted}
    assert all(got[(h, o)] == 3 for h in range(6) for o in range(6) if h != o)


def test_unknown_mode_is_refused(swarm: SimpleNamespace, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="bound mode"):
        Bound(swarm.fleet([(0.0, 0.0), (5.0, 0.0)]), Payloads(tmp_path, "lossless"), _cfg(), "all")


def test_command_prints_the_bound_beside_the_real_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["bench", "swarm", "--robots", "2", "--duration", "60", "--drain", "60", "--cache", str(tmp_path)]
    assert main([*argv, "--bound", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [b["senders"] for b in doc["bound"]] == ["turns", "one", "reuse", "reach"]
    for b in doc["bound"]:
        assert b["robots"] == 2 and b["accepted"] >= doc["rows"][0]["accepted"]
    assert main(argv) == 0
    assert "Bound" not in capsys.readouterr().out  # only when asked for
