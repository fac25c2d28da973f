"""Loopback TCP ports for the demo fleet, the benches and the tests: free, and staying free.

The usual trick, bind port 0 and close, hands out a port from the kernel's *ephemeral* range,
the same range every outgoing connection takes its local port from. Between that pick and the
daemon's own bind, any process's ``connect`` may take the port, and the daemon then fails with
"Address already in use" (seen in CI, where three test workers open zenoh sessions all the
time). A port below the ephemeral range is only ever taken by an explicit bind, so picking
there, at random so that parallel callers rarely meet, leaves only the small chance that two
callers pick the same port at the same moment.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

#: Linux's default ephemeral range, used where ``/proc`` does not tell.
DEFAULT_EPHEMERAL = (32768, 60999)
#: The lowest port picked: above the registered services most hosts run.
LOWEST = 20000
_TRIES = 200
_random = random.SystemRandom()


def ephemeral_range(path: Path = Path("/proc/sys/net/ipv4/ip_local_port_range")) -> tuple[int, int]:
    """The kernel's range for outgoing connections' local ports."""
    try:
        lo, hi = (int(x) for x in path.read_text().split())
    except (OSError, ValueError):
        return DEFAULT_EPHEMERAL
    return (lo, hi) if 0 < lo <= hi < 65536 else DEFAULT_EPHEMERAL


def _bindable(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def free_port() -> int:
    """A loopback TCP port that nothing holds now and no outgoing connection will take."""
    lo, hi = ephemeral_range()
    # The widest stretch outside the ephemeral range (below it on Linux's defaults).
    below, above = (LOWEST, lo - 1), (hi + 1, 65535)
    first, last = max(below, above, key=lambda r: r[1] - r[0])
    if last - first >= 1000:
        for _ in range(_TRIES):
            port = _random.randint(first, last)
            if _bindable(port):
                return port
    with socket.socket() as s:  # no room outside the range (a tuned host): the kernel's pick
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_ports(n: int) -> list[int]:
    """``n`` distinct :func:`free_port` ports (nothing holds a port until it is bound, so two draws
    could otherwise be the same one)."""
    ports: list[int] = []
    while len(ports) < n:
        port = free_port()
        if port not in ports:
            ports.append(port)
    return ports


def free_endpoint() -> str:
    """:func:`free_port` as a zenoh endpoint, ``tcp/127.0.0.1:PORT``."""
    return f"tcp/127.0.0.1:{free_port()}"
