"""Hostile files through the commands that read them: one ``mapd: error:`` line, no hang, no bomb.

Each of these failed before its fix:

* a map YAML whose value is an alias bomb, or a hex integer too long to print in decimal, hung
  ``mapd info`` (``repr`` of 10**11 items) or ended it with a ValueError traceback;
* a config with such an integer, or a NUL in a path, was accepted (and ``check-config`` then died in
  ``json.dumps`` or ``open``) or ended in a traceback from the error message itself;
* a FIFO named as a config, payload, recording or key file blocked for ever in ``open``;
* ``mapd record info`` decompressed whatever size a chunk declared (2 GiB from 64 KiB of zstd) and
  parsed millions of empty records a chunk;
* a restarted recorder truncated the recording of the run before (the crash it should show);
* ``mapd encode`` wrote its payload in place, so a full disk lost the previous one;
* ``mapd decode -o DIR`` wrote ``DIR.pgm`` beside the directory and named a hidden temp file.
"""

from __future__ import annotations

import os
import re
import resource
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd import config
from mapd.errors import ConfigError, MapFileError
from mapd.files import reading
from mapd.grid import OccupancyGrid
from mapd.grid.load import read_map_yaml
from mapd.grid.reprs import short_repr
from mapd.grid.save import save_map
from mapd.keys import read_key_file

MAPD = [sys.executable, "-m", "mapd"]
ROOT = Path(__file__).resolve().parents[1]
#: The fixtures of conftest.py that run mapd as a user does and read its one error line.
Run = Callable[..., subprocess.CompletedProcess[str]]
OneLine = Callable[..., str]


def write_yaml_map(tmp: Path, body: str, name: str = "m.yaml") -> Path:
    (tmp / "m.pgm").write_bytes(b"P5\n4 3\n255\n" + bytes([254, 0, 205] * 4))
    path = tmp / name
    path.write_text(body)
    return path


def alias_bomb(levels: int = 11) -> str:
    """A YAML of a few hundred bytes whose anchor ``a{levels}`` stands for 10**levels items."""
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ map YAML


@pytest.mark.parametrize("key", ["origin", "image", "resolution", "mode"])
def test_a_yaml_alias_bomb_in_a_map_is_one_short_line(
    tmp_path: Path, key: str, mapd_run: Run, one_error_line: OneLine
) -> None:
    fields = {"image": "m.pgm", "resolution": "0.05", "origin": "[0, 0, 0]", key: "*a11"}
    path = write_yaml_map(tmp_path, alias_bomb() + "".join(f"{k}: {v}\n" for k, v in fields.items()))
    t0 = time.monotonic()
    line = one_error_line(mapd_run("info", str(path), timeout=30))
    assert f"{path}: " in line and len(line) < 250
    assert time.monotonic() - t0 < 30


@pytest.mark.parametrize(
    "body",
    [
        "image: m.pgm\nresolution: 0x{big}\norigin: [0, 0, 0]\n",
        "image: m.pgm\nresolution: 0.05\norigin: [0x{big}, 0, 0]\n",
        "image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0x{big}\n",
        "image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: -0x{big}\n",
    ],
)
def test_a_hex_integer_too_long_to_print_is_a_map_file_error(tmp_path: Path, body: str) -> None:
    # 20,000 hex digits: more than the 4,300 decimal digits Python converts an int to (ValueError)
    path = write_yaml_map(tmp_path, body.format(big="F" * 20_000))
    with pytest.raises(MapFileError, match="integer of 80000 bits") as err:
        read_map_yaml(path)
    assert len(str(err.value)) < 250


_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.builds(lambda bits, sign: sign << bits, st.integers(0, 70_000), st.sampled_from([-1, 1]))
    | st.floats()
    | st.text(max_size=500)
    | st.binary(max_size=500),
    lambda inner: st.lists(inner, max_size=8) | st.dictionaries(st.text(max_size=5), inner, max_size=8),
    max_leaves=40,
)


@settings(max_examples=200, deadline=None)
@given(_values)
def test_short_repr_is_short_for_any_value(value: object) -> None:
    assert len(short_repr(value, 60)) <= 60


# ------------------------------------------------------------------ config.toml


