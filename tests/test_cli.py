"""The mapd command as a user runs it: real subprocesses, one-line errors, no tracebacks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from mapd.grid.load import load_map
from mapd.grid.save import save_map

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


def test_an_unknown_codec_is_a_usage_error_listing_the_codecs(tmp_path: Path, room_grid) -> None:  # type: ignore[no-untyped-def]
    """It exited 1 after the map was read (encode) or the work began (warmup, bench codec)."""
    src = save_map(room_grid, tmp_path / "room.yaml")
    for args in (
        ("encode", str(src), "-o", str(tmp_path / "x.mapd"), "--codec", "nope"),
        ("warmup", "--codec", "raw", "nope"),
        ("bench", "codec", "--codec", "nope", "--limit", "1"),
    ):
        out = run(*args)
        assert out.returncode == 2, (args, out.stderr)
        assert "no codec named 'nope'" in out.stderr and "lossless" in out.stderr, out.stderr
        assert "Traceback" not in out.stderr and out.stdout == ""
    assert not (tmp_path / "x.mapd").exists()


def test_payloads_go_through_stdout_and_stdin_and_maps_refuse_dash(tmp_path: Path, room_grid) -> None:  # type: ignore[no-untyped-def]
    """'-' made a file named '-' (encode) or failed to open one (decode)."""
    src = save_map(room_grid, tmp_path / "room.yaml")
    enc = subprocess.run(
        [*MAPD, "encode", str(src), "-o", "-", "--codec", "zstd"],
        capture_output=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert enc.returncode == 0, enc.stderr
    assert enc.stdout[:1] and not (tmp_path / "-").exists()
    dec = subprocess.run(
        [*MAPD, "decode", "-", "-o", "back.yaml"],
        input=enc.stdout,
        capture_output=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert dec.returncode == 0, dec.stderr
    assert load_map(tmp_path / "back.yaml").same_map(room_grid)
    for args in (("encode", "-", "-o", "x.mapd"), ("decode", "x.mapd", "-o", "-")):
        out = subprocess.run([*MAPD, *args], capture_output=True, text=True, cwd=tmp_path, timeout=60)
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2 and len(lines) == 1 and "cannot be '-'" in lines[0], out.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["back.pgm", "back.yaml", "room.pgm", "room.yaml"]


def test_check_config_json_is_json_alone(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text('[robot]\nname = "alpha"\nfleet = "lab"\n[fleet]\nallow_unsigned = true\n')
    out = run("check-config", str(cfg), "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["robot"]["name"] == "alpha"  # `| jq` needs nothing before the JSON


def test_keygen_prints_an_absolute_link_key_path_and_refuses_out_with_public(tmp_path: Path) -> None:
    mapd = lambda *a: subprocess.run([*MAPD, *a], capture_output=True, text=True, cwd=tmp_path, timeout=60)  # noqa: E731
    made = mapd("keygen", "--link-key", "link.key")
    assert made.returncode == 0, made.stderr
    # config paths are relative to the config's folder, not to where keygen ran
    assert made.stdout.startswith(f'link_key_file = "{tmp_path.resolve() / "link.key"}"'), made.stdout
    assert mapd("keygen", "r1", "-o", "old.key").returncode == 0
    both = mapd("keygen", "r1", "-o", "new.key", "--public", "old.key")
    assert both.returncode == 2 and both.stderr.startswith("mapd: error: keygen: --public"), both.stderr
    assert not (tmp_path / "new.key").exists()
