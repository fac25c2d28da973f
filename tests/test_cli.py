"""The mapd command as a user runs it: real subprocesses, one-line errors, no tracebacks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from mapd.grid import load_map, save_map

MAPD = [sys.executable, "-m", "mapd"]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*MAPD, *args], capture_output=True, text=True, timeout=120)


def test_help_lists_commands() -> None:
    out = run("--help")
    assert out.returncode == 0
    for cmd in ("plugins", "check-config", "info", "encode", "decode", "bench"):
        assert cmd in out.stdout


def test_info_encode_decode_round_trip(tmp_path: Path, room_grid) -> None:  # type: ignore[no-untyped-def]
    src = save_map(room_grid, tmp_path / "room.yaml")
    info = run("info", str(src), "--json")
    assert info.returncode == 0, info.stderr
    s = json.loads(info.stdout)
    assert (s["width"], s["height"]) == (room_grid.width, room_grid.height)
    assert s["free"] + s["occupied"] + s["unknown"] == room_grid.cells
    enc = run("encode", str(src), "-o", str(tmp_path / "room.mapd"), "--codec", "zstd")
    assert enc.returncode == 0, enc.stderr
    dec = run("decode", str(tmp_path / "room.mapd"), "-o", str(tmp_path / "back.yaml"))
    assert dec.returncode == 0, dec.stderr
    assert load_map(tmp_path / "back.yaml").same_map(room_grid)


def test_errors_are_one_line_without_traceback(tmp_path: Path) -> None:
    (tmp_path / "junk.mapd").write_bytes(b"not a payload")
    cases = [
        ("info", str(tmp_path / "missing.yaml")),
        ("decode", str(tmp_path / "junk.mapd"), "-o", str(tmp_path / "x.yaml")),
        ("check-config", str(tmp_path / "absent.toml")),
        # caller mistakes that the ARQ core raises as ValueError are checked by the command first
        ("link", "send", str(tmp_path / "junk.mapd"), "--port", "/dev/null", "--peer", "300"),
        ("link", "send", str(tmp_path / "junk.mapd"), "--port", "/dev/null", "--peer", "1", "--node", "1"),
    ]
    for args in cases:
        out = run(*args)
        assert out.returncode != 0
        assert "Traceback" not in out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mapd: error: "), out.stderr


def test_plugins_lists_all_kinds() -> None:
    out = run("plugins", "--json")
    assert out.returncode == 0
    rows = json.loads(out.stdout)
    assert {r["kind"] for r in rows} == {"source", "codec", "transport", "output"}
    assert any(r["name"] == "zstd" and r["status"] == "ok" for r in rows)
