"""Commands for map files, payloads, configs and plugins: info, encode, decode, check-config, plugins."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from mapd.commands.common import (
    codec_name,
    is_stdio,
    map_inputs,
    map_outputs,
    path_or_stdio,
    refuse_overwrite,
    refuse_stdio,
)
from mapd.errors import CodecError, ConfigError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plugins", help="list the source, codec and transport plugins installed")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_plugins)

    p = sub.add_parser(
        "check-config",
        help="validate a config file and print what it resolves to",
        description="Validate config.toml (every key and every plugin table) and print the result.",
    )
    p.add_argument("path", type=Path, help="config file (TOML)")
    p.add_argument("--json", action="store_true", help="print only the resolved config, as JSON (for jq)")
    p.set_defaults(func=cmd_check_config)

    p = sub.add_parser(
        "info",
        help="size, resolution, origin and cell counts of a map_server map",
        description="Load a map_server YAML + image the way map_server does and summarise it.",
    )
    p.add_argument("map", type=Path, help="map_server YAML")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser(
        "encode",
        help="compress a map_server map into a mapd payload",
        description="Encode a map into a self-describing payload; with --base, as a delta when smaller.",
    )
    p.add_argument("map", type=path_or_stdio, help="map_server YAML to encode")
    p.add_argument(
        "-o", "--output", type=path_or_stdio, required=True, help="payload file to write ('-': stdout)"
    )
    p.add_argument(
        "--codec",
        type=codec_name,
        default="lossless",
        help="codec plugin (default: lossless; see 'mapd plugins')",
    )
    p.add_argument(
        "--base", type=path_or_stdio, help="map_server YAML the receiver already holds (delta base)"
    )
    p.set_defaults(func=cmd_encode)

    p = sub.add_parser(
        "decode",
        help="turn a mapd payload back into map_server files",
        description="Decode a payload made by 'mapd encode' into map_server YAML + PGM.",
    )
    p.add_argument("payload", type=path_or_stdio, help="payload file ('-': stdin)")
    p.add_argument(
        "-o",
        "--output",
        type=path_or_stdio,
        required=True,
        help="map_server YAML to write (NAME.pgm beside it)",
    )
    p.add_argument("--base", type=path_or_stdio, help="the base map, when the payload is a delta")
    p.set_defaults(func=cmd_decode)

    p = sub.add_parser(
        "warmup",
        help="compile and cache the codecs' kernels now (install step), not at the robot's first map",
        description="Encode and decode a tiny map with each codec so numba compiles its kernels into "
        "the on-disk cache (NUMBA_CACHE_DIR if set) and models load once.",
    )
    p.add_argument(
        "--codec", nargs="+", type=codec_name, default=["lossless", "zstd", "raw"], help="codecs to warm up"
    )
    p.set_defaults(func=cmd_warmup)


def cmd_plugins(args: argparse.Namespace) -> int:
    from mapd import plugins

    rows: list[dict[str, Any]] = []
    for kind in plugins.GROUPS:
        for info in plugins.available(kind):
            status = "ok"
            try:
                plugins.load(kind, info.name)
            except Exception as exc:  # report every failure, keep listing
                status = str(exc)
            rows.append({"kind": kind, "name": info.name, "target": info.target, "status": status})
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for kind in plugins.GROUPS:
        print(f"{kind}s:")
        for r in (r for r in rows if r["kind"] == kind):
            mark = "" if r["status"] == "ok" else f"  [unavailable: {r['status']}]"
            print(f"  {r['name']:<10} {r['target']}{mark}")
    return 0


def cmd_check_config(args: argparse.Namespace) -> int:
    from mapd import config

    cfg = config.load(args.path)
    checked = config.check(cfg)
    resolved = cfg.model_dump(mode="json")
    resolved["keys"] = {
        "signed": checked.keys.signed,
        "public_key": checked.keys.identity.public_text if checked.keys.identity else None,
        "link_key": checked.keys.link_key is not None,
    }
    for section, tables in checked.options.items():
        for name, opts in tables.items():
            resolved[section][name] = opts.model_dump(mode="json")
    if not args.json:  # with --json, stdout is the JSON alone (``| jq``); the exit status says ok
        print(f"{args.path}: ok")
    print(json.dumps(resolved, indent=2))
    return 0


def _grid_summary(path: Path) -> dict[str, Any]:
    from mapd.grid.load import load_map, read_map_yaml

    meta = read_map_yaml(path)
    grid = load_map(path)
    counts = grid.counts()
    return {
        "map": str(path),
        "image": str(meta["image"]),
        "mode": meta["mode"],
        "width": grid.width,
        "height": grid.height,
        "cells": grid.cells,
        "resolution": grid.resolution,
        "size_m": [round(grid.width * grid.resolution, 3), round(grid.height * grid.resolution, 3)],
        "origin": {"x": grid.origin.x, "y": grid.origin.y, "yaw": grid.origin.yaw},
        **counts,
        "trinary": grid.is_trinary(),
    }


def cmd_info(args: argparse.Namespace) -> int:
    s = _grid_summary(args.map)
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    n = s["cells"]
    print(f"map        {s['map']}")
    print(f"image      {s['image']} (mode {s['mode']})")
    print(f"size       {s['width']} x {s['height']} cells = {n} cells, {s['size_m'][0]} x {s['size_m'][1]} m")
    print(f"resolution {s['resolution']} m/cell")
    o = s["origin"]
    print(f"origin     x {o['x']} m, y {o['y']} m, yaw {o['yaw']} rad ({math.degrees(o['yaw']):.1f} deg)")
    for k in ("free", "occupied", "unknown"):
        print(f"{k:<10} {s[k]:>10}  {100.0 * s[k] / n:5.1f} %")
    print(f"values     {'trinary (-1/0/100)' if s['trinary'] else 'graded occupancy (0..100)'}")
    return 0


def cmd_encode(args: argparse.Namespace) -> int:
    import time

    from mapd.codec import encode
    from mapd.grid.load import load_map

    refuse_stdio(args.map, "the map")
    refuse_stdio(args.base, "--base")
    inputs = map_inputs(args.map, "the input map")
    if args.base:
        inputs += map_inputs(args.base, "--base")
    if is_stdio(args.output):
        if sys.stdout.isatty():  # a binary payload would only garble the terminal
            raise ConfigError("-o -: stdout is a terminal; redirect it to a file or a pipe")
    else:
        refuse_overwrite([(args.output, f"-o {args.output}")], inputs)
    grid = load_map(args.map)
    base = load_map(args.base) if args.base else None
    t0 = time.perf_counter()
    payload = encode(grid, args.codec, base)
    ms = 1000 * (time.perf_counter() - t0)
    from mapd.files import atomic_write_bytes

    if is_stdio(args.output):
        sys.stdout.buffer.write(payload)
        sys.stdout.buffer.flush()
        args.output = "<stdout>"  # for the summary line below
    else:
        try:
            # Atomic: a full disk or a crash mid-write leaves the previous payload, never half of one.
            atomic_write_bytes(args.output, payload)
        except OSError as exc:
            raise CodecError(f"{args.output}: cannot write payload: {exc.strerror}") from None
    ratio = grid.cells / len(payload)
    print(
        f"{args.output}: {len(payload)} bytes for {grid.cells} cells "
        f"(ratio {ratio:.1f}:1, {8 * len(payload) / grid.cells:.4f} bits/cell, {ms:.0f} ms)",
        file=sys.stderr,
    )
    return 0


def cmd_decode(args: argparse.Namespace) -> int:
    from mapd.codec import decode
    from mapd.grid import DEFAULT_MAX_CELLS
    from mapd.grid.load import load_map
    from mapd.grid.save import save_map

    # Read at most what the largest payload decode accepts (a raw map at the cell limit plus its
    # header), so that /dev/zero or a wrong file is refused instead of read into memory.
    limit = DEFAULT_MAX_CELLS + (1 << 16)
    from mapd.files.reading import DATA_READ_TIMEOUT_S, read_capped

    refuse_stdio(args.output, "-o")
    refuse_stdio(args.base, "--base")
    inputs = [] if is_stdio(args.payload) else [(args.payload, f"the payload {args.payload}")]
    if args.base:
        inputs += map_inputs(args.base, "--base")
    refuse_overwrite(map_outputs(args.output, "-o"), inputs)
    if is_stdio(args.payload):
        if sys.stdin.isatty():  # nobody types a binary payload: say so instead of waiting
            raise ConfigError("decode -: stdin is a terminal; pipe a payload in")
        args.payload = "<stdin>"  # for the messages below
        # At most limit + 1 bytes, as from a file: a never-ending producer is refused, not buffered.
        payload = sys.stdin.buffer.read(limit + 1)
    else:
        try:
            # a FIFO with no writer reads as empty, one held open without data is given up
            payload = read_capped(args.payload, limit, timeout_s=DATA_READ_TIMEOUT_S)
        except OSError as exc:
            raise CodecError(f"{args.payload}: cannot read payload: {exc.strerror}") from None
    if len(payload) > limit:
        raise CodecError(f"{args.payload}: over {limit} bytes, larger than any payload mapd decodes")
    base = load_map(args.base) if args.base else None
    try:
        grid = decode(payload, base)
    except CodecError as exc:
        raise CodecError(f"{args.payload}: {exc}") from None  # say which file, as the other errors do
    save_map(grid, args.output)
    print(f"{args.output}: {grid.width} x {grid.height} cells", file=sys.stderr)
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    from mapd.codec.api import warm_up

    for name in args.codec:
        print(f"{name}: ready in {warm_up(name):.1f} s", flush=True)
    return 0
