"""``mapd bench paper``: the paper's Figures 7, 8a, 8b and 9 end to end on a short simulation and the log."""

from __future__ import annotations

import contextlib
import csv
import gzip
import io
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from mapd.bench import paper_figures, paper_localize
from mapd.bench.paper_data import Sample
from mapd.bench.paper_report import PAPER
from mapd.cli import build_parser
from mapd.grid import Pose2D
from mapd.mapping.lidar import Lidar
from mapd.mapping.replay import replay_log

SIM = ["--sim", "0", "--duration", "20", "--period", "10", "--poses", "3"]


def bench(out: Path, *extra: str) -> dict[str, Any]:
    """Run ``mapd bench paper ... --json`` in this process, as the CLI parses it; return its JSON."""
    args = build_parser().parse_args(["bench", "paper", *extra, "--out", str(out), "--json"])
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert args.func(args) == 0
    result: dict[str, Any] = json.loads(buf.getvalue())
    return result


def num(v: Any) -> float:
    """JSON numbers, with inf/nan written as strings by dump_json."""
    return float(v)


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("paper-sim")
    return out, bench(out, *SIM)


def test_report_states_the_papers_numbers_beside_ours(sim_run: tuple[Path, dict[str, Any]]) -> None:
    out, res = sim_run
    report = (out / "report.md").read_text()
    for claim in ("50.649", "0.975", "99 %", "720.4", "124.7", "3.59 / 3.43 / 0.72", "12.5 kb/s"):
        assert claim in report
    rows = {r["row"]: r for r in res["fig8"]["summary"]}
    assert f"| {num(rows['paper']['psnr']):.2f} |" in report
    assert f"{num(rows['paper']['ssim']):.4f}" in report
    loc = {(r["map"], r["against"]): r for r in res["fig9"]["rows"]}
    ours = loc[("paper", "original map")]
    assert f"{ours['mean_x_cm']:.2f} / {ours['mean_y_cm']:.2f} / {ours['mean_yaw_deg']:.2f}" in report
    assert res["command"] in report and res["command"].startswith("mapd bench paper --sim 0 --duration 20")
    for name in paper_figures.FILES:
        assert f"]({name})" in report
    # Fewer poses than the paper's 28 are flagged, not hidden.
    assert "fewer than the paper's 28" in report
    assert res["paper"] == PAPER


def test_figures_are_png_images(sim_run: tuple[Path, dict[str, Any]]) -> None:
    out, _ = sim_run
    for name in paper_figures.FILES:
        with Image.open(out / name) as im:
            assert im.format == "PNG"
            assert im.width >= 600 and im.height >= 400
            im.verify()


def test_fig8_rows(sim_run: tuple[Path, dict[str, Any]]) -> None:
    _, res = sim_run
    period = res["settings"]["period_s"]
    # 20 s of sim time at one update per 10 s: two updates per robot.
    assert res["run"]["updates_per_robot"] == {"robot0": 2, "robot1": 2}
    rows = {r["row"]: r for r in res["fig8"]["summary"]}
    assert list(rows) == ["paper", "lossless", "lossless+delta", "pooled+delta", "zstd-19"]
    for name in ("lossless", "lossless+delta", "zstd-19"):
        r = rows[name]
        assert num(r["psnr"]) == math.inf and r["ssim"] == 1.0 and r["f1"] == 1.0 and r["changed"] == 0.0
        assert r["exact"] is True
    for lossy in ("paper", "pooled+delta"):
        r = rows[lossy]
        assert r["exact"] is False and math.isfinite(num(r["psnr"])) and 0.0 < r["ssim"] < 1.0
        assert 0.0 < r["changed"] < 1.0
    # pooled: lossy, at fewer bytes than lossless.
    assert rows["pooled+delta"]["bytes"] < rows["lossless+delta"]["bytes"]
    updates = res["fig8"]["updates"]
    assert len(updates) == 4 * 5
    for u in updates:
        assert u["ratio"] == pytest.approx(u["cells"] / u["bytes"])
        assert u["rate"] == pytest.approx(1.0 - u["bytes"] / u["cells"])
        assert u["bps"] == pytest.approx(8 * u["bytes"] / period)
        assert u["transfer_s"] == pytest.approx(8 * u["bytes"] / 12_500)
        assert u["dec_ms"] > 0.0
    whole = {(u["robot"], u["version"]): u["bytes"] for u in updates if u["row"] == "lossless"}
    delta = {(u["robot"], u["version"]): u for u in updates if u["row"] == "lossless+delta"}
    for key, d in delta.items():
        assert d["bytes"] <= whole[key]
        # The first update of each robot has no base; later ones go as deltas.
        assert d["delta"] is (key[1] > 1)
    assert rows["lossless+delta"]["bytes"] <= rows["lossless"]["bytes"]
    assert rows["lossless+delta"]["deltas"] == 2
    assert rows["pooled+delta"]["deltas"] == 2  # decoded on the base as the receiver held it
    for r in rows.values():
        assert r["bytes"] == sum(u["bytes"] for u in updates if u["row"] == r["row"])
        per_robot = [
            np.mean([u["bps"] for u in updates if u["row"] == r["row"] and u["robot"] == n])
            for n in ("robot0", "robot1")
        ]
        assert r["fleet_bps"] == pytest.approx(sum(per_robot))
    with open(Path(sim_run[0]) / "updates.csv") as fh:
        assert len(list(csv.DictReader(fh))) == len(updates)


