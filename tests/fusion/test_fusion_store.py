"""FusionStore: the fusion files of the state directory, written whole and read forgivingly."""

from __future__ import annotations

import asyncio
import json
import logging
import pickle
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.config import FusionSection
from mapd.fusion.merge import NO_OWNER, Bounds, MergeResult
from mapd.fusion.placement import Placement
from mapd.fusion.store import OWNER_JSON, OWNER_NPY, TRANSFORMS_JSON, FusionStore, Saved, read_owner
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid, Pose2D

ZERO = Pose2D(0.0, 0.0, 0.0)


def _result(grid: OccupancyGrid) -> MergeResult:
    bounds = Bounds.of_grid(grid)
    assert bounds is not None
    owner = np.full(grid.data.shape, NO_OWNER, dtype=np.int16)
    owner[: grid.height // 2] = 1  # the top half is the second robot's
    return MergeResult(grid=grid, bounds=bounds, owner=owner)


def test_what_is_saved_is_what_a_restart_reads(tmp_path: Path, building: OccupancyGrid) -> None:
    store = FusionStore(tmp_path / "global", robot="a")
    grid = building.replace(origin=ZERO, version=9, frame_id="fleet")
    placed = {
        "a": Placement("a", ZERO, "anchor", True, 1.0, None, "its map frame is the fleet frame"),
        "b": Placement(
            "b",
            Pose2D(3.0, -1.0, 0.25),
            "estimate",
            True,
            0.9,
            0.95,
            "",
            "a",
            against_at=Pose2D(0.1, 0.2, 0.3),
        ),
    }
    result = _result(grid)
    store.save(result, placed, stamp=12.5, fleet_frame="a/map", mode="logodds")
    store.save_owner(result.owner, ["a", "b"])

    saved = store.load_placements()
    assert saved.version == 9 and saved.placements == placed
    restored = store.load_global()
    assert restored is not None and np.array_equal(restored.data, grid.data)
    doc = json.loads((tmp_path / "global" / TRANSFORMS_JSON).read_text())
    assert doc["fleet_frame"] == "a/map" and doc["robots"]["b"]["x"] == 3.0
    owner = read_owner(tmp_path / "global")
    assert owner is not None
    idx, names = owner
    assert names == ["a", "b"] and idx.shape == grid.data.shape
    assert (idx[: grid.height // 2] == 1).all() and (idx[grid.height // 2 :] == -1).all()


def test_a_store_with_nothing_in_it_restores_nothing(tmp_path: Path) -> None:
    store = FusionStore(tmp_path, robot="a")
    assert store.load_placements() == Saved() and store.load_global() is None
    assert read_owner(tmp_path) is None


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    doc=st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
        max_leaves=20,
    ),
    robots=st.dictionaries(
        st.text(max_size=6),
        st.dictionaries(
            st.sampled_from(
                ["robot", "x", "y", "yaw", "source", "accepted", "confidence", "agreement", "against_at"]
            ),
            # integers past a float's range too: JSON allows them, float() overflows on them
            st.none() | st.booleans() | st.floats() | st.text(max_size=5) | st.integers(-(10**400), 10**400),
            max_size=8,
        )
        | st.lists(st.integers(), max_size=2)
        | st.integers()
        | st.text(max_size=4),
        max_size=3,
    ),
    raw=st.binary(max_size=64),
)
def test_a_damaged_transforms_file_is_left_out_not_fatal(
    tmp_path: Path, doc: object, robots: dict[str, object], raw: bytes
) -> None:
    store = FusionStore(tmp_path, robot="a")
    for content in (json.dumps(doc).encode(), json.dumps({"version": 3, "robots": robots}).encode(), raw):
        (tmp_path / TRANSFORMS_JSON).write_bytes(content)
        saved = store.load_placements()  # never raises: a bad file costs the placements, not the daemon
        assert isinstance(saved.version, int)
        assert all(isinstance(p, Placement) for p in saved.placements.values())


@pytest.mark.parametrize(
    "entry",
    [[1], "a", 7, {"robot": "b", "x": 10**400, "y": 0, "yaw": 0}, {"robot": "b", "confidence": 10**400},
     {"robot": "b", "x": "1", "y": 0, "yaw": 0}, {"robot": "b", "agreement": [0.5]},
     {"robot": "b", "against_at": [1, 2, 3]}, {"robot": "b", "against_at": {"x": 1, "y": 2}},
     {"robot": "b", "against_at": {"x": 1e300, "y": 0, "yaw": 0}},
     {"robot": "b", "against_at": {"x": 0, "y": "0", "yaw": 0}},
     # far out: every merge's search overflowed to NaN and failed, the global map frozen for good
     {"robot": "b", "x": 1e308, "y": 1e308, "yaw": 0.5, "source": "estimate", "accepted": True}],
)  # fmt: skip
def test_a_damaged_placement_is_left_out_and_the_others_kept(
    tmp_path: Path, entry: object, caplog: pytest.LogCaptureFixture
) -> None:
    good = Placement("a", ZERO, "anchor", True, 1.0, None, "its map frame is the fleet frame")
    doc = {"version": 2, "robots": {"a": good.as_dict(), "b": entry}}
    (tmp_path / TRANSFORMS_JSON).write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING, logger="mapd.fusion.store"):
        assert FusionStore(tmp_path, robot="a").load_placements() == Saved({"a": good}, 2)
    # one line, naming the entry and the file
    assert [r.getMessage().split(":")[0] for r in caplog.records] == ["fusion"]
    assert f"ignoring entry 'b' of {tmp_path / TRANSFORMS_JSON}" in caplog.text


