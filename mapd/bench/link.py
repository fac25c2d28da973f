"""Goodput of the UWB transport through the fault relay (socat ptys, emulated 12.5 kb/s).

Scenarios, each a fresh relay and two fresh endpoints in this process:

* ``line``   the baseline: the message written straight into the relay, no framing and no ARQ; what
             the emulated line itself carries (the ceiling any protocol is measured against);
* ``clean``  the transport on a clean link (target: goodput >= 85 % of the link rate);
* ``faulty`` 2 % frame loss both ways, 1e-4 bit flips per byte and a 1 s outage 5 s in (target: delivered
             intact, goodput >= 60 % of the link rate);
* ``signed`` the clean link with the fleet's link key (every frame carries a 6-byte counter and a
             6-byte tag, and no CRC): how deployed fleets run, signed by default (target: goodput >= 85 %).
* ``poses``  the signed link with both robots sending signed pose messages every ``--pose-period``
             seconds (stream 254, background): the same map's goodput (poses must yield to maps),
             and the bytes per second poses cost on an idle link, over the HELLOs it sends anyway.

Goodput is the message's bytes over the time from ``send`` to the receiver's verified COMPLETE
acknowledgement reaching the sender.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

from mapd.bench.common import DAY_S, MAX_SEED, UWB_MAX_BPS, UWB_MIN_BPS, float_arg, int_arg
from mapd.tables import emit, table

HELP = "UWB transport goodput through the fault relay at 12.5 kb/s: clean, faulty, vs the raw line"
SCENARIOS = ("line", "clean", "faulty", "signed", "poses")
TARGETS = {"clean": 0.85, "faulty": 0.60, "signed": 0.85, "poses": 0.85}
#: The terminal's table.
COLUMNS = [
    ("scenario", "scenario", ""),
    ("intact", "intact", ""),
    ("seconds", "s", ".1f"),
    ("goodput_bps", "goodput b/s", ".0f"),
    ("of_rate", "x link rate", ".3f"),
    ("of_line", "x raw line", ".3f"),
    ("target", "target", ""),
    ("met", "met", ""),
    ("chunk", "data B/frame", ""),
    ("overhead", "other B/frame", ""),
    ("bytes_tx", "bytes tx", ""),
    ("resends", "resends", ""),
    ("timeouts", "RTOs", ""),
    ("damaged", "damaged", ""),
    ("duplicates", "dups", ""),
    ("acks", "acks", ""),
    ("rtt_ms", "RTT ms", ".0f"),
    ("peak_bps_1s", "peak b/s (1 s)", ".0f"),
    ("pose_bps", "pose b/s per robot", ".0f"),
    ("faults", "relay faults", ""),
]


def _size_arg(text: str) -> int:
    """``--size``: 1 byte to the most one uwb message carries (at 12.5 kb/s, three hours); the
    bound is imported when the option is given, as it comes with pydantic."""
    from transports.uwb.options import MAX_MESSAGE

    return int_arg(1, MAX_MESSAGE)(text)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size", type=_size_arg, default=50_000, help="message size in bytes (default 50000)")
    p.add_argument(
        "--rate-bps",
        type=float_arg(UWB_MIN_BPS, UWB_MAX_BPS),
        default=12500.0,
        help=f"emulated link rate, {UWB_MIN_BPS} to {UWB_MAX_BPS} (default 12500)",
    )
    p.add_argument("--seed", type=int_arg(0, MAX_SEED), default=1, help="fault seed, 0 or more (default 1)")
    p.add_argument(
        "--scenarios",
        nargs="+",
        choices=SCENARIOS,
        default=["line", "clean", "signed", "faulty"],
        help="which to run (default: line clean signed faulty)",
    )
    p.add_argument(
        "--outage-at", type=float_arg(0.0, DAY_S), default=5.0, help="faulty: outage start, s (default 5)"
    )
    # Faster than ten poses a second only floods the link (and 0 was a busy loop).
    p.add_argument(
        "--pose-period",
        type=float_arg(0.1, 3600.0),
        default=5.0,
        help="poses: seconds between poses, 0.1 to 3600 (default 5)",
    )
    p.add_argument(
        "--idle", type=float_arg(1.0, DAY_S), default=60.0, help="poses: idle seconds measured (default 60)"
    )


async def _line(size: int, rate: float, seed: int) -> dict[str, Any]:
    """Baseline: raw bytes through the relay, timed from the write to the last byte read."""
    import asyncio

    import serial_asyncio

    from transports.uwb.relay import FaultRelay

    data = os.urandom(size)
    got = bytearray()
    done = asyncio.Event()

    class Sink(asyncio.Protocol):
        def data_received(self, chunk: bytes) -> None:
            got.extend(chunk)
            if len(got) >= size:
                done.set()

    loop = asyncio.get_running_loop()
    async with FaultRelay(rate_bps=rate, seed=seed) as relay:
        rx, _ = await serial_asyncio.create_serial_connection(loop, Sink, relay.ports[1], baudrate=115200)
        tx, _ = await serial_asyncio.create_serial_connection(
            loop, asyncio.Protocol, relay.ports[0], baudrate=115200
        )
        t0 = loop.time()
        tx.write(data)
        await asyncio.wait_for(done.wait(), 10 + 3 * size * 8 / rate)
        dt = loop.time() - t0
        tx.abort()
        rx.abort()
        stats = relay.stats()
    return {
        "intact": bytes(got) == data,
        "seconds": dt,
        "bytes_tx": size,
        "chunk": "-",
        "overhead": "-",
        "relay": stats,
    }


async def _arq(
    size: int,
    rate: float,
    seed: int,
    scenario: str,
    outage_at: float,
    pose_period: float = 5.0,
    idle_s: float = 60.0,
) -> dict[str, Any]:
    import asyncio

    from transports.uwb import arq
    from transports.uwb.faults import Faults
    from transports.uwb.link import UwbLink
    from transports.uwb.relay import FaultRelay

    faults = Faults()
    if scenario == "faulty":
        faults = Faults(drop=0.02, flip=1e-4, outages=((outage_at, 1.0),))
    key = os.urandom(32) if scenario in ("signed", "poses") else None
    data = os.urandom(size)
    received: list[bytes] = []
    closed: asyncio.Future[str] = asyncio.get_running_loop().create_future()
    up = asyncio.Event()
    watch: list[int] = []  # the map's message id (poses close too, on their own stream)

    def on_a(e: arq.Event) -> None:
        if isinstance(e, arq.PeerUp):
            up.set()
        if isinstance(e, arq.MessageClosed) and e.msg in watch and not closed.done():
            closed.set_result(e.outcome)

    def on_b(e: arq.Event) -> None:
        if isinstance(e, arq.MessageReceived) and e.stream == 0:
            received.append(e.data)

    deadline = 20 + 4 * size * 8 / rate
    async with FaultRelay(rate_bps=rate, faults=faults, seed=seed) as relay:
        cfg_a = arq.ArqConfig(node_id=1, rate_bps=rate, deadline_s=deadline, key=key)
        cfg_b = arq.ArqConfig(node_id=2, rate_bps=rate, deadline_s=deadline, key=key)
        a = UwbLink(cfg_a, relay.ports[0], on_event=on_a)
        b = UwbLink(cfg_b, relay.ports[1], on_event=on_b)
        await a.start()
        await b.start()
        posing = None
        try:
            await asyncio.wait_for(up.wait(), 10)
            loop = asyncio.get_running_loop()
            pose_bps = None
            if scenario == "poses":
                posing = asyncio.create_task(_send_poses([(a, 1, "robot0"), (b, 2, "robot1")], pose_period))
                pose_bps = await _idle_cost(a, b, idle_s, pose_period)
            t0 = loop.time()
            relay.rebase(t0)  # scheduled outages count from the send, not from the relay's start
            watch.append(a.send(data, [2]))
            outcome = await closed
            dt = loop.time() - t0
            await asyncio.sleep(0.2)
            sa, sb = a.stats(), b.stats()
            assert a.core is not None
            chunk = a.core.chunk_size
        finally:
            if posing is not None:
                posing.cancel()
            await a.close()
            await b.close()
        rstats = relay.stats()
    return {
        "intact": outcome == "delivered" and received == [data],
        "seconds": dt,
        "bytes_tx": sa["bytes_tx"],
        "resends": sa["resends"],
        "timeouts": sa["timeouts"],
        # frames that failed their check: the CRC on an unkeyed link, the tag on a keyed one
        "damaged": sum(s.get(k, 0) for s in (sa, sb) for k in ("crc_errors", "bad_signature")),
        "duplicates": sb["duplicates"],
        "rtt_ms": sa["rtt_ms"],
        "peak_bps_1s": sa["write_peak_bps_1s"],
        "acks": sb["acks_tx"],
        "chunk": chunk,
        "overhead": cfg_a.max_frame - chunk,  # header, signature trailer, CRC and COBS at most
        "relay": rstats,
        "pose_bps": pose_bps,
    }


async def _send_poses(links: list[tuple[Any, int, str]], period: float) -> None:
    """Each link's robot sends a signed pose message every ``period`` s, as the daemon does."""
    import asyncio
    import time

    from mapd.grid import Pose2D
    from mapd.identity import Identity
    from mapd.poses import PoseMessage
    from transports.uwb.link import POSE_STREAM

    ids = {name: Identity.generate(name) for _, _, name in links}
    while True:
        for link, node, name in links:
            msg = PoseMessage("demo", name, time.time(), Pose2D(12.345, -6.789, 1.234)).signed(ids[name])
            peer = 2 if node == 1 else 1
            link.send(
                msg.pack(), [peer], stream=POSE_STREAM, deadline_s=2 * period, background=True, reliable=False
            )
        await asyncio.sleep(period)


