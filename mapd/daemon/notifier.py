"""What the daemon tells systemd (sd_notify): its state, the watchdog's pings, and the Status line.

``READY=1`` once it serves (a start cut short by a stop never says it), ``RELOADING=1`` then
``READY=1`` around a reload, ``STOPPING=1`` when a stop begins; ``WATCHDOG=1`` every half
``WatchdogSec``; and the Status line of ``systemctl status mapd`` (the map, the peers', the global
map and any fault, from :mod:`~mapd.daemon.headline`), said again only when it changes. Every
message goes through :class:`Notifier`, so the line systemd was last told is known in one place.
"""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections.abc import Callable
from typing import Any

from mapd.daemon.headline import status_line
from mapd.daemon.systemd import notify, watchdog_interval

log = logging.getLogger("mapd.daemon")
#: seconds between looks at whether the systemd Status line changed
STATUS_PERIOD_S = 2.0


class Notifier:
    """The daemon's side of sd_notify; ``snapshot()`` is what ``mapd status`` shows now."""

    def __init__(self, snapshot: Callable[[], dict[str, Any]]) -> None:
        self._snapshot = snapshot
        self._said = "running"  # the Status line systemd was last told

    def ready(self) -> None:
        """The daemon serves (started, or a reload done), with the Status line now.

        After a reload, READY=1 ends RELOADING=1; the Status line goes with it (not "running": the
        status loop says a line again only when it changes, so a steady robot's FAULTS would vanish).
        """
        notify(f"READY=1\nSTATUS={self.status_now()}")

    def reloading(self) -> None:
        """A reload begins (systemd waits for the READY=1 that ends it)."""
        notify(f"RELOADING=1\nMONOTONIC_USEC={time.monotonic_ns() // 1000}")

    def stopping(self) -> None:
        """A stop begins (during start-up, or of the running daemon)."""
        notify("STOPPING=1")

    async def watchdog(self) -> None:
        """Ping systemd's watchdog for as long as the loop runs, when the unit asks for it."""
        interval = watchdog_interval()
        if interval is None:
            return
        while True:
            notify("WATCHDOG=1")
            await asyncio.sleep(interval)

    async def keep_status(self) -> None:
        """Keep the Status line of ``systemctl status mapd`` current (sd_notify STATUS=): the map,
        the peers', the global map and any fault, said again only when it changes."""
        if not os.environ.get("NOTIFY_SOCKET"):
            return
        while True:
            await asyncio.sleep(STATUS_PERIOD_S)
            said = self._said
            line = self.status_now()
            if line != said:
                notify(f"STATUS={line}")

    def status_now(self) -> str:
        """The Status line for systemd now (remembered as said: every caller sends it)."""
        try:
            line = status_line(self._snapshot())
        except Exception:  # a status bug must never take the daemon down (as on the socket)
            log.exception("status line failed")
            line = self._said
        self._said = line
        return line
