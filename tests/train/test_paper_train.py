"""``mapd train`` end to end on a tiny synthetic map set: outputs, determinism, split by place."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mapd import cli
from mapd.codec import api
from mapd.codec import paper_model as pm
from mapd.codec import paper_net as pn
from mapd.codec.paper import PaperOptions
from mapd.grid import OccupancyGrid
from mapd.grid.load import load_map
from mapd.grid.save import save_map
from mapd.train.data import map_group, prepare_map, sample_tiles, split_maps
from mapd.train.loop import train
from mapd.train.settings import TrainConfig

PLACES = ["hall_a", "hall_b", "lab", "office_2019", "office_2020", "store", "yard"]


def _synthetic(h: int, w: int, seed: int) -> OccupancyGrid:
    rng = np.random.default_rng(seed)
    d = np.full((h, w), -1, dtype=np.int8)
    d[3 : h - 3, 4 : w - 4] = 0
    d[3, 4 : w - 4] = d[h - 4, 4 : w - 4] = 100
    d[3 : h - 3, 4] = d[3 : h - 3, w - 5] = 100
    d[(rng.random((h, w)) < 0.02) & (d == 0)] = 100
    return OccupancyGrid(d, 0.05)


@pytest.fixture(scope="module")
def map_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("maps")
    for i, place in enumerate(PLACES):
        save_map(_synthetic(30 + 3 * i, 41 - 2 * i, seed=i), root / place / "map.yaml")
    return root


def _cfg(map_dir: Path, out: Path, seed: int = 3, **kw: object) -> TrainConfig:
    base: dict = dict(epochs=2, tile=16, seed=seed, tiles_per_epoch=24, batch=8, val_tiles=16, progress=False)
    base.update(kw)
    return TrainConfig(maps=map_dir, out=out, **base)


def test_mapd_train_end_to_end(map_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "models" / "tiny"
    rc = cli.main(
        [
            "train", "--maps", str(map_dir), "--epochs", "2", "--tile", "16", "--seed", "1",
            "--tiles-per-epoch", "24", "--batch", "8", "--val-tiles", "16", "-o", str(out),
        ]
    )  # fmt: skip
    assert rc == 0
    captured = capsys.readouterr()
    assert "loss=" in captured.err  # the progress bar shows the loss
    assert "weights sha256" in captured.out

    meta = json.loads((out / pm.META_FILE).read_text())
    weights = (out / pm.WEIGHTS_FILE).read_bytes()
    assert meta["weights_sha256"] == hashlib.sha256(weights).hexdigest()
    assert [h["epoch"] for h in meta["training"]["history"]] == [1, 2]
    assert all(np.isfinite(h["train_mse"]) for h in meta["training"]["history"])
    assert meta["training"]["command"].startswith("mapd train --maps")
    assert meta["metrics"]["validation"]["maps"] == len(meta["split"]["validation"])
    card = (out / "MODEL_CARD.md").read_text()
    assert meta["weights_sha256"] in card
    assert "as the paper says" in card and "our choice" in card
    for name in meta["split"]["validation"]:
        assert name in card

    # The folder is a working model for the codec.
    opts = PaperOptions(model="tiny", model_dir=out.parent)
    grid = load_map(map_dir / "lab" / "map.yaml")
    back = api.decode(api.encode(grid, "paper", options=opts), options=opts)
    assert back.data.shape == grid.data.shape
    assert (
        api.read_header(api.encode(grid, "paper", options=opts)).variant
        == f"tiny:{meta['weights_sha256'][:12]}"
    )


def test_same_seed_same_weights_other_seed_other_weights(map_dir: Path, tmp_path: Path) -> None:
    a = train(_cfg(map_dir, tmp_path / "a", seed=7, evaluate=False))
    b = train(_cfg(map_dir, tmp_path / "b", seed=7, evaluate=False))
    c = train(_cfg(map_dir, tmp_path / "c", seed=8, evaluate=False))
    assert a["weights_sha256"] == b["weights_sha256"]
    assert (tmp_path / "a" / pm.WEIGHTS_FILE).read_bytes() == (tmp_path / "b" / pm.WEIGHTS_FILE).read_bytes()
    assert a["training"]["history"] == b["training"]["history"]
    assert a["weights_sha256"] != c["weights_sha256"]
    assert a["split"] == c["split"]  # the split depends on the maps, not the seed


@pytest.mark.parametrize("shape", [(2, 1, 7, 9), (1, 16, 1, 1), (3, 2, 1, 5), (1, 1, 33, 2)])
def test_the_deterministic_upsampling_is_bilinear_interpolation(shape: tuple[int, int, int, int]) -> None:
    """``bilinear2x`` (the skip on CUDA, where interpolate's gradient is refused in deterministic
    mode) gives interpolate's values and gradients, edges included."""
    import torch.nn.functional as F

    x = torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(sum(shape)))
    x.requires_grad_(True)
    ref = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)
    got = pn.bilinear2x(x)
    assert got.shape == ref.shape
    assert torch.allclose(got, ref, atol=1e-12)
    g = torch.randn_like(ref)
    (g_ref,) = torch.autograd.grad(ref, x, g)
    (g_got,) = torch.autograd.grad(got, x, g)
    assert torch.allclose(g_got, g_ref, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (run on a GPU machine)")
def test_training_on_cuda_runs_deterministically(map_dir: Path, tmp_path: Path) -> None:
    """``--device cuda`` trains under torch's deterministic mode, and the same seed repeats."""
    a = train(_cfg(map_dir, tmp_path / "a", seed=7, evaluate=False, device="cuda"))
    b = train(_cfg(map_dir, tmp_path / "b", seed=7, evaluate=False, device="cuda"))
    assert a["training"]["device"].startswith("cuda")
    assert a["weights_sha256"] == b["weights_sha256"]
    assert all(np.isfinite(h["train_mse"]) for h in a["training"]["history"])


def test_split_is_by_place_and_recorded(map_dir: Path, tmp_path: Path) -> None:
    meta = train(_cfg(map_dir, tmp_path / "m", evaluate=False, val_fraction=0.3))
    sp = meta["split"]
    assert sp["validation"] and sp["train"]
    assert not set(sp["validation"]) & set(sp["train"])
    assert sorted(sp["validation"] + sp["train"]) == sorted(PLACES)
    side = {m: ("val" if m in sp["validation"] else "train") for m in PLACES}
    assert side["office_2019"] == side["office_2020"]  # one place, one side
    assert side["hall_a"] == side["hall_b"]
    assert sp["groups"]["office_2019"] == sp["groups"]["office_2020"] == "office"


def test_split_rules() -> None:
    paths = [
        Path("m/radish/intel/intel.yaml"),
        Path("m/radish/intel_part1/intel_part1.yaml"),
        Path("m/radish/intel_part2/intel_part2.yaml"),
        Path("m/aws/002/map.yaml"),
        Path("m/aws/005/map.yaml"),
        Path("m/cob/ipa-office_2014/map.yaml"),
        Path("m/cob/ipa-office_2017/map.yaml"),
        Path("m/misc/kth_sim/map.yaml"),
        Path("m/misc/seattle/seattle.yaml"),
        Path("m/flat/a_1.yaml"),
        Path("m/flat/a_2.yaml"),
        Path("m/flat/b.yaml"),
    ]
    train_p, val_p, groups = split_maps(paths, 0.25)
    assert {groups[str(p)] for p in paths[:3]} == {"intel"}
    assert groups[str(paths[3])] == groups[str(paths[4])] == "aws"
    assert groups[str(paths[5])] == groups[str(paths[6])] == "ipa-office"
    assert groups[str(paths[9])] == groups[str(paths[10])] == "a"  # maps sharing a folder: by file name
    assert len(set(groups.values())) == 7
    for group in set(groups.values()):
        members = {str(p) for p in paths if groups[str(p)] == group}
        assert members <= {str(p) for p in train_p} or members <= {str(p) for p in val_p}
    assert map_group(Path("x/freiburg-079_part2/f.yaml")) == "freiburg-079"
    again = split_maps(list(reversed(paths)), 0.25)
    assert sorted(map(str, again[1])) == sorted(map(str, val_p))  # order of discovery does not matter


def test_tiles_come_only_from_the_given_maps_and_see_real_context() -> None:
    a = prepare_map("a", _synthetic(40, 50, seed=1), 16)
    rng = np.random.default_rng(0)
    batch = sample_tiles([a], 40, 16, rng)
    margin = pn.crop_margin()
    assert batch.x.shape == (40, 1, 16 + 2 * margin, 16 + 2 * margin)
    assert batch.fmask.shape == (40, 1, 8 + 2 * pn.RECOVERY_PAD, 8 + 2 * pn.RECOVERY_PAD)
    values = set(np.unique(batch.x.numpy()).tolist())
    assert values <= set(pn.map_to_input(np.array([-1, 0, 100], dtype=np.int8)).tolist())
    # Nine in ten tiles hold an edge: the output region is not one value.
    inner = batch.x[:, 0, margin:-margin, margin:-margin].numpy()
    varied = (inner.reshape(40, -1).max(1) != inner.reshape(40, -1).min(1)).mean()
    assert varied > 0.6
    # Features beyond the map's edge are marked invalid (the decoder pads them with unknown).
    assert not batch.fmask.all()


def test_edge_weight_weighs_boundary_cells_on_both_sides() -> None:
    grid = _synthetic(41, 51, seed=1)  # odd: some tiles reach past the map (weight 0 there)
    a = prepare_map("a", grid, 16)
    plain = sample_tiles([a], 30, 16, np.random.default_rng(5))
    heavy = sample_tiles([a], 30, 16, np.random.default_rng(5), edge_weight=3.0)
    assert torch.equal(plain.x, heavy.x)  # the same tiles: the weight does not touch the sampler
    assert set(np.unique(plain.lmask.numpy()).tolist()) <= {0.0, 1.0}
    assert set(np.unique(heavy.lmask.numpy()).tolist()) == {0.0, 1.0, 3.0}
    margin = pn.crop_margin()
    inner = heavy.x[:, 0, margin:-margin, margin:-margin].numpy()
    weights = heavy.lmask[:, 0].numpy()
    # A weighted cell differs from a 4-neighbour (inside the tile or in its context); an unweighted
    # cell inside the map equals all four.
    full = heavy.x[:, 0].numpy()
    c = slice(margin, -margin)
    differs = np.zeros_like(inner, dtype=bool)
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        shifted = full[
            :, margin + dr : full.shape[1] - margin + dr, margin + dc : full.shape[2] - margin + dc
        ]
        differs |= shifted != full[:, c, c]
    assert np.array_equal(weights == 3.0, differs & (plain.lmask[:, 0].numpy() > 0))


def test_bad_settings_are_config_errors(map_dir: Path, tmp_path: Path) -> None:
    from mapd.errors import ConfigError

    with pytest.raises(ConfigError, match="edge-weight"):
        train(_cfg(map_dir, tmp_path / "x", edge_weight=0.0))
    with pytest.raises(ConfigError, match="multiple of 4"):
        train(_cfg(map_dir, tmp_path / "x", tile=18))
    with pytest.raises(ConfigError, match="no map_server"):
        train(_cfg(tmp_path, tmp_path / "x"))
    assert cli.main(["train", "--maps", str(tmp_path / "nope"), "-o", str(tmp_path / "x")]) == 2
