"""``mapd bench swarm``: the loop over fleet sizes, codecs and MACs, and the table (options: ``args``)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import TYPE_CHECKING, Any

from mapd.tables import emit, table

if TYPE_CHECKING:
    from mapd.bench.swarm.sim import SwarmConfig
    from mapd.bench.swarm.streams import Fleet, Payloads

COLUMNS = [
    ("robots", "robots", ""),
    ("range_m", "range m", "g"),
    ("seed", "seed", ""),
    ("codec", "codec", ""),
    ("mac", "mac", ""),
    ("ack_mode", "acks", ""),
    ("lend", "lend", ""),
    ("fec", "fec", ""),
    ("hold", "hold", ""),
    ("arrival", "arrival", ""),
    ("clock_skew_ms", "skew ms", "g"),
    ("clock", "clock", ""),
    ("stale_p50_s", "stale p50 s", ".1f"),
    ("stale_p95_s", "p95 s", ".1f"),
    ("stale_max_s", "max s", ".0f"),
    ("stale_p95_periods", "p95 periods", ".2f"),
    ("stale_p95_reach_s", "p95 reach s", ".1f"),
    ("never_in_range", "never in range", ".0%"),
    ("converge_s", "converge s", ".0f"),
    ("channel_use", "channel use", ".2f"),
    ("coded_share", "coded load", ".3f"),
    ("ack_share", "ack %", ".0%"),
    ("bps_per_robot", "bit/s/robot", ".0f"),
    ("x_coded", "x coded", ".1f"),
    ("collided", "collided", ""),
    ("out_of_turn", "out of turn", ""),
    ("time_frames", "TIME frames", ""),
    ("lost", "lost", ""),
    ("degree", "hears", ".1f"),
    ("robot_hears_all", "hears all", ".1%"),
    ("versions", "versions", ""),
    ("keyframes", "keyframes", ""),
    ("deltas", "deltas", ""),
    ("accepted", "maps accepted", ""),
    ("relayed", "relays", ""),
    ("borrowed", "slots lent", ""),
    ("wall_s", "wall s", ".1f"),
]
#: The bound's table (``--bound``): the same staleness figures, and how the scheduler used the slots.
BOUND_COLUMNS = [
    ("robots", "robots", ""),
    ("range_m", "range m", "g"),
    ("seed", "seed", ""),
    ("codec", "codec", ""),
    ("senders", "senders", ""),
    ("stale_p50_s", "stale p50 s", ".1f"),
    ("stale_p95_s", "p95 s", ".1f"),
    ("stale_max_s", "max s", ".0f"),
    ("stale_p95_periods", "p95 periods", ".2f"),
    ("converge_s", "converge s", ".0f"),
    ("busy_share", "slots used", ".2f"),
    ("senders_per_slot", "senders/slot", ".2f"),
    ("sends", "sends", ""),
    ("accepted", "maps accepted", ""),
    ("wall_s", "wall s", ".1f"),
]


def run(args: argparse.Namespace) -> int:
    from mapd.bench.swarm.metrics import summarize
    from mapd.bench.swarm.sim import Swarm, SwarmConfig
    from mapd.bench.swarm.streams import Payloads, load_fleet
    from mapd.codec.api import warm_up
    from mapd.errors import ConfigError, SourceError

    if args.log is not None and not args.log.exists():
        raise SourceError(f"{args.log}: no such log file")
    if args.plot is not None:  # before the runs, which may take an hour, not after
        try:
            args.plot.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"{args.plot}: cannot write the plot: {exc.strerror or exc}") from None
    # The other numbers are bounded while parsing; --range keeps inf (all in range, the default).
    if not all(r > 0 for r in args.range_m):
        raise SourceError(f"--range {' '.join(f'{r:g}' for r in args.range_m)}: each must be above 0 m")
    sim_seed = 7 if args.sim is None and args.log is None else args.sim
    rows: list[dict[str, Any]] = []
    bounds: list[dict[str, Any]] = []
    t_all = time.perf_counter()
    for name in dict.fromkeys(args.codec):
        warm_up(name)
    for n in args.robots:
        t0 = time.perf_counter()
        fleet = load_fleet(
            cache=args.cache, n=n, period=args.period, duration=args.duration,
            sim_seed=sim_seed if args.log is None else None, log=args.log,
            size=args.building, scan_rate=args.scan_rate,
        )  # fmt: skip
        print(f"swarm: {n} robots: streams ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        for codec in dict.fromkeys(args.codec):
            payloads = Payloads(args.cache, codec)
            combos = [
                (rg, m, a, le, f, h, ar, sk, ck, sd)
                for rg in dict.fromkeys(args.range_m)
                for m in args.mac
                for a in dict.fromkeys(args.ack_mode)
                for le in args.lend
                for f in args.fec
                for h in args.hold
                for ar in dict.fromkeys(args.arrival)
                for sk in dict.fromkeys(args.clock_skew)
                for ck in dict.fromkeys(args.clock)
                for sd in dict.fromkeys(args.seed)
            ]
            for range_m, mac, ack_mode, lend, fec, hold, arrival, skew, clock, seed in combos:
                cfg = SwarmConfig(
                    codec=codec, period=args.period, duration=args.duration, drain=args.drain,
                    rate_bps=args.rate, loss=args.loss, wall_loss=args.wall_loss, range_m=range_m,
                    mac=mac, signed=not args.unsigned, seed=seed, relay=args.relay, acks=args.acks,
                    slot_s=args.slot_ms / 1000.0 if args.slot_ms is not None else None,
                    inflight_s=args.inflight_s, ack_mode=ack_mode, lend=lend == "on", fec=fec == "on",
                    hold=hold == "on", arrival=arrival, clock_skew_s=skew / 1000.0, clock=clock,
                    guard_s=args.guard_ms / 1000.0,
                    **({"keyframe_every": args.keyframe_every} if args.keyframe_every else {}),
                )  # fmt: skip
                res = Swarm(fleet, payloads, cfg).run()
                payloads.flush()
                row = summarize(res)
                row["coded_share"] = row["coded_bps_per_robot"] * n / args.rate
                row["source"] = fleet.source
                row["range_m"] = range_m
                row["ack_mode"] = ack_mode
                row["lend"] = lend
                row["fec"] = fec
                row["hold"] = hold
                row["arrival"] = arrival
                row["seed"] = seed
                row["clock_skew_ms"] = skew
                row["clock"] = clock
                row["time_frames"] = sum(r.arq.counters.times_tx for r in res.robots)
                row["borrowed"] = sum(r.arq.counters.borrowed for r in res.robots)
                row["out_of_turn"] = sum(r.arq.counters.out_of_turn for r in res.robots)
                rows.append(row)
                print(
                    f"swarm: {n} robots, range {range_m:g} m, {codec}, {mac}, acks {ack_mode}, lend {lend}, "
                    f"fec {fec}, hold {hold}, arrival {arrival}, skew {skew:g} ms, clock {clock}, seed {seed}: "
                    f"{res.end:.0f} s simulated in {res.wall_s:.1f} s "
                    f"({res.events} events, {payloads.encodes} encodes)",
                    file=sys.stderr,
                )
                if args.bound and (mac, ack_mode, lend, fec, hold, arrival, skew, clock) == combos[0][1:9]:
                    bounds += _bounds(fleet, payloads, cfg)  # the bound ignores the publisher's settings

    def key(r: dict[str, Any]) -> tuple[str, ...]:
        return (*(r[k] for k in _SETTINGS), str(r["seed"]))

    base = {key(r): r for r in rows if r["robots"] == min(args.robots)}
    for r in rows:
        b = base.get(key(r))
        r["p95_x_smallest"] = r["stale_p95_s"] / b["stale_p95_s"] if b and b["stale_p95_s"] > 0 else math.nan
    if len(set(args.seed)) > 1:
        rows = with_means(rows, ("robots", *_SETTINGS))
        bounds = with_means(bounds, ("robots", "codec", "range_m", "senders"))
    info = {
        "source": rows[0]["source"] if rows else "",
        "period_s": args.period,
        "duration_s": args.duration,
        "drain_s": args.drain,
        "rate_bps": args.rate,
        "loss": args.loss,
        "range_m": args.range_m[0] if len(args.range_m) == 1 else list(args.range_m),
        "wall_loss": args.wall_loss,
        "signed": not args.unsigned,
        "relay": args.relay,
        "acks": args.acks,
        "slot_ms": args.slot_ms,
        "guard_ms": args.guard_ms,
        "inflight_s": args.inflight_s,
        "keyframe_every": args.keyframe_every or SwarmConfig().keyframe_every,
        "wall_s": time.perf_counter() - t_all,
    }
    emit({**info, "rows": rows, "bound": bounds}, args.json, lambda: _text(info, rows, bounds))
    if args.plot is not None and rows:
        from mapd.bench.swarm.plot import plot

        title = (
            f"{info['source']}: {', '.join(map(str, args.robots))} robots, a version every "
            f"{args.period:g} s, {args.rate:g} bit/s, {args.wall_loss:g} loss per wall"
        )
        plot(args.plot, rows, bounds, settings=_SETTINGS, title=title, target=args.target)
        print(f"swarm: plot written to {args.plot}", file=sys.stderr)
    return 0


#: What sets a row apart, besides its fleet size and seed.
_SETTINGS = (
    "range_m", "codec", "mac", "ack_mode", "lend", "fec", "hold", "arrival", "clock_skew_ms", "clock",
)  # fmt: skip


def with_means(rows: list[dict[str, Any]], keys: tuple[str, ...]) -> list[dict[str, Any]]:
    """``rows`` (one per seed), each group of equal ``keys`` followed by a row of their means
    (seed ``"mean"``; numbers averaged, also inside dicts and lists, an ``inf`` staying ``inf``, the
    rest as in the first)."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    out: list[dict[str, Any]] = []
    for group in groups.values():
        out += group
        mean = dict(group[0], seed="mean")
        for k in group[0]:
            if k != "seed" and k not in keys:
                mean[k] = _mean_of([g[k] for g in group])
        out.append(mean)
    return out


