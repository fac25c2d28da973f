"""``mapd run``, ``mapd status`` and ``mapd demo``."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

# Light (no pydantic), and loaded by ``mapd bench``'s options at every start anyway.
from mapd.bench.common import DAY_S, MAX_SEED, MAX_SIM_ROBOTS, float_arg, int_arg

DEFAULT_CONFIG = Path(os.environ.get("MAPD_CONFIG", "/etc/mapd/config.toml"))


def _watch_seconds(text: str) -> float:
    """``--watch``: a finite period from 0.1 s (faster only spins on the daemon) to an hour."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number of seconds") from None
    if not 0.1 <= value <= 3600.0:  # NaN fails too; -1, nan and inf were tracebacks
        raise argparse.ArgumentTypeError(f"{text} is not within 0.1..3600 seconds")
    return value


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the daemon (source -> codec -> transports; peers -> fusion)",
        description="Run mapd in the foreground until SIGTERM/SIGINT (a second SIGINT forces exit). "
        "Under systemd it reports READY=1 and pings the watchdog.",
    )
    p.add_argument(
        "--config", type=Path, default=DEFAULT_CONFIG, help=f"config file (default {DEFAULT_CONFIG})"
    )
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "status",
        help="show what the local daemon is doing",
        description="Read the daemon's read-only control socket and print a summary. Exits 1 when no "
        "daemon answers.",
    )
    p.add_argument("--config", type=Path, default=None, help="config file, to find the control socket")
    p.add_argument("--socket", type=Path, default=None, help="control socket path (overrides --config)")
    p.add_argument("--json", action="store_true", help="print the raw JSON status")
    p.add_argument(
        "--watch",
        nargs="?",
        const=1.0,
        type=_watch_seconds,
        metavar="SECONDS",
        help="refresh every N s (0.1 to 3600)",
    )
    p.set_defaults(func=cmd_status)

    p = sub.add_parser(
        "demo",
        help="two robots exploring one building, sharing maps over an emulated 12.5 kb/s UWB link",
        description="Start N 'mapd run' daemons as separate processes, each with a simulated robot, exchanging "
        "maps over socat pty pairs through an emulated 12.5 kb/s radio (or zenoh), then write the "
        "global map, bandwidth and quality figures and a metrics table.",
    )
    p.add_argument(
        "--robots",
        type=int_arg(2, MAX_SIM_ROBOTS),  # "the demo needs at least 2 robots", said while parsing
        default=2,
        help=f"fleet size, 2 to {MAX_SIM_ROBOTS} (default 2)",
    )
    p.add_argument("--transport", choices=["uwb", "zenoh"], default="uwb", help="link between robots")
    p.add_argument("--codec", default="lossless", help="codec the robots use (default lossless)")
    p.add_argument("--log", type=Path, default=None, help="replay a CARMEN log instead of the simulator")
    p.add_argument(
        "--duration", type=float_arg(1.0, DAY_S), default=60.0, help="seconds to run, 1 to 86400 (default 60)"
    )
    p.add_argument("--seed", type=int_arg(0, MAX_SEED), default=7, help="building and robots seed, 0 or more")
    p.add_argument("--out", type=Path, default=Path("out"), help="output folder (default out/)")
    p.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="FILE",
        help="record robot0's view of the fleet to an MCAP file (global map, robots' maps, TF, links)",
    )
    p.add_argument(
        "--view",
        type=int_arg(1, 65535),
        default=None,
        metavar="PORT",
        help="serve robot0's live web view on http://127.0.0.1:PORT/ while the demo runs",
    )
    p.add_argument(
        "--ros2-listen",
        default=None,
        metavar="ENDPOINT",
        help="also run a base station whose ros2 output (rmw_zenoh: /map, /<robot>/map, /tf_static, /tf) listens on this "
        "zenoh endpoint, e.g. tcp/127.0.0.1:7447",
    )
    faults = p.add_argument_group("faults on the emulated UWB link (--transport uwb)")
    probability = float_arg(0.0, 1.0)
    faults.add_argument("--drop", type=probability, default=0.0, metavar="P", help="frame loss probability")
    faults.add_argument(
        "--flip", type=probability, default=0.0, metavar="P", help="bit-flip probability per byte"
    )
    faults.add_argument(
        "--outage",
        action="append",
        default=[],
        type=_outage_arg,
        metavar="START:SECONDS",
        help="radio silence from START s for SECONDS (repeatable)",
    )
    faults.add_argument(
        "--out-of-range",
        action="append",
        default=[],
        type=_pair_arg,
        metavar="A-B",
        help="robots A and B (0-based) never hear each other: maps between them go through a relay "
        "robot that hears both (repeatable; needs --robots 3 or more)",
    )
    p.set_defaults(func=cmd_demo)


