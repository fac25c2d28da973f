"""The fleet key file, read one way for the daemon (``robot.key_file``) and ``mapd link`` (``--key``).

A key file holds the key as hex text (surrounding white space ignored) or as raw bytes. Anything
that does not decode as hex is taken as raw bytes, so a random binary key works as it is.
"""

from __future__ import annotations

from pathlib import Path

from mapd.errors import ConfigError
from mapd.files.reading import read_capped

#: Shortest key accepted (128 bits): a shorter signing key could be found by brute force.
MIN_KEY_BYTES = 16
#: Longest key file read. A key is 16 to a few hundred bytes (hex doubles it); reading stops here, so
#: a key_file naming ``/dev/zero`` or a log file is refused at once instead of read forever.
MAX_KEY_FILE_BYTES = 4096


def read_key_file(path: Path | None, option: str) -> bytes | None:
    """The fleet key in ``path`` (None: no key), at least :data:`MIN_KEY_BYTES` long.

    ``option`` names where the path came from (``robot.key_file``, ``--key``); every error starts
    with it, so the user knows which setting to fix. Raises :class:`~mapd.errors.ConfigError` when
    the file cannot be read, holds more than :data:`MAX_KEY_FILE_BYTES` or the key is too short.
    At most ``MAX_KEY_FILE_BYTES + 1`` bytes are ever read (a pipe, as in ``--key <(...)``, works).
    """
    if path is None:
        return None
    try:
        raw = read_capped(path, MAX_KEY_FILE_BYTES)
    except OSError as exc:
        raise ConfigError(f"{option}: cannot read {path}: {exc.strerror}") from None
    if len(raw) > MAX_KEY_FILE_BYTES:
        raise ConfigError(
            f"{option}: {path} holds more than {MAX_KEY_FILE_BYTES} bytes; a fleet key file holds one "
            f"key of {MIN_KEY_BYTES}+ bytes (raw or hex)"
        )
    text = raw.strip()
    try:
        key = bytes.fromhex(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        if text and all(c in b"0123456789abcdefABCDEF" for c in text):
            # hex, cut short or pasted with a digit missing: taken as raw bytes it would be another
            # key, and every frame would fail its signature with no word of why
            raise ConfigError(
                f"{option}: {path} holds {len(text)} hex digits, an odd number: the key is damaged "
                "(cut short?); copy it again, or make one with mapd keygen"
            ) from None
        key = raw
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError(
            f"{option}: {path} holds {len(key)} bytes; a fleet key needs at least {MIN_KEY_BYTES}"
        )
    return key