@pytest.mark.parametrize(
    ("body", "where"),
    [
        ('[robot]\nname = "r"\n[limits]\nmax_cells = 0x{big}\n', "limits.max_cells"),
        ("[robot]\nname = 0x{big}\n", "robot.name"),
        ('[robot]\nname = "r"\n[fusion]\nposes = {{r = [0x{big}, 0, 0]}}\n', "fusion.poses.r[0]"),
        ('[robot]\nname = "r"\n[source.sim]\nseed = 0x{big}\n', "source.sim.seed"),
        ('[robot]\nname = "r"\n[source.sim]\nseed = 0x8000000000000000\n', "source.sim.seed"),
    ],
)
def test_a_config_integer_outside_64_bits_is_refused(tmp_path: Path, body: str, where: str) -> None:
    path = tmp_path / "config.toml"
    path.write_text(body.format(big="F" * 20_000))
    with pytest.raises(ConfigError, match=f": {re.escape(where)}: integer out of the 64-bit range"):
        config.load(path)


def test_validation_errors_show_an_unprintable_integer_in_one_line() -> None:
    with pytest.raises(ConfigError, match=r"robot\.name: .*\(got <integer of 80000 bits>\)$"):
        config.validate(config.MapdConfig, {"robot": {"name": (1 << 80_000) - 1}}, "c.toml")


@pytest.mark.parametrize(
    ("section", "where"),
    [
        ('[robot]\nname = "r"\nkey_file = "k\\u0000ey"\n', "robot.key_file"),
        (
            '[robot]\nname = "r"\n[fleet]\nallow_unsigned = true\nlink_key_file = "\\u0000"\n',
            "fleet.link_key_file",
        ),
        ('[robot]\nname = "r"\n[state]\ndir = "/var/lib/\\u0000"\n', "state.dir"),
        ('[robot]\nname = "r"\n[source.mapfile]\npath = "m\\u0000.yaml"\n', "source.mapfile.path"),
    ],
)
def test_a_nul_in_a_config_string_is_a_config_error(tmp_path: Path, section: str, where: str) -> None:
    path = tmp_path / "config.toml"
    path.write_text(section)
    with pytest.raises(ConfigError, match=f": {re.escape(where)}: the string holds a NUL character$"):
        config.load(path)


# ------------------------------------------------------------------ FIFOs


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "fifo"
    os.mkfifo(path)
    return path


