"""systemd integration with the standard library only: sd_notify and journal-friendly logs."""

from __future__ import annotations

import logging
import os
import socket
import sys

log = logging.getLogger(__name__)


def notify(message: str) -> bool:
    """Send ``message`` (e.g. ``READY=1``) to ``$NOTIFY_SOCKET``; False when not under systemd."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]  # abstract namespace
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(message.encode())
        return True
    except OSError as exc:
        log.debug("sd_notify failed: %s", exc)
        return False


def watchdog_interval() -> float | None:
    """Seconds between ``WATCHDOG=1`` pings (half of ``WatchdogSec``), or None when not asked for."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        return max(int(usec) / 2e6, 0.05)
    except ValueError:
        return None


_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}


class JournalFormatter(logging.Formatter):
    """``<prio>logger: message key=value ...``: journald reads the ``<N>`` prefix as the priority.

    Extra structured fields passed as ``log.info("...", extra={"fields": {...}})`` are appended as
    ``key=value`` pairs so they are searchable with ``journalctl -g``.
    """

    def __init__(self, journal: bool) -> None:
        super().__init__()
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        fields = getattr(record, "fields", None)
        if isinstance(fields, dict) and fields:
            msg += " " + " ".join(f"{k}={v}" for k, v in fields.items())
        if record.exc_info:
            msg += "\n" + self.formatException(record.exc_info)
        if self.journal:
            # journald takes each line as an entry of its own, at the default (info) priority
            # unless it starts with the prefix: a traceback's lines must carry it too, or
            # ``journalctl -p err`` shows the headline without its traceback.
            prio = f"<{_PRIORITY.get(record.levelno, 6)}>"
            return "\n".join(prio + line for line in f"{record.name}: {msg}".split("\n"))
        return f"{self.formatTime(record, '%H:%M:%S')} {record.levelname:<7} {record.name}: {msg}"


def stderr_is_journal() -> bool:
    """Whether stderr is the journal stream systemd gave this service (``$JOURNAL_STREAM``).

    Compared with stderr's device and inode, as sd_journal_stream_fd(3) says: the variable is
    inherited by every process the service starts, whose stderr may be anything.
    """
    value = os.environ.get("JOURNAL_STREAM", "")
    dev, _, ino = value.partition(":")
    try:
        st = os.fstat(sys.stderr.fileno())
        return (st.st_dev, st.st_ino) == (int(dev), int(ino))
    except (OSError, ValueError, AttributeError):  # no stderr, a stream without fd, a bad value
        return False


def print_error(exc: BaseException) -> None:
    """The one ``mapd: error: ...`` line (a line per line of the message) on stderr.

    Under systemd this line is why the unit stopped: at error priority, so that ``journalctl -p err
    -u mapd`` shows it (an unprefixed line is taken as info).
    """
    prio = "<3>" if stderr_is_journal() else ""
    for line in str(exc).splitlines() or [type(exc).__name__]:
        print(f"{prio}mapd: error: {line}", file=sys.stderr)


def setup_logging(level: str = "info") -> None:
    """Log to stderr; with journald attached (``$JOURNAL_STREAM``) use priority prefixes."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JournalFormatter(journal=stderr_is_journal()))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
