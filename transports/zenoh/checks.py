"""Where received updates and query replies are verified: one daemon thread, off the event loop.

Checking a sample (msgpack parse and an Ed25519 signature over up to ``max_message_bytes``) takes
about 15 ms for 8 MiB, and a bad signature is only found after that work, so it must neither run on
the event loop nor queue without bound. :class:`CheckQueue` runs checks one at a time, in arrival
order, on its own thread, and bounds what waits per robot:

* **Byte budget, latest wins.** A robot's waiting samples may total ``budget`` bytes (each charged
  its length plus :data:`OVERHEAD`); a newer sample that does not fit pushes out that robot's oldest
  waiting ones (``superseded``), and the newest is always kept. A burst of small samples is thus
  checked whole, in order (every forgery counted as one), while large samples arriving faster than
  they can be checked collapse to the newest: at most one waits when each is over half the budget.
* **Few robots.** At most ``max_robots`` robots have samples waiting; a sample of one more is
  refused (``rejected``).
* **Order.** One thread, first in first out, so for each robot the results come out in arrival
  order and an older update is never handed on after a newer one.

The thread is a daemon thread for the same reason as the outbox's (:mod:`transports.zenoh.jobs`):
nothing here may hold the process at exit.
"""

from __future__ import annotations

import itertools
import threading
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

R = TypeVar("R")

#: Bytes each waiting sample is charged beyond its length: a stand-in for its bookkeeping, so that
#: a flood of tiny samples is bounded in number too (``budget / OVERHEAD`` per robot at most).
OVERHEAD = 1024


@dataclass
class _Entry(Generic[R]):
    robot: str | None
    charge: int
    data: bytes
    then: Callable[[bytes, R], None] | None = None
    fn: Callable[[], None] | None = None


@dataclass
class _Waiting:
    seqs: deque[int] = field(default_factory=deque)
    charged: int = 0


class CheckQueue(Generic[R]):
    """Run ``check`` on samples on one daemon thread, FIFO, a byte budget per robot (module docstring)."""

    def __init__(
        self,
        name: str,
        check: Callable[[bytes], R],
        *,
        budget: int,
        max_robots: int,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        if budget <= 0 or max_robots <= 0:
            raise ValueError("budget and max_robots must be positive")
        self.budget = budget
        self.max_robots = max_robots
        self._check = check
        self._on_error = on_error
        self._cond = threading.Condition()
        self._queue: OrderedDict[int, _Entry[R]] = OrderedDict()
        self._waiting: dict[str, _Waiting] = {}
        self._calls = 0
        self._seq = itertools.count()
        self._stopping = False
        #: Samples pushed out of the queue by a newer one of the same robot, never checked.
        self.superseded = 0
        #: Samples (and calls) refused: too many robots waiting, too many calls, or stopping.
        self.rejected = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, robot: str, data: bytes, then: Callable[[bytes, R], None]) -> bool:
        """Queue ``data`` of ``robot``; once checked, ``then(data, result)`` runs on the check thread.

        May push out ``robot``'s oldest waiting samples (latest wins). False when refused.
        """
        charge = len(data) + OVERHEAD
        with self._cond:
            if self._stopping:
                self.rejected += 1
                return False
            w = self._waiting.get(robot)
            if w is None:
                if len(self._waiting) >= self.max_robots:
                    self.rejected += 1
                    return False
                w = self._waiting[robot] = _Waiting()
            while w.seqs and w.charged + charge > self.budget:
                old = self._queue.pop(w.seqs.popleft())
                w.charged -= old.charge
                self.superseded += 1
            seq = next(self._seq)
            self._queue[seq] = _Entry(robot, charge, data, then=then)
            w.seqs.append(seq)
            w.charged += charge
            self._cond.notify()
            return True

    def after(self, fn: Callable[[], None]) -> bool:
        """Run ``fn`` on the check thread once everything submitted so far is done; False if refused."""
        with self._cond:
            if self._stopping or self._calls >= self.max_robots:
                self.rejected += 1
                return False
            self._calls += 1
            self._queue[next(self._seq)] = _Entry(None, 0, b"", fn=fn)
            self._cond.notify()
            return True

    def waiting(self, robot: str | None = None) -> int:
        """Samples (of ``robot``, or of all) waiting to be checked, not counting one being checked."""
        with self._cond:
            if robot is None:
                return sum(len(w.seqs) for w in self._waiting.values())
            w = self._waiting.get(robot)
            return len(w.seqs) if w is not None else 0

    def stop(self) -> None:
        """Drop what waits and end the thread after the check in progress (without waiting for it)."""
        with self._cond:
            self._stopping = True
            self._queue.clear()
            self._waiting.clear()
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                _, entry = self._queue.popitem(last=False)
                if entry.robot is None:
                    self._calls -= 1
                else:
                    # FIFO per robot too, so this is the robot's oldest waiting sample.
                    w = self._waiting[entry.robot]
                    w.seqs.popleft()
                    w.charged -= entry.charge
                    if not w.seqs:
                        del self._waiting[entry.robot]
            try:
                if entry.fn is not None:
                    entry.fn()
                elif entry.then is not None:
                    entry.then(entry.data, self._check(entry.data))
            except Exception as exc:  # a bug in a callback must not end the thread
                if self._on_error is not None:
                    self._on_error(exc)
