"""Fleet benchmark: N real ``mapd run`` daemons over zenoh on loopback, each with a simulated robot.

For each fleet size it reports the update latency from publish (the sender encodes and offers an
update) to fused (a receiver's fusion worker has merged that version into its global map), at the
median and 95th percentile over every (sender, receiver, version); the bytes each robot sends per
second (its map payloads, and all it puts on the wire: updates, poses, acks and keyframe replies,
and of that its poses); and the CPU each daemon used per second of wall time. All daemons share this machine's
clock, so latencies need no clock sync. The single-robot-pair run (N = 2) is the baseline the
larger fleets are compared with, as ratios.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path
from typing import Any

from mapd.bench.common import DAY_S, MAX_SEED, MAX_SIM_ROBOTS, float_arg, int_arg
from mapd.tables import emit, table

HELP = "N daemons over zenoh on loopback (peers, or clients of one router): latency, bytes, CPU, memory"


def add_arguments(p: argparse.ArgumentParser) -> None:
    # A fleet is 2 robots at least (the latencies are between robots), at most what mapd demo runs.
    p.add_argument(
        "--robots",
        type=int_arg(2, MAX_SIM_ROBOTS),
        nargs="+",
        default=[2, 4, 8],
        help=f"fleet sizes, 2 to {MAX_SIM_ROBOTS} (default 2 4 8)",
    )
    p.add_argument(
        "--duration",
        type=float_arg(1.0, DAY_S),
        default=40.0,
        help="seconds per fleet size, 1 to 86400 (default 40)",
    )
    p.add_argument("--codec", default="lossless", help="codec (default lossless)")
    p.add_argument(
        "--seed", type=int_arg(0, MAX_SEED), default=7, help="building seed, 0 or more (default 7)"
    )
    p.add_argument("--out", type=Path, default=Path("out/bench-fleet"), help="work folder")
    p.add_argument(
        "--router",
        action="store_true",
        help="robots as zenoh clients of one router process (deploy/zenoh/router.json5) instead of peers",
    )


def _cpu_seconds(pid: int) -> float:
    """utime + stime of a live process from /proc (Linux)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def _rss_mb(pid: int) -> float:
    """Resident memory of a live process in MB, from /proc (Linux)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return float("nan")


def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _percentile(xs: list[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(xs, q)) if xs else float("nan")


def measure(n: int, args: argparse.Namespace) -> dict[str, Any]:
    from mapd.demo.fleet import Fleet

    fa = argparse.Namespace(
        robots=n,
        transport="zenoh",
        codec=args.codec,
        log=None,
        seed=args.seed,
        out=args.out / f"n{n}",
        duration=args.duration,
        router=args.router,
    )
    fleet = Fleet(fa)
    fleet.prepare()
    fleet.start()
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < args.duration:
            time.sleep(1.0)
            fleet.check_alive()
        # Once more at the end: a daemon that died in the last second left a table of 0 updates.
        fleet.check_alive()
        wall = time.monotonic() - t0
        cpu = {name: _cpu_seconds(p.pid) for name, p in fleet.procs.items()}
        rss = {name: _rss_mb(p.pid) for name, p in fleet.procs.items()}
        router_cpu = _cpu_seconds(fleet.router.pid) if fleet.router is not None else float("nan")
        router_rss = _rss_mb(fleet.router.pid) if fleet.router is not None else float("nan")
        snaps = fleet.status()
    finally:
        codes = fleet.stop()
    # One that died after the last check, or could not stop cleanly, measured nothing to trust.
    bad = {name: code for name, code in codes.items() if code != 0}
    if bad:
        from mapd.errors import DaemonError

        said = ", ".join(
            f"{name} ({'killed' if c is None else f'exit {c}'})" for name, c in sorted(bad.items())
        )
        raise DaemonError(
            f"fleet of {n}: daemons did not run to the end: {said}; see {fleet.run_dir}/*/daemon.log"
        )
    published: dict[tuple[str, int], float] = {}
    sent_bytes: dict[str, int] = {}
    for name in fleet.names:
        for r in _read_csv(fleet.run_dir / name / "state" / "updates.csv"):
            published.setdefault((name, int(r["version"])), float(r["time"]))
            sent_bytes[name] = sent_bytes.get(name, 0) + int(r["bytes"])
    latencies = []
    for name in fleet.names:
        for r in _read_csv(fleet.run_dir / name / "state" / "fused.csv"):
            key = (r["robot"], int(r["version"]))
            if r["robot"] != name and key in published:
                latencies.append(1000.0 * (float(r["time"]) - published[key]))
    links = [s.get("links", {}).get("zenoh", {}) for s in snaps.values()]
    tx = [link.get("bytes_tx", 0) for link in links]  # updates, poses, acks and keyframe replies
    pose_tx = [link.get("pose_bytes_tx", 0) for link in links]
    return {
        "robots": n,
        "latency_p50_ms": _percentile(latencies, 50),
        "latency_p95_ms": _percentile(latencies, 95),
        "samples": len(latencies),
        "payload_bps_per_robot": 8 * sum(sent_bytes.values()) / max(len(sent_bytes), 1) / wall,
        "wire_bps_per_robot": 8 * sum(tx) / max(len(tx), 1) / wall if tx else float("nan"),
        "pose_bps_per_robot": 8 * sum(pose_tx) / max(len(pose_tx), 1) / wall if pose_tx else float("nan"),
        "cpu_per_daemon": sum(cpu.values()) / len(cpu) / wall,
        "rss_mb_per_daemon": sum(rss.values()) / len(rss),
        "router_cpu": router_cpu / wall,
        "router_rss_mb": router_rss,
        # How late each daemon's event loop ran (mapd.daemon.loop_lag; the daemons share this
        # machine's cores, so it counts their waits for a core as well as work on the loop).
        "loop_p99_ms": _mean([_loop(s, "lag_ms_recent_p99") for s in snaps.values()]),
        "loop_max_ms": max([_loop(s, "lag_ms_max") for s in snaps.values()], default=float("nan")),
    }


def _loop(snap: dict[str, Any], key: str) -> float:
    """One figure of a daemon's ``loop`` status (NaN when it has none)."""
    v = (snap.get("loop") or {}).get(key)
    return float(v) if isinstance(v, int | float) else float("nan")


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else float("nan")


