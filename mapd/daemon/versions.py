"""Map versions as (incarnation, number), packed in one integer so that newer is simply larger.

A robot's version is ``incarnation << 32 | number``. The number counts the robot's map versions
within one incarnation. A robot whose state directory is lost (a new disk, a wiped SD card) starts a
new incarnation from its clock: seconds since :data:`EPOCH`, which is larger than any incarnation
it had before (given a clock that does not run backwards by more than the downtime). So its next
map is newer than everything its peers hold and is taken at once, where bare counters restarting
at 1 were ignored until they passed the old ones. A state directory from before incarnations has
incarnation 0 and keeps counting.

Peers bound what they accept (:func:`check_step`): an incarnation from the future (beyond the
receiver's clock plus a tolerance) or a number that jumps further than the elapsed time explains is
refused, so a buggy or compromised robot cannot push its versions out of reach of its own future
maps, and nothing another robot sends can lock a robot out (only its own key signs its maps). A
leaked key can still sign a version up to the tolerance (a day) ahead; it is revoked with the key
when the robot is re-keyed, and maps refused under it meanwhile are logged
(:attr:`VersionBounds.clock_tolerance_s`).
"""

from __future__ import annotations

from dataclasses import dataclass

#: Incarnations count seconds from 2024-01-01T00:00:00Z (31 bits last until 2092).
EPOCH = 1_704_067_200
NUMBER_BITS = 32
NUMBER_MASK = (1 << NUMBER_BITS) - 1
MAX_INCARNATION = (1 << 31) - 1


def make(incarnation: int, number: int) -> int:
    """The version of map ``number`` in ``incarnation``."""
    if not 0 <= incarnation <= MAX_INCARNATION or not 0 <= number <= NUMBER_MASK:
        raise ValueError(f"incarnation {incarnation} or number {number} out of range")
    return incarnation << NUMBER_BITS | number


def split(version: int) -> tuple[int, int]:
    """``(incarnation, number)`` of ``version``."""
    return version >> NUMBER_BITS, version & NUMBER_MASK


def incarnation_at(wall_time: float) -> int:
    """A new incarnation for a robot starting at ``wall_time`` (seconds since 1970)."""
    return max(1, min(MAX_INCARNATION, int(wall_time - EPOCH)))


def next_version(current: int, wall_time: float) -> int:
    """The version after ``current`` (0: none yet): the next number, or a new incarnation when full."""
    incarnation, number = split(current)
    if current == 0:
        return make(incarnation_at(wall_time), 1)
    if number < NUMBER_MASK:
        return current + 1
    return make(max(incarnation + 1, incarnation_at(wall_time)), 1)


@dataclass(frozen=True)
class VersionBounds:
    """How far a peer's versions may move: ``max_jump`` numbers plus ``max_rate`` per second elapsed."""

    max_jump: int = 1000
    max_rate: float = 10.0
    #: How far a new incarnation may lie ahead of the receiver's clock. Not shrunk to minutes: an
    #: incarnation is the robot's clock when its state began, kept for good, and a robot that
    #: starts afresh before its clock is set (an RTC kept in local time, up to 14 h ahead; a board
    #: with a wrong battery-backed clock before NTP steps it) would be refused by every peer until
    #: their clocks catch up, that is for hours, where its only fault was an honest clock. What a
    #: day allows a leaked key (a version up to a day ahead that holds the real robot's maps off as
    #: "not newer") ends when the robot is re-keyed or removed: the reload revokes the held map and
    #: version with the key (and a start revokes what the replaced key signed), and until then the
    #: refusals are logged as warnings (:meth:`~mapd.daemon.receiver.Receiver.plan`).
    clock_tolerance_s: float = 86400.0


def check_step(held: int, held_at: float, new: int, now: float, bounds: VersionBounds) -> str | None:
    """Why ``new`` must be refused after ``held`` (received or made at wall time ``held_at``), or None.

    ``now`` is the receiver's wall time. ``held`` 0 means nothing is held. Only the incarnation's
    plausibility is checked for a new incarnation: its numbers start again.
    """
    incarnation, number = split(new)
    if incarnation > incarnation_at(now + bounds.clock_tolerance_s) and incarnation != 0:
        return f"incarnation {incarnation} is in the future of this robot's clock"
    held_incarnation, held_number = split(held)
    if held == 0 or incarnation != held_incarnation:
        return None
    allowed = bounds.max_jump + bounds.max_rate * max(0.0, now - held_at)
    if number - held_number > allowed:
        return f"version jumps {number - held_number} ahead (at most {int(allowed)} allowed)"
    return None


def label(version: object) -> str:
    """``v<number>`` for people (``mapd status``, the demo), the incarnation left out; ``-`` if none."""
    if not isinstance(version, int) or isinstance(version, bool) or version < 0:
        return "-"
    return f"v{split(version)[1]}"
