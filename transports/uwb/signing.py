"""Frame signing in the manner of MAVLink 2: a per-sender counter and a truncated HMAC-SHA256.

A signed frame body ends with ``u48 counter || tag`` where ``tag`` is the first 6 bytes of
``HMAC-SHA256(key, DOMAIN || body || counter)``: 48 bits, as MAVLink 2's signature. At the seven
frames a second a 12.5 kb/s link carries, a forger needs about 2^47 tries, some 600,000 years, per
expected success; two more bytes would buy nothing a fleet needs and cost 1 % of every frame. The tag
is also the frame's check against damage: keyed links send no CRC (:mod:`transports.uwb.framing`). The counter rises with every frame a node signs and
never repeats, across restarts too: the adapter reserves blocks of counters in a file under the
state directory before the core may use them (:class:`CounterStore`), and starts no lower than a
clock-derived floor (10 µs ticks since 2015, as MAVLink's timestamp), so a node without a state
directory still never reuses a counter unless its clock runs backwards.

Receivers keep, per sender id, the highest counter seen and a 64-frame window below it (as IPsec
does), so reordered frames are accepted once and replayed or duplicated frames are dropped. The
highest counters are kept across restarts as well (:class:`ReplayStore`, saved every few seconds
and at close): a receiver that forgot them took every frame recorded before its restart once more.
They are kept with a fingerprint of the link key they were taken under, and read only under that
key: frames signed with another key fail their tag anyway, and a key rotated after it leaked takes
with it any mark its holder pushed ahead. A counter is accepted at most :data:`MAX_AHEAD_S` ahead
of the receiver's clock, so one forged frame can hold a sender's frames off no longer than that.

:class:`Signer` and :class:`Verifier` are pure; only :class:`CounterStore` and :class:`ReplayStore`
touch files.
"""

from __future__ import annotations

import errno
import hashlib
import hmac
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from mapd.errors import DiskFullError, StateError
from mapd.files import atomic_write_bytes, atomic_write_json
from mapd.files.reading import read_capped, read_json_capped

log = logging.getLogger(__name__)

COUNTER_LEN = 6
TAG_LEN = 6
TRAILER_LEN = COUNTER_LEN + TAG_LEN
COUNTER_MAX = (1 << 48) - 1
DOMAIN = b"mapd-uwb-frame/2\x00"
_EPOCH_2015 = 1420070400.0
REPLAY_WINDOW = 64
#: How far ahead of its own clock a receiver lets a sender's counter be. An honest sender's counter
#: is its clock floor, or the block it saved before a restart (4096 counters: 41 ms) when that is
#: higher, plus the frames it signed (a few a second, of 100,000 ticks a second); and the fleet's
#: clocks agree within milliseconds (TDMA needs 10 ms, chrony is a precondition). Five minutes cover
#: that with room for a clock that chrony stepped back since a save, yet a key holder's one frame
#: with a counter at this bound holds the real sender's frames off (as replays) for five minutes at
#: most, where a day's window let one frame silence a robot for a day (audit F1).
MAX_AHEAD_S = 300.0


def clock_floor(wall_time: float) -> int:
    """A counter value derived from the wall clock (10 µs ticks since 2015-01-01)."""
    return max(0, min(COUNTER_MAX, int((wall_time - _EPOCH_2015) * 100_000)))


def counter_bound(wall_now: float) -> int:
    """The highest counter a receiver whose clock reads ``wall_now`` accepts (:data:`MAX_AHEAD_S`)."""
    return clock_floor(wall_now + MAX_AHEAD_S)


def bound_marks(marks: Mapping[int, int], wall_now: float) -> dict[int, int]:
    """``marks`` with every mark above :func:`counter_bound` lowered to it.

    A mark above it was taken under a wider window (before the window shrank) or with a clock set
    ahead since: kept as it was, a forged far-ahead counter would refuse the real sender's frames
    until its clock reached it. Lowered, every counter a frame recorded so far can carry is still
    refused.
    """
    top = counter_bound(wall_now)
    return {src: min(mark, top) for src, mark in marks.items()}


def key_id(key: bytes) -> str:
    """A short fingerprint of a link key, for the files that must hold only under that key."""
    return hmac.new(key, b"mapd-uwb-replay-marks\x00", hashlib.sha256).hexdigest()[:16]


