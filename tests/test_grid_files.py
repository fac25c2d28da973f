"""map_server files: exact loading rules, exact round trips, and clear errors for bad files."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from mapd.errors import LimitError, MapdError, MapFileError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map, read_map_yaml
from mapd.grid.save import save_map


def write_map(tmp: Path, pixels: np.ndarray, name: str = "m", ext: str = "pgm", **meta: object) -> Path:
    img_path = tmp / f"{name}.{ext}"
    Image.fromarray(pixels).save(img_path)
    doc = {
        "image": img_path.name,
        "resolution": 0.05,
        "origin": [0.0, 0.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    doc.update(meta)
    y = tmp / f"{name}.yaml"
    y.write_text(yaml.safe_dump(doc))
    return y


def test_trinary_rules_and_row_order(tmp_path: Path) -> None:
    # Top image row is the last map row (nav_msgs row 0 is at the origin, image row 0 is the top).
    px = np.array([[254, 0, 205], [255, 204, 128]], dtype=np.uint8)
    g = load_map(write_map(tmp_path, px))
    assert g.data.tolist() == [[0, -1, -1], [0, 100, -1]]
    assert g.data.dtype == np.int8 and (g.height, g.width) == (2, 3)


def test_thresholds_are_strict_and_205_reads_free_under_high_free_thresh(tmp_path: Path) -> None:
    px = np.array([[205, 89, 90]], dtype=np.uint8)
    # occ(205) = 50/255 = 0.196 < 0.25 -> free (the depot map's case); occ(89) = 0.651 > 0.65 -> occupied;
    # occ(90) = 0.647 -> not occupied.
    g = load_map(write_map(tmp_path, px, free_thresh=0.25))
    assert g.data.tolist() == [[0, 100, -1]]


def test_negate_flips_meaning(tmp_path: Path) -> None:
    px = np.array([[0, 255]], dtype=np.uint8)
    g = load_map(write_map(tmp_path, px, negate=1))
    assert g.data.tolist() == [[0, 100]]


def test_scale_mode_formula(tmp_path: Path) -> None:
    px = np.array([[254, 0, 160, 120]], dtype=np.uint8)
    g = load_map(write_map(tmp_path, px, mode="scale"))
    occ = (255 - np.array([160.0, 120.0])) / 255
    expect = (1 + 98 * (occ - 0.196) / (0.65 - 0.196)).astype(int)
    assert g.data.tolist() == [[0, 100, *expect.tolist()]]


def test_scale_mode_alpha_zero_is_unknown(tmp_path: Path) -> None:
    px = np.array([[[160, 160, 160, 255], [160, 160, 160, 0]]], dtype=np.uint8)
    g = load_map(write_map(tmp_path, px, ext="png", mode="scale"))
    assert g.data[0, 0] > 0 and g.data[0, 1] == -1


def test_raw_mode_stores_byte_values(tmp_path: Path) -> None:
    px = np.array([[0, 37, 100, 255]], dtype=np.uint8)
    g = load_map(write_map(tmp_path, px, mode="raw"))
    assert g.data.tolist() == [[0, 37, 100, -1]]


def test_rgb_is_averaged(tmp_path: Path) -> None:
    # Mean of (254, 254, 254) is free; mean of (255, 0, 0) = 85 -> occ 0.667 -> occupied.
    px = np.array([[[254, 254, 254], [255, 0, 0]]], dtype=np.uint8)
    g = load_map(write_map(tmp_path, px, ext="png"))
    assert g.data.tolist() == [[0, 100]]


def test_sixteen_bit_image(tmp_path: Path) -> None:
    px = np.array([[65535, 0, 205 * 257]], dtype=np.uint16)
    img = tmp_path / "m.png"
    Image.fromarray(px).save(img)
    y = tmp_path / "m.yaml"
    y.write_text(yaml.safe_dump({"image": "m.png", "resolution": 0.1, "origin": [0, 0, 0]}))
    assert load_map(y).data.tolist() == [[0, 100, -1]]


@pytest.mark.parametrize("yaw", [0.0, math.pi, -math.pi / 2, 0.3])
def test_save_load_round_trip_keeps_origin_and_yaw(tmp_path: Path, yaw: float) -> None:
    rng = np.random.default_rng(1)
    g = OccupancyGrid(rng.choice([-1, 0, 100], (31, 17)).astype(np.int8), 0.025, Pose2D(-3.5, 12.25, yaw))
    back = load_map(save_map(g, tmp_path / "out.yaml"))
    assert back.same_map(g)
    assert back.origin.yaw == yaw


def test_graded_values_round_trip_through_raw_mode(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    g = OccupancyGrid(rng.integers(-1, 101, (23, 29)).astype(np.int8), 0.05)
    path = save_map(g, tmp_path / "graded.yaml")
    assert read_map_yaml(path)["mode"] == "raw"
    assert load_map(path).same_map(g)


def test_every_shared_map_loads_and_round_trips(shared_maps: list[Path], tmp_path: Path) -> None:
    from mapd.codec import decode, encode

    assert len(shared_maps) >= 50
    for path in shared_maps:
        g = load_map(path)
        assert g.cells > 0 and g.data.dtype == np.int8
        back = load_map(save_map(g, tmp_path / "copy.yaml"))
        assert back.same_map(g), path
        for codec in ("raw", "zstd"):
            assert decode(encode(g, codec)).same_map(g), (path, codec)


def test_shared_maps_with_odd_grey_levels_load_like_map_server(data_dir: Path) -> None:
    maps = data_dir / "maps"
    # depot: free_thresh 0.25 makes 205 free, so it has no unknown cells at all.
    depot = load_map(maps / "navigation2/depot_sim/depot.yaml")
    assert depot.counts()["unknown"] == 0
    # willow: unknown is 204 (occ 0.2 > 0.196) and 128 is neither free nor occupied.
    willow = load_map(maps / "ros_navigation/willow-full/willow-full-0.05.yaml")
    img = np.asarray(Image.open(maps / "ros_navigation/willow-full/willow-full-0.05.pgm"))
    cells = np.flipud(willow.data)
    assert np.all(cells[img == 204] == -1) and np.all(cells[img == 128] == -1)
    assert np.all(cells[img == 255] == 0) and np.all(cells[img == 0] == 100)
    # An RGB png with grey level 203 for unknown.
    aws = load_map(maps / "aws_small_warehouse/005/map.yaml")
    assert aws.counts()["unknown"] > 0


# --------------------------------------------------------------------------- bad files


def test_missing_yaml(tmp_path: Path) -> None:
    with pytest.raises(MapFileError, match="no such map file"):
        load_map(tmp_path / "nope.yaml")


def test_missing_image_names_file(tmp_path: Path) -> None:
    y = tmp_path / "m.yaml"
    y.write_text("image: gone.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapFileError, match=r"m\.yaml.*gone\.pgm.*does not exist"):
        load_map(y)


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ({"occupied_thresh": 1.5}, "thresholds must lie in"),
        ({"free_thresh": -0.1}, "thresholds must lie in"),
        ({"free_thresh": 0.9, "occupied_thresh": 0.5}, "above occupied_thresh"),
        ({"mode": "fancy"}, "unknown mode 'fancy'"),
        ({"resolution": 0}, "resolution must be positive"),
        ({"origin": [1, 2]}, "origin must be a list"),
        ({"negate": 3}, "negate must be 0 or 1"),
        ({"resolution": "abc"}, "resolution"),
    ],
)
def test_bad_yaml_fields(tmp_path: Path, extra: dict, match: str) -> None:
    y = write_map(tmp_path, np.zeros((2, 2), np.uint8), **extra)
    with pytest.raises(MapFileError, match=match):
        load_map(y)


def test_malformed_yaml(tmp_path: Path) -> None:
    y = tmp_path / "m.yaml"
    y.write_text("image: [unclosed\nresolution: 0.05\n")
    with pytest.raises(MapFileError, match="malformed YAML"):
        load_map(y)


def test_truncated_image(tmp_path: Path) -> None:
    y = write_map(tmp_path, np.full((64, 64), 254, np.uint8), ext="png")
    png = tmp_path / "m.png"
    png.write_bytes(png.read_bytes()[:60])
    with pytest.raises(MapFileError, match=r"m\.png"):
        load_map(y)


def test_zero_pixel_image(tmp_path: Path) -> None:
    (tmp_path / "m.pgm").write_bytes(b"P5\n0 0\n255\n")
    y = tmp_path / "m.yaml"
    y.write_text("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapFileError, match=r"m\.pgm"):
        load_map(y)


def test_declared_size_over_cell_limit_is_refused_before_decoding(tmp_path: Path) -> None:
    # A PGM header claiming 100000 x 100000 pixels with no data behind it.
    (tmp_path / "m.pgm").write_bytes(b"P5\n100000 100000\n255\n" + bytes(10))
    y = tmp_path / "m.yaml"
    y.write_text("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises((LimitError, MapFileError), match="100000"):
        load_map(y, max_cells=10_000_000)


def test_cell_limit_is_configurable(tmp_path: Path) -> None:
    y = write_map(tmp_path, np.zeros((10, 10), np.uint8))
    with pytest.raises(LimitError, match="over the limit of 99 cells"):
        load_map(y, max_cells=99)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(max_size=300))
def test_fuzz_yaml_text_gives_only_mapd_errors(tmp_path: Path, text: str) -> None:
    y = tmp_path / "fuzz.yaml"
    y.write_text(text)
    with contextlib.suppress(MapdError):
        load_map(y)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(blob=st.binary(max_size=400))
def test_fuzz_image_bytes_give_only_mapd_errors(tmp_path: Path, blob: bytes) -> None:
    (tmp_path / "f.pgm").write_bytes(b"P5\n4 4\n255\n" + blob if blob[:1] == b"\x00" else blob)
    y = tmp_path / "f.yaml"
    y.write_text("image: f.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    try:
        g = load_map(y, max_cells=1 << 20)
    except MapdError:
        return
    assert g.data.dtype == np.int8


@pytest.mark.parametrize("maxval", [1, 7, 100, 254, 255, 256, 1000, 65535])
@pytest.mark.parametrize("kind", ["P5", "P6"])
def test_binary_pnm_reads_like_pillow_for_any_maxval(tmp_path: Path, kind: str, maxval: int) -> None:
    # mapd reads P5/P6 pixels itself (Pillow converts maxval != 255 one sample at a time in Python);
    # the grey levels must be Pillow's, which is what mapd has always loaded.
    rng = np.random.default_rng(maxval)
    channels = 3 if kind == "P6" else 1
    samples = rng.integers(0, maxval + 1, size=(5, 7, channels))
    raw = samples.astype(">u2" if maxval > 255 else np.uint8).tobytes()
    (tmp_path / "m.pnm").write_bytes(f"{kind}\n# comment\n7 5\n{maxval}\n".encode() + raw)
    y = tmp_path / "m.yaml"
    y.write_text("image: m.pnm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: raw\n")
    with Image.open(tmp_path / "m.pnm") as img:
        grey = np.asarray(img).astype(np.float64)
        if img.mode == "I":
            grey = grey * (255.0 / 65535.0)
    if grey.ndim == 3:
        grey = grey.sum(axis=2) / 3
    expect = np.flipud(grey.astype(np.uint8).view(np.int8))
    assert load_map(y).data.tolist() == expect.tolist()


@pytest.mark.parametrize(("maxval", "over"), [(10, 11), (10, 255), (254, 255), (300, 301), (1000, 65535)])
def test_a_binary_pnm_sample_over_its_maxval_is_refused(tmp_path: Path, maxval: int, over: int) -> None:
    # Netpbm: no sample is above maxval. Clamped, such a sample read as white (free space) where
    # the plain form of the same file is refused ("Channel value too large").
    samples = np.full((3, 4), maxval // 2)
    samples[1, 2] = over
    raw = samples.astype(">u2" if maxval > 255 else np.uint8).tobytes()
    (tmp_path / "m.pgm").write_bytes(f"P5\n4 3\n{maxval}\n".encode() + raw)
    y = tmp_path / "m.yaml"
    y.write_text("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapFileError, match=rf"m.pgm' has a sample of {over}, over its PNM maxval {maxval}$"):
        load_map(y)
