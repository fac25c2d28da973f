"""Why a peer's maps are refused, in words an operator can act on: robots of one fleet whose configs
drifted apart (a roster without a robot's key or with its old one, another ``robot.fleet``, smaller
``limits``, ``[transports.uwb] nodes`` lists that differ, a codec model one robot lacks) refuse each
other's maps with every map they send. :class:`~mapd.daemon.receiver.Receiver` keeps one
:class:`Refusal` per robot, said once with its fix and shown in ``mapd status``; this module holds
the record and the lines (no state, no I/O).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from mapd.config import NAME_PATTERN
from mapd.errors import EnvelopeError, SignatureError

#: Robots whose refusal is kept (and so said once, not per map); beyond, refusals go unsaid but
#: counted. Names of robots not on the roster come unverified from the bytes, so they are bounded.
MAX_REFUSED_NAMES = 256
#: Robots off the roster shown in ``mapd status`` with their refusal (those on it always are).
MAX_REFUSED_SHOWN = 8
#: A peer whose maps keep coming while it has acked none of ours for this long (and our offer
#: waits for it) does not take them: said once. The publisher's in-flight timeout: by then an
#: offer to it has timed out unacked (mapd.daemon.publisher.INFLIGHT_TIMEOUT_S).
UNACKED_S = 30.0


@dataclass
class Refusal:
    """Why a robot's maps are refused now: said once (``fix``), shown in ``mapd status`` (``why``)."""

    #: A few words for the status lines (``over limits.max_cells``).
    why: str
    #: The whole line for the log and ``mapd status``: what is wrong, and what to change where.
    fix: str
    since: float
    last: float
    maps: int = 1

    def to_json(self, now: float) -> dict[str, Any]:
        return {
            "why": self.why,
            "fix": self.fix,
            "maps": self.maps,
            "for_s": round(now - self.since, 1),
            "last_s": round(now - self.last, 1),
        }


def shown(name: str) -> str:
    """``name`` as a log line may hold it: as it is when it is a valid robot or fleet name, else
    quoted and cut (names in refused bytes are unverified, and may hold anything, newlines too)."""
    return name if re.fullmatch(NAME_PATTERN, name) else ascii(name[:40])


def _printable(text: str, limit: int = 240) -> str:
    """An error's text from untrusted bytes, fit for one log line."""
    return "".join(c if c.isprintable() else "?" for c in text[:limit])


def _keygen_line(robot: str) -> str:
    return f"the line 'mapd keygen {robot} --public <its key file>' prints on {robot}"


def envelope_refusal(exc: EnvelopeError, robot: str, me: str) -> tuple[str, str]:
    """``(why, fix)`` for bytes of ``robot`` that :func:`open_envelope` refused on robot ``me``."""
    text, robot = _printable(str(exc)), shown(robot)
    if isinstance(exc, SignatureError):
        if "not on the fleet's roster" in text:
            return "not on this roster", (
                f"maps of {robot} refused: {robot} is not on this robot's [fleet.roster]; if it is a "
                f"robot of this fleet, add {_keygen_line(robot)}, then 'systemctl reload mapd' (if it "
                f"was removed on purpose, it still runs: stop it)"
            )
        if text.startswith("unsigned"):
            return "unsigned", (
                f"maps of {robot} refused: {robot} sends them unsigned and this fleet requires "
                f"signatures: give {robot} its key (robot.key_file) and fleet.allow_unsigned = false"
            )
        return "signed with another key than this roster's", (
            f"maps of {robot} refused: {robot}'s key in this robot's [fleet.roster] is not the one "
            f"its maps are signed with ({robot} re-keyed, or this roster is old; or a forgery): "
            f"put {_keygen_line(robot)} in [fleet.roster], then 'systemctl reload mapd'"
        )
    if "over the limit of" in text:
        return "over limits.max_message_bytes", (
            f"maps of {robot} refused: {text}, this robot's limits.max_message_bytes: raise it on "
            f"{me} (the same on every robot), or have {robot} send smaller maps"
        )
    if "format" in text and "not supported" in text:
        return "another mapd version", f"maps of {robot} refused: {text}: run one mapd release on every robot"
    return "malformed", f"maps of {robot} refused: {text}"


def decode_cause(text: str) -> tuple[str, str] | None:
    """``(why, fix)`` when a payload does not decode for this robot's install or config (a codec or
    model it lacks), which every map of that robot meets; None for damage or a base that differs."""
    if "variant" in text:
        return "another codec model", (
            "; the robots use different models of that codec ([codec.paper] model, or the files in "
            "models/): use one on every robot"
        )
    if "no codec plugin" in text or ("codec plugin" in text and "not installed" in text):
        return "a codec missing here", "; install the same mapd (and its extras) on every robot"
    return None
