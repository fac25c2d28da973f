"""Who signed this: each robot's Ed25519 key, and the fleet's roster of public keys.

Every message between robots (a map envelope, a zenoh ack) is signed with the key of the robot it
names, and accepted only when the roster's key for that robot verifies it. So a robot that holds its
own key cannot write as another, and an outsider can write as nobody.

* :class:`Identity`: this robot's private key (``[robot] key_file``, PEM PKCS#8, made by
  ``mapd keygen``). Files are read with a size cap and must not be readable by others.
* :class:`Roster`: robot name -> public key (``[fleet.roster]``, lines as ``mapd keygen`` prints
  them: ``robot0 = "ed25519:<base64>"``), and whether unsigned messages are allowed at all
  (``[fleet] allow_unsigned = true``, which must be said in so many words).

The keys come from ``cryptography`` (Ed25519: 32-byte keys, 64-byte signatures, deterministic).
"""

from __future__ import annotations

import base64
import binascii
import os
from collections.abc import Mapping
from pathlib import Path

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from mapd.errors import ConfigError, SignatureError
from mapd.files import write_new_secret
from mapd.files.reading import NotRegularFileError, open_regular
from mapd.keys import MAX_KEY_FILE_BYTES

SIG_LEN = 64
PREFIX = "ed25519:"


class Identity:
    """This robot's signing key."""

    def __init__(self, robot: str, private: Ed25519PrivateKey) -> None:
        self.robot = robot
        self._key = private

    @classmethod
    def generate(cls, robot: str) -> Identity:
        return cls(robot, Ed25519PrivateKey.generate())

    def sign(self, data: bytes) -> bytes:
        """The 64-byte Ed25519 signature of ``data``."""
        return self._key.sign(data)

    @property
    def public_key(self) -> Ed25519PublicKey:
        return self._key.public_key()

    @property
    def public_text(self) -> str:
        """The public key as the roster writes it: ``ed25519:<base64>``."""
        raw = self.public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
        return PREFIX + base64.b64encode(raw).decode("ascii")

    def private_pem(self) -> bytes:
        return self._key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )

    def write(self, path: Path) -> None:
        """Write the private key to ``path`` (mode 0600, never over an existing file)."""
        try:
            write_new_secret(path, self.private_pem())
        except FileExistsError:
            raise ConfigError(f"{path} exists; refusing to overwrite a robot's key") from None
        except OSError as exc:
            raise ConfigError(f"cannot write {path}: {exc.strerror}") from None


def read_identity(path: Path, robot: str, option: str = "robot.key_file") -> Identity:
    """The robot's private key in ``path``; one :class:`ConfigError` line for anything wrong.

    Read with a size cap (``/dev/zero`` or a log file given by mistake is refused, not read for
    ever); refused when other users may read it (as ssh refuses a private key).
    """
    try:
        # Not open(): that blocks on a FIFO with no writer before the regular-file check can refuse it.
        with open_regular(path) as fh:
            st = os.fstat(fh.fileno())
            if st.st_mode & 0o077 & ~0o040:  # the daemon's group may read it (install.sh: root:mapd 0640)
                raise ConfigError(f"{option}: {path} is readable by other users; chmod 600 it")
            raw = fh.read(MAX_KEY_FILE_BYTES + 1)
    except NotRegularFileError:
        raise ConfigError(f"{option}: {path} is not a regular file") from None
    except OSError as exc:
        raise ConfigError(f"{option}: cannot read {path}: {exc.strerror}") from None
    if len(raw) > MAX_KEY_FILE_BYTES:
        raise ConfigError(f"{option}: {path} is larger than a key file ({MAX_KEY_FILE_BYTES} bytes)")
    try:
        key = serialization.load_pem_private_key(raw, password=None)
    except (ValueError, TypeError, binascii.Error, UnsupportedAlgorithm):
        # UnsupportedAlgorithm: a PEM key of a kind OpenSSL cannot load (an EC key on secp112r1)
        raise ConfigError(
            f"{option}: {path} is not a PEM private key (make one with 'mapd keygen')"
        ) from None
    if not isinstance(key, Ed25519PrivateKey):
        raise ConfigError(f"{option}: {path} is not an Ed25519 key (make one with 'mapd keygen')")
    return Identity(robot, key)


def parse_public_key(text: str, where: str) -> Ed25519PublicKey:
    """A roster entry ``ed25519:<base64 of 32 bytes>``; :class:`ConfigError` naming ``where``."""
    if not text.startswith(PREFIX):
        raise ConfigError(f"{where}: expected '{PREFIX}<base64>' as 'mapd keygen' prints it")
    try:
        raw = base64.b64decode(text[len(PREFIX) :], validate=True)
    except (binascii.Error, ValueError):
        raise ConfigError(f"{where}: the key is not valid base64") from None
    if len(raw) != 32:
        raise ConfigError(f"{where}: an Ed25519 public key is 32 bytes, this one {len(raw)}")
    return Ed25519PublicKey.from_public_bytes(raw)


class Roster:
    """The fleet's public keys by robot, and the rule for unsigned messages."""

    def __init__(self, keys: Mapping[str, Ed25519PublicKey], *, allow_unsigned: bool = False) -> None:
        self._keys = dict(keys)
        self.allow_unsigned = allow_unsigned

    @classmethod
    def from_texts(cls, texts: Mapping[str, str], *, allow_unsigned: bool = False) -> Roster:
        return cls(
            {robot: parse_public_key(t, f"fleet.roster.{robot}") for robot, t in texts.items()},
            allow_unsigned=allow_unsigned,
        )

    @classmethod
    def open(cls) -> Roster:
        """No keys, unsigned allowed: for tools that read envelopes without a fleet (tests, benches)."""
        return cls({}, allow_unsigned=True)

    def __contains__(self, robot: object) -> bool:
        return robot in self._keys

    def adopt(self, other: Roster) -> None:
        """Take ``other``'s keys (a config reload), keeping this roster's rule for unsigned messages.

        Every holder of this object verifies with the new keys from its next call on. The dict is
        swapped whole, so a verification on a worker thread sees the old keys or the new, never a mix.
        """
        self._keys = dict(other._keys)

    @property
    def robots(self) -> list[str]:
        return sorted(self._keys)

    def admits(self, robot: str) -> bool:
        """Whether messages naming ``robot`` can be accepted at all (on the roster, or unsigned allowed)."""
        return robot in self._keys or self.allow_unsigned

    def verify(self, robot: str, data: bytes, sig: bytes, what: str) -> None:
        """Check that ``robot``'s key signed ``data``; :class:`SignatureError` says why not.

        Unsigned (``sig`` empty) passes only with ``allow_unsigned``; so does a robot that is not
        on the roster (its signature cannot be checked). A robot on the roster whose message is
        signed is always checked.
        """
        key = self._keys.get(robot)
        if key is None:
            if self.allow_unsigned:
                return
            raise SignatureError(f"{what} from '{robot}', which is not on the fleet's roster")
        if not sig:
            if self.allow_unsigned:
                return
            raise SignatureError(f"unsigned {what} from '{robot}' (the fleet requires signatures)")
        if len(sig) != SIG_LEN:
            raise SignatureError(f"{what} from '{robot}' has a signature of {len(sig)} bytes, not {SIG_LEN}")
        try:
            key.verify(sig, data)
        except InvalidSignature:
            raise SignatureError(f"bad signature on {what} from '{robot}'") from None