async def _idle_cost(a: Any, b: Any, idle_s: float, period: float) -> float:
    """Bits per second per robot the poses add on an idle link: the bytes both sides wrote over
    ``idle_s``, less what HELLO beacons alone cost (a beacon goes after ``beacon_s`` without sending).
    Poses go as unacknowledged DGRAM frames, as the daemon sends them."""
    import asyncio

    from transports.uwb import wire
    from transports.uwb.framing import cobs_max_len
    from transports.uwb.signing import TRAILER_LEN

    await asyncio.sleep(1.0)  # the first poses are on their way
    before = a.stats()["bytes_tx"] + b.stats()["bytes_tx"]
    await asyncio.sleep(idle_s)
    spent = a.stats()["bytes_tx"] + b.stats()["bytes_tx"] - before
    hello = cobs_max_len(wire.HEADER_LEN + TRAILER_LEN) + 1
    beacon_s = a.core.cfg.beacon_s
    beacons = 2 * hello * idle_s / max(beacon_s, period)  # what the two robots send anyway
    return 8 * max(0.0, spent - beacons) / idle_s / 2


def run(args: argparse.Namespace) -> int:
    import asyncio

    rows: list[dict[str, Any]] = []
    line_bps: float | None = None
    for sc in args.scenarios:
        if sc == "line":
            r = asyncio.run(_line(args.size, args.rate_bps, args.seed))
        else:
            r = asyncio.run(
                _arq(args.size, args.rate_bps, args.seed, sc, args.outage_at, args.pose_period, args.idle)
            )
        r["scenario"] = sc
        r["goodput_bps"] = 8 * args.size / r["seconds"]
        r["of_rate"] = r["goodput_bps"] / args.rate_bps
        if sc == "line":
            line_bps = r["goodput_bps"]
        r["of_line"] = r["goodput_bps"] / line_bps if line_bps else float("nan")
        target = TARGETS.get(sc)
        r["target"] = f">= {target:.2f}" if target else "-"
        r["met"] = ("yes" if r["intact"] and r["of_rate"] >= target else "NO") if target else "-"
        rs = r["relay"]
        r["faults"] = f"drop {rs['dropped']} cut {rs['cut']} flip {rs['flipped_bits']}"
        rows.append(r)
        print(f"  {sc}: {r['seconds']:.1f} s", flush=True) if not args.json else None
    doc = {"size": args.size, "rate_bps": args.rate_bps, "seed": args.seed, "rows": rows}
    emit(doc, args.json, lambda: _text(args, rows))
    return 0 if all(r["intact"] for r in rows) else 1


def _text(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """The terminal's table, one row per scenario, under a line of the settings."""
    head = f"\nmapd bench link: {args.size} bytes at {args.rate_bps:.0f} b/s, seed {args.seed}"
    return f"{head}\n{table(rows, COLUMNS)}"
