"""The ``paper`` codec through the real codec API, with small throw-away models.

These tests do not depend on the shipped weights (see test_paper_shipped.py for those): each model
here is a freshly initialised network written to a temporary model folder the way ``mapd train``
writes one.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.codec import api, hexruns, huffman
from mapd.codec import paper_model as pm
from mapd.codec import paper_net as pn
from mapd.codec.paper import (
    FLAG_FREE,
    FLAG_GRADED,
    FLAG_OCCUPIED,
    FLAG_UNKNOWN,
    PaperCodec,
    PaperOptions,
    snap,
    source_flags,
)
from mapd.errors import CodecError
from mapd.grid import OccupancyGrid, Pose2D, grey_levels


def make_model(folder: Path, seed: int, levels: int = 16) -> None:
    """A freshly initialised model folder, written the way ``mapd train`` writes one."""
    torch.manual_seed(seed)
    net = pn.PaperNet(levels)
    folder.mkdir(parents=True)
    sha = pm.write_weights(folder / pm.WEIGHTS_FILE, pm.state_arrays(net))
    meta = {
        "name": folder.name,
        "format": pm.MODEL_FORMAT,
        "levels": levels,
        "channels": 16,
        "weights_sha256": sha,
    }
    (folder / pm.META_FILE).write_text(json.dumps(meta))


def room_grid_of(h: int, w: int, seed: int) -> OccupancyGrid:
    """A trinary map of any size: unknown around, a free room with walls, random clutter."""
    rng = np.random.default_rng(seed)
    d = np.full((h, w), -1, dtype=np.int8)
    r0, r1, c0, c1 = h // 5, h - h // 5, w // 6, w - w // 6
    d[r0:r1, c0:c1] = 0
    if r1 > r0 and c1 > c0:
        d[r0, c0:c1] = d[r1 - 1, c0:c1] = 100
        d[r0:r1, c0] = d[r0:r1, c1 - 1] = 100
    d[(rng.random((h, w)) < 0.03) & (d == 0)] = 100
    return OccupancyGrid(d, 0.05)


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("models")
    make_model(root / "tiny-a", seed=1)
    make_model(root / "tiny-b", seed=2)
    return root


def _opts(root: Path, name: str = "tiny-a") -> PaperOptions:
    return PaperOptions(model=name, model_dir=root)


@pytest.mark.parametrize(("h", "w"), [(1, 1), (1, 7), (9, 1), (33, 47), (64, 64), (101, 77)])
def test_round_trip_keeps_size_resolution_origin(models: Path, h: int, w: int) -> None:
    grid = room_grid_of(h, w, seed=h * w)
    grid = grid.replace(resolution=0.07, origin=Pose2D(1.5, -2.25, 0.3))
    payload = api.encode(grid, "paper", options=_opts(models))
    back = api.decode(payload, options=_opts(models))
    assert back.data.shape == (h, w)
    assert back.resolution == 0.07
    assert tuple(back.origin) == (1.5, -2.25, 0.3)
    assert back.data.dtype == np.int8
    held = set(np.unique(grid.data).tolist())
    assert set(np.unique(back.data).tolist()) <= held  # only values the source map held
    head = api.read_header(payload)
    assert head.lossy and head.codec == "paper"
    assert head.variant.startswith("tiny-a:") and len(head.variant.split(":")[1]) == 12


def test_stage_timings_are_reported(models: Path) -> None:
    grid = room_grid_of(40, 50, seed=0)
    codec = api.get_codec("paper", _opts(models))
    assert isinstance(codec, PaperCodec)
    payload = api.encode(grid, "paper", options=_opts(models))
    assert set(codec.last_timings) == {"cnn_encode_ms", "huffman_encode_ms"}
    api.decode(payload, options=_opts(models))
    assert set(codec.last_timings) == {"huffman_decode_ms", "cnn_decode_ms"}
    assert all(v >= 0 for v in codec.last_timings.values())


@pytest.mark.parametrize("threads", [1, 2])
def test_threads_option_sets_torch_threads_for_inference_only(
    models: Path, threads: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    opts = PaperOptions(model="tiny-a", model_dir=models, threads=threads)
    codec = api.get_codec("paper", opts)
    assert isinstance(codec, PaperCodec)
    model = codec.model()
    seen: list[int] = []
    for name in ("encode_symbols", "decode_values"):
        real = getattr(model, name)

        def spy(*a: object, _real: object = real) -> np.ndarray:
            seen.append(torch.get_num_threads())
            return _real(*a)  # type: ignore[operator]

        monkeypatch.setattr(model, name, spy)
    before = torch.get_num_threads()
    grid = room_grid_of(40, 50, seed=0)
    back = api.decode(api.encode(grid, "paper", options=opts), options=opts)
    assert back.data.shape == grid.data.shape
    assert seen == [threads, threads]  # the CNNs ran with the configured thread count
    assert torch.get_num_threads() == before  # and the process's own count came back


def test_threads_option_is_validated() -> None:
    assert PaperOptions().threads == 1
    assert PaperOptions(threads=0).threads == 0  # torch's default
    with pytest.raises(ValueError, match="threads"):
        PaperOptions(threads=-1)


def test_other_weights_refuse_the_payload(models: Path) -> None:
    grid = room_grid_of(30, 30, seed=4)
    payload = api.encode(grid, "paper", options=_opts(models, "tiny-a"))
    with pytest.raises(CodecError, match=r"variant .tiny-a:.*but this mapd has .tiny-b:"):
        api.decode(payload, options=_opts(models, "tiny-b"))


def test_unknown_model_id_in_a_payload_is_refused(models: Path) -> None:
    grid = room_grid_of(30, 30, seed=4)
    payload = api.encode(grid, "paper", options=_opts(models))
    head = api.read_header(payload)
    old = head.variant.encode()
    new = b"paper-v9:0123456789ab"
    forged = payload.replace(bytes([len(old)]) + old, bytes([len(new)]) + new, 1)
    with pytest.raises(CodecError, match="paper-v9:0123456789ab"):
        api.decode(forged, options=_opts(models))


def test_missing_model_folder_is_a_codec_error(tmp_path: Path) -> None:
    grid = room_grid_of(10, 10, seed=0)
    with pytest.raises(CodecError, match=r"paper model not found.*models in .*: none\)"):
        api.encode(grid, "paper", options=PaperOptions(model="nope", model_dir=tmp_path))


def test_missing_model_names_the_models_that_are_there(tmp_path: Path) -> None:
    # A config still naming the model an upgrade replaced gets told what it could name instead.
    make_model(tmp_path / "paper-v9", seed=5)
    make_model(tmp_path / "other", seed=6)
    with pytest.raises(CodecError, match=r"paper-v1 needs .*: other, paper-v9\)"):
        pm.load_model(tmp_path / "paper-v1")


def test_tampered_weights_are_refused(tmp_path: Path) -> None:
    make_model(tmp_path / "m", seed=5)
    weights = tmp_path / "m" / pm.WEIGHTS_FILE
    data = bytearray(weights.read_bytes())
    data[-20] ^= 0x01
    weights.write_bytes(bytes(data))
    with pytest.raises(CodecError, match=r"does not match model\.json"):
        pm.load_model(tmp_path / "m")


def test_weights_of_the_wrong_shape_are_refused(tmp_path: Path) -> None:
    make_model(tmp_path / "m", seed=5)
    meta = json.loads((tmp_path / "m" / pm.META_FILE).read_text())
    meta["channels"] = 8
    (tmp_path / "m" / pm.META_FILE).write_text(json.dumps(meta))
    with pytest.raises(CodecError, match=r"shape|do not fit"):
        pm.load_model(tmp_path / "m")


@pytest.mark.parametrize(
    "damage",
    ['"levels": 1e999', '"levels": "x"', '"channels": [8]', "[" * 100_000],
)
def test_damaged_model_metadata_is_one_codec_error(tmp_path: Path, damage: str) -> None:
    make_model(tmp_path / "m", seed=5)
    path = tmp_path / "m" / pm.META_FILE
    text = path.read_text()
    # 1e999 reads as inf, which int() cannot take (OverflowError); deep nesting, RecursionError
    path.write_text(
        damage if damage.startswith("[") else text.rstrip()[:-1] + ", " + damage + "}"
    )  # last wins
    with pytest.raises(CodecError, match=r"unreadable model metadata"):
        pm.load_model(tmp_path / "m")


def test_models_root_follows_option_then_environment(
    models: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("MAPD_MODELS", str(models))
    codec = PaperCodec(PaperOptions(model="tiny-b"))
    assert codec.model_path == models / "tiny-b"
    assert codec.variant().startswith("tiny-b:")
    codec = PaperCodec(PaperOptions(model="tiny-b", model_dir=tmp_path))
    assert codec.model_path == tmp_path / "tiny-b"


def test_model_name_must_be_a_plain_folder_name() -> None:
    with pytest.raises(ValueError):
        PaperOptions(model="../etc")


# --------------------------------------------------------------------------------------------
# Snapping to what the source map holds
# --------------------------------------------------------------------------------------------


def _grey_to_value(grey: list[float]) -> np.ndarray:
    return ((np.array(grey, dtype=np.float32) - 205.0) / 255.0).astype(np.float32)


def test_snap_trinary_picks_the_nearest_grey_among_held_classes() -> None:
    vals = _grey_to_value([250.0, 230.0, 229.0, 210.0, 150.0, 102.0, 103.0, 5.0])
    all3 = FLAG_FREE | FLAG_OCCUPIED | FLAG_UNKNOWN
    # Nearest of 254 / 205 / 0: the free/unknown boundary is 229.5, unknown/occupied is 102.5.
    assert snap(vals, all3).tolist() == [0, 0, -1, -1, -1, 100, -1, 100]
    # Without unknown in the source, everything is free or occupied (boundary 127).
    assert snap(vals, FLAG_FREE | FLAG_OCCUPIED).tolist() == [0, 0, 0, 0, 0, 100, 100, 100]
    assert snap(vals, FLAG_UNKNOWN).tolist() == [-1] * 8


def test_snap_graded_returns_the_nearest_percentage() -> None:
    v = np.array([0, 10, 37, 64, 65, 99, 100], dtype=np.int8)
    x = pn.map_to_input(v)
    flags = FLAG_FREE | FLAG_OCCUPIED | FLAG_GRADED
    assert snap(x, flags).tolist() == v.tolist()
    assert snap(x + np.float32(0.004), flags).tolist() == [0, 10, 37, 64, 65, 99, 100]  # 1 grey level off
    unk = pn.map_to_input(np.array([-1], dtype=np.int8))
    assert snap(unk, flags | FLAG_UNKNOWN).tolist() == [-1]
    assert snap(unk, flags).tolist() == [19]  # no unknown in the source: the nearest percentage


def test_source_flags() -> None:
    assert source_flags(np.array([[0, 100], [-1, 0]], np.int8)) == FLAG_FREE | FLAG_OCCUPIED | FLAG_UNKNOWN
    assert source_flags(np.array([[0, 0]], np.int8)) == FLAG_FREE
    assert source_flags(np.array([[0, 50]], np.int8)) == FLAG_FREE | FLAG_GRADED


def test_input_encoding_matches_the_metric_grey_levels() -> None:
    d = np.array([[-1, 0, 100, 70, 20]], dtype=np.int8)
    x = pn.map_to_input(d)
    # Trinary cells: exactly the map_server grey levels the PSNR uses.
    assert np.allclose(x[0, :3] * 255 + 205, grey_levels(d)[0, :3])
    assert x[0, 0] == 0.0  # unknown is the padding value


def test_graded_map_round_trips_to_percentages(models: Path) -> None:
    rng = np.random.default_rng(0)
    d = rng.integers(0, 101, size=(20, 30)).astype(np.int8)
    d[:5] = -1
    grid = OccupancyGrid(d, 0.05)
    back = api.decode(api.encode(grid, "paper", options=_opts(models)), options=_opts(models))
    assert back.data.min() >= -1 and back.data.max() <= 100


def test_single_class_maps_come_back_as_that_class(models: Path) -> None:
    for value in (-1, 0, 100):
        grid = OccupancyGrid(np.full((17, 23), value, dtype=np.int8), 0.05)
        back = api.decode(api.encode(grid, "paper", options=_opts(models)), options=_opts(models))
        assert np.all(back.data == value)


# --------------------------------------------------------------------------------------------
# Tiled inference computes what the whole network computes
# --------------------------------------------------------------------------------------------


def test_tiled_inference_equals_the_whole_map_network(models: Path) -> None:
    model = pm.load_model(models / "tiny-a")
    model.tile = 8  # many tiles, constant and not
    grid = room_grid_of(70, 90, seed=11)
    x = pn.map_to_input(grid.data)
    sym = model.encode_symbols(x)
    net = model.net.eval()
    with torch.no_grad():
        padded = np.zeros((70 + 2 * pn.FEATURE_PAD, 90 + 2 * pn.FEATURE_PAD), dtype=np.float32)
        padded[pn.FEATURE_PAD : -pn.FEATURE_PAD, pn.FEATURE_PAD : -pn.FEATURE_PAD] = x
        soft = net.quant.soft(net.feature(torch.from_numpy(padded)[None, None]))[0, 0].numpy()
    direct = np.rint(soft)
    differ = sym != direct
    # Float summation order may differ; only a value at a rounding boundary may flip.
    assert np.all(np.abs(np.abs(soft[differ] - np.floor(soft[differ])) - 0.5) < 1e-3)
    assert differ.mean() < 0.01

    values = model.decode_values(sym, 70, 90)
    p = pn.RECOVERY_PAD
    fpad = np.full((35 + 2 * p, 45 + 2 * p), 0.0, dtype=np.float32)
    level_values = net.quant.value(torch.arange(model.levels, dtype=torch.float32)).numpy()
    fpad[:] = level_values[model.unknown_symbol]
    fpad[p:-p, p:-p] = level_values[sym]
    with torch.no_grad():
        whole = net.recovery(torch.from_numpy(fpad)[None, None])[0, 0].numpy()
    assert whole.shape == (70, 90)
    assert np.allclose(values, whole, atol=1e-4)


def test_constant_tiles_match_the_network(models: Path) -> None:
    model = pm.load_model(models / "tiny-b")
    values = pn.map_to_input(np.array([-1, 0, 100], dtype=np.int8))
    syms = model.symbols_for_constants(values)
    net = model.net.eval()
    with torch.no_grad():
        for v, s in zip(values, syms, strict=True):
            x = torch.full((1, 1, 30, 30), float(v))
            assert int(net.quant.symbols(net.feature(x))[0, 0, 5, 5]) == int(s)


# --------------------------------------------------------------------------------------------
# Hostile bodies
# --------------------------------------------------------------------------------------------


def _with_body(payload: bytes, body: bytes) -> bytes:
    """The payload with its body replaced and the header's body checksum and length fixed."""
    import hashlib

    head = api.read_header(payload)
    fixed_at = head.body_offset - api._FIXED.size
    fields = list(api._FIXED.unpack_from(payload, fixed_at))
    fields[-2] = hashlib.blake2b(body, digest_size=16).digest()
    fields[-1] = len(body)
    return payload[:fixed_at] + api._FIXED.pack(*fields) + body