class _Mac:
    def __init__(self, key: bytes) -> None:
        self._base = hmac.new(key, DOMAIN, hashlib.sha256)

    def tag(self, data: bytes) -> bytes:
        h = self._base.copy()
        h.update(data)
        return h.digest()[:TAG_LEN]


class Signer:
    """Appends counter and tag to frame bodies, within the counters the adapter has persisted.

    The core asks :meth:`reservation` after each frame; when it returns a value, the adapter writes
    it to disk and calls :meth:`confirm`. Until then :meth:`can_sign` turns false once the confirmed
    block is used up, so no counter is ever used that a restart could hand out again.
    """

    def __init__(self, key: bytes, start: int, *, block: int = 4096) -> None:
        self._mac = _Mac(key)
        self.next = start
        self.limit = start
        self.block = block

    def can_sign(self) -> bool:
        return self.next < self.limit

    def reservation(self) -> int | None:
        """A new upper bound to persist, when less than half a block is left; else None."""
        if self.limit - self.next < self.block // 2 and self.limit < COUNTER_MAX:
            return min(COUNTER_MAX, self.next + self.block)
        return None

    def confirm(self, upto: int) -> None:
        """The adapter has persisted ``upto``: counters below it may be used."""
        self.limit = max(self.limit, upto)

    def raise_to(self, floor: int) -> bool:
        """Go on from counter ``floor`` if that is higher (never lower: a counter is never used
        twice); nothing is signed with it before a block past it is saved. True when it rose."""
        if floor <= self.next:
            return False
        self.next = min(floor, COUNTER_MAX)
        return True

    def sign(self, body: bytes) -> bytes:
        if not self.can_sign():
            raise RuntimeError("uwb: signing counter not reserved")  # core checks can_sign first
        counter = self.next.to_bytes(COUNTER_LEN, "little")
        self.next += 1
        data = body + counter
        return data + self._mac.tag(data)


@dataclass
class VerifyStats:
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0
    future: int = 0


class Verifier:
    """Checks signed bodies and drops replays; bounded state (one window per sender id)."""

    def __init__(self, key: bytes, marks: Mapping[int, int] | None = None) -> None:
        """``marks``: sender id -> the highest counter a previous run accepted from it (:meth:`marks`);
        that counter and every one below it are refused."""
        self._mac = _Mac(key)
        full = (1 << REPLAY_WINDOW) - 1  # every counter below the mark taken: none comes again
        # src -> (highest counter, bitmask below it)
        self._windows: dict[int, tuple[int, int]] = {src: (top, full) for src, top in (marks or {}).items()}
        self.stats = VerifyStats()

    def marks(self) -> dict[int, int]:
        """Sender id -> the highest counter accepted from it: what a restart must not accept again."""
        return {src: top for src, (top, _) in self._windows.items()}

    def check(self, body: bytes, signed: bool, wall_now: float | None = None) -> bytes | None:
        """The body without its trailer when it is signed, authentic and fresh; else None (counted).

        With ``wall_now`` (the receiver's clock), a counter more than :data:`MAX_AHEAD_S` ahead of
        the clock-derived floor is refused as well: honest senders count from that floor and send a
        few frames a second, so only a forger with the key sends one, and accepting it would make
        every later frame of the real sender look like a replay.
        """
        if not signed or len(body) < TRAILER_LEN + 2:
            self.stats.unsigned += 1
            return None
        data, tag = body[:-TAG_LEN], body[-TAG_LEN:]
        if not hmac.compare_digest(self._mac.tag(data), tag):
            self.stats.bad_signature += 1
            return None
        src = body[1]
        counter = int.from_bytes(data[-COUNTER_LEN:], "little")
        if wall_now is not None and counter > counter_bound(wall_now):
            self.stats.future += 1
            return None
        if not self._accept(src, counter):
            self.stats.replayed += 1
            return None
        return data[:-COUNTER_LEN]

    def _accept(self, src: int, counter: int) -> bool:
        top, mask = self._windows.get(src, (-1, 0))
        if counter > top:
            shift = counter - top
            mask = ((mask << shift) | (1 << (shift - 1))) & ((1 << REPLAY_WINDOW) - 1) if top >= 0 else 0
            self._windows[src] = (counter, mask)
            return True
        back = top - counter
        if back == 0 or back > REPLAY_WINDOW:
            return False
        bit = 1 << (back - 1)
        if mask & bit:
            return False
        self._windows[src] = (top, mask | bit)
        return True


