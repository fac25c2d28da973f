"""The ``mapd run`` process around :class:`~mapd.daemon.server.Daemon`: signals, the event loop, the exit.

SIGTERM and SIGINT drain (a second SIGINT exits at once), SIGHUP reloads, SIGUSR1 writes every
thread's stack to the journal. The loop is closed without waiting for worker threads: the state is
saved by the time the daemon's ``run()`` returns, and ``mapd run`` then leaves with ``os._exit``.
"""

from __future__ import annotations

import asyncio
import faulthandler
import logging
import os
import signal

from mapd import config as configmod
from mapd.daemon.server import Daemon

log = logging.getLogger("mapd.daemon")


def run_daemon(cfg: configmod.MapdConfig) -> int:
    """Run the daemon with signal handling: SIGTERM/SIGINT drain, a second SIGINT forces exit, SIGHUP
    reloads the roster, SIGUSR1 writes every thread's stack to stderr (the journal)."""
    # For a daemon that hangs (in a stop that never ends, or stuck in a driver): `systemctl kill
    # -s USR1 mapd` shows where, without stopping it. Written by the interpreter itself, so it
    # works when the event loop is the thing that is stuck.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    # And when it dies of one (systemd's watchdog sends SIGABRT to a daemon that stopped pinging;
    # SIGSEGV in a native library): every thread's stack first, or the journal says nothing of where.
    faulthandler.enable(all_threads=True)

    async def main() -> None:
        daemon = Daemon(cfg)
        loop = asyncio.get_running_loop()
        hits = {"int": 0}

        def on_sigint() -> None:
            hits["int"] += 1
            if hits["int"] > 1:
                log.warning("second SIGINT: exiting now")
                os._exit(130)
            daemon.request_stop()

        loop.add_signal_handler(signal.SIGTERM, daemon.request_stop)
        loop.add_signal_handler(signal.SIGHUP, daemon.request_reload)
        loop.add_signal_handler(signal.SIGINT, on_sigint)
        await daemon.run()

    # Not asyncio.run: at its end it waits for every job on the default executor, and a job that a
    # stop cancelled the await of (a source's start_pose) runs on in its thread for as long as it
    # takes, past systemd's TimeoutStopSec (a placement search gives up at its next stage). The state is saved by the time run()
    # returns (or raises), and mapd run leaves with os._exit either way, which ends such a thread.
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    try:
        loop.run_until_complete(main())
    finally:
        pending = asyncio.all_tasks(loop)
        for task in pending:
            task.cancel()
        if pending:
            loop.run_until_complete(asyncio.wait(pending))
        loop.run_until_complete(loop.shutdown_asyncgens())
        asyncio.set_event_loop(None)
        loop.close()  # shuts the default executor down without waiting for its threads
    return 0
