"""A seeded, rate-limited, fault-injecting relay between socat pty pairs: a bench radio channel.

Each robot gets a serial device path (a socat pty); the relay holds the other end of every pair and
carries bytes between them the way a slow, lossy radio would::

    robot A ── pty pair ── ┐            ┌── pty pair ── robot B
                           └─ relay ────┘
              12.5 kb/s per lane · drops · bit flips · duplicates · reordering · outages

The relay cuts the byte stream at 0x00 (the COBS delimiter) so that loss, duplication and reordering
act on whole frames; bit flips act per byte; an outage cuts whatever is on the line, mid-frame too.
With two robots each direction is its own lane (a full-duplex serial link). With three or more (or
``shared=True``) it is a broadcast medium: every frame reaches every other robot, and all robots share
one lane's airtime. With ``collisions=True`` frames are not queued for the medium: two of different
robots that overlap in the air are both garbled, as on a half-duplex radio without a MAC (each
robot's radio still sends its own frames one after another). ``out_of_range`` pairs of
robots never hear each other (a building's walls, distance): what one sends never reaches the other,
so maps between them can only go through a robot that hears both (the daemon's multi-hop relay).

Use it from code::

    async with FaultRelay(robots=2, rate_bps=12500, faults=Faults(drop=0.02), seed=1) as relay:
        port_a, port_b = relay.ports
        ...
        relay.cut(1.0)          # an outage starting now
        print(relay.stats())

or run one: ``python -m transports.uwb.relay --robots 2 --rate-bps 12500 --drop 0.02 --dir /tmp/uwb``.
The pty pairs and the relay's end of each are :mod:`transports.uwb.relay_ports`.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import sys
import tempfile
import tty
from collections.abc import Iterable
from dataclasses import asdict
from pathlib import Path
from types import TracebackType
from typing import Any

from mapd.errors import TransportError
from transports.uwb.faults import FaultInjector, Faults
from transports.uwb.relay_ports import PtyPair, _Port

_MAX_PENDING = 4096  # bytes without a delimiter before the relay forwards them anyway
_IDLE_FLUSH_S = 0.02  # and how long it waits for more before forwarding a tail without a delimiter


class FaultRelay:
    """Carries frames between robots' ptys at ``rate_bps`` with seeded faults (see module docs)."""

    def __init__(
        self,
        *,
        robots: int = 2,
        rate_bps: float = 12500.0,
        faults: Faults | None = None,
        seed: int = 0,
        shared: bool | None = None,
        collisions: bool = False,
        workdir: str | os.PathLike[str] | None = None,
        out_of_range: Iterable[tuple[int, int]] = (),
    ) -> None:
        if robots < 2:
            raise ValueError("a relay needs at least two robots")
        self.deaf = {(a, b) for a, b in out_of_range} | {(b, a) for a, b in out_of_range}
        if any(not (0 <= a < robots and 0 <= b < robots) or a == b for a, b in self.deaf):
            raise ValueError(f"out-of-range pairs must name two different robots of 0..{robots - 1}")
        self.unheard = 0
        self.robots = robots
        self.rate_bps = float(rate_bps)
        self.faults = faults or Faults()
        self.seed = seed
        self.shared = robots > 2 if shared is None else shared
        self.collisions = collisions
        self._workdir = Path(workdir) if workdir is not None else None
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._pairs: list[PtyPair] = []
        self._ports: list[_Port] = []
        self._inj: dict[tuple[int, int], FaultInjector] = {}
        self._busy: dict[int, float] = {}
        self._sending: dict[int, float] = {}  # collisions mode: when each robot's radio is free
        self._on_air: list[tuple[float, float, int, list[bool]]] = []
        self.collided = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._t0 = 0.0

    @property
    def ports(self) -> list[str]:
        """Device paths the robots open, in robot order."""
        return [str(p.robot_path) for p in self._ports]

    async def __aenter__(self) -> FaultRelay:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    async def start(self) -> None:
        """Make the pty pairs and start relaying."""
        self._loop = asyncio.get_running_loop()
        self._t0 = self._loop.time()
        if self._workdir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="uwb-relay-")
            base = Path(self._tmp.name)
        else:
            base = self._workdir
            base.mkdir(parents=True, exist_ok=True)
        try:
            for i in range(self.robots):
                port = _Port(i, base / f"robot{i}", base / f".relay{i}")
                for stale in (port.robot_path, port.relay_path):
                    with contextlib.suppress(FileNotFoundError):
                        stale.unlink()
                pair = PtyPair(port.robot_path, port.relay_path)
                await pair.start()
                self._pairs.append(pair)
                port.fd = os.open(port.relay_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
                tty.setraw(port.fd)
                # Holding the robot's side open keeps the pty alive while a robot closes and reopens it.
                port.hold_fd = os.open(port.robot_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
                self._ports.append(port)
                self._loop.add_reader(port.fd, self._readable, port)
        except BaseException:
            await self.stop()
            raise
        for i in range(self.robots):
            for j in range(self.robots):
                if i != j:
                    seed = (self.seed * 1_000_003 + i * 257 + j) & 0xFFFFFFFF
                    self._inj[(i, j)] = FaultInjector(self.faults, seed=seed, t0=self._t0)

    async def stop(self) -> None:
        """Stop relaying and remove the ptys."""
        loop = self._loop
        for port in self._ports:
            if port.flush_timer is not None:
                port.flush_timer.cancel()
            for fd in (port.fd, port.hold_fd):
                if fd >= 0:
                    if loop is not None:
                        loop.remove_reader(fd)
                        loop.remove_writer(fd)
                    with contextlib.suppress(OSError):
                        os.close(fd)
            port.fd = port.hold_fd = -1
        for pair in self._pairs:
            await pair.stop()
        self._pairs.clear()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def cut(self, duration: float, at: float | None = None) -> None:
        """An outage of ``duration`` seconds on every lane, starting now (or at loop time ``at``)."""
        assert self._loop is not None
        start = self._loop.time() if at is None else at
        for inj in self._inj.values():
            inj.cuts.append((start, start + duration))

    def rebase(self, t0: float | None = None) -> None:
        """Count the scheduled outages (``Faults.outages``) from loop time ``t0`` (default: now)."""
        assert self._loop is not None
        self._t0 = self._loop.time() if t0 is None else t0
        for inj in self._inj.values():
            inj.t0 = self._t0

    def stats(self) -> dict[str, Any]:
        """Per-port byte counts and peak input rate, and the fault counts summed over lanes."""
        totals: dict[str, int] = {}
        for inj in self._inj.values():
            for k, v in asdict(inj.stats).items():
                totals[k] = totals.get(k, 0) + v
        return {
            "rate_bps": self.rate_bps,
            "elapsed_s": round((self._loop.time() if self._loop else 0.0) - self._t0, 3),
            "ports": [{"port": p.robot_path.name, **asdict(p.stats)} for p in self._ports],
            "collided": self.collided,
            "unheard": self.unheard,
            **totals,
        }

    # --- relaying -------------------------------------------------------------------------------

    def _readable(self, port: _Port) -> None:
        assert self._loop is not None
        try:
            data = os.read(port.fd, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            return
        now = self._loop.time()
        port.stats.bytes_in += len(data)
        port.note_arrival(now, len(data))
        port.pending += data
        if port.flush_timer is not None:
            port.flush_timer.cancel()
            port.flush_timer = None
        while True:
            end = port.pending.find(0)
            if end < 0:
                if len(port.pending) > _MAX_PENDING:
                    self._flush_pending(port)
                elif port.pending:
                    port.flush_timer = self._loop.call_later(_IDLE_FLUSH_S, self._flush_pending, port)
                return
            frame = bytes(port.pending[: end + 1])
            del port.pending[: end + 1]
            port.stats.frames_in += 1
            self._launch(port.index, frame, now)

    def _flush_pending(self, port: _Port) -> None:
        """Forward bytes that no delimiter followed (raw traffic, or a frame cut by its writer)."""
        assert self._loop is not None
        port.flush_timer = None
        if port.pending:
            frame = bytes(port.pending)
            port.pending.clear()
            self._launch(port.index, frame, self._loop.time())

    def _launch(self, src: int, frame: bytes, now: float) -> None:
        assert self._loop is not None
        airtime = len(frame) * 8 / self.rate_bps
        lane = 0 if self.shared else src
        if self.collisions and self.shared:
            # A radio sends one frame at a time: a frame written while its own previous one is
            # still on the air starts when that one ends (only other robots' frames collide).
            start = max(now, self._sending.get(src, now))
            self._sending[src] = start + airtime
            flag = [False]
            for s0, e0, other, other_flag in self._on_air:
                if other != src and s0 < start + airtime and start < e0:
                    if not other_flag[0]:
                        other_flag[0] = True
                        self.collided += 1
                    if not flag[0]:
                        flag[0] = True
                        self.collided += 1
            self._on_air = [a for a in self._on_air if a[1] > now] + [(start, start + airtime, src, flag)]
        else:
            start = max(now, self._busy.get(lane, now))
            flag = [False]
        end = start + airtime
        self._busy[lane] = max(self._busy.get(lane, 0.0), end)
        for dst in range(self.robots):
            if dst == src:
                continue
            if (src, dst) in self.deaf:
                self.unheard += 1
                continue
            for delay, data in self._inj[(src, dst)].apply(frame, start, end):
                self._loop.call_at(end + delay, self._deliver, dst, data, flag)

    def _deliver(self, dst: int, data: bytes, collided: list[bool]) -> None:
        port = self._ports[dst]
        if port.fd < 0:
            return
        if collided[0]:
            data = bytes(b ^ 0x5A for b in data[:-1]) + data[-1:]  # garbled, delimiter kept
        port.out += data
        self._flush(port)

    def _flush(self, port: _Port) -> None:
        assert self._loop is not None
        try:
            n = os.write(port.fd, port.out)
        except BlockingIOError:
            n = 0
        except OSError:
            port.out.clear()
            return
        port.stats.bytes_out += n
        del port.out[:n]
        if port.out:
            self._loop.add_writer(port.fd, self._writable, port)

    def _writable(self, port: _Port) -> None:
        assert self._loop is not None
        self._loop.remove_writer(port.fd)
        self._flush(port)


class MediumRelay(FaultRelay):
    """A broadcast medium for three or more robots: one shared lane, every frame to every other robot."""

    def __init__(self, *, robots: int = 3, **kw: Any) -> None:
        kw.setdefault("shared", True)
        super().__init__(robots=robots, **kw)


def _outage(text: str) -> tuple[float, float]:
    try:
        start, dur = text.split(":")
        return float(start), float(dur)
    except ValueError:
        raise argparse.ArgumentTypeError(f"outage '{text}' is not START:SECONDS") from None


def parse_pair(text: str) -> tuple[int, int]:
    """``A-B`` for ``--out-of-range`` (here and in ``mapd demo``): two different robot indices >= 0."""
    try:
        a, b = (int(x) for x in text.split("-"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not A-B (two robot indices)") from None
    if a < 0 or b < 0 or a == b:
        raise argparse.ArgumentTypeError(f"'{text}': A and B must be two different robot indices >= 0")
    return a, b


def main(argv: list[str] | None = None) -> int:
    """``python -m transports.uwb.relay``: run a relay until interrupted, then print its stats."""
    p = argparse.ArgumentParser(prog="python -m transports.uwb.relay", description=__doc__.split("\n\n")[0])
    p.add_argument("--robots", type=int, default=2, help="robots on the channel (default 2)")
    p.add_argument("--rate-bps", type=float, default=12500.0, help="emulated link rate (default 12500)")
    p.add_argument("--drop", type=float, default=0.0, help="frame loss probability")
    p.add_argument("--dup", type=float, default=0.0, help="frame duplication probability")
    p.add_argument("--flip", type=float, default=0.0, help="bit-flip probability per byte")
    p.add_argument("--reorder", type=float, default=0.0, help="probability a frame arrives late")
    p.add_argument("--latency-ms", type=float, default=0.0, help="fixed one-way latency")
    p.add_argument("--outage", type=_outage, action="append", default=[], help="START:SECONDS (repeatable)")
    p.add_argument("--shared", action="store_true", help="one shared lane even for two robots")
    p.add_argument("--collisions", action="store_true", help="overlapping frames garble each other")
    p.add_argument(
        "--out-of-range",
        type=parse_pair,
        action="append",
        default=[],
        metavar="A-B",
        help="robots A and B (0-based) never hear each other (repeatable)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dir", type=Path, help="where to put the robots' pty links (default: a temp dir)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    args = p.parse_args(argv)
    faults = Faults(
        drop=args.drop,
        dup=args.dup,
        flip=args.flip,
        reorder=args.reorder,
        latency_s=args.latency_ms / 1000,
        outages=tuple(args.outage),
    )

    if any(max(pair) >= args.robots for pair in args.out_of_range):
        p.error(f"--out-of-range: robots are numbered 0..{args.robots - 1}")

    async def run() -> dict[str, Any]:
        relay = FaultRelay(
            robots=args.robots,
            rate_bps=args.rate_bps,
            faults=faults,
            seed=args.seed,
            shared=args.shared or None,
            collisions=args.collisions,
            workdir=args.dir,
            out_of_range=args.out_of_range,
        )
        await relay.start()
        for i, port in enumerate(relay.ports):
            print(f"robot {i}: {port}", flush=True)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), args.duration)
        stats = relay.stats()
        await relay.stop()
        return stats

    try:
        stats = asyncio.run(run())
    except TransportError as exc:
        print(f"relay: error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(stats, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