class CounterStore:
    """The persisted high-water mark of a node's signing counter (one small file, written atomically)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._memory = 0

    def load(self) -> int:
        if self.path is None:
            return self._memory
        try:
            # a counter is 15 digits: more is a damaged file, not a reason to read it all
            text = read_capped(self.path, 64).decode("ascii").strip()
        except FileNotFoundError:
            return 0
        except (OSError, UnicodeDecodeError) as exc:
            raise StateError(f"uwb: cannot read signing counter {self.path}: {exc}") from None
        try:
            value = int(text)
        except ValueError:
            raise StateError(f"uwb: signing counter file {self.path} is corrupt ({text[:20]!r})") from None
        if not 0 <= value <= COUNTER_MAX:
            raise StateError(f"uwb: signing counter file {self.path} holds {value}, out of range")
        return value

    def save(self, value: int) -> None:
        """Persist ``value`` durably before the caller uses counters below it."""
        if self.path is None:
            self._memory = value
            return
        try:
            # The link's own folder only: a state directory that is gone (its disk unmounted) is
            # not made again here, on the disk under the mount point; the daemon's state store
            # makes its layout again once it can be written.
            self.path.parent.mkdir(exist_ok=True)
            # file and directory fsynced: a power cut never brings back a lower counter
            atomic_write_bytes(self.path, f"{value}\n".encode("ascii"))
        except OSError as exc:
            cls = DiskFullError if exc.errno in (errno.ENOSPC, errno.EDQUOT) else StateError
            raise cls(f"uwb: cannot write signing counter {self.path}: {exc.strerror}") from None


#: A replay file holds at most one mark a sender id (256), about 30 bytes each, and a key fingerprint.
MAX_REPLAY_FILE = 16 << 10


class ReplayStore:
    """The highest counter accepted from each sender, kept across restarts (a small JSON file:
    ``{"key": <key_id>, "marks": {"<sender id>": <counter>, ...}}``).

    Marks are read back only under the link key they were saved under: after the key is rotated
    they are void (one warning). A file from before keys were recorded (the marks alone) is read
    under any key. A file that cannot be read or is damaged costs what it held (one warning; frames
    recorded before the restart are refused again from each sender's first frame heard after it),
    never the start.
    """

    def __init__(self, path: Path | None) -> None:
        self.path = path

    def load(self, key: bytes | None = None) -> dict[int, int]:
        """The marks saved under ``key`` (None: whatever key)."""
        if self.path is None:
            return {}
        try:
            doc = read_json_capped(self.path, MAX_REPLAY_FILE)
        except FileNotFoundError:
            return {}
        except (OSError, ValueError, RecursionError) as exc:
            log.warning("uwb: replay marks %s unreadable (%s); starting without them", self.path, exc)
            return {}
        if isinstance(doc, dict) and "marks" in doc:
            saved_under = doc.get("key")
            if set(doc) - {"key", "marks"} or not isinstance(saved_under, str):
                log.warning("uwb: replay marks %s are damaged; starting without them", self.path)
                return {}
            if key is not None and saved_under != key_id(key):
                log.warning(
                    "uwb: replay marks %s were kept under another link key (rotated?); starting without them",
                    self.path,
                )
                return {}
            doc = doc["marks"]
        marks = {}
        if isinstance(doc, dict):
            for src, value in doc.items():
                if src.isdigit() and int(src) < 256 and type(value) is int and 0 <= value <= COUNTER_MAX:
                    marks[int(src)] = value
        if not isinstance(doc, dict) or len(marks) != len(doc):
            log.warning(
                "uwb: replay marks %s are damaged; keeping the %d that are not", self.path, len(marks)
            )
        return marks

    def save(self, marks: Mapping[int, int], key: bytes | None = None) -> None:
        """Write ``marks``, taken under link key ``key``, atomically; StateError when the disk refuses.

        Without ``key`` the marks alone are written (read back under any key)."""
        if self.path is None:
            return
        doc: dict[str, object] = {str(src): top for src, top in sorted(marks.items())}
        if key is not None:
            doc = {"key": key_id(key), "marks": doc}
        try:
            atomic_write_json(self.path, doc)
        except OSError as exc:
            raise StateError(f"uwb: cannot write replay marks {self.path}: {exc.strerror}") from None
