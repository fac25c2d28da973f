"""Whether the kernel holds the wall clock synchronized (NTP, PTP, GPS): what TDMA's turns count on.

TDMA cuts time into turns on each robot's wall clock, so the fleet's clocks must agree within the
guard (docs/uwb.md, *One clock for the fleet*). A robot cannot see another's clock, but it can ask
its own kernel whether a time service keeps its clock disciplined: ``adjtimex`` with no change
requested returns the clock's state, ``TIME_ERROR`` while no time service keeps it synchronized.
The uwb link shows the answer in ``mapd status``, on the FAULTS line when it is no, before the
collisions it leads to show.
"""

from __future__ import annotations

import ctypes
import sys

#: adjtimex's return value while the clock is not synchronized (linux/timex.h).
TIME_ERROR = 5
#: Room for ``struct timex`` (208 bytes on 64-bit Linux), zeroed: ``modes`` 0 asks, changes nothing.
_TIMEX_BYTES = 512

_adjtimex = None
if sys.platform.startswith("linux"):
    try:
        # the process's own symbols, libc's among them (find_library would run ldconfig)
        _libc = ctypes.CDLL(None, use_errno=True)
        _adjtimex = _libc.adjtimex
    except (OSError, AttributeError):
        _adjtimex = None


def synchronized() -> bool | None:
    """Whether the kernel says the wall clock is synchronized; None where it cannot be asked."""
    if _adjtimex is None:
        return None
    state = int(_adjtimex(ctypes.create_string_buffer(_TIMEX_BYTES)))
    if state < 0:
        return None
    return state != TIME_ERROR
