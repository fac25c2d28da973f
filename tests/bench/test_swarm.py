"""``mapd bench swarm``: the radio, the staleness metric and small swarms of the real UWB cores."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.bench.swarm.links import count_walls, hop_counts, link_matrices
from mapd.bench.swarm.metrics import (
    convergence,
    staleness_rows,
    staleness_samples,
    staleness_trend,
    summarize,
)
from mapd.bench.swarm.radio import Radio, channel_use
from mapd.bench.swarm.run import with_means
from mapd.bench.swarm.sim import Swarm, SwarmConfig
from mapd.bench.swarm.streams import Building, Fleet, Payloads, RobotStream, load_fleet
from mapd.cli import main
from mapd.codec import encode
from mapd.grid import OccupancyGrid


def _run(fleet: Fleet, tmp_path: Path, **kw: Any) -> dict[str, Any]:
    cfg = SwarmConfig(**{"duration": 90.0, "drain": 60.0, "start_spread": 5.0, **kw})
    res = Swarm(fleet, Payloads(tmp_path, "lossless"), cfg).run()
    row = summarize(res)
    row["accepted_log"] = res.accepted
    row["borrowed"] = sum(r.arq.counters.borrowed for r in res.robots)
    row["robot_tx"] = [r.arq.counters.data_tx for r in res.robots]
    row["out_of_turn"] = sum(r.arq.counters.out_of_turn for r in res.robots)
    return row


# --- the radio -----------------------------------------------------------------------------------


def test_two_frames_at_once_collide_at_every_receiver() -> None:
    radio = Radio(3, rate_bps=8000.0)  # 1 byte per ms
    a = radio.transmit(0, b"x" * 100, 0.0)
    b = radio.transmit(1, b"y" * 100, 0.05)
    assert (a.start, a.end) == (0.0, pytest.approx(0.1))
    got_a, got_b = radio.finish(a, a.end), radio.finish(b, b.end)
    assert [d for d, _ in got_a] == [2] and [d for d, _ in got_b] == [2]
    assert got_a[0][1] != a.data and len(got_a[0][1]) == len(a.data)  # garbled: its CRC fails
    c = radio.counters
    assert c.collided == 2  # node 2 heard both frames over each other
    assert c.deaf == 2  # nodes 0 and 1 were sending while the other's frame arrived
    assert c.delivered == 0
    late = radio.transmit(0, b"z" * 10, 1.0)
    assert radio.finish(late, late.end) == [(1, late.data), (2, late.data)]


def test_out_of_range_frames_neither_arrive_nor_interfere() -> None:
    radio = Radio(3)
    hears = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=bool)  # 0 and 2 are out of range
    radio.set_links(hears)
    a = radio.transmit(0, b"a" * 50, 0.0)
    assert radio.finish(a, a.end) == [(1, a.data)]
    # 0 and 2 send at once: 1 hears both (collision), but neither disturbs the other's silence
    a, b = radio.transmit(0, b"a" * 50, 1.0), radio.transmit(2, b"b" * 50, 1.0)
    assert [d for d, _ in radio.finish(a, a.end) + radio.finish(b, b.end)] == [1, 1]
    assert radio.counters.collided == 2 and radio.counters.deaf == 0


def test_channel_use_is_the_union_of_airtime() -> None:
    assert channel_use([(0.0, 1.0), (0.5, 1.5), (3.0, 4.0)], 0.0, 10.0) == pytest.approx(0.25)
    assert channel_use([(0.0, 20.0)], 0.0, 10.0) == pytest.approx(1.0)
    assert channel_use([], 0.0, 10.0) == 0.0


def test_walls_are_counted_once_per_crossing() -> None:
    data = np.zeros((20, 100), dtype=np.int8)
    data[:, 30:33] = 100  # a wall three cells thick
    data[:, 60] = 100  # and a thin one
    b = Building(OccupancyGrid(data, 0.1))
    walls = count_walls(b, np.array([[0.5, 1.0], [0.5, 1.0]]), np.array([[9.5, 1.0], [4.0, 1.0]]))
    assert walls.tolist() == [2, 1]
    hears, w = link_matrices(np.array([[0.5, 1.0], [9.5, 1.0], [50.0, 1.0]]), 20.0, b)
    assert hears.tolist() == [[False, True, False], [True, False, False], [False, False, False]]
    assert w[0, 1] == w[1, 0] == 2


# --- staleness -----------------------------------------------------------------------------------


def test_staleness_on_a_hand_made_scenario() -> None:
    # origin 0 makes v1 at 0 s and v2 at 10 s; holder 1 gets v1 at 3 s, v2 at 14 s.
    # origin 1 makes v1 at 0 s; holder 0 never gets it.
    made = [[0.0, 10.0], [0.0]]
    accepted = [(3.0, 1, 0, 1), (14.0, 1, 0, 2)]
    st = staleness_samples(made, accepted, 20.0, dt=1.0)
    pair_1_0 = st[:21]  # origin 0, holder 1
    pair_0_1 = st[21:]  # origin 1, holder 0
    expect = [0, 1, 2, 0, 0, 0, 0, 0, 0, 0, 0, 1, 2, 3, 0, 0, 0, 0, 0, 0, 0]
    assert pair_1_0.tolist() == expect
    assert pair_0_1.tolist() == [float(t) for t in range(21)]
    assert convergence(made, accepted, 2) == math.inf
    assert convergence(made, [*accepted, (25.0, 0, 1, 1)], 2) == pytest.approx(15.0)


def test_hop_counts_follow_the_radio_graph() -> None:
    hears = np.zeros((4, 4), dtype=bool)
    for a, b in ((0, 1), (1, 2)):  # a line 0 - 1 - 2; robot 3 hears nobody
        hears[a, b] = hears[b, a] = True
    assert hop_counts(hears).tolist() == [[0, 1, 2, -1], [1, 0, 1, -1], [2, 1, 0, -1], [-1, -1, -1, 0]]


def test_staleness_trend_rises_only_while_a_pair_goes_unserved() -> None:
    made = [[0.0, 30.0, 60.0], [0.0, 30.0, 60.0]]
    served = [(t + 2.0, h, 1 - h, v + 1) for v, t in enumerate((0.0, 30.0, 60.0)) for h in (0, 1)]
    flat = staleness_trend(staleness_rows(made, served, 90.0), 90.0, windows=3)
    assert [w[0] for w in flat] == [0.0, 30.0, 60.0] and max(w[1] for w in flat) < 1.0
    starved = staleness_trend(staleness_rows(made, served[:2], 90.0), 90.0, windows=3)  # only v1 gets through
    assert starved[0][1] < starved[1][1] < starved[2][1]


def test_means_over_seeds_reach_into_dicts_and_lists() -> None:
    a = {"robots": 2, "seed": 0, "p": 1.0, "hops": {"1": {"mean_s": 2.0}}, "trend": [[0.0, 4.0]], "c": "x"}
    b = {"robots": 2, "seed": 1, "p": 3.0, "hops": {"1": {"mean_s": 6.0}}, "trend": [[0.0, 8.0]], "c": "x"}
    mean = with_means([a, b], ("robots",))[-1]
    assert mean == {
        "robots": 2,
        "seed": "mean",
        "p": 2.0,
        "hops": {"1": {"mean_s": 4.0}},
        "trend": [[0.0, 6.0]],
        "c": "x",
    }


# --- small swarms of the real cores --------------------------------------------------------------


def test_two_robots_in_range_exchange_every_version(swarm: SimpleNamespace, tmp_path: Path) -> None:
    row = _run(swarm.fleet([(0.0, 0.0), (5.0, 0.0)]), tmp_path, mac="tdma")
    assert row["accepted"] == 6  # 3 versions each way
    assert math.isfinite(row["converge_s"])
    assert 0.0 < row["channel_use"] <= 1.0
    assert row["stale_p95_s"] < 30.0
    assert row["deltas"] > 0  # lossless sends deltas against the acked version
    assert row["collided"] == 0  # TDMA: one robot per slot
    assert row["hears_all"] == row["robot_hears_all"] == 1.0


def test_a_robot_out_of_range_never_receives_without_relay(swarm: SimpleNamespace, tmp_path: Path) -> None:
    row = _run(swarm.fleet([(0.0, 0.0), (5.0, 0.0), (500.0, 0.0)]), tmp_path, range_m=50.0, mac="backoff")
    log = row["accepted_log"]
    assert isinstance(log, list)
    assert not [a for a in log if a[1] == 2 or a[2] == 2]  # robot 2 neither gets nor gives a map
    assert {(a[1], a[2]) for a in log} == {(0, 1), (1, 0)}
    assert row["converge_s"] == math.inf
    assert row["stale_max_s"] > 85.0  # robot 2's first version, made within 5 s of the start, never received
    assert row["never_in_range"] == pytest.approx(4 / 6)
    assert row["hears_all"] == row["robot_hears_all"] == 0.0  # robot 2 hears nobody, nobody hears it
    assert row["stale_p95_reach_s"] < 30.0  # the two robots in range keep up with each other


def test_relay_hook_carries_maps_over_two_hops(swarm: SimpleNamespace, tmp_path: Path) -> None:
    fleet = swarm.fleet([(0.0, 0.0), (40.0, 0.0), (80.0, 0.0)])
    row = _run(fleet, tmp_path, range_m=50.0, relay="flood", acks="up", drain=200.0)
    log = row["accepted_log"]
    assert isinstance(log, list)
    assert (2, 0) in {(a[1], a[2]) for a in log}  # robot 2 got robot 0's map through robot 1


@pytest.mark.parametrize("relay", ["none", "summary"])
def test_summary_relay_carries_every_version_over_two_hops(
    swarm: SimpleNamespace, tmp_path: Path, relay: str
) -> None:
    """Robots 0 and 2 are out of range, 1 hears both: with the relay core, 1 forwards their maps
    (from the neighbours' summaries) until each holds the other's newest version; without, never."""
    fleet = swarm.fleet([(0.0, 0.0), (40.0, 0.0), (80.0, 0.0)])
    row = _run(fleet, tmp_path, range_m=50.0, relay=relay, acks="up", drain=200.0)
    got = {(a[1], a[2]): a[3] for a in row["accepted_log"]}  # newest version accepted per pair
    assert row["hears_all"] == 0.0  # robots 0 and 2 never hear each other...
    assert row["robot_hears_all"] == pytest.approx(1 / 3)  # ...while robot 1 always hears both
    hops = row["stale_by_hops"]  # two of the six pairs are two hops apart all run long
    assert hops["1"]["samples"] == pytest.approx(4 / 6) and hops["2"]["samples"] == pytest.approx(2 / 6)
    assert hops["3+"]["samples"] == hops["none"]["samples"] == 0.0
    if relay == "none":
        assert (2, 0) not in got and (0, 2) not in got
        assert row["converge_s"] == math.inf
        assert hops["2"]["tail"] == 1.0  # the unserved far pairs make the whole p95 tail
        trend = [m for _, m in row["stale_trend"]]
        assert trend == sorted(trend) and trend[-1] > 2 * trend[0]  # and their staleness only grows
    else:
        assert got[(2, 0)] == got[(0, 2)] == 3  # the newest version, over two hops
        assert math.isfinite(row["converge_s"])
        # each summary reaches the neighbours in range (robot 1's both ends, the ends' robot 1) at most
        assert 0 < row["summaries_rx"] <= 2 * row["summaries"]


def test_runs_are_deterministic_for_a_seed(swarm: SimpleNamespace, tmp_path: Path) -> None:
    fleet = swarm.fleet([(0.0, 0.0), (5.0, 0.0), (10.0, 0.0), (15.0, 0.0)])
    a = _run(fleet, tmp_path, mac="backoff", loss=0.05, seed=3)
    b = _run(fleet, tmp_path, mac="backoff", loss=0.05, seed=3)
    c = _run(fleet, tmp_path, mac="backoff", loss=0.05, seed=4)
    for row in (a, b, c):
        row.pop("wall_s")
    assert a == b
    assert a != c
    assert a["lost"] > 0


def test_signed_frames_cost_airtime(swarm: SimpleNamespace, tmp_path: Path) -> None:
    fleet = swarm.fleet([(0.0, 0.0), (5.0, 0.0)])
    signed = _run(fleet, tmp_path, signed=True)
    plain = _run(fleet, tmp_path, signed=False)
    assert signed["accepted"] == plain["accepted"] == 6
    assert signed["bps_per_robot"] > plain["bps_per_robot"]


def _heavy_stream(
    i: int, xy: tuple[float, float], versions: int = 3, period: float = 30.0, side: int = 120
) -> RobotStream:
    """A robot whose every version is a map of noise: some twenty chunks each (``side`` 120), where
    the others need one."""
    rng = np.random.default_rng(i)
    kfs = [
        encode(
            OccupancyGrid(rng.choice(np.array([-1, 0, 100], dtype=np.int8), (side, side)), 0.05), "lossless"
        )
        for _ in range(versions)
    ]
    poses = np.tile(np.asarray(xy, dtype=np.float64), (10, 1))
    return RobotStream(f"r{i}", f"heavy-{i}-{side}", [v * period for v in range(versions)], kfs, poses)


def test_turn_lending_gives_idle_turns_to_the_robot_with_a_large_map(
    swarm: SimpleNamespace, tmp_path: Path
) -> None:
    robots = [_heavy_stream(0, (0.0, 0.0))] + [swarm.stream(i, (2.0 * i, 0.0)) for i in range(1, 6)]
    fleet = Fleet(robots, None, "test")
    lent = _run(fleet, tmp_path, mac="tdma", lend=True)
    fixed = _run(fleet, tmp_path, mac="tdma", lend=False)
    for row in (lent, fixed):
        assert row["collided"] == 0  # one sender per slot, lending or not
        assert row["accepted"] == 3 * 5 * 6  # every version of every robot reached every other
    assert lent["borrowed"] > 0
    assert fixed["borrowed"] == 0
    # the heavy robot's maps reach the others sooner
    assert lent["stale_p95_s"] < 0.7 * fixed["stale_p95_s"], (lent["stale_p95_s"], fixed["stale_p95_s"])


def test_parity_repairs_a_lossy_broadcast_in_fewer_frames(swarm: SimpleNamespace, tmp_path: Path) -> None:
    robots = [_heavy_stream(0, (0.0, 0.0))] + [swarm.stream(i, (2.0 * i, 0.0)) for i in range(1, 6)]
    fleet = Fleet(robots, None, "test")
    rows = {f: _run(fleet, tmp_path, mac="tdma", loss=0.25, fec=f, drain=200.0) for f in (True, False)}
    for row in rows.values():
        assert math.isfinite(row["converge_s"])  # every robot got every other's last version
    heavy = {f: row["robot_tx"][0] for f, row in rows.items()}
    assert heavy[True] < 0.9 * heavy[False], heavy  # the heavy robot's repairs: parity, not the union
    assert rows[False]["parity_frames"] == 0 < rows[True]["parity_frames"] < rows[True]["data_frames"]
    assert rows[True]["stale_p95_s"] <= rows[False]["stale_p95_s"]


def test_a_map_is_held_until_it_is_on_the_air(tmp_path: Path) -> None:
    """Three robots, each map some 55 chunks (about 24 s of its turns), a version every 10 s and an
    in-flight timeout of 10 s: superseding at the timeout (hold off) restarts every map before its
    last chunk goes, so none arrives while versions are made; holding it until it is wholly on the
    air (the daemon's publisher on uwb, P1) gets maps through all along."""
    fleet = Fleet([_heavy_stream(i, (2.0 * i, 0.0), 6, 10.0, side=200) for i in range(3)], None, "test")
    rows = {
        h: _run(fleet, tmp_path, mac="tdma", duration=60.0, inflight_s=5.0, hold=h) for h in (True, False)
    }
    during = {h: [a for a in row["accepted_log"] if a[0] <= 60.0] for h, row in rows.items()}
    assert not during[False]  # every map restarted before it was whole
    assert len(during[True]) >= 6, during[True]
    assert rows[True]["accepted"] > 2 * rows[False]["accepted"]
    assert rows[True]["keyframes"] < rows[False]["keyframes"]  # fewer maps coded only to be dropped
    assert rows[True]["stale_p95_s"] < rows[False]["stale_p95_s"]


def test_a_robot_that_comes_into_range_is_offered_the_newest_map(
    swarm: SimpleNamespace, tmp_path: Path
) -> None:
    """Robot 1 comes into range at 40 s, after robot 0 made its last version (at about 30 s) and
    sent it to nobody. With P6 (the daemon's uwb) robot 0 offers it as soon as it hears robot 1; the
    daemon before P6 had robot 1 ask for it (a control message more); with neither, robot 1 waits for
    a version that never comes."""
    still = swarm.stream(0, (0.0, 0.0), versions=2)
    comer = swarm.stream(1, (5.0, 0.0), versions=1)
    comer.poses = np.array([(500.0, 0.0) if t < 40 else (5.0, 0.0) for t in range(200)])
    fleet = Fleet([still, comer], None, "test")
    rows = {a: _run(fleet, tmp_path, range_m=50.0, acks="up", arrival=a) for a in ("offer", "ask", "none")}
    got = {a: [(t, v) for t, h, o, v in row["accepted_log"] if (h, o) == (1, 0)] for a, row in rows.items()}
    assert not got["none"]
    for a in ("offer", "ask"):
        assert [v for _, v in got[a]] == [2] and 40.0 < got[a][0][0] < 60.0, got[a]
        assert rows[a]["stale_p95_s"] < rows["none"]["stale_p95_s"]
    assert rows["offer"]["kf_requests"] == 0 < rows["ask"]["kf_requests"]
    with pytest.raises(ValueError, match="arrival"):
        _run(fleet, tmp_path, arrival="wave")


def test_config_is_plain_data() -> None:
    assert dataclasses.asdict(SwarmConfig())["codec"] == "lossless"


# --- the command and real streams ----------------------------------------------------------------


def test_command_runs_a_small_sim_swarm(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bench", "swarm", "--robots", "2", "3", "--duration", "60", "--drain", "60"]
    assert main([*argv, "--cache", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["robots"] for r in out["rows"]] == [2, 3]
    for r in out["rows"]:
        assert 2 * r["robots"] <= r["versions"] <= 3 * r["robots"]  # at 1, 30, 60 s after a random start
        assert 0 < r["channel_use"] <= 1
        assert r["converge_s"] != "inf"
    assert any(tmp_path.glob("fleet-*.msgpack")) and (tmp_path / "sizes-lossless.json").exists()


def test_several_seeds_give_a_row_each_and_their_mean(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["bench", "swarm", "--robots", "3", "--duration", "60", "--drain", "30", "--loss", "0.2"]
    assert main([*argv, "--seed", "0", "1", "--cache", str(tmp_path), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert [(r["robots"], r["seed"]) for r in rows] == [(3, 0), (3, 1), (3, "mean")]
    a, b, mean = rows
    assert a["lost"] != b["lost"]  # another seed, other losses
    for k in ("stale_p95_s", "accepted", "channel_use", "lost"):
        assert mean[k] == pytest.approx((a[k] + b[k]) / 2)


def test_a_range_sweep_gives_rows_per_range_and_a_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    png = tmp_path / "sweep.png"
    argv = ["bench", "swarm", "--robots", "3", "--duration", "60", "--drain", "30", "--wall-loss", "0.1"]
    argv += ["--range", "inf", "6", "--seed", "0", "1", "--bound", "--plot", str(png), "--target", "2"]
    assert main([*argv, "--cache", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    rows = out["rows"]
    assert [(r["range_m"], r["seed"]) for r in rows] == [
        ("inf", 0), ("inf", 1), ("inf", "mean"), (6.0, 0), (6.0, 1), (6.0, "mean"),
    ]  # fmt: skip
    for i in (0, 3):  # each range's mean is of its own seeds
        a, b, mean = rows[i : i + 3]
        assert mean["accepted"] == pytest.approx((a["accepted"] + b["accepted"]) / 2)
    assert rows[0]["degree"] == 2.0 and rows[3]["degree"] < 2.0  # 6 m apart, some do not hear others
    assert {(b["range_m"], b["senders"]) for b in out["bound"]} == {
        (r, m) for r in ("inf", 6.0) for m in ("turns", "one", "reuse", "reach")
    }
    assert out["range_m"] == ["inf", 6.0]
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    assert img.shape == (495, 880, 3)

    def pixels(colour: str) -> int:
        rgb = np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)])
        return int((np.abs(img - rgb).sum(axis=2) < 30).sum())

    assert pixels("#1f77b4") > 100  # the real protocol's line
    assert pixels("#ff7f0e") > 20  # the bound's one sender at a time


def test_a_range_of_zero_is_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "swarm", "--robots", "2", "--range", "30", "0", "--cache", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["mapd: error: --range 30 0: each must be above 0 m"]


def test_a_plot_that_cannot_be_written_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "file").write_text("")
    png = tmp_path / "file" / "sweep.png"  # under a file: no folder can be made there
    argv = ["bench", "swarm", "--robots", "2", "--duration", "30", "--drain", "30", "--plot", str(png)]
    assert main([*argv, "--cache", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"mapd: error: {png}: cannot write the plot")  # before any run


def test_log_slices_make_streams_with_poses(intel_log: Path, tmp_path: Path) -> None:
    fleet = load_fleet(cache=tmp_path, n=3, period=30.0, duration=90.0, log=intel_log)
    assert len(fleet.robots) == 3 and fleet.building is not None
    for r in fleet.robots:
        assert r.versions >= 3 and r.times[0] == 0.0 and r.times[-1] <= 90.0
        assert int((r.grid(r.versions).data >= 0).sum()) > int((r.grid(1).data >= 0).sum())
        assert len(r.poses) >= 80
    starts = {tuple(np.round(r.poses[0], 2)) for r in fleet.robots}
    assert len(starts) == 3  # each robot starts where its slice of the log does
    again = load_fleet(cache=tmp_path, n=3, period=30.0, duration=90.0, log=intel_log)
    assert again.robots[1].times == fleet.robots[1].times  # from the cache


def test_clocks_that_disagree_past_the_guard_collide_and_are_heard_out_of_turn(
    swarm: SimpleNamespace, tmp_path: Path
) -> None:
    """TDMA counts its slots on each robot's clock (``clock = "system"``): within the guard (10 ms)
    they never overlap; two thirds of a slot apart they collide, and the robots count frames heard
    in their own slot (R18). On the clock the fleet agrees over the radio (the default) they keep
    apart once the first TIME frames are heard."""
    robots = [_heavy_stream(0, (0.0, 0.0))] + [swarm.stream(i, (2.0 * i, 0.0)) for i in range(1, 4)]
    fleet = Fleet(robots, None, "test")
    rows = {
        skew: _run(fleet, tmp_path, mac="tdma", clock_skew_s=skew, clock="system")
        for skew in (0.0, 0.008, 0.4)
    }
    for skew in (0.0, 0.008):
        assert rows[skew]["collided"] == 0 and rows[skew]["out_of_turn"] == 0, skew
    assert rows[0.4]["collided"] > 0 and rows[0.4]["out_of_turn"] > 0
    assert rows[0.4]["stale_p95_s"] > rows[0.0]["stale_p95_s"]
    # A guard as long as the disagreement keeps the turns apart again, at the cost of airtime.
    guarded = _run(fleet, tmp_path, mac="tdma", clock_skew_s=0.4, guard_s=0.45, clock="system")
    assert guarded["collided"] == 0 and guarded["out_of_turn"] == 0
    # The radio clock: only the first seconds collide, before the robots have heard its TIME frames.
    radio = _run(fleet, tmp_path, mac="tdma", clock_skew_s=0.4)
    assert (
        radio["out_of_turn"] < rows[0.4]["out_of_turn"] / 2 and radio["collided"] < rows[0.4]["collided"] / 2
    )
    assert radio["stale_p95_s"] < rows[0.4]["stale_p95_s"]