def test_fig9_localization(sim_run: tuple[Path, dict[str, Any]]) -> None:
    out, res = sim_run
    loc = {(r["map"], r["against"]): r for r in res["fig9"]["rows"]}
    assert res["fig9"]["picked"] == 3
    for r in loc.values():
        assert r["poses"] == 3
        assert all(math.isfinite(v) for k, v in r.items() if k.startswith(("mean_", "max_", "p95_")))
    # The original map of the simulated building puts each scan near its true pose...
    truth = loc[("original", "true pose")]
    assert truth["max_x_cm"] < 5.0 and truth["max_y_cm"] < 5.0 and truth["max_yaw_deg"] < 1.0
    assert truth["score"] > 0.8
    # ...and exact maps give exactly the original map's answer.
    for name in ("lossless", "lossless+delta", "zstd-19"):
        same = loc[(name, "original map")]
        assert same["max_x_cm"] == 0.0 and same["max_y_cm"] == 0.0 and same["max_yaw_deg"] == 0.0
    with open(out / "poses.csv") as fh:
        poses = list(csv.DictReader(fh))
    assert len(poses) == 3
    starts = []
    for p in poses:
        starts.append(math.hypot(float(p["start_dx"]), float(p["start_dy"])))
        assert starts[-1] <= 0.3 and abs(math.degrees(float(p["start_dyaw"]))) <= 10.0
        err = math.hypot(float(p["original_x"]) - float(p["x"]), float(p["original_y"]) - float(p["y"]))
        assert err < 0.05
    # The matcher had to find its way back: the starts were not all next to the truth.
    assert max(starts) > 0.1


def test_pick_poses_spreads_and_skips_blind_scans() -> None:
    angles = np.linspace(-math.pi / 2, math.pi / 2, 10)
    seeing, blind = np.full(10, 3.0), np.full(10, np.inf)
    samples = [Sample(Pose2D(0.1 * i, 0.0, 0.0), seeing, angles, float(i)) for i in range(101)]
    samples.append(Sample(Pose2D(50.0, 0.0, 0.0), blind, angles, 101.0))  # far away, but sees nothing
    picks = paper_localize.pick_poses(samples, 3)
    xs = sorted(samples[i].truth.x for i in picks)
    assert xs == pytest.approx([0.0, 5.0, 10.0])
    assert len(paper_localize.pick_poses(samples, 500)) == 101


def test_start_offsets_are_bounded_and_seeded() -> None:
    a = paper_localize.start_offsets(200, seed=1)
    assert np.hypot(a[:, 0], a[:, 1]).max() <= 0.3
    assert np.abs(np.degrees(a[:, 2])).max() <= 10.0
    # They fill the allowed range rather than clustering at the start.
    assert np.hypot(a[:, 0], a[:, 1]).max() > 0.25 and np.abs(np.degrees(a[:, 2])).max() > 9.0
    assert np.array_equal(a, paper_localize.start_offsets(200, seed=1))
    assert not np.array_equal(a, paper_localize.start_offsets(200, seed=2))


def write_log(path: Path, stamps: list[float]) -> None:
    """A CARMEN log of a robot turning on the spot in a 6 m square room, one scan per stamp."""
    d = np.zeros((120, 120), bool)
    d[:3, :] = d[-3:, :] = d[:, :3] = d[:, -3:] = True
    lidar = Lidar(d, 0.05, Pose2D(-3.0, -3.0, 0.0), beams=180, fov_deg=180.0, max_range=30.0)
    lidar.angles = -math.pi / 2 + math.pi / 180 * np.arange(180)
    lines = []
    for k, t in enumerate(stamps):
        pose = Pose2D(0.3 * math.cos(k), 0.3 * math.sin(k), 0.4 * k)
        rs = " ".join(f"{r:.3f}" for r in lidar.scan(pose))
        p = f"{pose.x:.6f} {pose.y:.6f} {pose.yaw:.6f}"
        lines.append(f"FLASER 180 {rs} {p} {p} {t:.6f} testhost {t:.6f}\n")
    path.write_bytes(gzip.compress("".join(lines).encode()))


