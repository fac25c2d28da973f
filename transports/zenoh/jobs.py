"""A latest-wins job queue served by one daemon thread: where the zenoh transport blocks.

zenoh's Python API is synchronous (``put`` may wait on a full send queue, ``open`` on a router), so
every zenoh call the transport makes runs here, never on the event loop. Jobs carry a key; a job
submitted while another with the same key is still waiting replaces it in place, so a slow link
sends the newest map update and never a queue of stale ones. Jobs that need an answer (open, close)
go through :meth:`JobQueue.call` and return a :class:`concurrent.futures.Future`.

The thread is a daemon thread on purpose: if zenoh ever blocks past the transport's close timeout,
the process can still exit (a pool thread would be joined at interpreter exit and hang it).
"""

from __future__ import annotations

import concurrent.futures
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

T = TypeVar("T")


class JobQueue:
    """Run jobs one at a time on a daemon thread; a newer job replaces a waiting one with the same key."""

    def __init__(
        self,
        name: str,
        *,
        max_pending: int = 256,
        on_error: Callable[[Hashable, BaseException], None] | None = None,
    ) -> None:
        self.max_pending = max_pending
        self._on_error = on_error
        self._cond = threading.Condition()
        self._jobs: OrderedDict[Hashable, Callable[[], None]] = OrderedDict()
        self._futures: dict[Hashable, concurrent.futures.Future[Any]] = {}
        self._stopping = False
        self._finishing = False
        self.replaced = 0
        self.rejected = 0
        self.failed = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, key: Hashable, job: Callable[[], None]) -> bool:
        """Queue ``job``, replacing a waiting job with the same ``key``.

        Returns False (and drops the job) when the outbox is stopping or ``max_pending`` jobs wait.
        """
        with self._cond:
            if self._stopping or self._finishing:
                self.rejected += 1
                return False
            if key in self._jobs:
                self._jobs[key] = job
                self.replaced += 1
                return True
            if len(self._jobs) - len(self._futures) >= self.max_pending:
                self.rejected += 1
                return False
            self._jobs[key] = job
            self._cond.notify()
            return True

    def call(self, fn: Callable[[], T]) -> concurrent.futures.Future[T]:
        """Run ``fn`` after the jobs already waiting; its result or exception comes in the future."""
        fut: concurrent.futures.Future[T] = concurrent.futures.Future()
        key = object()

        def job() -> None:
            if not fut.set_running_or_notify_cancel():
                return
            try:
                fut.set_result(fn())
            except BaseException as exc:  # handed to the caller through the future
                fut.set_exception(exc)

        with self._cond:
            if self._stopping or self._finishing:
                fut.cancel()
                return fut
            self._jobs[key] = job
            self._futures[key] = fut
            self._cond.notify()
        return fut

    def pending(self) -> int:
        """Jobs waiting (not counting one running)."""
        with self._cond:
            return len(self._jobs)

    def discard_pending(self) -> int:
        """Drop every waiting fire-and-forget job (calls stay); returns how many were dropped."""
        with self._cond:
            drop = [k for k in self._jobs if k not in self._futures]
            for k in drop:
                del self._jobs[k]
            return len(drop)

    def finish(self) -> None:
        """Run the jobs already waiting, then end the thread; takes no new ones and does not wait."""
        with self._cond:
            self._finishing = True
            self._cond.notify()

    def stop(self, timeout: float) -> bool:
        """Let the running job finish, drop the rest, end the thread; False if it is still busy."""
        with self._cond:
            self._stopping = True
            for fut in self._futures.values():
                fut.cancel()
            self._jobs.clear()
            self._futures.clear()
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._jobs and not self._stopping:
                    if self._finishing:
                        return
                    self._cond.wait()
                if self._stopping:
                    return
                key, job = self._jobs.popitem(last=False)
                self._futures.pop(key, None)
            try:
                job()
            except Exception as exc:  # a failed send must not end the thread
                self.failed += 1
                if self._on_error is not None:
                    self._on_error(key, exc)
