"""``mapd bench ...``: benchmarks that print a table (and --json) with their baselines in the same run.

Each benchmark is a module of :mod:`mapd.bench` with ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``; heavy imports stay inside ``run``.
"""

from __future__ import annotations

import argparse
import importlib

BENCHES = {
    "codec": "mapd.bench.codec",
    "stream": "mapd.bench.stream",
    "mapper": "mapd.bench.mapper",
    "link": "mapd.bench.link",
    "merge": "mapd.bench.merge",
    "fleet": "mapd.bench.fleet",
    "paper": "mapd.bench.paper",
    "swarm": "mapd.bench.swarm",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="benchmarks: " + ", ".join(BENCHES),
        description="Benchmarks. Each prints a table with its baselines measured in the same run.",
    )
    bsub = p.add_subparsers(dest="bench", metavar="BENCH", title="benchmarks")
    for name, module_name in BENCHES.items():
        module = importlib.import_module(module_name)
        bp = bsub.add_parser(name, help=module.HELP, description=module.__doc__)
        module.add_arguments(bp)
        bp.add_argument("--json", action="store_true", help="print JSON instead of a table")
        bp.set_defaults(func=module.run)
    p.set_defaults(func=lambda args: p.print_help() or 2)
