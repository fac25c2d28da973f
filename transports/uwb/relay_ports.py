"""The fault relay's ports: socat pty pairs, and the relay's end of each robot's pair with its counts.

:class:`PtyPair` runs one ``socat`` that joins two pseudo-terminals, reachable at two symlinks: a
robot opens one as its serial device, and :class:`~transports.uwb.relay.FaultRelay` holds the other.
:class:`_Port` is the relay's state for one robot's pair (its descriptors, the bytes waiting for a
frame delimiter or for the pty to take them), and :class:`PortStats` what it counted there, the peak
input rate over any one second included.
"""

from __future__ import annotations

import asyncio
import shutil
from dataclasses import dataclass
from pathlib import Path

from mapd.errors import TransportError
from transports.uwb.pacing import ByteWindow


class PtyPair:
    """Two connected pseudo-terminals made by socat, reachable at ``a`` and ``b`` (symlinks)."""

    def __init__(self, a: Path, b: Path) -> None:
        self.a = a
        self.b = b
        self._proc: asyncio.subprocess.Process | None = None

    async def start(self, timeout: float = 5.0) -> None:
        exe = shutil.which("socat")
        if exe is None:
            raise TransportError("uwb relay: socat is not installed (apt-get install socat)")
        self._proc = await asyncio.create_subprocess_exec(
            exe,
            "-d",
            "-d",
            f"pty,raw,echo=0,link={self.a}",
            f"pty,raw,echo=0,link={self.b}",
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
        )
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        while not (self.a.exists() and self.b.exists()):
            if self._proc.returncode is not None or loop.time() > end:
                await self.stop()
                raise TransportError(f"uwb relay: socat did not make ptys {self.a} and {self.b}")
            await asyncio.sleep(0.01)

    async def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None or proc.returncode is not None:
            return
        proc.terminate()
        try:
            await asyncio.wait_for(proc.wait(), 2.0)
        except TimeoutError:
            proc.kill()
            await proc.wait()


@dataclass
class PortStats:
    bytes_in: int = 0
    frames_in: int = 0
    bytes_out: int = 0
    peak_in_bps_1s: float = 0.0


class _Port:
    """The relay's end of one robot's pty pair."""

    def __init__(self, index: int, robot_path: Path, relay_path: Path) -> None:
        self.index = index
        self.robot_path = robot_path
        self.relay_path = relay_path
        self.fd = -1
        self.hold_fd = -1
        self.pending = bytearray()
        self.flush_timer: asyncio.TimerHandle | None = None
        self.out = bytearray()
        self.stats = PortStats()
        self._arrivals = ByteWindow(1.0)

    def note_arrival(self, now: float, n: int) -> None:
        self._arrivals.add(n, now)
        self.stats.peak_in_bps_1s = 8.0 * self._arrivals.peak
