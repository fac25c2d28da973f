"""The ``mapd`` command: one entry point, one subcommand per job.

Each subcommand lives in a module of :mod:`mapd.commands` with a ``register(subparsers)`` function;
modules import their heavy dependencies inside the handlers, so ``mapd --help`` stays fast. Any
:class:`~mapd.errors.MapdError` becomes one line on stderr and a non-zero exit
(:func:`~mapd.errors.exit_code`: 2 for what no retry heals, 1 for what one may).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from mapd import __version__
from mapd.errors import MapdError, exit_code

COMMAND_MODULES = [
    "mapd.commands.maps",  # plugins, check-config, info, encode, decode
    "mapd.commands.daemon",  # run, status, demo
    "mapd.commands.fusion",  # merge
    "mapd.commands.mapping",  # replay
    "mapd.commands.link",  # link send / recv
    "mapd.commands.train",  # train
    "mapd.commands.keys",  # keygen
    "mapd.commands.record",  # record info
    "mapd.commands.bench",  # bench ...
]

DESCRIPTION = """\
mapd shares 2D occupancy-grid maps across a robot fleet over thin links (UWB serial at 12.5 kb/s,
or zenoh over Wi-Fi), compresses them (the Zhang & Deng 2024 CNN + Huffman codec, or mapd's exact
lossless and delta codecs), and fuses what it receives into one global map.
"""

EPILOG = """\
examples:
  mapd info ../shared/data/maps/radish_derived/intel/intel.yaml
  mapd encode MAP.yaml -o map.mapd --codec zstd
  mapd decode map.mapd -o copy.yaml
  mapd keygen alpha -o robot.key     # then add the printed line to [fleet.roster]
  mapd check-config /etc/mapd/config.toml
  mapd bench codec --codec raw zstd

Run 'mapd COMMAND --help' for a command's options.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mapd",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mapd {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        return int(args.func(args) or 0)
    except MapdError as exc:
        from mapd.daemon.systemd import print_error

        print_error(exc)
        return exit_code(exc)
    except KeyboardInterrupt:
        print("mapd: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
