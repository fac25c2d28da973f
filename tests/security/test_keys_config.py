"""Key files and configs are read with a size cap, and deep nesting is one ConfigError line.

Before the fix ``key_file = "/dev/zero"`` was read forever, and a config of nested arrays or inline
tables ended ``mapd check-config`` with a RecursionError traceback.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from mapd import config
from mapd.errors import ConfigError
from mapd.keys import MAX_KEY_FILE_BYTES, read_key_file


def test_key_file_on_dev_zero_is_refused_at_once() -> None:
    t0 = time.perf_counter()
    with pytest.raises(
        ConfigError, match=f"^robot.key_file: /dev/zero holds more than {MAX_KEY_FILE_BYTES} bytes"
    ):
        read_key_file(Path("/dev/zero"), "robot.key_file")
    assert time.perf_counter() - t0 < 0.5


def test_key_file_size_cap_is_exact(tmp_path: Path) -> None:
    key = tmp_path / "k"
    key.write_bytes(bytes(range(200, 256)) * (MAX_KEY_FILE_BYTES // 56) + b"\xff" * (MAX_KEY_FILE_BYTES % 56))
    assert len(read_key_file(key, "--key") or b"") == MAX_KEY_FILE_BYTES  # at the cap: read, whole
    key.write_bytes(key.read_bytes() + b"\x00")
    with pytest.raises(ConfigError, match=f"^--key: .* holds more than {MAX_KEY_FILE_BYTES} bytes"):
        read_key_file(key, "--key")
    (tmp_path / "big").write_bytes(bytes(50 << 20))  # a log file named by mistake: refused unread
    with pytest.raises(ConfigError, match="holds more than"):
        read_key_file(tmp_path / "big", "robot.key_file")


#: An EC key on secp112r1 (``openssl ecparam -name secp112r1 -genkey -noout``): a PEM private key
#: that OpenSSL cannot load, which raised UnsupportedAlgorithm out of ``mapd run``.
SECP112R1_KEY = """-----BEGIN EC PRIVATE KEY-----
MD4CAQEEDoP5yDApELG44M2jr10coAcGBSuBBAAGoSADHgAEa6bCmR0xpGtI8Iap
6oYVfkupWtsiGjS5cYSI9Q==
-----END EC PRIVATE KEY-----
"""


def test_a_key_of_a_kind_openssl_cannot_load_is_one_error_line(
    tmp_path: Path,
    mapd_run: Callable[..., subprocess.CompletedProcess[str]],
    one_error_line: Callable[..., str],
) -> None:
    key = tmp_path / "r0.key"
    key.write_text(SECP112R1_KEY)
    key.chmod(0o600)
    cfg = tmp_path / "config.toml"
    cfg.write_text(f'[robot]\nname = "r0"\nkey_file = "{key}"\n[fleet]\nallow_unsigned = true\n')
    out = mapd_run("check-config", str(cfg))
    assert "is not a PEM private key" in one_error_line(out)


def test_mapd_link_with_dev_zero_as_key_is_one_error_line(
    tmp_path: Path,
    mapd_run: Callable[..., subprocess.CompletedProcess[str]],
    one_error_line: Callable[..., str],
) -> None:
    (tmp_path / "p.mapd").write_bytes(b"payload")
    out = mapd_run(
        "link", "send", str(tmp_path / "p.mapd"), "--port", "/dev/null", "--peer", "2", "--key", "/dev/zero"
    )
    assert "--key: /dev/zero holds more than" in one_error_line(out, code=2)


def test_mapd_link_send_of_dev_zero_is_one_error_line(
    mapd_run: Callable[..., subprocess.CompletedProcess[str]], one_error_line: Callable[..., str]
) -> None:
    # It was read until memory ran out: no message on the link is over 16 MiB.
    out = mapd_run("link", "send", "/dev/zero", "--port", "/dev/null", "--peer", "2")
    assert "/dev/zero: over the 16777" in one_error_line(out)


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("a = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
        ("a = " + "{b = " * 3000 + "1" + "}" * 3000 + "\n", "nested too deeply"),
        (
            '[robot]\nname = "r0"\n[source.sim]\nx = ' + "[" * 40 + "]" * 40 + "\n",
            f"nested more than {config.MAX_CONFIG_DEPTH} levels deep",
        ),
        ("[" + ".".join(["t"] * 200) + "]\n", f"nested more than {config.MAX_CONFIG_DEPTH} levels deep"),
        ('[robot]\nname = "' + "x" * 100_000 + '"\n', "robot.name: String should match pattern"),
    ],
)
def test_hostile_config_through_the_cli(
    tmp_path: Path,
    body: str,
    match: str,
    mapd_run: Callable[..., subprocess.CompletedProcess[str]],
    one_error_line: Callable[..., str],
) -> None:
    path = tmp_path / "config.toml"
    path.write_text(body)
    line = one_error_line(mapd_run("check-config", str(path)), code=2)
    assert match in line and len(line) < 300


@pytest.mark.parametrize(
    ("body", "match"),
    [
        # inf became a count (int(cells * inf)) at the first map of a peer: the daemon stopped
        ("[limits]\nmax_growth = inf\n", "limits.max_growth: inf is not a finite number"),
        ("[limits]\nmax_growth = 1e308\n", "limits.max_growth: Input should be less than or equal"),
        ("[fusion]\nmax_extent_m = nan\n", "fusion.max_extent_m: nan is not a finite number"),
        ('[source]\nuse = "sim"\n[source.sim]\nemit_period = -inf\n', "not a finite number"),
        # below the clock's resolution the next emit never moved on: the event loop hung
        (
            '[source]\nuse = "sim"\n[source.sim]\nemit_period = 1e-300\n',
            "emit_period: Input should be greater",
        ),
        # a timer that short fired on every pass of the link's loop
        ("[transports.uwb]\nbeacon_s = 1e-300\n", "beacon_s: Input should be greater"),
    ],
)
def test_numbers_no_setting_can_mean_are_refused(tmp_path: Path, body: str, match: str) -> None:
    path = tmp_path / "config.toml"
    path.write_text('[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n' + body)
    with pytest.raises(ConfigError, match=match):
        config.check_plugins(config.load(path))


def test_config_size_is_capped(
    mapd_run: Callable[..., subprocess.CompletedProcess[str]], one_error_line: Callable[..., str]
) -> None:
    t0 = time.perf_counter()
    line = one_error_line(mapd_run("check-config", "/dev/zero"), code=2)
    assert f"over {config.MAX_CONFIG_BYTES} bytes" in line
    assert time.perf_counter() - t0 < 30


@pytest.mark.parametrize("name", ['a"b', "a\nb", "a b", "r" * 33, "é"])
def test_keygen_refuses_a_name_the_config_would_refuse(
    tmp_path: Path,
    name: str,
    mapd_run: Callable[..., subprocess.CompletedProcess[str]],
    one_error_line: Callable[..., str],
) -> None:
    """It wrote a key and printed a roster line that was not TOML, or that the config refuses."""
    key = tmp_path / "k.pem"
    line = one_error_line(mapd_run("keygen", name, "-o", str(key)))
    assert "is not a robot name" in line
    assert not key.exists()