@pytest.mark.parametrize(
    "damage",
    ["truncated", "pickled", "names not a list", "floats", "one axis"],
)
def test_a_damaged_owner_map_is_no_owner_map(tmp_path: Path, damage: str) -> None:
    store = FusionStore(tmp_path, robot="a")
    store.save_owner(np.zeros((4, 5), dtype=np.int16), ["a"])
    assert read_owner(tmp_path) is not None
    npy, names = tmp_path / OWNER_NPY, tmp_path / OWNER_JSON
    if damage == "truncated":
        npy.write_bytes(npy.read_bytes()[:-7])
    elif damage == "pickled":  # np.load would run code from the file if allowed to unpickle
        npy.write_bytes(pickle.dumps(np.zeros((2, 2), dtype=object)))
    elif damage == "names not a list":
        names.write_text(json.dumps({"robots": "a"}))
    elif damage == "floats":
        np.save(npy, np.zeros((4, 5), dtype=np.float32))
    else:
        np.save(npy, np.zeros(20, dtype=np.int16))
    assert read_owner(tmp_path) is None


def test_an_owner_map_that_cannot_be_written_does_not_cost_the_global_map(
    tmp_path: Path, building: OccupancyGrid
) -> None:
    # owner.json cannot be replaced (a directory stands in its place): the pictures lose their
    # colours, but the merge is published and the global map saved as always.
    (tmp_path / OWNER_JSON).mkdir()
    a = building.replace(origin=ZERO, robot="a")

    async def main() -> FusionWorker:
        w = FusionWorker("a", FusionSection(debounce_s=0.0), tmp_path)
        w.submit(a)
        await w.merge_now()
        return w

    w = asyncio.run(main())
    assert w.status()["error"] is None and w.global_map is not None
    assert FusionStore(tmp_path, robot="a").load_placements().version == 1


def test_a_failing_owner_map_write_is_said_once_naming_the_file(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A full or read-only disk logged a warning on every merge (17 in 20 s), naming the temp file."""
    import logging

    store = FusionStore(tmp_path, robot="a")
    (tmp_path / OWNER_NPY).mkdir()  # (every write fails, as on a full disk)
    owner = np.zeros((4, 4), np.uint8)
    with caplog.at_level(logging.INFO, logger="mapd"):
        for _ in range(5):
            store.save_owner(owner, ["a"])
        said = [r for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(said) == 1 and str(tmp_path / OWNER_NPY) in said[0].getMessage(), said
        assert ".tmp" not in said[0].getMessage()
        (tmp_path / OWNER_NPY).rmdir()
        store.save_owner(owner, ["a"])
    assert "again" in caplog.records[-1].getMessage()
    assert read_owner(tmp_path) is not None


def _global_room(version: int, fill: int) -> MergeResult:
    data = np.full((64, 64), fill, np.int8)
    return _result(OccupancyGrid(data, 0.05, origin=ZERO, version=version, frame_id="fleet"))


def test_the_global_map_names_an_image_of_its_own_and_keeps_one(tmp_path: Path) -> None:
    # A fixed global.pgm renamed before global.yaml: a kill between the two left the old YAML (its
    # origin) over the new image, a map shifted by as much as the global map grew.
    import yaml

    store = FusionStore(tmp_path, robot="a")
    (tmp_path / "global.pgm").parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / "global.pgm").write_bytes(b"P5\n1 1\n255\n\x00")  # an earlier release's image
    for v in (1, 2, 3):
        store.save(_global_room(v, 0 if v < 3 else 100), {}, stamp=1.0, fleet_frame=None, mode="logodds")
    meta = yaml.safe_load((tmp_path / "global.yaml").read_text())
    assert meta["image"] == "global-3.pgm" and meta["mapd_version"] == 3
    assert meta["mapd_digest"] == _global_room(3, 100).grid.digest().hex()
    assert sorted(p.name for p in tmp_path.glob("*.pgm")) == ["global-3.pgm"]  # none piles up
    restored = store.load_global()
    assert restored is not None and restored.version == 3 and int(restored.data.min()) == 100


def test_a_global_image_not_matching_its_yaml_is_one_warning_and_a_new_global_map(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, building: OccupancyGrid
) -> None:
    import logging

    store = FusionStore(tmp_path, robot="a")
    store.save(_global_room(4, 0), {}, stamp=1.0, fleet_frame=None, mode="logodds")
    image = tmp_path / "global-4.pgm"
    raw = bytearray(image.read_bytes())
    raw[-1] = 0  # one free cell now occupied: another image than the YAML's
    image.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING, logger="mapd"):
        assert store.load_global() is None
        w = FusionWorker("a", FusionSection(debounce_s=0.0), tmp_path)
        w.submit(building.replace(origin=ZERO, robot="a"))
        asyncio.run(w.merge_now())  # starts a new global map
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(said) == 2 and all("global.yaml" in m and "digest" in m for m in said), said
    assert w.status()["error"] is None and w.global_map is not None
    assert w.global_map.same_map(store.load_global())  # type: ignore[arg-type]


def test_a_global_map_of_an_earlier_release_is_still_restored(tmp_path: Path) -> None:
    # global.yaml + global.pgm, no version or digest in the YAML: as an earlier release wrote them
    from mapd.grid.save import save_map

    grid = _global_room(7, 100).grid
    save_map(grid, tmp_path / "global.yaml")
    restored = FusionStore(tmp_path, robot="a").load_global()
    assert restored is not None and restored.same_map(grid)