def test_fifos_named_as_inputs_never_block(
    tmp_path: Path, fifo: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    assert "not a regular file" in one_error_line(mapd_run("keygen", "r0", "--public", str(fifo), timeout=30))
    assert f"{fifo}: " in one_error_line(
        mapd_run("decode", str(fifo), "-o", str(tmp_path / "o.yaml"), timeout=30)
    )
    assert "not an MCAP recording" in one_error_line(mapd_run("record", "info", str(fifo), timeout=30))
    assert "the config is empty; is this the right file?" in one_error_line(
        mapd_run("check-config", str(fifo), timeout=30), code=2
    )
    # a device reads as empty too (before: "robot: required key is missing", as if it were a config)
    assert one_error_line(mapd_run("check-config", "/dev/null", timeout=30), code=2).startswith(
        "mapd: error: /dev/null: the config is empty"
    )


@pytest.mark.parametrize(
    ("tail", "match"),
    [
        ('key_file = "fifo"\n', "robot.key_file: .*fifo is not a regular file"),
        (
            '[fleet]\nallow_unsigned = true\nlink_key_file = "fifo"\n',
            "fleet.link_key_file: .*fifo holds 0 bytes",
        ),
        (
            '[fleet]\nallow_unsigned = true\n[view]\nlisten = "0.0.0.0:8080"\ntoken_file = "fifo"\n',
            "view.token_file: .*fifo must hold one token",
        ),
    ],
)
def test_a_fifo_named_as_a_key_or_token_file_never_blocks(
    tmp_path: Path, fifo: Path, tail: str, match: str, mapd_run: Run, one_error_line: OneLine
) -> None:
    path = tmp_path / "config.toml"
    path.write_text('[robot]\nname = "r0"\n' + tail)
    line = one_error_line(mapd_run("check-config", str(path), timeout=30), code=2)
    assert re.search(match, line), line


def test_a_pipe_with_a_writer_is_still_read_as_a_key() -> None:
    r, w = os.pipe()
    try:
        os.write(w, b"00112233445566778899aabbccddeeff\n")
        os.close(w)
        assert read_key_file(Path(f"/dev/fd/{r}"), "--key") == bytes.fromhex(
            "00112233445566778899aabbccddeeff"
        )
    finally:
        os.close(r)


@pytest.fixture
def held_fifo(fifo: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A FIFO whose writer holds it open and writes nothing, and a short read deadline."""
    monkeypatch.setattr(reading, "READ_TIMEOUT_S", 0.5)
    fd = os.open(fifo, os.O_RDWR)  # a writer that never closes it (O_RDWR opens without waiting)
    try:
        yield fifo
    finally:
        os.close(fd)


def test_a_fifo_held_open_by_its_writer_is_given_up_after_the_deadline(held_fifo: Path) -> None:
    # The daemon's reload read such a config (or key, or token) for ever, in a thread the
    # daemon's exit waits for: SIGTERM could not stop it.
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=r"cannot read config: its writer did not finish it in 0\.5 s"):
        config.load(held_fifo)
    with pytest.raises(ConfigError, match=r"--key: cannot read .*: its writer did not finish it in 0\.5 s"):
        read_key_file(held_fifo, "--key")
    assert time.monotonic() - t0 < 3.0


def test_a_pipe_read_in_pieces_is_read_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(reading, "READ_TIMEOUT_S", 5.0)
    r, w = os.pipe()

    def write() -> None:  # a slow writer that finishes within the deadline
        for piece in (b"[robot]\n", b'name = "r0"\n'):
            time.sleep(0.2)
            os.write(w, piece)
        os.close(w)

    t = threading.Thread(target=write)
    t.start()
    try:
        assert reading.read_capped(Path(f"/dev/fd/{r}"), 1000) == b'[robot]\nname = "r0"\n'
    finally:
        t.join()
        os.close(r)


# ------------------------------------------------------------------ MCAP recordings

_MAGIC = b"\x89MCAP0\r\n"


def _record(opcode: int, body: bytes) -> bytes:
    return bytes([opcode]) + struct.pack("<Q", len(body)) + body


def _text(s: bytes) -> bytes:
    return struct.pack("<I", len(s)) + s


def _chunk(declared: int, data: bytes, compression: bytes = b"zstd") -> bytes:
    body = struct.pack("<QQQI", 0, 0, declared, 0) + _text(compression) + struct.pack("<Q", len(data)) + data
    return _record(6, body)


def _zstd_zeros(n: int) -> bytes:
    import zstandard

    c = zstandard.ZstdCompressor(level=3).compressobj()
    return b"".join([c.compress(bytes(1 << 20)) for _ in range(n >> 20)] + [c.flush()])


# Runs a command as its child and writes the child's peak resident memory (KiB) to a file.
_PEAK = (
    "import resource, subprocess, sys; p = subprocess.run(sys.argv[2:]); "
    "open(sys.argv[1], 'w').write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)); "
    "sys.exit(p.returncode)"
)


def _peak_of_record_info(path: Path) -> tuple[subprocess.CompletedProcess[str], float]:
    """``mapd record info PATH`` and its peak resident memory (MiB).

    A process's peak starts from the memory of the process it was forked from: Linux keeps the
    high-water mark across exec, and a pytest worker is hundreds of MiB by then (490 and 820 MiB
    were read as mapd's, with the children's rusage and with ``wait4`` alike). So mapd is started
    by a small Python process of its own, which reports its child's peak.
    """
    peak_file = path.with_suffix(".peak")
    out = subprocess.run(
        [sys.executable, "-c", _PEAK, str(peak_file), *MAPD, "record", "info", str(path)],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip
    return out, int(peak_file.read_text()) / 1024.0


def test_a_zstd_chunk_declaring_gigabytes_is_refused_unread(tmp_path: Path, one_error_line: OneLine) -> None:
    path = tmp_path / "bomb.mcap"
    header = _record(1, _text(b"ros2") + _text(b"x"))
    path.write_bytes(_MAGIC + header + _chunk(1 << 30, _zstd_zeros(1 << 30)))
    assert path.stat().st_size < 64 << 10
    out, peak_mb = _peak_of_record_info(path)
    line = one_error_line(out)
    assert "a chunk declares 1073741824 bytes, over the" in line
    assert peak_mb < 300, peak_mb


def test_a_zstd_chunk_that_inflates_past_what_it_declares_is_refused(
    tmp_path: Path, one_error_line: OneLine
) -> None:
    path = tmp_path / "lie.mcap"
    header = _record(1, _text(b"ros2") + _text(b"x"))
    path.write_bytes(_MAGIC + header + _chunk(1 << 20, _zstd_zeros(1 << 30)))
    out, peak_mb = _peak_of_record_info(path)
    assert "decompresses to more than 1048576 bytes" in one_error_line(out)
    assert peak_mb < 300, peak_mb


def test_chunks_of_millions_of_empty_records_are_refused_quickly(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    import zstandard

    size = (60 << 20) // 9 * 9  # 7 million records of opcode 0 and length 0, each in 9 bytes
    data = zstandard.ZstdCompressor().compress(bytes(size))
    path = tmp_path / "records.mcap"
    path.write_bytes(_MAGIC + _record(1, _text(b"ros2") + _text(b"x")) + _chunk(size, data) * 4)
    t0 = time.monotonic()
    line = one_error_line(mapd_run("record", "info", str(path), timeout=30))
    assert "a compression bomb, not a recording" in line
    assert time.monotonic() - t0 < 30


@pytest.mark.parametrize("compression", ["none", "lz4", "zstd"])
def test_recordings_in_every_chunk_compression_are_counted(tmp_path: Path, compression: str) -> None:
    from mcap.writer import CompressionType, Writer

    from mapd.record.info import summarize

    path = tmp_path / "r.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=4096, compression=getattr(CompressionType, compression.upper()))
        w.start(profile="ros2", library="test")
        sid = w.register_schema(name="mapd.links", encoding="jsonschema", data=b"{}")
        cid = w.register_channel(topic="/mapd/links", message_encoding="json", schema_id=sid)
        for i in range(3000):
            w.add_message(channel_id=cid, log_time=1000 + i, publish_time=1000 + i, data=b'{"tx": %d}' % i)
        w.finish()
    s = summarize(path)
    assert s.complete and s.error is None and s.messages == 3000
    t = s.topics["/mapd/links"]
    assert (t.schema, t.messages, t.first_ns, t.last_ns) == ("mapd.links", 3000, 1000, 3999)


def _schema(sid: int, name: bytes, data: bytes) -> bytes:
    return _record(3, struct.pack("<H", sid) + _text(name) + _text(b"jsonschema") + _text(data))


def test_schemas_that_inflate_to_megabytes_are_not_kept(tmp_path: Path, one_error_line: OneLine) -> None:
    """A 22 KB file of chunks each holding one schema of 60 MB (zeros) kept every schema whole:
    837 MB for ten, 2.8 GB for forty. Only names are kept now."""
    import zstandard

    chunks = []
    for sid in range(1, 13):  # each its own id, so each is kept
        big = _schema(sid, b"s", bytes(60 << 20))
        chunks.append(_chunk(len(big), zstandard.ZstdCompressor().compress(big)))
    path = tmp_path / "schemas.mcap"
    path.write_bytes(_MAGIC + _record(1, _text(b"ros2") + _text(b"x")) + b"".join(chunks))
    assert path.stat().st_size < 200 << 10
    out, peak_mb = _peak_of_record_info(path)
    assert "not an MCAP recording" in one_error_line(out)  # (no message, no footer)
    assert peak_mb < 450, peak_mb  # one chunk's schema at a time (before: a GB for twelve)


def test_topics_past_the_cap_end_the_summary_with_a_reason(tmp_path: Path) -> None:
    from mcap.writer import Writer

    from mapd.record.info import MAX_TOPICS, summarize

    path = tmp_path / "topics.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=1 << 16)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
        for i in range(MAX_TOPICS + 50):
            cid = w.register_channel(topic=f"/t{i}", message_encoding="json", schema_id=sid)
            w.add_message(channel_id=cid, log_time=i, publish_time=i, data=b"{}")
        w.finish()
    s = summarize(path)
    assert len(s.topics) == MAX_TOPICS and s.messages == MAX_TOPICS
    assert s.error is not None and f"more than {MAX_TOPICS} topics" in s.error


def test_bytes_outside_chunks_earn_no_records(tmp_path: Path, mapd_run: Run, one_error_line: OneLine) -> None:
    """1 MB of records mapd skips bought 16 million records in chunks: 27 s of parsing a MB."""
    import zstandard

    records = bytes(9 << 20)  # a million records of opcode 0 and length 0
    data = zstandard.ZstdCompressor().compress(records)
    padding = _record(0x80, bytes(2 << 20))  # an opcode the spec says readers skip
    path = tmp_path / "padded.mcap"
    path.write_bytes(_MAGIC + _record(1, _text(b"ros2") + _text(b"x")) + padding + _chunk(len(records), data))
    line = one_error_line(mapd_run("record", "info", str(path), timeout=60))
    assert "a compression bomb, not a recording" in line


def test_record_info_reads_a_pipe_and_escapes_control_characters(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "r.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(name="s\x1b[2J", encoding="jsonschema", data=b"{}")
        cid = w.register_channel(topic="/a\n  /fake 999 msgs", message_encoding="json", schema_id=sid)
        w.add_message(channel_id=cid, log_time=1, publish_time=1, data=b"{}")
        w.finish()
    out = subprocess.run(
        [*MAPD, "record", "info", "/dev/stdin"],
        input=path.read_bytes(),
        capture_output=True,
        timeout=60,
        cwd=ROOT,
    )  # /dev/stdin is a pipe here: it was "cannot read: Illegal seek"
    assert out.returncode == 0, out.stderr
    lines = out.stdout.decode().splitlines()
    assert len(lines) == 2 and "1 messages, complete" in lines[0], lines
    assert "\x1b" not in lines[1] and "\\n  /fake" in lines[1] and "\\x1b[2J" in lines[1], lines


def test_a_restarted_recorder_never_truncates_the_last_recording(tmp_path: Path) -> None:
    from mapd.record.info import summarize
    from mapd.record.writer import Recorder

    grid = OccupancyGrid(np.zeros((20, 30), np.int8), 0.05)
    first = Recorder(tmp_path / "fleet.mcap", chunk_bytes=1024)
    for i in range(5):
        first.grid("/map", grid, "map", 10.0 + i)
    # no close(): the daemon was killed; systemd starts it again on the same path
    first._file.close()  # type: ignore[union-attr]
    before = (tmp_path / "fleet.mcap").read_bytes()
    second = Recorder(tmp_path / "fleet.mcap", chunk_bytes=1024)
    second.grid("/map", grid, "map", 20.0)
    second.close()
    assert (tmp_path / "fleet.mcap").read_bytes() == before
    assert second.files == [tmp_path / "fleet.1.mcap"]
    assert summarize(tmp_path / "fleet.mcap").topics["/map"].messages >= 1
    assert summarize(tmp_path / "fleet.1.mcap").topics["/map"].messages == 1


# ------------------------------------------------------------------ map and payload outputs


def test_encode_on_a_full_disk_keeps_the_previous_payload(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    rng = np.random.default_rng(0)
    save_map(
        OccupancyGrid(rng.choice(np.array([-1, 0, 100], np.int8), (100, 100)), 0.05), tmp_path / "m.yaml"
    )
    out = tmp_path / "m.mapd"
    out.write_bytes(b"the previous payload")

    def small_disk() -> None:  # writes past 4 KiB fail with EFBIG, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

    res = mapd_run(
        "encode", str(tmp_path / "m.yaml"), "-o", str(out), "--codec", "raw", preexec_fn=small_disk
    )
    assert "cannot write payload" in one_error_line(res)
    assert out.read_bytes() == b"the previous payload"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp file left


def test_save_map_to_a_directory_writes_nothing_and_says_so(tmp_path: Path) -> None:
    target = tmp_path / "out"
    target.mkdir()
    with pytest.raises(MapFileError) as err:
        save_map(OccupancyGrid(np.zeros((3, 4), np.int8), 0.05), target)
    assert str(err.value) == f"{target}: is a directory; name the map's YAML file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no out.pgm beside it


def test_decode_names_the_payload_it_cannot_decode(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    junk = tmp_path / "junk.mapd"
    junk.write_bytes(os.urandom(500))
    line = one_error_line(mapd_run("decode", str(junk), "-o", str(tmp_path / "o.yaml")))
    assert line.startswith(f"mapd: error: {junk}: ")
