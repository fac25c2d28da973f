"""``mapd record info FILE``: the channels, message counts and time span of an MCAP recording."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mapd.bench.common import int_arg
from mapd.grid import DEFAULT_MAX_CELLS

#: The most ``--max-cells`` takes (16 Gi cells): a chunk of up to about 16 GiB is then read whole.
MAX_MAX_CELLS = 1 << 34


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="inspect MCAP recordings made with [record] path or mapd demo --record",
        description="Recordings hold the global map (/map), each robot's map (/<robot>/map), "
        "/tf_static, /tf (robots' poses) and /diagnostics (the links); Foxglove and ros2 bag read them too.",
    )
    rsub = p.add_subparsers(dest="record_cmd", required=True, metavar="SUBCOMMAND")
    info = rsub.add_parser("info", help="summarise a recording (also one cut short by a crash)")
    info.add_argument("file", type=Path)
    info.add_argument("--json", action="store_true", help="print JSON")
    info.add_argument(
        "--max-cells",
        type=int_arg(1, MAX_MAX_CELLS),
        default=DEFAULT_MAX_CELLS,
        help="largest map the recording holds, as the recording daemon's [limits] max_cells "
        f"(default {DEFAULT_MAX_CELLS}); a chunk holding more is refused unread",
    )
    info.set_defaults(func=cmd_info)


def cmd_info(args: argparse.Namespace) -> int:
    from mapd.record.info import render, summarize

    s = summarize(args.file, max_cells=args.max_cells)
    print(json.dumps(s.to_json(), indent=1) if args.json else render(s))
    return 0
