"""``mapd train`` on maps in the making: snapshots from sim runs and logs, their cache, the recipe in the card."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mapd import cli
from mapd.codec import paper_model as pm
from mapd.grid import OccupancyGrid, Pose2D
from mapd.train import snapshots as sn
from mapd.train.heldout import growing_maps, table
from mapd.train.loop import train
from mapd.train.settings import TrainConfig

from .conftest import write_rooms

PLACES = ["hall_a", "lab", "office", "store", "yard"]


def _known(g: OccupancyGrid) -> int:
    return int((g.data != -1).sum())


@pytest.fixture(scope="module")
def map_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_rooms(tmp_path_factory.mktemp("maps"), PLACES, 30, 36)


def test_sim_snapshots_grow_and_are_cached(tmp_path: Path) -> None:
    before = dict(sn.REPLAYS)
    grids, path = sn.sim_snapshots(5, every=15, scans=50, cache=tmp_path)
    assert sn.REPLAYS["sim"] == before["sim"] + 1
    assert len(grids) == 4  # scans 15, 30, 45 and the last one (50)
    for g in grids:
        assert g.data.ndim == 2 and g.data.dtype == np.int8 and min(g.data.shape) > 0
        assert g.resolution == pytest.approx(0.05)
        assert set(np.unique(g.data).tolist()) <= {-1, 0, 100}
    known = [_known(g) for g in grids]
    assert known == sorted(known) and known[-1] > known[0]  # a map in the making grows
    assert path.is_file() and path.is_relative_to(tmp_path)

    mtime = path.stat().st_mtime_ns
    again, path2 = sn.sim_snapshots(5, every=15, scans=50, cache=tmp_path)
    assert sn.REPLAYS["sim"] == before["sim"] + 1  # loaded, not replayed
    assert path2 == path and path.stat().st_mtime_ns == mtime
    assert len(again) == len(grids)
    assert all(np.array_equal(a.data, b.data) for a, b in zip(again, grids, strict=True))
    # Another cadence is another cache entry.
    other, path3 = sn.sim_snapshots(5, every=25, scans=50, cache=tmp_path)
    assert path3 != path and len(other) == 2 and sn.REPLAYS["sim"] == before["sim"] + 2


def test_log_snapshots_every_n_scans(
    box_log: Callable[..., tuple[Path, list[Pose2D]]], tmp_path: Path
) -> None:
    log, _ = box_log(scans=25)
    before = sn.REPLAYS["log"]
    grids, _ = sn.log_snapshots(log, every=10, cache=tmp_path / "c")
    assert len(grids) == 3  # after scans 10, 20 and the last (25)
    known = [_known(g) for g in grids]
    assert known == sorted(known) and known[0] > 0
    again, _ = sn.log_snapshots(log, every=10, cache=tmp_path / "c")
    assert sn.REPLAYS["log"] == before + 1
    assert [g.data.shape for g in again] == [g.data.shape for g in grids]

    spec = sn.SnapshotSpec(logs=(log,), sims=(5,), every=10, sim_scans=20, cache=tmp_path / "c")
    maps, recipe = sn.snapshot_maps(spec)
    assert recipe["snapshots"] == len(maps) == 3 + 2
    assert maps[0][0] == "snapshots/box/0001"
    assert "every 10 scans" in sn.describe(recipe) and "sim building seed 5" in sn.describe(recipe)


def test_default_cache_follows_the_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("MAPD_CACHE", str(tmp_path / "x"))
    assert sn.default_cache() == tmp_path / "x"
    monkeypatch.delenv("MAPD_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert sn.default_cache() == tmp_path / "xdg" / "mapd"


def test_mapd_train_snapshots_only_end_to_end(map_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "models" / "snap"
    cache = tmp_path / "cache"
    rc = cli.main(
        [
            "train", "--maps", str(map_dir), "--epochs", "1", "--tile", "16", "--tiles-per-epoch", "16",
            "--batch", "8", "--val-tiles", "8", "--threads", "1", "--quiet",
            "--snapshots-sim", "5", "--snapshot-every", "20", "--sim-scans", "40", "--no-finished",
            "--exclude-place", "yard", "--cache", str(cache), "-o", str(out),
        ]
    )  # fmt: skip
    assert rc == 0
    meta = json.loads((out / pm.META_FILE).read_text())
    assert (out / pm.WEIGHTS_FILE).is_file()
    recipe = meta["training"]["recipe"]
    assert recipe["finished"] is False and recipe["finished_maps"] == 0
    assert recipe["snapshots"]["sources"] == [{"sim_seed": 5, "scans": 40, "snapshots": 2}]
    assert meta["split"]["train"] == []
    assert meta["split"]["excluded"] == ["yard"] and "yard" not in meta["split"]["validation"]
    assert meta["metrics"]["validation"]["maps"] == len(meta["split"]["validation"]) > 0
    cmd = meta["training"]["command"]
    assert "--snapshots-sim 5 --snapshot-every 20 --sim-scans 40 --no-finished --exclude-place yard" in cmd
    card = (out / "MODEL_CARD.md").read_text()
    assert "maps in the making, only (`--no-finished`)" in card
    assert "sim building seed 5, 40 scans (2)" in card
    assert "places yard" in card


def test_recipes_that_cannot_train_are_config_errors(map_dir: Path, tmp_path: Path) -> None:
    from mapd.errors import ConfigError

    cfg = dict(epochs=1, tile=16, tiles_per_epoch=8, batch=8, val_tiles=0, progress=False, evaluate=False)
    with pytest.raises(ConfigError, match="nothing to train on"):
        train(TrainConfig(maps=map_dir, out=tmp_path / "a", finished=False, **cfg))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="no such place"):
        train(TrainConfig(maps=map_dir, out=tmp_path / "b", exclude_places=("mars",), **cfg))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="snapshot-every"):
        spec = sn.SnapshotSpec(sims=(1,), every=0)
        train(TrainConfig(maps=map_dir, out=tmp_path / "c", snapshots=spec, **cfg))  # type: ignore[arg-type]
    assert cli.main(["train", "--maps", str(map_dir), "--no-finished", "-o", str(tmp_path / "d")]) == 2


def test_heldout_growing_maps_are_bench_papers_streams(
    box_log: Callable[..., tuple[Path, list[Pose2D]]], tmp_path: Path
) -> None:
    log, _ = box_log(scans=40, dt=0.5)  # 20 s of log
    grids = growing_maps(log, robots=2, period=5.0, cache=tmp_path)
    robots = {label.split("/")[0] for label, _ in grids}
    assert robots == {"robot0", "robot1"}
    assert len(grids) >= 4
    row = {"ratio": 10.0, "psnr_mean": 30.0, "ssim_mean": 0.9, "f1_mean": 0.9, "changed_mean": 0.01}
    text = table([{"model": "models/x", "growing": row, "finished": row}])
    assert text.count("\n") == 2 and "| x | 10.0 | 30.00 |" in text
