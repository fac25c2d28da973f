"""What a :class:`~transports.uwb.link.UwbLink` keeps of its signing on disk: the counter block the
core may sign within, saved before any frame uses it (R15 in ``arq.py``), and the highest counter
accepted from each sender (the replay marks), as a mixin over the link's state.

A save that fails (a full or read-only disk) is said once and tried again: the core signs on within
the block saved before, then goes quiet until a save goes through, and frames a sender signed since
the last saved marks are all a restart could take again. Saves (fsyncs, which an SD card under load
can take seconds over) run on a worker thread, never on the event loop's.
"""

from __future__ import annotations

import asyncio
import logging

from mapd.errors import DiskFullError, StateError
from transports.uwb import arq
from transports.uwb.signing import CounterStore, ReplayStore

log = logging.getLogger("mapd.uwb")

#: How often a signing counter that could not be saved is tried again.
COUNTER_RETRY_S = 1.0
#: Seconds between saves of the replay marks: frames a sender signed in the last few seconds
#: before a kill -9 are all a restart could take again (a clean close saves them all).
REPLAY_SAVE_S = 5.0


class SigningSide:
    """The signing state's half of a link (a mixin: :class:`~transports.uwb.link.UwbLink` owns the
    state declared here)."""

    port: str
    core: arq.ArqEndpoint | None
    _cfg: arq.ArqConfig
    _store: CounterStore
    _replay: ReplayStore
    #: The replay marks as last saved, and when the next periodic save may be.
    _replay_saved: dict[int, int]
    _replay_save_at: float
    replay_save_errors: int
    #: The last save of the replay marks failed.
    _replay_fault: bool
    counter_save_errors: int
    #: The last failed counter save's line ("" when the last went through), and the next retry.
    _counter_fault: str
    _counter_retry_at: float

    async def _save_replay(self, *, force: bool = False) -> None:
        """Save the highest counter accepted from each sender, at most every :data:`REPLAY_SAVE_S`
        (on a worker thread), when it changed."""
        if self.core is None:
            return
        now = asyncio.get_running_loop().time()
        if not force and now < self._replay_save_at:
            return
        marks = self.core.replay_marks()
        if marks == self._replay_saved:
            return
        self._replay_save_at = now + REPLAY_SAVE_S
        try:
            await asyncio.to_thread(self._replay.save, marks, self._cfg.key)
        except StateError as exc:
            self.replay_save_errors += 1
            if not self._replay_fault:  # said once an outage (it was once a process), not each try
                log.warning("%s; frames from before a restart may be taken again after it", exc)
            self._replay_fault = True
            return
        if self._replay_fault:
            self._replay_fault = False
            log.warning("uwb: replay marks saved again on %s", self.port)
        self._replay_saved = marks

    async def _persist_counter(self, *, strict: bool = False) -> None:
        """Save the counter bound the core asks for, then let it sign below it.

        Only at start (``strict``) does a failed save raise, unless the disk is full: then, as
        later, the loop goes on. The core still has the rest of the block saved before (half a
        block, minutes of frames; none at start), after which it sends nothing signed; each wake
        retries, and a save that goes through resumes it. The save
        (two fsyncs, which an SD card under load can take seconds over) runs on a worker thread:
        this link waits for it, the event loop does not.
        """
        assert self.core is not None
        upto = self.core.counter_reservation()
        if upto is None:
            return
        now = asyncio.get_running_loop().time()
        if self._counter_fault and now < self._counter_retry_at:
            return  # not a write per frame to a disk that refused the last one
        try:
            await asyncio.to_thread(self._store.save, upto)
        except StateError as exc:
            if strict and not isinstance(exc, DiskFullError):
                raise
            self._counter_retry_at = now + COUNTER_RETRY_S
            self.counter_save_errors += 1
            if str(exc) != self._counter_fault:
                self._counter_fault = str(exc)
                if strict:
                    log.warning(
                        "%s; this link signs and sends nothing until a save goes through, retrying", exc
                    )
                else:
                    log.warning("%s; signing on within the counters saved before, retrying", exc)
            return
        if self._counter_fault:
            self._counter_fault = ""
            log.warning("uwb: signing counter saved again on %s", self.port)
        self.core.confirm_counter(upto)