def run(args: argparse.Namespace) -> int:
    from mapd.codec.api import get_codec

    # Before any daemon starts, as bench codec, stream and swarm do: an unknown codec made every
    # daemon die at start, and a short run printed a table of 0 updates.
    get_codec(args.codec)
    rows = []
    for n in args.robots:
        print(f"fleet of {n}: running {args.duration:.0f} s ...", file=sys.stderr, flush=True)
        rows.append(measure(n, args))
    base = rows[0]
    for r in rows:
        for k in ("latency_p50_ms", "latency_p95_ms", "cpu_per_daemon", "payload_bps_per_robot"):
            r[f"{k}_x"] = r[k] / base[k] if base[k] else float("nan")
    emit(rows, args.json, lambda: _text(rows))
    return 0


def _text(rows: list[dict[str, Any]]) -> str:
    """The terminal's table: one row per fleet size, ratios against the first."""
    base = rows[0]["robots"]
    cols = [
        ("robots", "robots", ""),
        ("samples", "updates fused", ""),
        ("latency_p50_ms", "p50 ms", ".0f"),
        ("latency_p95_ms", "p95 ms", ".0f"),
        ("latency_p95_ms_x", f"p95 x N={base}", ".2f"),
        ("payload_bps_per_robot", "payload b/s/robot", ".0f"),
        ("wire_bps_per_robot", "wire b/s/robot", ".0f"),
        ("pose_bps_per_robot", "of it poses", ".0f"),
        ("cpu_per_daemon", "CPU/daemon", ".2f"),
        ("cpu_per_daemon_x", f"CPU x N={base}", ".2f"),
        ("rss_mb_per_daemon", "MB/daemon", ".0f"),
        ("loop_p99_ms", "loop p99 ms", ".0f"),
        ("loop_max_ms", "loop max ms", ".0f"),
    ]
    if any(r["router_cpu"] == r["router_cpu"] for r in rows):  # not NaN: a --router run
        cols += [("router_cpu", "router CPU", ".2f"), ("router_rss_mb", "router MB", ".0f")]
    note = f"(CPU/daemon is CPU seconds per wall second; this machine has {os.cpu_count()} cores)"
    return f"{table(rows, cols)}\n{note}"