def _pair_arg(text: str) -> str:
    """``A-B`` for the relay's ``--out-of-range``, checked here so a typo is one clear line."""
    from transports.uwb.relay import parse_pair  # the relay parses it the same way

    parse_pair(text)
    return text


def _outage_arg(text: str) -> str:
    """``START:SECONDS`` for the relay's ``--outage``, checked here so a typo is one clear line."""
    try:
        start, seconds = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"outage '{text}' is not START:SECONDS") from None
    if not (0.0 <= start <= DAY_S and 0.0 < seconds <= DAY_S):  # NaN fails too
        raise argparse.ArgumentTypeError(
            f"outage '{text}': START must be 0 to {DAY_S:g} s and SECONDS above 0, at most {DAY_S:g}"
        )
    return text


def cmd_run(args: argparse.Namespace) -> int:
    from mapd import config
    from mapd.daemon.process import run_daemon
    from mapd.daemon.systemd import print_error, setup_logging
    from mapd.errors import MapdError, exit_code

    cfg = config.load(args.config)
    setup_logging(cfg.log.level)
    try:
        code = run_daemon(cfg)
    except MapdError as exc:
        # Said here, not by cli.main, so that this path too leaves with os._exit below: returning
        # would make the interpreter join every executor thread first (a search, a start_pose).
        print_error(exc)
        code = exit_code(exc)
    # By now the state directory is written and fsynced, the transports and the control socket are
    # closed. All the interpreter's finalization would add is tearing down native extensions (numba's
    # LLVM, zenoh's runtime, OpenCV): 1-3 s on a loaded 2-core robot, measured after the "stopped"
    # log line, which delays every systemd stop and restart. So flush what is buffered and leave.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _socket_path(args: argparse.Namespace) -> Path:
    if args.socket is not None:
        return Path(args.socket)
    from mapd import config
    from mapd.errors import ConfigError

    try:
        default = DEFAULT_CONFIG if DEFAULT_CONFIG.exists() else None
    except OSError:  # /etc/mapd is 0750 root:mapd: a user outside group mapd may not look in
        default = None  # the socket's own refusal then says who may ask
    cfg_path = args.config or default
    if cfg_path is not None:
        try:
            return config.load(cfg_path).control_socket()
        except ConfigError as exc:
            # Edited with a mistake while the daemon runs on the config it loaded before (its
            # reload refused): say so, and still ask the socket the file names.
            socket = config.control_socket_of(cfg_path)
            if socket is None:
                raise
            print(f"mapd: warning: {exc} (asking {socket}, which it names)", file=sys.stderr)
            return socket
    return Path("/run/mapd/mapd.sock")


def cmd_status(args: argparse.Namespace) -> int:
    from mapd.commands.status_text import render_status
    from mapd.daemon.status_socket import query
    from mapd.errors import DaemonError

    path = _socket_path(args)
    while True:
        try:
            doc = query(path)
        except DaemonError as exc:
            if not args.watch:
                raise
            # Watching through a restart (or before the daemon is up): say why, and keep watching.
            if not args.json:
                print("\033[2J\033[H", end="")
            print(f"mapd: {exc} (watching: trying again in {args.watch:g} s)", flush=True)
            time.sleep(args.watch)
            continue
        if args.json:
            print(json.dumps(doc, indent=2))
        else:
            if args.watch:
                print("\033[2J\033[H", end="")
            try:
                text = render_status(doc)
            except (AttributeError, TypeError, IndexError, KeyError, ValueError) as exc:
                # a daemon of another mapd version, most likely: say so, not a traceback
                raise DaemonError(
                    f"the daemon at {path} sent a status this mapd cannot show ({type(exc).__name__}: "
                    f"{exc}); 'mapd status --json' prints it as sent"
                ) from None
            print(text)
        if not args.watch:
            return 0
        sys.stdout.flush()
        time.sleep(args.watch)


def cmd_demo(args: argparse.Namespace) -> int:
    from mapd.demo.fleet import run_demo

    return run_demo(args)
