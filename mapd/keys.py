"""The fleet key file, read one way for the daemon (``robot.key_file``) and ``mapd link`` (``--key``).

A key file holds the key as hex text (surrounding white space ignored) or as raw bytes. Anything
that does not decode as hex is taken as raw bytes, so a random binary key works as it is.
"""

from __future__ import annotations

from pathlib import Path

from mapd.errors import ConfigError

#: Shortest key accepted (128 bits): a shorter signing key could be found by brute force.
MIN_KEY_BYTES = 16


def read_key_file(path: Path | None, option: str) -> bytes | None:
    """The fleet key in ``path`` (None: no key), at least :data:`MIN_KEY_BYTES` long.

    ``option`` names where the path came from (``robot.key_file``, ``--key``); every error starts
    with it, so the user knows which setting to fix. Raises :class:`~mapd.errors.ConfigError` when
    the file cannot be read or the key is too short.
    """
    if path is None:
        return None
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{option}: cannot read {path}: {exc.strerror}") from None
    try:
        key = bytes.fromhex(raw.strip().decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        key = raw
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError(
            f"{option}: {path} holds {len(key)} bytes; a fleet key needs at least {MIN_KEY_BYTES}"
        )
    return key