def test_corrupt_bodies_are_codec_errors(models: Path) -> None:
    grid = room_grid_of(40, 60, seed=2)
    payload = api.encode(grid, "paper", options=_opts(models))
    body = payload[api.read_header(payload).body_offset :]
    cases = {
        "empty": b"",
        "bad flags": bytes([0x30]) + body[1:],
        "no classes": bytes([0x00]) + body[1:],
        "table over-full": body[:1] + huffman.pack_table(np.array([1, 1, 1], np.uint8)) + body[4:],
        "truncated": body[:-1],
        "alphabet too big": body[:1] + bytes([200]) + body[2:],
    }
    for name, bad in cases.items():
        with pytest.raises(CodecError):
            api.decode(_with_body(payload, bad), options=_opts(models))
        assert name


def test_corruption_in_transit_is_caught_by_the_checksum(models: Path) -> None:
    grid = room_grid_of(40, 60, seed=2)
    payload = bytearray(api.encode(grid, "paper", options=_opts(models)))
    payload[-3] ^= 0x10
    with pytest.raises(CodecError, match="checksum"):
        api.decode(bytes(payload), options=_opts(models))


def test_rle_past_the_declared_size_in_a_payload(models: Path) -> None:
    grid = room_grid_of(20, 20, seed=2)
    payload = api.encode(grid, "paper", options=_opts(models))
    body = bytes([FLAG_FREE]) + huffman.pack_table(np.array([1, 1], np.uint8))
    body += hexruns.pack_runs(np.array([1 << 29]), np.array([0]))
    with pytest.raises(CodecError, match="more than the"):
        api.decode(_with_body(payload, body), options=_opts(models))


_SMALL: dict[Path, bytes] = {}


@settings(max_examples=60, deadline=None)
@given(st.binary(min_size=0, max_size=80))
def test_random_bodies_never_crash(models: Path, blob: bytes) -> None:
    if models not in _SMALL:
        _SMALL[models] = api.encode(room_grid_of(12, 14, seed=0), "paper", options=_opts(models))
    payload = _SMALL[models]
    try:
        out = api.decode(_with_body(payload, blob), options=_opts(models))
    except CodecError:
        return
    assert out.data.shape == (12, 14)


def test_header_struct_is_what_this_test_expects() -> None:
    # _with_body relies on the body checksum and length being the last two fixed fields.
    assert api._FIXED.format.endswith("16s16sI")
    assert struct.calcsize(api._FIXED.format) == api._FIXED.size
