"""``mapd train`` on bad input: one error line before the work, and an old model kept whole.

* The output folder is checked before training, and a model is written so that a failure (a full
  disk, a read-only folder, a diverged run) leaves any model already there as it was.
* Settings have upper bounds, so a typo is one line, not a crash of torch or numpy.
* A damaged snapshot cache is a cache miss; a cache path that cannot be a folder is one line.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from mapd import cli
from mapd.codec import paper_model as pm
from mapd.codec import paper_net as pn
from mapd.errors import ConfigError, MapdError
from mapd.grid import OccupancyGrid
from mapd.train import install, loop
from mapd.train import snapshots as sn
from mapd.train.data import sample_tiles
from mapd.train.loop import main_train, train
from mapd.train.settings import TrainConfig

from .conftest import write_rooms

PLACES = ["hall", "lab", "office", "store"]
MODEL_FILES = (pm.WEIGHTS_FILE, pm.META_FILE, "MODEL_CARD.md")


@pytest.fixture(scope="module")
def map_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_rooms(tmp_path_factory.mktemp("maps"), PLACES, 26, 30)


def _cfg(map_dir: Path, out: Path, **kw: Any) -> TrainConfig:
    base: dict[str, Any] = dict(
        epochs=1, tile=16, tiles_per_epoch=8, batch=8, val_tiles=8, progress=False, evaluate=False
    )
    base.update(kw)
    return TrainConfig(maps=map_dir, out=out, **base)


def _tiny_argv(map_dir: Path, out: Path, *extra: str) -> list[str]:
    return [
        "train", "--maps", str(map_dir), "--epochs", "1", "--tile", "16", "--tiles-per-epoch", "8",
        "--batch", "8", "--val-tiles", "8", "--quiet", "--no-eval", *extra, "-o", str(out),
    ]  # fmt: skip


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make any start of the real work (maps prepared, tiles drawn, threads set) fail the test."""

    def started(*_: object, **__: object) -> None:
        raise AssertionError("the work started before the bad setting was refused")

    monkeypatch.setattr(loop, "prepare_map", started)
    monkeypatch.setattr(loop, "sample_tiles", started)
    monkeypatch.setattr(torch, "set_num_threads", started)


def _error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


# --------------------------------------------------------------------------------------------
# 6: the output folder
# --------------------------------------------------------------------------------------------


