"""A robot in its own process, driving one ZenohTransport, for the multi-process tests.

    python zenoh_robot_proc.py --robot a --listen tcp/127.0.0.1:7447 [--connect ...] [--fleet-seed HEX]

It runs the transport inside an asyncio loop with SIGTERM/SIGINT handling that calls ``close()``
(the shape of the daemon), prints one JSON line per event on stdout, and takes JSON commands on
stdin, one a line: ``{"offer": [version, base]}``, ``{"ack": ["robot", version]}``,
``{"stats": true}``, ``{"quit": true}``. Received updates are acked like
the daemon would after a successful decode.
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import json
import signal
import sys
import threading
from typing import Any

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mapd.envelope import Envelope, unpack
from mapd.grid import Pose2D
from mapd.identity import Identity, Roster
from transports.base import Received, TransportContext, TransportEvent
from transports.zenoh.link import ZenohTransport

FLEET = "testfleet"


def say(**obj: Any) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def fleet_keys(robot: str, seed: str | None) -> tuple[Identity | None, Roster]:
    """Robots a, b and c with keys derived from ``seed`` (a test's fleet), or an unsigned fleet."""
    if seed is None:
        return None, Roster.open()
    ids = {
        r: Identity(
            r, Ed25519PrivateKey.from_private_bytes(hashlib.sha256(bytes.fromhex(seed) + r.encode()).digest())
        )
        for r in ("a", "b", "c")
    }
    return ids[robot], Roster({r: i.public_key for r, i in ids.items()})


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--robot", required=True)
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--fleet-seed", default=None, help="sign: every robot's key derives from this seed")
    args = ap.parse_args()
    identity, roster = fleet_keys(args.robot, args.fleet_seed)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    latest: dict[str, Envelope] = {}
    transport: ZenohTransport

    def emit(ev: TransportEvent) -> None:
        if isinstance(ev, Received):
            env = unpack(ev.data, roster=roster, fleet=FLEET)
            say(event="Received", peer=ev.peer, version=env.version, base=env.base_version)
            transport.ack(env.robot, env.version)
        else:
            say(event=type(ev).__name__, **{k: v for k, v in vars(ev).items() if k != "transport"})

    ctx = TransportContext(
        robot=args.robot,
        fleet=FLEET,
        identity=identity,
        roster=roster,
        max_message_bytes=1 << 20,
        emit=emit,
        latest_keyframe=lambda: latest.get("kf"),
    )
    opts = ZenohTransport.Options(multicast_scouting=False, listen=args.listen, connect=args.connect)
    transport = ZenohTransport(opts, ctx)
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    def command(line: str) -> None:
        cmd = json.loads(line)
        if "offer" in cmd:
            v, base = cmd["offer"]
            env = Envelope(
                fleet=FLEET,
                robot=args.robot,
                version=v,
                base_version=base,
                codec="raw",
                width=2,
                height=2,
                resolution=0.05,
                origin=Pose2D(0.0, 0.0, 0.0),
                payload=bytes(4),
                seq=v,
            )
            env = env.signed(identity) if identity else env
            if env.is_keyframe:
                latest["kf"] = env
            transport.offer(env)
        elif "ack" in cmd:
            transport.ack(*cmd["ack"])
        elif "stats" in cmd:
            say(event="stats", peer_list=transport.peers(), **transport.stats())
        elif "quit" in cmd:
            stop.set()

    def read_stdin() -> None:
        for line in sys.stdin:
            if line.strip():
                loop.call_soon_threadsafe(command, line)

    await transport.start()
    threading.Thread(target=read_stdin, daemon=True).start()
    say(event="ready")
    await stop.wait()
    await transport.close()
    say(event="closed")
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
