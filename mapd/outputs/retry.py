"""An output's zenoh session that found no router at start: tried again while the daemon runs.

The ``zenoh`` and ``ros2`` outputs open a session of their own. A base station whose router (or
rmw_zenohd) is not up yet must not stop the daemon for it, and an output has no way to stop the
daemon later, so it keeps trying, after a refusal too (systemd would restart the daemon into the
same tries), and says so in its stats: ``session_open`` and ``session_refusals``, which ``mapd
status`` and the STATUS= line show as FAULTS.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

from mapd.errors import TransportError, UnreachableError
from mapd.ros2.zenoh_config import open_when_reachable

log = logging.getLogger("mapd.outputs")


class SessionRetry:
    """The tries of one output (``what``: its name in the log), and what its stats say of them."""

    def __init__(self, what: str) -> None:
        self.what = what
        #: Why the session is not open yet (None: open, or never tried)
        self.unreached: str | None = None
        #: Tries a router answered and refused (a certificate, an ACL)
        self.refusals = 0
        self._task: asyncio.Task[Any] | None = None

    def begin(self, exc: UnreachableError, open_session: Callable[[], None]) -> None:
        """The first try found no router: run ``open_session`` (blocking, on a worker thread) again
        until it opens. It must itself close what it opened once the output closed."""
        self.unreached = self._said(exc)
        log.warning("%s; trying again (the daemon runs meanwhile)", self.unreached)
        self._task = asyncio.create_task(
            open_when_reachable(open_session, on_refusal=self._refused), name=f"{self.what}-retry"
        )

    def _refused(self, exc: TransportError) -> None:
        if self._said(exc) != self.unreached:
            log.warning("%s; trying again", self._said(exc))
        self.unreached = self._said(exc)
        self.refusals += 1

    def _said(self, exc: TransportError) -> str:
        """The error as the log says it: named after the output, once."""
        text = str(exc)
        return text if text.startswith(self.what) else f"{self.what}: {text}"

    def opened(self) -> None:
        """Called by ``open_session`` once the session is in use."""
        self.unreached = None
        log.info("%s: session open", self.what)

    async def stop(self) -> None:
        """Stop trying (a try under way on its thread ends on its own)."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task

    def stats(self) -> dict[str, int | float | str]:
        # False while no router answers (a FAULTS line in mapd status)
        return {"session_open": self.unreached is None, "session_refusals": self.refusals}