def test_output_that_is_a_file_fails_before_training(
    map_dir: Path, tmp_path: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "model"
    target.write_bytes(b"not a model")
    assert cli.main(_tiny_argv(map_dir, target)) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "not a folder" in lines[0], lines
    assert target.read_bytes() == b"not a model"


def test_output_folder_holding_other_files_is_not_replaced(
    map_dir: Path, tmp_path: Path, no_work: None
) -> None:
    out = tmp_path / "notes"
    out.mkdir()
    (out / "todo.txt").write_text("keep me")
    with pytest.raises(ConfigError, match=r"todo\.txt"):
        train(_cfg(map_dir, out))
    assert _files(out) == {"todo.txt": b"keep me"}


def test_read_only_output_folder_fails_before_training(
    map_dir: Path,
    tmp_path: Path,
    no_work: None,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    real_mkdir = os.mkdir

    def mkdir(path: Any, mode: int = 0o777, **kw: Any) -> None:
        # A read-only file system (tests often run as root, whom chmod does not stop).
        if os.fspath(path).startswith(f"{ro}{os.sep}"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(path))
        real_mkdir(path, mode, **kw)

    monkeypatch.setattr(os, "mkdir", mkdir)
    assert cli.main(_tiny_argv(map_dir, ro / "model")) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "Read-only file system" in lines[0], lines


@pytest.mark.parametrize("exchange", [True, False], ids=["atomic-swap", "rename-aside"])
@pytest.mark.parametrize("fails", ["weights", "card"])
def test_failed_write_leaves_the_old_model_whole(
    map_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fails: str, exchange: bool
) -> None:
    if not exchange:  # a system without an atomic swap of two folders
        monkeypatch.setattr(install, "exchange", lambda a, b: False)
    out = tmp_path / "models" / "tiny"
    train(_cfg(map_dir, out, seed=1))
    old = _files(out)
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    real_write_weights, real_model_card = pm.write_weights, loop.model_card

    def write_weights(path: Path, arrays: dict[str, np.ndarray]) -> str:
        path.write_bytes(b"")  # a full disk: the file is created, its bytes never arrive
        raise full

    def model_card(meta: dict[str, Any]) -> str:
        raise full

    if fails == "weights":
        monkeypatch.setattr(pm, "write_weights", write_weights)
    else:
        monkeypatch.setattr(loop, "model_card", model_card)
    with pytest.raises(MapdError, match="No space left on device"):
        main_train(_cfg(map_dir, out, seed=2))
    assert _files(out) == old
    assert os.listdir(out.parent) == ["tiny"]  # nothing staged is left behind

    # The next run that can write replaces the model whole.
    monkeypatch.setattr(pm, "write_weights", real_write_weights)
    monkeypatch.setattr(loop, "model_card", real_model_card)
    meta = train(_cfg(map_dir, out, seed=2))
    new = _files(out)
    assert sorted(new) == sorted(MODEL_FILES) and new != old
    assert json.loads(new[pm.META_FILE])["weights_sha256"] == hashlib.sha256(new[pm.WEIGHTS_FILE]).hexdigest()
    assert meta["weights_sha256"] == json.loads(new[pm.META_FILE])["weights_sha256"]
    assert pm.load_model(out).sha256 == meta["weights_sha256"]
    assert os.listdir(out.parent) == ["tiny"]


# --------------------------------------------------------------------------------------------
# 7: bounds of the settings, diverged runs, memory
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("setting", "option"),
    [
        ({"threads": 100_000_000}, "--threads"),
        ({"tile": 1_000_000}, "--tile"),
        ({"batch": 100_000_000}, "--batch"),
        ({"tiles_per_epoch": 100_000_000}, "--tiles-per-epoch"),
        ({"val_tiles": 100_000_000}, "--val-tiles"),
        ({"epochs": 10**12}, "--epochs"),
        ({"lr": math.inf}, "--lr"),
        ({"lr": math.nan}, "--lr"),
        ({"lr": 0.0}, "--lr"),
        ({"lr": 1e6}, "--lr"),
        ({"batch": 1024, "tile": 256}, "--batch 1024 of --tile 256"),
        ({"levels": 1000}, "--levels"),
        ({"seed": -1}, "--seed"),
    ],
)
def test_settings_out_of_range_are_refused_before_any_work(
    map_dir: Path, tmp_path: Path, no_work: None, setting: dict[str, Any], option: str
) -> None:
    with pytest.raises(ConfigError, match=option):
        main_train(_cfg(map_dir, tmp_path / "x", **setting))
    assert not (tmp_path / "x").exists()


def test_absurd_threads_on_the_command_line_is_one_line(
    map_dir: Path, tmp_path: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(_tiny_argv(map_dir, tmp_path / "x", "--threads", "100000000")) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "--threads" in lines[0], lines


def test_out_of_memory_is_one_line(map_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def sample(*_: object, **__: object) -> None:
        raise MemoryError

    monkeypatch.setattr(loop, "sample_tiles", sample)
    with pytest.raises(MapdError, match="out of memory"):
        main_train(_cfg(map_dir, tmp_path / "x"))


def test_model_with_non_finite_weights_is_not_saved(
    map_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = pm.state_arrays

    def nan_arrays(net: pn.PaperNet) -> dict[str, np.ndarray]:
        arrays = real(net)
        first = sorted(arrays)[0]
        arrays[first] = np.full_like(arrays[first], np.nan)
        return arrays

    monkeypatch.setattr(pm, "state_arrays", nan_arrays)
    with pytest.raises(MapdError, match="NaN or infinity"):
        main_train(_cfg(map_dir, tmp_path / "x"))
    assert not (tmp_path / "x").exists()


def test_diverged_loss_stops_the_run(map_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = loop._loss
    monkeypatch.setattr(loop, "_loss", lambda net, batch, device: real(net, batch, device) * math.nan)
    with pytest.raises(MapdError, match="diverged in epoch 1"):
        main_train(_cfg(map_dir, tmp_path / "x", epochs=2))
    assert not (tmp_path / "x").exists()


def test_tiles_drawn_a_batch_at_a_time_are_the_tiles_of_one_draw() -> None:
    grid = OccupancyGrid(
        np.where(np.random.default_rng(0).random((40, 44)) < 0.3, 100, 0).astype(np.int8), 0.05
    )
    maps = [loop.prepare_map("a", grid, 16)]
    whole = sample_tiles(maps, 21, 16, np.random.default_rng(4), 2.0)
    parts = list(loop._batches(maps, 21, 8, 16, np.random.default_rng(4), 2.0))
    assert [p.x.shape[0] for p in parts] == [8, 8, 5]
    for name in ("x", "fmask", "lmask"):
        assert torch.equal(torch.cat([getattr(p, name) for p in parts]), getattr(whole, name))


# --------------------------------------------------------------------------------------------
# 8: the snapshot cache
# --------------------------------------------------------------------------------------------


def _garbage(path: Path) -> None:
    path.write_bytes(b"\x00garbage" * 50)


def _truncated(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _count_too_high(path: Path) -> None:
    with np.load(path) as z:
        one = z["m0000"]
    with path.open("wb") as fh:
        np.savez_compressed(fh, m0000=one, count=np.int64(5), resolution=np.float64(0.05))


def _bad_resolution(path: Path) -> None:
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["resolution"] = np.array([1.0, 2.0])
    with path.open("wb") as fh:
        np.savez_compressed(fh, **arrays)


@pytest.mark.parametrize("damage", [_garbage, _truncated, _count_too_high, _bad_resolution])
def test_damaged_cache_entry_is_a_miss_and_is_rebuilt(
    tmp_path: Path, damage: Any, caplog: pytest.LogCaptureFixture
) -> None:
    grids, path = sn.sim_snapshots(5, every=15, scans=30, cache=tmp_path)
    damage(path)
    before = sn.REPLAYS["sim"]
    with caplog.at_level("WARNING", logger="mapd.train.snapshots"):
        again, path2 = sn.sim_snapshots(5, every=15, scans=30, cache=tmp_path)
    assert path2 == path and sn.REPLAYS["sim"] == before + 1  # made again
    assert [r.levelname for r in caplog.records] == ["WARNING"] and "damaged" in caplog.text
    assert [g.data.tobytes() for g in again] == [g.data.tobytes() for g in grids]
    sn.sim_snapshots(5, every=15, scans=30, cache=tmp_path)
    assert sn.REPLAYS["sim"] == before + 1  # the rewritten entry loads


def test_cache_that_cannot_be_written_is_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def full(*_: object, **__: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np, "savez_compressed", full)
    with caplog.at_level("WARNING", logger="mapd.train.snapshots"):
        grids, path = sn.sim_snapshots(5, every=15, scans=30, cache=tmp_path)
    assert len(grids) == 2 and not path.exists()
    assert "No space left on device" in caplog.text
    assert os.listdir(path.parent) == []  # no temp file left


@pytest.mark.parametrize("under", [False, True], ids=["file", "path-through-a-file"])
def test_cache_path_that_is_not_a_folder_is_one_line_before_the_snapshots(
    map_dir: Path, tmp_path: Path, under: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    cache = tmp_path / "cache"
    cache.write_text("a file")
    before = dict(sn.REPLAYS)
    argv = _tiny_argv(
        map_dir,
        tmp_path / "m",
        "--snapshots-sim", "5", "--snapshot-every", "10", "--sim-scans", "20",
        "--cache", str(cache / "sub" if under else cache),
    )  # fmt: skip
    assert cli.main(argv) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "--cache" in lines[0], lines
    assert dict(sn.REPLAYS) == before  # refused before any snapshot was made
    assert cache.read_text() == "a file"