def test_replay_log_snapshots_by_log_time(tmp_path: Path) -> None:
    log = tmp_path / "t.log.gz"
    # Scans every 4 s, then a 50 s gap: snapshots at the first scan past 10, 20, 30 s, one after
    # the gap (not three), then the last scan.
    stamps = [100.0 + 4 * k for k in range(9)] + [182.0, 184.0]
    write_log(log, stamps)
    snaps = list(replay_log(log, every_s=10.0))
    assert [t for t, _ in snaps] == [112.0, 120.0, 132.0, 182.0, 184.0]
    assert [g.version for _, g in snaps] == [1, 2, 3, 4, 5]
    with pytest.raises(ValueError):
        next(replay_log(log, every_s=0.0))


def mapd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapd", *args], capture_output=True, text=True, timeout=120, check=False
    )


def test_bad_input_is_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "missing.log"
    r = mapd("bench", "paper", "--log", str(missing), "--out", str(tmp_path / "o"))
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [f"mapd: error: {missing}: no such log file"]
    r = mapd("bench", "paper", "--sim", "0", "--poses", "0", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and r.stderr.strip() == "mapd: error: --poses must be at least 1"
    r = mapd("bench", "paper", "--sim", "0", "--log", str(missing), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "not allowed with argument" in r.stderr and "Traceback" not in r.stderr


def test_intel_log_short(intel_log: Path, tmp_path: Path) -> None:
    res = bench(tmp_path, "--log", str(intel_log), "--limit", "2", "--poses", "3")
    assert res["run"]["updates_per_robot"] == {"robot0": 2, "robot1": 2}
    assert res["run"]["clock"] == "log time"
    times = sorted({u["t"] for u in res["fig8"]["updates"] if u["robot"] == "robot0"})
    # Snapshots follow log time: the first scan at or past 30 s and 60 s after the robot's first.
    assert 30.0 <= times[0] < 45.0 and 60.0 <= times[1] < 75.0
    loc = {(r["map"], r["against"]): r for r in res["fig9"]["rows"]}
    truth = loc[("original", "corrected pose")]
    assert truth["poses"] == 3 and truth["mean_x_cm"] < 15.0 and truth["mean_y_cm"] < 15.0
    assert (tmp_path / "report.md").read_text().count("intel-corrected.log.gz") >= 2


def test_fig7_global_maps_with_and_without_compression(sim_run: tuple[Path, dict[str, Any]]) -> None:
    """The paper's measure: global maps, the receiver's own map exact, peers' maps as recovered."""
    out, res = sim_run
    f7 = res["fig7"]
    robot0 = [u for u in res["fig8"]["updates"] if u["robot"] == f7["receiver"] and u["row"] == "paper"]
    assert f7["receiver"] == "robot0" and len(f7["steps"]) == len(robot0)  # one step per receiver snapshot
    assert [s["t"] for s in f7["steps"]] == sorted(s["t"] for s in f7["steps"])
    g = f7["global"]
    assert set(g) == {"paper", "lossless", "lossless+delta", "pooled+delta", "zstd-19"}
    for exact in ("lossless", "lossless+delta", "zstd-19"):  # exact codecs change nothing in the global map
        assert num(g[exact]["psnr"]) == math.inf and num(g[exact]["ssim"]) == 1.0
    steps = [s for s in f7["steps"] if s["robots"] == 2]
    assert steps, "no step where both robots had a map"
    lossy = [num(s["paper"]["psnr"]) for s in steps]
    assert all(math.isfinite(v) and v > 10 for v in lossy)
    # the receiver's own exact part raises the global figure over the per-robot one (Fig. 8a)
    per_robot = {r["row"]: r for r in res["fig8"]["summary"]}["paper"]
    assert num(g["paper"]["psnr"]) > num(per_robot["psnr"])
    assert 0 < num(g["paper"]["ssim"]) <= 1
    report = (out / "report.md").read_text()
    assert "](fig7_global.png)" in report and f"{num(g['paper']['psnr']):.2f}" in report
    with Image.open(out / "fig7_global.png") as im:
        assert im.format == "PNG" and im.width >= 600 and im.height >= 400
        im.verify()
