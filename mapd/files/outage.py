"""A run of failed writes (a full disk) said in two log lines, not one a try, and counted.

Whoever writes carries on either way, and tries again every :data:`WRITE_RETRY_S` while nothing
newer comes to write; :class:`WriteOutage` keeps what ``mapd status`` shows of the outage.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

#: Seconds between tries of a write that failed (a full disk) while nothing newer comes to write: a
#: parked robot or a fleet at rest makes no new map, and the disk may have room again meanwhile.
WRITE_RETRY_S = 5.0


@dataclass
class WriteOutage:
    """A run of failed writes (a full disk) said in two lines, not one a try: the first failure as
    an error, and the first success after it. Whoever writes carries on either way.

    It also keeps what ``mapd status`` shows of it (:meth:`status`): whether writes fail now, since
    when, the last failure's line, and how many writes failed in all. With ``logger`` None nothing
    is logged (another part says the outage; this one only counts it).
    """

    logger: logging.Logger | None
    failing: bool = False
    #: Writes that failed, over the life of the writer (not only this outage).
    failures: int = 0
    #: Wall time of the first failure of the outage now (None: writes go through).
    since: float | None = None
    #: The last failure's line while failing (None: writes go through).
    error: str | None = None

    def failed(self, message: str) -> None:
        """A write failed: said once per outage (the first), counted every time."""
        self.failures += 1
        self.error = message
        if not self.failing:
            self.since = time.time()
            if self.logger is not None:
                self.logger.error("%s", message)
        self.failing = True

    def recovered(self, message: str) -> None:
        """A write went through: said when it ends an outage."""
        if self.failing and self.logger is not None:
            self.logger.info("%s", message)
        self.failing = False
        self.since = None
        self.error = None

    @contextlib.contextmanager
    def counted(self, failure: type[Exception]) -> Iterator[None]:
        """Count the write in the block: a ``failure`` out of it is a failed write (re-raised),
        getting through is a success. For an outage kept without a logger: whoever writes says it,
        with what it costs."""
        try:
            yield
        except failure as exc:
            self.failed(str(exc))
            raise
        self.recovered("")

    def status(self) -> dict[str, Any]:
        """For ``mapd status --json``: ``writing`` (False while writes fail), ``failures`` (in all),
        ``failing_s`` (how long the outage has lasted, or None) and ``error`` (its last line)."""
        since = self.since
        return {
            "writing": not self.failing,
            "failures": self.failures,
            "failing_s": None if since is None else round(max(0.0, time.time() - since), 1),
            "error": self.error,
        }
