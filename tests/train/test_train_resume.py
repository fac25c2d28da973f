"""``mapd train`` stopped and resumed: the checkpoint after each epoch, and the same weights after."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
import torch

from mapd import cli
from mapd.codec import paper_model as pm
from mapd.errors import ConfigError
from mapd.train import checkpoint as ckpt
from mapd.train.loop import train
from mapd.train.settings import TrainConfig
from tests.train.conftest import write_rooms


@pytest.fixture(scope="module")
def map_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_rooms(tmp_path_factory.mktemp("maps"), ["hall_a", "hall_b", "lab", "store", "yard"], 30, 37)


def _cfg(map_dir: Path, out: Path, **kw: object) -> TrainConfig:
    base: dict = dict(
        epochs=4, tile=16, seed=5, tiles_per_epoch=24, batch=8, val_tiles=16, progress=False, evaluate=False
    )
    base.update(kw)
    return TrainConfig(maps=map_dir, out=out, **base)


def _args(map_dir: Path, out: Path, *more: str) -> list[str]:
    return [
        "train", "--maps", str(map_dir), "--epochs", "4", "--tile", "16", "--seed", "5",
        "--tiles-per-epoch", "24", "--batch", "8", "--val-tiles", "16", "--no-eval", "--quiet",
        "--threads", "1", "-o", str(out), *more,
    ]  # fmt: skip


def test_a_run_stopped_and_resumed_gives_the_weights_of_an_unbroken_run(
    map_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    straight = tmp_path / "straight"
    assert cli.main(_args(map_dir, straight)) == 0
    assert not ckpt.checkpoint_path(straight).exists()  # a finished run leaves no checkpoint

    out = tmp_path / "stopped"
    capsys.readouterr()
    # A limit of 0 s stops after the first epoch; each resume goes one epoch further.
    assert cli.main(_args(map_dir, out, "--time-limit", "1e-9")) == 3
    err = capsys.readouterr().err
    assert "stopped after epoch 1 of 4" in err and "--resume" in err
    assert not out.exists() and ckpt.checkpoint_path(out).is_file()
    assert cli.main(_args(map_dir, out, "--resume", "--time-limit", "1e-9")) == 3
    assert "stopped after epoch 2 of 4" in capsys.readouterr().err
    assert cli.main(_args(map_dir, out, "--resume")) == 0
    assert not ckpt.checkpoint_path(out).exists()

    a = json.loads((straight / pm.META_FILE).read_text())
    b = json.loads((out / pm.META_FILE).read_text())
    assert (out / pm.WEIGHTS_FILE).read_bytes() == (straight / pm.WEIGHTS_FILE).read_bytes()
    assert b["weights_sha256"] == hashlib.sha256((out / pm.WEIGHTS_FILE).read_bytes()).hexdigest()
    assert a["training"]["history"] == b["training"]["history"]
    assert (a["training"]["resumed_after_epochs"], b["training"]["resumed_after_epochs"]) == ([], [1, 2])


def test_a_checkpoint_is_not_run_over_or_resumed_with_other_settings(map_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "m"
    with pytest.raises(ckpt.TrainingPaused):
        train(_cfg(map_dir, out, time_limit=1e-9))
    saved = ckpt.checkpoint_path(out)
    before = saved.read_bytes()
    with pytest.raises(ConfigError, match="add --resume"):  # starting over would lose the stopped run
        train(_cfg(map_dir, out))
    with pytest.raises(ConfigError, match=r"made with lr 0\.002, this run has 0\.001"):
        train(_cfg(map_dir, out, resume=True, lr=1e-3))
    with pytest.raises(ConfigError, match="made with epochs 4, this run has 5"):
        train(_cfg(map_dir, out, resume=True, epochs=5))
    with pytest.raises(ConfigError, match="no checkpoint"):
        train(_cfg(map_dir, tmp_path / "other", resume=True))
    assert saved.read_bytes() == before  # refusals leave it as it was


@pytest.mark.parametrize(
    ("damage", "why"),
    [
        (lambda b: b[: len(b) // 2], "damaged or not a checkpoint"),
        (lambda b: b"", "damaged or not a checkpoint"),
        (lambda b: b"not a zip at all" * 10, "damaged or not a checkpoint"),
    ],
)
def test_a_damaged_checkpoint_is_one_line(map_dir: Path, tmp_path: Path, damage: object, why: str) -> None:
    out = tmp_path / "m"
    with pytest.raises(ckpt.TrainingPaused):
        train(_cfg(map_dir, out, time_limit=1e-9))
    saved = ckpt.checkpoint_path(out)
    saved.write_bytes(damage(saved.read_bytes()))  # type: ignore[operator]
    with pytest.raises(ConfigError, match=why):
        train(_cfg(map_dir, out, resume=True))


def test_a_checkpoint_that_would_run_code_is_refused(map_dir: Path, tmp_path: Path) -> None:
    """weights_only loading: a pickle that calls a function is refused, and the function never runs."""

    class Boom:
        def __reduce__(self) -> tuple[object, tuple[str]]:
            return (Path("/nonexistent-mapd-boom").mkdir, ())  # type: ignore[return-value]

    saved = ckpt.checkpoint_path(tmp_path / "m")
    torch.save({"format": ckpt.FORMAT, "settings": Boom()}, saved)
    with pytest.raises(ConfigError, match="damaged or not a checkpoint"):
        train(_cfg(map_dir, tmp_path / "m", resume=True))
    assert not Path("/nonexistent-mapd-boom").exists()


def test_a_foreign_or_tampered_checkpoint_is_one_line(map_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "m"
    saved = ckpt.checkpoint_path(out)
    torch.save({"format": 99}, saved)
    with pytest.raises(ConfigError, match="not a checkpoint of this mapd"):
        train(_cfg(map_dir, out, resume=True))
    with pytest.raises(ckpt.TrainingPaused):
        train(_cfg(map_dir, tmp_path / "n", time_limit=1e-9))
    state = torch.load(ckpt.checkpoint_path(tmp_path / "n"), weights_only=True)
    state["net"] = {"nope": torch.zeros(1)}
    torch.save(state, ckpt.checkpoint_path(tmp_path / "n"))
    with pytest.raises(ConfigError, match="does not fit this run"):
        train(_cfg(map_dir, tmp_path / "n", resume=True))