def _mean_of(values: list[Any]) -> Any:
    """The mean of numbers, of dicts key by key, of equally long lists item by item; else the first."""
    first = values[0]
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return sum(float(v) for v in values) / len(values)
    if all(isinstance(v, dict) and v.keys() == first.keys() for v in values):
        return {k: _mean_of([v[k] for v in values]) for k in first}
    if all(isinstance(v, list) and len(v) == len(first) for v in values):
        return [_mean_of([v[i] for v in values]) for i in range(len(first))]
    return first


def _bounds(fleet: Fleet, payloads: Payloads, cfg: SwarmConfig) -> list[dict[str, Any]]:
    """The bound's rows, one per schedule (:data:`~mapd.bench.swarm.bound.MODES`), for one fleet and codec."""
    from mapd.bench.swarm.bound import MODES, Bound, summarize_bound

    out = []
    for mode in MODES:
        res = Bound(fleet, payloads, cfg, mode).run()
        out.append({**summarize_bound(res, cfg), "range_m": cfg.range_m, "seed": cfg.seed})
        print(f"swarm: bound, {res.n} robots, {cfg.codec}, {mode}: {res.wall_s:.1f} s", file=sys.stderr)
    return out


def _text(info: dict[str, Any], rows: list[dict[str, Any]], bounds: list[dict[str, Any]]) -> str:
    ranges = info["range_m"] if isinstance(info["range_m"], list) else [info["range_m"]]
    rng = ", ".join("all in range" if math.isinf(r) else f"range {r:g} m" for r in ranges)
    rng += f", {info['wall_loss']:g} loss per wall"
    head = (
        f"{info['source']}: a version every {info['period_s']:g} s for {info['duration_s']:g} s, "
        f"{info['rate_bps']:g} bit/s shared, {rng}, frame loss {info['loss']:g}, "
        f"{'signed' if info['signed'] else 'unsigned'}, relay {info['relay']}, acks from {info['acks']} peers, "
        f"a keyframe every {info['keyframe_every']} versions at least; "
        f"{info['wall_s']:.0f} s wall"
    )
    text = f"{head}\n{table(rows, COLUMNS)}"
    if bounds:
        text += (
            "\n\nBound: one scheduler that knows every position and holding, no acks or control frames "
            "(mapd.bench.swarm.bound)\n" + table(bounds, BOUND_COLUMNS)
        )
    return text
