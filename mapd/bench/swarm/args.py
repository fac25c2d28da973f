"""``mapd bench swarm``'s options: fleet sizes, codecs, MACs, the channel, the daemon settings to sweep.

Numbers are bounded while parsing, so a bad one is one usage line before any stream is made: fleet
sizes to what one channel holds (link ids 1..254), times to at most :data:`MAX_SIM_S` of sim time,
building sides to what ``[source.sim]`` takes. ``--range`` is the exception: it keeps ``inf`` (all
in range), so :func:`~mapd.bench.swarm.run.run` refuses one not above 0. ``--lend``, ``--fec`` and
``--hold`` take ``on``, ``off`` or both, to run a daemon setting both ways.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from mapd.bench.common import MAX_SEED, UWB_MAX_BPS, UWB_MIN_BPS, float_arg, int_arg

#: Sim seconds a run makes versions (or drains) for at most: 64 robots take minutes for the default
#: 600, and each robot's streams are simulated ahead for all of it.
MAX_SIM_S = 3600.0
#: A building's sides (m), as ``[source.sim] width_m`` and ``height_m`` take them.
BUILDING_M = (6.0, 500.0)
#: Fleet sizes one channel holds: link ids 1..254, two robots at least to share anything.
ROBOTS = int_arg(2, 254)
PROBABILITY = float_arg(0.0, 1.0)
SEED = int_arg(0, MAX_SEED)


def _size(text: str) -> tuple[float, float]:
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not WxH in metres (e.g. 60x40)") from None
    low, high = BUILDING_M
    if not (low <= w <= high and low <= h <= high):  # NaN fails too
        raise argparse.ArgumentTypeError(f"'{text}': each side must be {low:g} to {high:g} m")
    return w, h


def _on_off(p: argparse.ArgumentParser, flag: str, text: str) -> None:
    """A daemon setting the bench can run both ways (``on``, ``off`` or both; default on)."""
    p.add_argument(flag, nargs="+", default=["on"], choices=["on", "off"], help=text)


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--sim",
        type=SEED,
        metavar="SEED",
        default=None,
        help="drive the simulator's building (default seed 7)",
    )
    src.add_argument("--log", type=Path, default=None, help="robots replay slices of this CARMEN log")
    p.add_argument(
        "--robots",
        type=ROBOTS,
        nargs="+",
        default=[2, 4, 8, 16, 32, 64],
        help="fleet sizes (default 2 .. 64)",
    )
    p.add_argument(
        "--codec",
        nargs="+",
        default=["lossless"],
        help="codecs (default lossless; deltas when the codec takes a base)",
    )
    p.add_argument(
        "--mac",
        nargs="+",
        default=["tdma"],
        choices=["tdma", "backoff", "none"],
        help="medium access (default tdma)",
    )
    p.add_argument(
        "--period",
        type=float_arg(1.0, MAX_SIM_S),
        default=30.0,
        help="seconds between map versions (default 30, as the paper)",
    )
    p.add_argument(
        "--duration",
        type=float_arg(1.0, MAX_SIM_S),
        default=600.0,
        help=f"seconds during which versions are made, 1 to {MAX_SIM_S:g} (default 600)",
    )
    p.add_argument(
        "--drain",
        type=float_arg(0.0, MAX_SIM_S),
        default=300.0,
        help="then at most this long to converge (default 300)",
    )
    p.add_argument(
        "--rate",
        type=float_arg(UWB_MIN_BPS, UWB_MAX_BPS),
        default=12_500.0,
        help=f"channel bit/s, {UWB_MIN_BPS} to {UWB_MAX_BPS} (default 12500)",
    )
    p.add_argument("--loss", type=PROBABILITY, default=0.0, help="per-frame loss probability (default 0)")
    p.add_argument(
        "--range",
        dest="range_m",
        type=float,
        nargs="+",
        default=[math.inf],
        help="radio range in m of line-of-sight distance; several: a run each (default: all in range)",
    )
    p.add_argument(
        "--wall-loss", type=PROBABILITY, default=0.0, help="extra loss per wall crossed (default 0)"
    )
    p.add_argument(
        "--building",
        type=_size,
        default=(30.0, 20.0),
        metavar="WxH",
        help="sim building size in m (default 30x20)",
    )
    p.add_argument(
        "--scan-rate",
        type=float_arg(0.1, 50.0),  # [source.sim] scan_rate's top; 0 divided by zero
        default=1.0,
        help="sim lidar scans per second, 0.1 to 50 (default 1)",
    )
    p.add_argument(
        "--unsigned",
        action="store_true",
        help="frames without the link key's 12-byte trailer (fleets sign by default)",
    )
    p.add_argument(
        "--relay",
        default="none",
        choices=["none", "flood", "summary"],
        help="relay policy hook (default none: today's daemon)",
    )
    p.add_argument(
        "--acks",
        default="configured",
        choices=["configured", "up"],
        help="who must ack a map (default: every configured robot)",
    )
    p.add_argument(
        "--ack-mode",
        nargs="+",
        default=["auto"],
        choices=["auto", "each", "nack"],
        help="how receivers ack (transports.uwb acks; default auto: NACKs for broadcast maps)",
    )
    _on_off(
        p,
        "--lend",
        "tdma: an owner lends the rest of an idle slot to a robot with chunks left "
        "(transports.uwb lend, R17; default on, the daemon's)",
    )
    _on_off(
        p,
        "--fec",
        "broadcast maps repaired with parity chunks, each of use to every receiver lacking "
        "any chunk of its block (transports.uwb fec; default on, the daemon's)",
    )
    _on_off(
        p,
        "--hold",
        "the publisher supersedes a map only once it is wholly on the air "
        "(P1 on a paced link, as the daemon's uwb; default on)",
    )
    p.add_argument(
        "--arrival",
        nargs="+",
        default=["offer"],
        choices=["offer", "ask", "none"],
        help="when a robot comes into range: offer it the newest map if no map on its way reaches "
        "it (P6, the daemon's uwb; default), ask it for a keyframe if none of its maps came yet (the "
        "daemon before P6), or nothing",
    )
    p.add_argument(
        "--guard-ms",
        type=float_arg(0.0, 1000.0),
        default=10.0,
        help="tdma: quiet time at the end of each slot, added to the default slot (default 10, the "
        "daemon's guard_ms)",
    )
    p.add_argument(
        "--clock-skew",
        type=float_arg(0.0, 3_600_000.0),
        nargs="+",
        default=[0.0],
        metavar="MS",
        help="how far the robots' clocks disagree, in ms: each is off by a seeded draw within half "
        "of it either way (TDMA counts its slots on them; default 0, one clock); several: a run each",
    )
    p.add_argument(
        "--clock",
        choices=["radio", "system"],
        nargs="+",
        default=["radio"],
        help="tdma: the clock the turns are counted on, as the daemon's [transports.uwb] clock: radio "
        "(default: with --clock-skew the robots agree one over the radio; without, every robot's clock "
        "is taken as kept by a time service and no TIME frame is sent) or system (each robot's own "
        "clock, skewed or not); several: a run each",
    )
    p.add_argument(
        "--slot-ms",
        type=float_arg(1.0, 60_000.0),  # 0 divided by zero; each slot is simulated, so not much finer
        default=None,
        help="tdma slot per robot (default the daemon's: 4 full frames + 10 ms guard, 583 ms at 12.5 kb/s)",
    )
    p.add_argument(
        "--inflight-s",
        type=float_arg(1.0, MAX_SIM_S),
        default=30.0,
        help="publisher's in-flight timeout (default 30, the daemon's; 5 s per peer if longer)",
    )
    p.add_argument(
        "--keyframe-every",
        type=int_arg(1),
        default=None,
        metavar="K",
        help="a keyframe every K coded versions at least (default: the daemon's [codec] keyframe_every)",
    )
    p.add_argument(
        "--bound",
        action="store_true",
        help="also run the optimistic bound (one scheduler that knows everything: the daemon's TDMA "
        "turns, one sender at a time, spatial reuse, no channel limit) on the same fleet and "
        "channel: a second table",
    )
    p.add_argument(
        "--seed",
        type=SEED,
        nargs="+",
        default=[0],
        help="radio, backoff, session and start-phase seed; several: a row each, then their mean "
        "(a few pairs decide a small fleet's p95, so one seed's figure is noisy)",
    )
    p.add_argument(
        "--plot",
        type=Path,
        default=None,
        metavar="PNG",
        help="also draw p95 staleness against range (several --range) or fleet size, beside the "
        "bound's schedules (--bound)",
    )
    p.add_argument(
        "--target",
        type=float_arg(0.0, 1000.0),
        default=None,
        metavar="PERIODS",
        help="with --plot: the goal, as a horizontal line",
    )
    p.add_argument(
        "--cache",
        type=Path,
        default=Path("out/swarm-cache"),
        help="streams and payload sizes (default out/swarm-cache)",
    )
