"""zenoh callbacks whose threads close() can wait for, so the process never aborts at exit.

zenoh-python runs each Python callback (of a subscriber, queryable or query) on a Python thread of
its own, which ends some time after the entity is undeclared or the session closed. If such a
thread is still ending when the interpreter finalizes, Python kills it inside zenoh's Rust frames
and the process aborts ("FATAL: exception not rethrown"), seen here about one exit in ten. zenoh
calls a handler's ``drop`` function on that thread as its last act, so :class:`HandlerSet` counts
the handlers it made, notes each thread as it drops, and :meth:`HandlerSet.wait` blocks until all
of them have dropped and their threads have ended.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any


class HandlerSet:
    """Makes ``zenoh.handlers.Callback`` objects and waits for their threads to end."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._live = 0
        self._ended: list[threading.Thread] = []

    def callback(self, fn: Callable[[Any], Any], on_drop: Callable[[], Any] | None = None) -> Any:
        """A zenoh callback handler running ``fn``, tracked until zenoh drops it (then ``on_drop()``).

        Make it only just before handing it to zenoh: one that zenoh never gets is never dropped.
        """
        import zenoh

        with self._cond:
            self._live += 1
        return zenoh.handlers.Callback(fn, lambda: self._dropped(on_drop))

    def _dropped(self, on_drop: Callable[[], Any] | None) -> None:
        try:
            if on_drop is not None:
                on_drop()
        finally:
            self._note_end()

    def _note_end(self) -> None:
        with self._cond:
            self._live -= 1
            self._ended.append(threading.current_thread())
            self._cond.notify_all()

    @property
    def live(self) -> int:
        """Handlers zenoh has not dropped yet."""
        with self._cond:
            return self._live

    def wait(self, deadline: float) -> bool:
        """Wait until every handler is dropped and its thread has ended, or ``deadline`` (monotonic)."""
        with self._cond:
            self._cond.wait_for(lambda: self._live == 0, timeout=max(0.0, deadline - time.monotonic()))
            threads, self._ended = self._ended, []
            done = self._live == 0
        me = threading.current_thread()
        for t in threads:
            if t is not me:
                t.join(max(0.0, deadline - time.monotonic()))
        return done and not any(t.is_alive() for t in threads if t is not me)
