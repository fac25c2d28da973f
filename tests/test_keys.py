"""The fleet key file, read one way for ``robot.key_file`` and ``mapd link --key``."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapd.errors import ConfigError
from mapd.keys import read_key_file


def test_hex_text_with_white_space(tmp_path: Path) -> None:
    (tmp_path / "k").write_text("  " + "0f" * 16 + "\n")
    assert read_key_file(tmp_path / "k", "--key") == bytes.fromhex("0f" * 16)


def test_raw_bytes_are_the_key(tmp_path: Path) -> None:
    raw = bytes(range(200, 232))  # not ASCII, so not hex
    (tmp_path / "k").write_bytes(raw)
    assert read_key_file(tmp_path / "k", "--key") == raw


def test_no_path_no_key() -> None:
    assert read_key_file(None, "robot.key_file") is None


@pytest.mark.parametrize("option", ["robot.key_file", "--key"])
def test_errors_name_the_option(tmp_path: Path, option: str) -> None:
    (tmp_path / "short").write_text("ab" * 15)
    with pytest.raises(
        ConfigError, match=rf"^{option}: .*short holds 15 bytes; a fleet key needs at least 16$"
    ):
        read_key_file(tmp_path / "short", option)
    with pytest.raises(ConfigError, match=rf"^{option}: cannot read .*absent"):
        read_key_file(tmp_path / "absent", option)


def test_hex_cut_to_an_odd_number_of_digits_is_refused_not_taken_as_raw_bytes(tmp_path: Path) -> None:
    # Before, the 63 ASCII digits became the key: another key than the fleet's, and every frame
    # failed its signature with no word at start.
    (tmp_path / "k").write_text("0f" * 31 + "a\n")
    with pytest.raises(ConfigError, match=r"^robot.key_file: .*k holds 63 hex digits, an odd number"):
        read_key_file(tmp_path / "k", "robot.key_file")
    (tmp_path / "p").write_text("correct horse battery staple\n")  # a passphrase: raw, as before
    assert read_key_file(tmp_path / "p", "robot.key_file") == b"correct horse battery staple\n"
