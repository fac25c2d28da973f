"""The log-odds mapper against hand-made scans whose cells are known."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import ConfigError, LimitError
from mapd.grid import Pose2D
from mapd.mapping.mapper import (
    Mapper,
    MapperOptions,
    compose,
    inverse,
    relative,
)
from mapd.mapping.replay import replay_log, split_range

ONE = MapperOptions(resolution=1.0)


def test_single_beam_marks_known_cells() -> None:
    m = Mapper(ONE)
    # Sensor at the centre of cell (0, 0); one beam along +x, 3 m: cells 0..2 free, cell 3 hit.
    m.integrate(np.array([3.0]), np.array([0.0]), Pose2D(0.5, 0.5, 0.0))
    g = m.snapshot(version=1)
    assert g.origin == Pose2D(0.0, 0.0, 0.0)
    assert g.data.tolist() == [[0, 0, 0, 100]]
    assert g.version == 1


def test_beams_in_two_directions_and_growth_to_negative_cells() -> None:
    m = Mapper(ONE)
    # +y 2 m: rows 0, 1 free, row 2 hit; -x 3 m: cols -1, -2 free, col -3 hit (end at x = -2.5).
    m.integrate(np.array([2.0, 3.0]), np.array([math.pi / 2, math.pi]), Pose2D(0.5, 0.5, 0.0))
    g = m.snapshot()
    assert g.origin.x == -3.0 and g.origin.y == 0.0
    expected = np.full((3, 4), -1, dtype=np.int8)
    expected[0, :] = [100, 0, 0, 0]  # cols -3..0 of row 0
    expected[1, 3] = 0
    expected[2, 3] = 100
    assert g.data.tolist() == expected.tolist()


def test_yaw_rotates_beams() -> None:
    m = Mapper(ONE)
    m.integrate(np.array([3.0]), np.array([0.0]), Pose2D(0.5, 0.5, math.pi / 2))
    g = m.snapshot()
    assert g.data[:, 0].tolist() == [0, 0, 0, 100] and g.width == 1


def test_diagonal_beam_is_a_connected_line() -> None:
    m = Mapper(ONE)
    m.integrate(np.array([20.0]), np.array([0.4]), Pose2D(0.5, 0.5, 0.0))
    g = m.snapshot()
    rows, cols = np.nonzero(g.data == 0)
    order = np.argsort(cols)
    steps = np.abs(np.diff(np.stack([rows[order], cols[order]]), axis=1))
    assert steps.max() <= 1  # no gaps between consecutive free cells
    hit_r, hit_c = np.nonzero(g.data == 100)
    end = Pose2D(0.5 + 20 * math.cos(0.4), 0.5 + 20 * math.sin(0.4), 0)
    assert (hit_r[0], hit_c[0]) == (math.floor(end.y) - int(g.origin.y), math.floor(end.x) - int(g.origin.x))


def test_hit_wins_over_miss_in_the_same_scan() -> None:
    m = Mapper(ONE)
    # Beam 1 ends in cell (0, 2); beam 2 passes through it on the way to cell (0, 5).
    m.integrate(np.array([2.0, 5.0]), np.array([0.0, 0.0]), Pose2D(0.5, 0.5, 0.0))
    lo = m.logodds()
    assert lo[0, 2] == pytest.approx(0.85)
    assert lo[0, 1] == pytest.approx(-0.4)  # once per scan, although two beams crossed it


def test_log_odds_clamp_and_threshold() -> None:
    m = Mapper(MapperOptions(resolution=1.0, clamp_max=2.0, clamp_min=-1.0))
    for _ in range(10):
        m.integrate(np.array([3.0]), np.array([0.0]), Pose2D(0.5, 0.5, 0.0))
    lo = m.logodds()
    assert lo[0, 3] == pytest.approx(2.0) and lo[0, 0] == pytest.approx(-1.0)
    # A cell hit once and missed once is uncertain: unknown in the thresholded map.
    m2 = Mapper(ONE)
    m2.integrate(np.array([2.0]), np.array([0.0]), Pose2D(0.5, 0.5, 0.0))
    m2.integrate(np.array([4.0]), np.array([0.0]), Pose2D(0.5, 0.5, 0.0))
    assert m2.snapshot().data[0, 2] == -1


def test_no_return_and_max_range() -> None:
    # inf and readings at or above no_return leave no trace by default.
    m = Mapper(ONE)
    assert m.integrate(np.array([np.inf, 90.0]), np.array([0.0, 1.0]), Pose2D(0.5, 0.5, 0.0)) == 0
    assert m.bounds is None
    # With clear_no_return they clear up to max_range; a finite reading beyond max_range clears, no hit.
    m = Mapper(MapperOptions(resolution=1.0, max_range=3.0, clear_no_return=True))
    m.integrate(np.array([np.inf, 10.0]), np.array([0.0, math.pi / 2]), Pose2D(0.5, 0.5, 0.0))
    g = m.snapshot()
    assert 100 not in g.data
    assert g.data[0, :3].tolist() == [0, 0, 0] and g.data[:3, 0].tolist() == [0, 0, 0]


def test_invalid_readings_are_ignored() -> None:
    m = Mapper(ONE)
    used = m.integrate(np.array([np.nan, -1.0, 0.0, 2.0]), np.zeros(4), Pose2D(0.5, 0.5, 0.0))
    assert used == 1
    assert m.snapshot().data.tolist() == [[0, 0, 100]]
    with pytest.raises(ValueError):
        m.integrate(np.array([1.0, 2.0]), np.zeros(3), Pose2D())
    with pytest.raises(ValueError):
        m.integrate(np.array([1.0]), np.zeros(1), Pose2D(math.nan, 0.0, 0.0))


def test_growth_past_the_limit_raises_and_changes_nothing() -> None:
    m = Mapper(MapperOptions(resolution=0.05), max_cells=200 * 200)
    m.integrate(np.array([2.0]), np.array([0.0]), Pose2D())
    before = m.snapshot()
    with pytest.raises(LimitError):
        m.integrate(np.array([2.0]), np.array([0.0]), Pose2D(1000.0, 1000.0, 0.0))
    assert m.snapshot().same_map(before)


def test_snapshots_stay_on_one_lattice_as_the_map_grows() -> None:
    m = Mapper(MapperOptions(resolution=0.05))
    prev = None
    for k in range(6):
        m.integrate(
            np.full(90, 3.0 + k), np.linspace(-math.pi, math.pi, 90), Pose2D(0.3 * k, 0.1 * k, 0.2 * k)
        )
        g = m.snapshot(version=k + 1)
        assert g.is_trinary()
        ox, oy = g.origin.x / 0.05, g.origin.y / 0.05
        assert abs(ox - round(ox)) < 1e-6 and abs(oy - round(oy)) < 1e-6
        if prev is not None:
            # Bounds only grow: the new map covers the old one.
            assert g.origin.x <= prev.origin.x + 1e-9 and g.origin.y <= prev.origin.y + 1e-9
            assert g.origin.x + g.width * 0.05 >= prev.origin.x + prev.width * 0.05 - 1e-9
            assert g.origin.y + g.height * 0.05 >= prev.origin.y + prev.height * 0.05 - 1e-9
        prev = g


def test_pose_algebra() -> None:
    a, b = Pose2D(1.0, 2.0, 0.7), Pose2D(-0.5, 3.0, -2.0)
    c = compose(a, relative(a, b))
    assert c.x == pytest.approx(b.x) and c.y == pytest.approx(b.y) and c.yaw == pytest.approx(b.yaw)
    z = compose(a, inverse(a))
    assert z.x == pytest.approx(0.0, abs=1e-12) and z.yaw == pytest.approx(0.0, abs=1e-12)


def test_split_range_matches_the_reference_parts() -> None:
    # radish_derived intel_part1/part2: scans 0..545 and 364..909 of 910.
    assert split_range(910, 2, 0) == range(0, 546)
    assert split_range(910, 2, 1) == range(364, 910)
    parts = [split_range(100, 4, i) for i in range(4)]
    assert parts[0].start == 0 and parts[-1].stop == 100
    assert all(len(p) == len(parts[0]) for p in parts)
    assert all(parts[i].stop > parts[i + 1].start for i in range(3))  # neighbours overlap
    with pytest.raises(ValueError):
        split_range(10, 2, 2)


@settings(max_examples=40, deadline=None)
@given(
    ranges=st.lists(
        st.one_of(st.floats(min_value=-5, max_value=60), st.sampled_from([math.inf, math.nan, 0.0])),
        min_size=1,
        max_size=40,
    ),
    x=st.floats(-20, 20),
    y=st.floats(-20, 20),
    yaw=st.floats(-7, 7),
)
def test_fuzz_integrate_gives_trinary_grids(ranges: list[float], x: float, y: float, yaw: float) -> None:
    m = Mapper(MapperOptions(resolution=0.1, max_range=30.0, clear_no_return=True))
    r = np.array(ranges)
    m.integrate(r, np.linspace(-math.pi, math.pi, r.size), Pose2D(x, y, yaw))
    g = m.snapshot()
    assert g.is_trinary()
    assert g.cells <= m.max_cells


def test_long_scans_cast_in_chunks_give_the_same_map(monkeypatch: pytest.MonkeyPatch) -> None:
    import mapd.mapping.mapper as mapping

    rng = np.random.default_rng(3)
    scans = [
        (rng.uniform(0.5, 9.0, 200), np.linspace(-3, 3, 200), Pose2D(*rng.uniform(-1, 1, 3)))
        for _ in range(5)
    ]
    whole = Mapper(MapperOptions(resolution=0.05))
    for r, a, p in scans:
        whole.integrate(r, a, p)
    monkeypatch.setattr(mapping, "MAX_SAMPLES", 97)  # many chunks per scan
    chunked = Mapper(MapperOptions(resolution=0.05))
    for r, a, p in scans:
        chunked.integrate(r, a, p)
    assert np.array_equal(whole.logodds(), chunked.logodds())
    assert not chunked._seen.any()  # the per-scan marks are cleared again


def test_growth_past_the_limit_says_its_sizes_compactly() -> None:
    m = Mapper(ONE)
    m.integrate(np.array([3.0]), np.array([0.0]), Pose2D(0.5, 0.5, 0.0))
    # A pose so far away that the grid spanning both scans has a side hundreds of digits long.
    with pytest.raises(LimitError) as err:
        m.integrate(np.array([3.0]), np.array([0.0]), Pose2D(1e300, 0.5, 0.0))
    message = str(err.value)
    assert len(message) < 150, message
    # rows: the first scan's buffer; columns: the distance to the second, 1e300 cells of 1 m
    assert re.match(r"map would grow to \d+ x 1\.00e\+300 = \d\.\d\de\+30\d cells, over", message), message


@pytest.mark.parametrize("resolution", [1e-300, 1e-5, 100.0, math.inf, math.nan])
def test_replay_log_refuses_a_resolution_the_mapper_cannot_take(
    box_log: Callable[..., tuple[Path, list[Pose2D]]], resolution: float
) -> None:
    log, _poses = box_log(scans=4)
    # One ConfigError naming the bounds, not pydantic's ValidationError (above 10 m) or a growth
    # error hundreds of digits long (below the finest cells a map file may hold).
    with pytest.raises(ConfigError, match=r"m/cell is not within \[0.0001, 10\]"):
        list(replay_log(log, resolution=resolution))
