"""A stop: one asked for during start-up cuts the start-up short; then every part closes in time.

``systemctl stop`` of a start that takes long (a source building its world, a transport opening)
must not wait for the whole start-up, say READY=1 and only then stop: :func:`unless_stopped`
cancels the start-up there. The shutdown closes the transports, the outputs, the source and the
control socket within the daemon's shutdown timeout (a part that fails to close does not keep the
others open), and :func:`log_stopped` says how long the stop took, and where: systemd's
``TimeoutStopSec`` must cover it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Coroutine, Sequence
from typing import Any

from mapd.daemon.status_socket import StatusServer
from mapd.outputs.base import Output
from mapd.sources.base import MapSource
from transports.base import Transport

log = logging.getLogger("mapd.daemon")


async def unless_stopped(job: Coroutine[Any, Any, None], stop: asyncio.Event) -> bool:
    """Run ``job`` unless ``stop`` is set first, which cancels it: True when it finished."""
    task = asyncio.ensure_future(job)
    stopped = asyncio.ensure_future(stop.wait())
    cut = True
    try:
        await asyncio.wait({task, stopped}, return_when=asyncio.FIRST_COMPLETED)
        cut = not task.done()
    finally:
        stopped.cancel()
        if not task.done():
            # A stop came first, or the caller itself was cancelled: either way the start-up must
            # not go on starting transports and the control socket after the shutdown that
            # follows has closed them.
            task.cancel()
            await asyncio.wait({task})
    if not cut:
        task.result()  # its error, if it failed
        return True
    if not task.cancelled():
        task.exception()  # (retrieved: what its cancellation raised is not news now)
    return False


async def close_all(
    transports: Sequence[Transport],
    outputs: Sequence[Output],
    source: MapSource | None,
    status_server: StatusServer,
    timeout: float,
) -> None:
    """Close every part, each despite the others' errors, within ``timeout`` seconds in all."""

    async def close() -> None:
        for t in transports:
            with contextlib.suppress(Exception):
                await t.close()
        for o in outputs:
            with contextlib.suppress(Exception):
                await o.close()
        if source is not None:
            with contextlib.suppress(Exception):
                await source.close()
        await status_server.close()

    try:
        await asyncio.wait_for(close(), timeout)
    except TimeoutError:
        log.warning("shutdown timed out after %.1f s", timeout)


def log_stopped(stopping_at: float, tasks_done: float, closed: float) -> None:
    """Say how long a stop took (``time.monotonic()`` times: asked for, the tasks done, the parts
    closed; now, the state saved), and where: systemd's TimeoutStopSec must cover it."""
    done = time.monotonic()
    log.info(
        "stopped",
        extra={
            "fields": {
                "seconds": round(done - stopping_at, 2),
                "tasks_s": round(tasks_done - stopping_at, 2),
                "transports_s": round(closed - tasks_done, 2),
                "flush_s": round(done - closed, 2),
            }
        },
    )
