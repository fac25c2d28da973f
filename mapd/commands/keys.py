"""``mapd keygen``: a robot's signing key (and its roster line), or the fleet's uwb link key."""

from __future__ import annotations

import argparse
import json
import re
import secrets
from pathlib import Path

EPILOG = """\
examples:
  mapd keygen robot0 -o /etc/mapd/robot.key     # prints: robot0 = "ed25519:..."  (add it to [fleet.roster])
  mapd keygen robot0 --public /etc/mapd/robot.key   # print the roster line of an existing key again
  mapd keygen --link-key /etc/mapd/link.key     # once per fleet: copy the same file to every robot

Every robot's config lists the whole roster; a robot signs with its own key only, so no robot can
write as another. The link key authenticates uwb frames (a shared secret, like MAVLink 2's).
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "keygen",
        help="make a robot's Ed25519 key and print its roster line, or the fleet's uwb link key",
        description="Make this robot's signing key (private, mode 0600) and print the line to add "
        "to [fleet.roster] on every robot; or make the fleet's shared uwb link key.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("robot", nargs="?", help="the robot's name, as in [robot] name")
    p.add_argument(
        "-o", "--out", type=Path, help="where to write the robot's private key (never overwritten)"
    )
    p.add_argument(
        "--public", type=Path, metavar="KEY_FILE", help="print the roster line of this existing key"
    )
    p.add_argument(
        "--link-key", type=Path, metavar="FILE", help="write a new fleet link key (32 random bytes, hex)"
    )
    p.set_defaults(func=cmd_keygen)


def cmd_keygen(args: argparse.Namespace) -> int:
    from mapd.errors import ConfigError
    from mapd.identity import Identity, read_identity

    if args.link_key is not None:
        _write_secret(args.link_key, secrets.token_hex(32).encode() + b"\n")
        # Absolute: the config reads its paths relative to its own folder, not to where keygen ran.
        path = json.dumps(str(args.link_key.resolve()))  # a TOML basic string: quotes escaped
        print(f"link_key_file = {path}   # in [fleet]; copy this file to every robot of the fleet")
        return 0
    if not args.robot:
        raise ConfigError("keygen: name the robot (mapd keygen ROBOT -o FILE), or give --link-key FILE")
    from mapd.config import NAME_PATTERN

    if not re.fullmatch(NAME_PATTERN, args.robot):  # else a roster line the config refuses, or not TOML
        raise ConfigError(
            f"keygen: {args.robot!r} is not a robot name (1 to 32 letters, digits, '_' or '-', as the config takes)"
        )
    if args.public is not None:
        if args.out is not None:  # -o was silently ignored: the user expected a key written there
            raise ConfigError(
                "keygen: --public prints the line of an existing key; it writes nothing, so drop -o"
            )
        identity = read_identity(args.public, args.robot, "--public")
    else:
        if args.out is None:
            raise ConfigError("keygen: give -o FILE for the private key (it is never printed)")
        identity = Identity.generate(args.robot)
        identity.write(args.out)
    print(f'{args.robot} = "{identity.public_text}"')
    return 0


def _write_secret(path: Path, data: bytes) -> None:
    from mapd.errors import ConfigError
    from mapd.files import write_new_secret

    try:
        write_new_secret(path, data)
    except FileExistsError:
        raise ConfigError(f"{path} exists; refusing to overwrite the fleet's link key") from None
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror}") from None
