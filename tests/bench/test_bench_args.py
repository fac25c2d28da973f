"""Bad ``mapd bench`` arguments and inputs: one clear line, never a traceback, and no work first."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapd.cli import build_parser, main
from mapd.grid import OccupancyGrid
from mapd.grid.save import save_map

REFUSED_WHILE_PARSING = [
    (["codec", "--limit", "0"], "--limit"),
    (["codec", "--limit", "-2"], "--limit"),
    (["mapper", "--sim-seconds", "inf"], "--sim-seconds"),
    (["mapper", "--sim-seconds", "1e300"], "--sim-seconds"),
    (["mapper", "--sim-seconds", "nan"], "--sim-seconds"),
    (["mapper", "--baseline-scans", "0"], "--baseline-scans"),
    (["merge", "--seed", "-1"], "--seed"),
    (["merge", "--merge-size", "100000"], "--merge-size"),
    (["paper", "--sim", "-1", "--out", "x"], "--sim"),
    (["paper", "--seed", "-1", "--out", "x"], "--seed"),
    (["stream", "--resolution", "0"], "--resolution"),
    (["stream", "--resolution", "nan"], "--resolution"),
    (["stream", "--resolution", "100"], "--resolution"),
]


@pytest.mark.parametrize(("argv", "option"), REFUSED_WHILE_PARSING)
def test_bad_numbers_are_one_usage_line_before_any_work(
    argv: list[str], option: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # parse_args alone: each of these once ran (for minutes, or out of memory) before failing.
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(["bench", *argv])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.splitlines()[-1].startswith(f"mapd bench {argv[0]}: error: argument {option}: ")


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("mapd: error: ")]
    assert len(lines) == 1, err
    return lines[0]


def test_merge_on_a_data_folder_without_maps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "maps").mkdir()
    monkeypatch.setenv("MAPD_DATA", str(tmp_path))
    assert main(["bench", "merge", "--pairs", "2", "--no-real", "--merge-size", "64", "--repeat", "1"]) == 1
    assert _one_error_line(capsys.readouterr().err) == (
        f"mapd: error: {tmp_path}: no map_server maps to build pairs from"
    )


def test_merge_speed_rows_on_a_data_folder_with_fewer_than_four_maps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    data = np.full((40, 60), -1, dtype=np.int8)
    data[5:35, 5:55] = 0
    data[5, 5:55] = 100
    save_map(OccupancyGrid(data, 0.05), tmp_path / "maps" / "room" / "room.yaml")
    monkeypatch.setenv("MAPD_DATA", str(tmp_path))
    argv = ["bench", "merge", "--pairs", "0", "--no-real", "--merge-size", "64", "--repeat", "1"]
    assert main(argv) == 0, capsys.readouterr().err
    assert "merge 1 maps of 64x64 cells" in capsys.readouterr().out


def test_mapper_on_a_log_without_scans(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "empty.log").write_text("# a CARMEN log with no laser lines\nPARAM x 1 nohost 0\n")
    monkeypatch.setenv("MAPD_DATA", str(tmp_path))
    assert main(["bench", "mapper", "--log", "empty", "--sim-seconds", "0"]) == 1
    assert _one_error_line(capsys.readouterr().err) == (
        f"mapd: error: {tmp_path / 'logs' / 'empty.log'}: no laser scans"
    )


def test_paper_with_a_folder_where_a_figure_goes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "fig7_global.png").mkdir()
    argv = ["bench", "paper", "--sim", "0", "--duration", "4", "--period", "2", "--poses", "1"]
    assert main([*argv, "--robots", "1", "--out", str(tmp_path)]) == 1
    assert _one_error_line(capsys.readouterr().err) == (
        f"mapd: error: {tmp_path / 'fig7_global.png'}: cannot write the report: Is a directory"
    )
